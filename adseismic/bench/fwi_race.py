"""``adseismic bench --fwi``: the same FWI run by adseismic and by Deepwave + torch.optim.LBFGS, one process.

The scene (issue 22): an 8 km x 3 km crop of Marmousi-II (data/marmousi2) on a 20 m grid (151 x 401 nodes), the
start model its slowness smoothed over 300 m, N shots (default 32) and a receiver every 20 m, 40 m deep, a 5 Hz Ricker,
4 s records, three low-pass bands (3, 5, 8 Hz), the same iterations a band, velocities bounded to
[1400, 5000] m/s, no free surface (an absorbing boundary all round, as Deepwave's default). Sources and receivers
sit on grid nodes, so both tools inject and record at the same points.

Each tool inverts data it simulated itself from the true model (its own forward operator, so neither inverts
another solver's errors); the data are simulated before the clock starts. Then:
- adseismic: the fwi workflow (inversion.fwi: what ``adseismic fwi`` runs) with its defaults, clocked from loading the
  config to the end (the observed data waiting in the run directory, where a run reads them); the wall time of each
  iteration from the workflow's iteration log records, the model of each iteration from history.h5. The defaults
  include the gradient's depth preconditioning (inversion.preconditioning: the default under this surface
  acquisition); ``--fwi-inversion preconditioning=none`` races without it, as Deepwave's recipe runs.
- Deepwave: ``deepwave.scalar`` (order 4, 20-cell PML) with Deepwave's documented FWI recipe: v = vmin + (vmax -
  vmin) sigmoid(theta), the L2 misfit of the band-passed data normalised by its value at the band's start,
  ``torch.optim.LBFGS(max_iter=iterations, line_search_fn="strong_wolfe")``, one step a band; clocked from the first
  band's start; the model error at every evaluation, tagged with LBFGS's iteration count.
The model error is ||v - v_true|| / ||v_true - v_start|| over the whole grid (1 at the start). Reported: both
curves, the final errors, and `time to Deepwave's final error / Deepwave's total time` (issue 22's target <= 1/2).

Deepwave missing or failing is "reference failed: <reason>" in the report, never our exit status.
"""

from __future__ import annotations

import json
import logging
import math
import pathlib
import re
import time
from dataclasses import asdict, dataclass, field

import numpy as np

log = logging.getLogger(__name__)

MODEL = pathlib.Path(__file__).resolve().parents[2] / "data" / "marmousi2" / "marmousi2_resampled_1601x401_7.5m_kms.f32"
DX, DURATION, F_PEAK, BANDS, BOUNDS, PML = 20.0, 4.0, 5.0, (3.0, 5.0, 8.0), (1400.0, 5000.0), 20
_ITERATION = re.compile(r"band (\d+) \(.*\) iteration (\d+): misfit")


@dataclass
class RaceScene:
    """The race's settings: shots, iterations a band, device, the crop [x0, x1] (m) and depth (m) of the section,
    grid spacing dx (m), record duration (s), low-pass band corners (Hz)."""

    shots: int = 32
    iterations: int = 20
    device: str = "cpu"
    x_range: tuple = (3000.0, 11000.0)
    depth: float = 3000.0
    dx: float = DX
    duration: float = DURATION
    bands: tuple = BANDS
    inversion: dict = field(default_factory=dict)  # our inversion keys over the defaults (an "option" of the race)


@dataclass
class Curve:
    """One tool's run: seconds (wall, from its start), error (relative model error, 1 at the start), band and
    iteration of each point; total seconds, evaluations, the gradient's preconditioning, and the failure reason of a
    reference that did not run."""

    engine: str
    seconds: list = field(default_factory=list)
    error: list = field(default_factory=list)
    band: list = field(default_factory=list)
    iteration: list = field(default_factory=list)
    total_seconds: float = math.nan
    evaluations: int = 0
    preconditioning: str = "none"
    failed: str | None = None

    @property
    def final_error(self) -> float:
        return self.error[-1] if self.error else math.nan


def _points(count: int, lo: float, hi: float, dx: float, depth: float) -> list:
    """count points on grid nodes from lo to hi (m) at depth (m), as config points."""
    xs = np.rint(np.linspace(lo, hi, count) / dx) * dx
    return [{"x": float(x), "z": depth} for x in xs]


