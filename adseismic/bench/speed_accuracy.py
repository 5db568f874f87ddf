"""Speed/accuracy sweep: trace error against the 2D analytic solution versus time per shot.

Scene: homogeneous 2D medium, c = 2000 m/s, 1200 m x 1200 m, Ricker 15 Hz source at (z, x) =
(600, 300) m, receivers at (600, 600), (600, 750), (600, 900) m (offsets 300-600 m, 2.3-4.5
dominant wavelengths), record 0.5 s: every boundary (PML) echo arrives after 0.6 s, so the error is
the discretisation's alone (plus rounding). Sources and receivers fall between grid nodes for most
dx (the Hicks operator is part of what is measured).

For each spatial order, points per minimum wavelength ppw = c / (f_max dx) (f_max = the Ricker's
-20 dB frequency, 2.21 f_peak, the planner's convention), Courant number as a fraction of the exact
CFL limit (0.9 is the planner's cfl_safety; a smaller dt cuts the time error, which dominates at
orders 4 and 8 near the limit) and precision, the error is the relative L2 misfit of all receiver traces
against adseismic.analytic.acoustic_2d in absolute amplitude; the time is the wall time of one
adseismic.forward call for the shot (setup and transfers included), best of ``repeat`` after a
warm-up. On the CPU the chart uses the process CPU time (core-seconds) of the run instead, which
other jobs on a shared machine do not inflate. The planner's default choice (plan_scene for this scene at the default accuracy target
1% and order 4, float32) is measured the same way and marked on the chart.
"""
from __future__ import annotations

import json
import logging
import math
import pathlib
import time
from dataclasses import asdict, dataclass, field

import numpy as np

log = logging.getLogger("adseismic.bench")

C, PEAK_FREQUENCY = 2000.0, 15.0  # m/s, Hz
LENGTH, RECORD = 1200.0, 0.5  # m (square domain), s
SOURCE = (600.0, 300.0)  # (z, x) m
RECEIVERS = ((600.0, 600.0), (600.0, 750.0), (600.0, 900.0))
PML = 20
ORDER_COLOUR = {2: 0, 4: 1, 8: 2}  # matplotlib colour cycle index per order


@dataclass
class SweepPoint:
    """One discretisation on one device: cfl_fraction: v dt / dx over the CFL limit; dx (m), dt (s),
    nt; padded_cells of the grid; error:
    relative L2 trace error; seconds: best wall time per shot (s), of ``times``; cpu_seconds: least
    process CPU time of a run (s); cost: what the chart plots (CPU: cpu_seconds, CUDA: seconds); planner: the
    planner's default choice; status "ok" or "failed: why"."""

    device: str
    order: int
    precision: str
    ppw: float
    cfl_fraction: float
    dx: float
    dt: float
    nt: int
    padded_cells: int
    error: float | None = None
    seconds: float | None = None
    cpu_seconds: float | None = None
    times: list = field(default_factory=list)
    planner: bool = False
    status: str = "ok"

    @property
    def cost(self) -> float | None:
        return self.cpu_seconds if self.device == "cpu" else self.seconds


def f_max() -> float:
    """The Ricker wavelet's -20 dB frequency (Hz)."""
    from adseismic.wavelets import ricker, spectral_fmax

    return spectral_fmax(ricker(PEAK_FREQUENCY, 2000, 1e-4), 1e-4, -20.0)


def grid_for(order: int, ppw: float, cfl_fraction: float) -> tuple[float, float]:
    """(dx, dt) for ppw points per minimum wavelength at cfl_fraction x the CFL limit."""
    from adseismic.kernels.numerics import cfl_limit

    dx = C / (f_max() * ppw)
    return dx, cfl_fraction * cfl_limit(order, 2) * dx / C


def inputs(dx: float, dt: float):
    """(velocity (n, n) m/s, wavelet (nt,), sources (1, 1, 2) m, receivers (1, 3, 2) m) of the scene."""
    from adseismic.wavelets import ricker

    n = int(math.ceil(LENGTH / dx - 1e-9)) + 1
    nt = int(round(RECORD / dt)) + 1
    return np.full((n, n), C), ricker(PEAK_FREQUENCY, nt, dt), np.array([[SOURCE]]), np.array([RECEIVERS])


def analytic(wavelet: np.ndarray, dt: float) -> np.ndarray:
    """Exact traces (3, nt) for the wavelet sampled at dt (adseismic.analytic.acoustic_2d)."""
    from adseismic.analytic import acoustic_2d

    r = np.hypot(*(np.array(RECEIVERS) - np.array(SOURCE)).T)
    return acoustic_2d(wavelet, dt, r, C)