def race_config(sc: RaceScene, true_model: bool) -> dict:
    """The forward (true_model=True: the true model) or fwi (the smoothed start model) config of the race."""
    x0, x1 = sc.x_range
    model = {"kind": "raw", "path": str(MODEL), "shape": [1601, 401], "axes": "xz", "units": "km/s", "spacing": 7.5,
             "crop": {"x": [x0, x1], "z": [0.0, sc.depth]}}  # fmt: skip
    cfg = {
        "model": model if true_model else {**model, "smoothing": 300.0},
        "geometry": {"sources": {"points": _points(sc.shots, x0 + 100, x1 - 100, sc.dx, 2 * sc.dx)},
                     "receivers": {"points": _points(int((x1 - x0) / sc.dx) - 1, x0 + sc.dx, x1 - sc.dx, sc.dx, 2 * sc.dx)}},
        "wavelet": {"kind": "ricker", "peak_frequency": F_PEAK},
        "simulation": {"order": 4, "dx": sc.dx, "duration": sc.duration, "domain": "model", "pml_width": PML,
                       "free_surface": False, "device": sc.device, "precision": "float32"},
    }  # fmt: skip
    if not true_model:
        cfg["inversion"] = {"bands": list(sc.bands), "iterations": sc.iterations, "bounds": list(BOUNDS), **sc.inversion}
    return cfg


def fwi_config(sc: RaceScene) -> dict:
    """Our fwi config of the race: the start model, and the true model to simulate the observed data from."""
    cfg = race_config(sc, False)
    cfg["true_model"] = race_config(sc, True)["model"]
    return cfg


def relative_errors(models, v_true, v_start) -> list[float]:
    ref = float(np.linalg.norm(v_true - v_start))
    return [float(np.linalg.norm(np.asarray(m, float) - v_true)) / ref for m in models]


def run_ours(sc: RaceScene, workdir: pathlib.Path) -> tuple[Curve, dict]:
    """Simulate the observed data as `adseismic fwi` would from its true_model and leave them where the run reads
    them (RUNDIR/observed.h5), then clock `adseismic fwi`. Returns the curve and the arrays the reference needs (true
    and start model, wavelet, geometry in grid indices, dt) on the fwi's grid."""
    import h5py
    import yaml

    from adseismic.config import load_fwi_config
    from adseismic.data.atomic import write_h5_atomic
    from adseismic.inversion.fwi import prepare_fwi, read_history, run_fwi
    from adseismic.solve.acoustic import forward

    rundir, cfg_path = workdir / "ours", workdir / "fwi.yaml"
    rundir.mkdir(parents=True, exist_ok=True)
    cfg_path.write_text(yaml.safe_dump(fwi_config(sc)))
    config = load_fwi_config(cfg_path)
    prep = prepare_fwi(config)
    p, scene = prep.plan, prep.scene
    v_true = np.asarray(config.true_model.resample(p.dx, p.origin, p.shape).values, float)
    v_start = np.asarray(scene.model.values, float)
    log.info("simulating adseismic's observed data (%d shots, %d steps)", sc.shots, p.nt)
    data = forward(v_true, p.dx, p.dt, scene.source_amplitudes, scene.source_locations, scene.receiver_locations, order=p.order,
                   pml_width=p.pml_width, pml_reflection=p.pml_reflection, free_surface=p.free_surface, device=p.device,
                   precision=p.precision).receiver_amplitudes  # fmt: skip
    write_h5_atomic(rundir / "observed.h5", lambda f: f.create_dataset("data", data=data))
    stamps = []

    class Stamp(logging.Handler):
        def emit(self, record):
            m = _ITERATION.search(record.getMessage())
            if m:
                stamps.append((time.perf_counter(), int(m.group(1)), int(m.group(2))))

    handler = Stamp(logging.INFO)
    fwi_log = logging.getLogger("adseismic.inversion")
    level = fwi_log.level
    fwi_log.addHandler(handler)
    fwi_log.setLevel(logging.INFO)
    log.info("adseismic fwi: %d bands x %d iterations", len(sc.bands), sc.iterations)
    t0 = time.perf_counter()  # what `adseismic fwi` runs after its checks: the plan and the inversion
    try:
        run_fwi(config, rundir, progress=False)  # (it plans again: part of what a run costs)
    finally:
        fwi_log.removeHandler(handler)
        fwi_log.setLevel(level)
    total = time.perf_counter() - t0
    history = {(r["band"], r["iteration"]): r["model"] for r in read_history(rundir / "history.h5")}
    curve = Curve("adseismic", seconds=[0.0], error=[1.0], band=[0], iteration=[0], total_seconds=total,
                  preconditioning=config.inversion.preconditioning)
    errors = relative_errors([history[(b, i)] for _, b, i in stamps], v_true, v_start)
    for (t, b, i), e in zip(stamps, errors):
        curve.seconds.append(t - t0)
        curve.error.append(e)
        curve.band.append(b)
        curve.iteration.append(i)
    curve.evaluations = _evaluations(rundir / "summary.json")
    with h5py.File(rundir / "model.h5", "r") as f:  # the last point: the final model
        curve.error[-1] = relative_errors([f["model"][...]], v_true, v_start)[0]
    arrays = {"v_true": v_true, "v_start": v_start, "dt": p.dt, "nt": scene.source_amplitudes.shape[-1],
              "wavelet": np.asarray(scene.wavelet, float), "sources": np.rint(scene.source_locations / p.dx).astype(int),
              "receivers": np.rint(scene.receiver_locations / p.dx).astype(int), "dx": p.dx}  # fmt: skip
    return curve, arrays


def _evaluations(summary: pathlib.Path) -> int:
    try:
        return sum(int(b["evaluations"]) for b in json.loads(summary.read_text())["bands"])
    except (OSError, KeyError, ValueError):
        return 0


def run_deepwave_fwi(sc: RaceScene, a: dict) -> Curve:
    """Deepwave's FWI of its own data on the same grid, geometry, wavelet, bands and iterations (see the module)."""
    import deepwave
    import torch

    from adseismic.inversion.fwi import band_filter

    dev = torch.device(sc.device)
    dx, dt, lo, hi = a["dx"], a["dt"], *BOUNDS

    def tensor(x):
        return torch.tensor(np.ascontiguousarray(x), dtype=torch.float32, device=dev)

    src = torch.tensor(a["sources"], device=dev)
    rec = torch.tensor(a["receivers"], device=dev)
    full = np.broadcast_to(a["wavelet"], (len(a["sources"]), a["sources"].shape[1], a["nt"]))

    def simulate(v, amp, band):
        return deepwave.scalar(v, dx, dt, source_amplitudes=amp, source_locations=src, receiver_locations=rec,
                               accuracy=4, pml_width=PML, pml_freq=band / 2)[-1]  # fmt: skip

    with torch.no_grad():
        observed = simulate(tensor(a["v_true"]), tensor(full), F_PEAK).cpu().numpy()
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
    start = np.clip((a["v_start"] - lo) / (hi - lo), 1e-6, 1 - 1e-6)
    theta = torch.nn.Parameter(tensor(np.log(start / (1 - start))))
    curve = Curve("deepwave", seconds=[0.0], error=[1.0], band=[0], iteration=[0])
    ref = float(np.linalg.norm(a["v_true"] - a["v_start"]))
    t0 = time.perf_counter()
    for b, f_high in enumerate(sc.bands):
        amp = tensor(band_filter(full, dt, (None, f_high)))
        obs = tensor(band_filter(observed, dt, (None, f_high)))
        opt = torch.optim.LBFGS([theta], max_iter=sc.iterations, line_search_fn="strong_wolfe")
        scale = []

        def closure(amp=amp, obs=obs, scale=scale, b=b, f_high=f_high, opt=opt):
            opt.zero_grad()
            v = lo + (hi - lo) * torch.sigmoid(theta)
            loss = ((simulate(v, amp, f_high) - obs) ** 2).sum()
            if not scale:
                scale.append(loss.item())
            loss = loss / scale[0]
            loss.backward()
            err = float(torch.linalg.vector_norm(v.detach() - tensor(a["v_true"]))) / ref
            curve.seconds.append(time.perf_counter() - t0)
            curve.error.append(err)
            curve.band.append(b)
            curve.iteration.append(int(opt.state[theta].get("n_iter", 0)))
            curve.evaluations += 1
            return loss

        opt.step(closure)
        log.info("deepwave band %d (<= %g Hz): %d evaluations, error %.4f", b, f_high, curve.evaluations, curve.error[-1])
    curve.total_seconds = time.perf_counter() - t0
    return curve