def measure(device: str, order: int, precision: str, dx: float, dt: float, repeat: int, planner: bool = False) -> SweepPoint:
    """Run one discretisation ``repeat`` times; error against the analytic traces, best time."""
    import warp as wp

    from adseismic.kernels.numerics import cfl_limit
    from adseismic.solve.acoustic import forward
    from adseismic.solve.common import resolve_device

    device = resolve_device(device)
    v, w, src, rec = inputs(dx, dt)
    p = SweepPoint(device, order, precision, float(f"{C / (f_max() * dx):.6g}"), C * dt / dx / cfl_limit(order, 2), float(dx), float(dt), len(w),
                   math.prod(n + 2 * PML + order for n in v.shape), planner=planner)  # fmt: skip
    cpu = []
    try:
        for _ in range(repeat):
            wp.synchronize_device(device)
            t0, c0 = time.perf_counter(), time.process_time()
            out = forward(v, dx, dt, w[None, None], src, rec, order=order, precision=precision, device=device, pml_width=PML)
            wp.synchronize_device(device)
            p.times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
    except Exception as exc:  # an unstable or failed point is reported, the sweep goes on
        p.status = f"failed: {type(exc).__name__}: {exc}"[:300]
        return p
    exact = analytic(w, dt)
    p.error = float(np.linalg.norm(out.receiver_amplitudes[0] - exact) / np.linalg.norm(exact))
    p.seconds, p.cpu_seconds = min(p.times), min(cpu)
    return p


def planner_choice(device: str):
    """The planner's Plan for this scene at its defaults (order 4, accuracy 1%, float32)."""
    from adseismic.config import parse_config
    from adseismic.scene import plan_scene

    n = int(LENGTH / 5.0) + 1
    raw = {
        "model": {"kind": "constant", "shape": [n, n], "spacing": 5.0, "velocity": C},
        "geometry": {"sources": {"points": [{"z": SOURCE[0], "x": SOURCE[1]}]},
                     "receivers": {"points": [{"z": z, "x": x} for z, x in RECEIVERS]}},
        "wavelet": {"kind": "ricker", "peak_frequency": PEAK_FREQUENCY},
        "simulation": {"device": "cuda" if device.startswith("cuda") else "cpu", "domain": "model", "duration": RECORD},
    }  # fmt: skip
    return plan_scene(parse_config(raw))


def sweep(devices, orders, ppws, precisions, cfl_fractions=(0.9, 0.4), repeat: int = 2, progress: bool = True) -> list[SweepPoint]:
    """Every (device, order, ppw, Courant fraction, precision) point plus the planner's default per device."""
    from tqdm.auto import tqdm

    from adseismic.solve.common import resolve_device

    points = []
    for device in devices:
        device = resolve_device(device)
        plan = planner_choice(device)
        todo = [(o, p, f, q) for o in orders for q in precisions for f in cfl_fractions for p in sorted(ppws)]
        for o, q in dict.fromkeys((o, q) for o, _, _, q in todo):  # compile the kernels outside the timings
            measure(device, o, q, *grid_for(o, 3.0, 0.9), repeat=1)
        bar = tqdm(todo, desc=f"speed/accuracy sweep on {device}", unit="run", disable=not progress)
        for o, p, f, q in bar:
            points.append(measure(device, o, q, *grid_for(o, p, f), repeat=repeat))
            log.info("sweep %s order %d %s ppw %g cfl %g: %s", device, o, q, p, f, _describe(points[-1]))
        pt = measure(device, plan.order, plan.precision, plan.dx, plan.dt, repeat, planner=True)
        log.info("sweep %s planner default (order %d, dx %g m, dt %g s): %s", device, plan.order, plan.dx, plan.dt, _describe(pt))
        points.append(pt)
    return points


def _describe(p: SweepPoint) -> str:
    return p.status if p.status != "ok" else f"error {p.error:.3g}, {p.seconds:.3g} s (CPU {p.cpu_seconds:.3g} s)"


def pareto_front(points) -> list[SweepPoint]:
    """The points no other point beats in both cost and error, by increasing cost."""
    front, best = [], math.inf
    for p in sorted((p for p in points if p.status == "ok"), key=lambda p: (p.cost, p.error)):
        if p.error < best:
            front.append(p)
            best = p.error
    return front


def chart_name(device: str, devices) -> str:
    """speed_accuracy_cpu.png, speed_accuracy_cuda.png (speed_accuracy_cuda1.png etc. when several GPUs)."""
    kind = device.split(":")[0]
    several = sum(d.split(":")[0] == kind for d in devices) > 1
    return f"speed_accuracy_{device.replace(':', '') if several else kind}.png"