def time_to_reach(ours: Curve, target: float) -> float:
    """Seconds our run needed to reach a model error <= target (nan if it never did)."""
    return next((t for t, e in zip(ours.seconds, ours.error) if e <= target), math.nan)


def race(sc: RaceScene, workdir: pathlib.Path, deepwave: bool) -> dict:
    """Run both and return the report dict (curves, final errors, the time ratio)."""
    ours, arrays = run_ours(sc, workdir)
    if deepwave:
        try:
            ref = run_deepwave_fwi(sc, arrays)
        except Exception as exc:  # a reference failure is reported, never ours
            log.warning("deepwave failed: %s: %s", type(exc).__name__, exc)
            ref = Curve("deepwave", failed=f"reference failed: {type(exc).__name__}: {str(exc)[:200]}")
    else:
        ref = Curve("deepwave", failed="reference failed: deepwave not installed (or --no-deepwave)")
    reach = time_to_reach(ours, ref.final_error) if ref.failed is None else math.nan
    return {"scene": asdict(sc), "ours": asdict(ours), "deepwave": asdict(ref), "our_final_error": ours.final_error,
            "deepwave_final_error": ref.final_error, "our_seconds_to_deepwave_error": reach,
            "ratio_to_deepwave_total": reach / ref.total_seconds if ref.failed is None else math.nan}  # fmt: skip


def markdown(report: dict) -> str:
    """The race as a markdown table (per band: iterations, seconds, error) and the headline ratios."""
    ours, ref = report["ours"], report["deepwave"]
    lines = ["| engine | band | last iteration | seconds (from start) | model error |", "|---|---|---|---|---|"]
    for c in (ours, ref):
        if c["failed"]:
            lines.append(f"| {c['engine']} | - | - | - | {c['failed']} |")
            continue
        for b in sorted(set(c["band"])):
            k = max(i for i, bb in enumerate(c["band"]) if bb == b)
            lines.append(f"| {c['engine']} | {b} | {c['iteration'][k]} | {c['seconds'][k]:.1f} | {c['error'][k]:.4f} |")
    options = ", ".join(f"{k}: {v}" for k, v in report["scene"]["inversion"].items()) or "defaults"
    if "preconditioning" not in report["scene"]["inversion"]:
        options += f"; preconditioning {ours['preconditioning']}"
    lines += ["", f"- adseismic ({options}): {ours['total_seconds']:.1f} s, "
                  f"{ours['evaluations']} evaluations, final error {report['our_final_error']:.4f}"]
    if not ref["failed"]:
        lines += [f"- Deepwave (its recipe: preconditioning {ref['preconditioning']}): {ref['total_seconds']:.1f} s, "
                  f"{ref['evaluations']} evaluations, final error {report['deepwave_final_error']:.4f}",
                  f"- adseismic reached Deepwave's final error after {report['our_seconds_to_deepwave_error']:.1f} s: "
                  f"{report['ratio_to_deepwave_total']:.2f} x Deepwave's total time (target <= 0.5)"]  # fmt: skip
    return "\n".join(lines) + "\n"


def plot(path: pathlib.Path, report: dict) -> None:
    """Model error against wall time for both tools."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from adseismic.data.atomic import atomic_write

    fig, ax = plt.subplots(figsize=(6, 4))
    for c in (report["ours"], report["deepwave"]):
        if not c["failed"]:
            label = f"{c['engine']} ({c['evaluations']} evaluations, preconditioning {c['preconditioning']})"
            ax.plot(c["seconds"], c["error"], marker=".", label=label)
    ax.set_xlabel("wall time (s)")
    ax.set_ylabel("model error ||v - v_true|| / ||v_start - v_true||")
    ax.set_title(f"FWI race: Marmousi-II, {report['scene']['shots']} shots, {report['scene']['device']}")
    ax.grid(alpha=0.3)
    ax.legend()
    with atomic_write(path) as part:
        fig.savefig(part, format="png", dpi=110)
    plt.close(fig)


def write(outdir: pathlib.Path, report: dict) -> list[pathlib.Path]:
    from adseismic.data.atomic import write_text_atomic

    paths = [outdir / "fwi_race.json", outdir / "fwi_race.md", outdir / "fwi_race.png"]
    write_text_atomic(paths[0], json.dumps(report, indent=1, default=float))
    write_text_atomic(paths[1], markdown(report))
    plot(paths[2], report)
    return paths