def plot(path, points, device_name: str = "") -> pathlib.Path:
    """Error (log) against time per shot (log) for one device: one line per (order, Courant fraction,
    precision) through its ppw values (colour: order; line: Courant fraction; filled/open marker:
    float32/float64; numbers: ppw), the Pareto front, and the planner's default as a star."""
    from matplotlib.lines import Line2D

    from adseismic.plotting import _figure, save_figure

    fig = _figure(9.0, 6.5)
    ax = fig.add_subplot()
    ok = [p for p in points if p.status == "ok"]
    lines = sorted({(p.order, round(p.cfl_fraction, 3), p.precision) for p in ok if not p.planner})
    fractions = sorted({f for _, f, _ in lines}, reverse=True)
    styles = dict(zip(fractions, ("-", "--", ":", "-.")))
    for o, f, q in lines:
        pts = sorted((p for p in ok if (p.order, round(p.cfl_fraction, 3), p.precision) == (o, f, q) and not p.planner), key=lambda p: p.ppw)
        colour = f"C{ORDER_COLOUR[o]}"
        ax.plot([p.cost for p in pts], [p.error for p in pts], styles.get(f, "-"), marker="o" if q == "float32" else "s",
                color=colour, ms=5, lw=1, mfc=colour if q == "float32" else "white")  # fmt: skip
        if q == lines[0][2]:
            for p in pts:
                ax.annotate(f"{p.ppw:g}", (p.cost, p.error), textcoords="offset points", xytext=(4, 3), fontsize=7, color=colour)
    handles = [Line2D([], [], color=f"C{ORDER_COLOUR[o]}", lw=2, label=f"order {o}") for o in sorted({o for o, _, _ in lines})]
    handles += [Line2D([], [], color="gray", ls=styles[f], label=f"dt = {f:g} x CFL limit") for f in fractions]
    handles += [Line2D([], [], color="gray", marker=m, ls="none", mfc=fc, label=q)
                for q, m, fc in (("float32", "o", "gray"), ("float64", "s", "white")) if any(q == x for _, _, x in lines)]  # fmt: skip
    front = pareto_front([p for p in ok if not p.planner])
    if front:
        (h,) = ax.step([p.cost for p in front], [p.error for p in front], where="post", color="black", lw=2, alpha=0.35,
                       label="Pareto front (least error for the time)")  # fmt: skip
        handles.append(h)
    for p in ok:
        if p.planner:
            (h,) = ax.plot([p.cost], [p.error], "*", ms=18, color="gold", mec="black", zorder=5, ls="none",
                           label=f"planner default: order {p.order}, {p.ppw:.1f} ppw, dt = {p.cfl_fraction:.2f} CFL, {p.precision}")
            handles.append(h)
    ax.set_xscale("log")
    ax.set_yscale("log")
    on_cpu = bool(points) and points[0].device == "cpu"
    ax.set_xlabel("CPU time per shot (core-seconds, best of runs)" if on_cpu else "wall time per shot (s), best of runs")
    ax.set_ylabel("relative L2 error of the traces vs the analytic solution")
    dev = points[0].device if points else ""
    ax.set_title(f"speed vs accuracy: 2D homogeneous, offsets 2.3-4.5 wavelengths, {dev}{f' ({device_name})' if device_name else ''}\n"
                 "numbers: points per minimum wavelength (f_max = Ricker -20 dB)", fontsize=10)  # fmt: skip
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(handles=handles, fontsize=8, loc="upper right")
    return save_figure(fig, path)


def markdown(points) -> str:
    """A table of every point, the Pareto front marked."""
    front = {id(p) for d in dict.fromkeys(p.device for p in points) for p in pareto_front([q for q in points if q.device == d and not q.planner])}
    lines = ["# Speed/accuracy sweep", "",
             f"2D homogeneous {C:g} m/s, Ricker {PEAK_FREQUENCY:g} Hz, {LENGTH:g} m square, record {RECORD:g} s; error = relative "
             "L2 of the 3 traces vs the analytic solution; seconds = best wall time per shot (setup included), CPU s = least "
             "process CPU time (the Pareto front uses CPU s on the CPU, seconds on CUDA).",
             "", "| device | order | precision | ppw | dt / CFL limit | dx (m) | dt (ms) | nt | error | seconds | CPU s | Pareto | note |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for p in points:
        err = "" if p.error is None else f"{p.error:.3g}"
        sec = " | " if p.seconds is None else f"{p.seconds:.3g} | {p.cpu_seconds:.3g}"
        note = "planner default" if p.planner else ("" if p.status == "ok" else p.status)
        lines.append(f"| {p.device} | {p.order} | {p.precision} | {p.ppw:.3g} | {p.cfl_fraction:.2f} | {p.dx:.3g} | {1e3 * p.dt:.3g} | "
                     f"{p.nt} | {err} | {sec} | {'yes' if id(p) in front else ''} | {note} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def write_outputs(outdir, points, machine: dict) -> list[pathlib.Path]:
    """speed_accuracy.json, speed_accuracy.md and one chart per device, written atomically."""
    from adseismic.data.atomic import write_text_atomic

    outdir = pathlib.Path(outdir)
    devices = list(dict.fromkeys(p.device for p in points))
    payload = {"machine": machine, "scene": {"velocity": C, "peak_frequency": PEAK_FREQUENCY, "f_max": f_max(), "length": LENGTH,
               "record": RECORD, "source": SOURCE, "receivers": RECEIVERS, "pml_width": PML},
               "points": [asdict(p) for p in points]}  # fmt: skip
    paths = [outdir / "speed_accuracy.json", outdir / "speed_accuracy.md"]
    write_text_atomic(paths[0], json.dumps(payload, indent=1) + "\n")
    write_text_atomic(paths[1], markdown(points))
    for d in devices:
        paths.append(plot(outdir / chart_name(d, devices), [p for p in points if p.device == d], machine.get("devices", {}).get(d, "")))
    return paths
