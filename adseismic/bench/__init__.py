"""``adseismic bench``: speed and memory on the standard scenes, beside Deepwave.

Scenes (../shared/docs/reference.md section 6; dx 10 m, dt 1 ms, Ricker 15 Hz, PML 20 cells, float32):

    S600      600 x 600 two-layer (1500/2000 m/s), 1 shot, nt 1000     (CPU default)
    S600x4    the same, 4 shots                                          (CPU default)
    S600x16   the same, 16 shots
    S4000     4000 x 4000 two-layer, 1 shot, nt 500
    S3D400    400^3 two-layer 3D acoustic, 1 shot, nt 500
    E2000     elastic 2000 x 2000 (vp 2000, vs vp/1.8, rho 2200 kg/m^3), 1 shot, nt 500
    E600x16   elastic 600 x 600, 16 shots, nt 1000

The physics family (issue 26; ``--physics``, or by name with --scenes; bench/physics.py: models, geometry, Deepwave's
counterparts and the conventions aligned): VD1000 (variable-density acoustic), Q1000 (visco-acoustic), VTI1000
(acoustic VTI), each 1000 x 1000, nt 1000, and E3D200 (3D elastic, 200^3, nt 500), 1 shot each (CUDA default); VD40,
Q40, VTI40 (40 x 40) and E3D16 (16^3), nt 30 (the CPU default: a quick check). Beside the rates, a live Deepwave
forward's receiver data are compared with ours (relative L2 difference and scale, a table of bench.md); without
Deepwave the physics rows say "reference failed: not installed".

Every scene runs "forward" (adseismic.forward) and "gradient" (forward + gradient: adseismic.gradient
with respect to the velocity, default checkpointing). Rate = padded-grid cell updates per second:
prod(n + 2 PML + order over the axes) x nt x shots / seconds, the unit of the Deepwave anchors.
On the CPU the per-core rate divides the cell updates by the process CPU time (user + system)
of the timed run instead of the wall time. On a GPU the model (acoustic velocity, elastic vp, vs, rho) is
passed as device arrays (as Deepwave's benchmark passes CUDA tensors); sources, receivers and wavelets
come from the host. The acoustic traces and gradients then stay on the device (as Deepwave's tensors do),
the elastic traces go back to the host inside the timing. The best of the repeats is
reported: forward then reuses the time loop it captured in the first (as in an inversion loop); the
first repeat's time is in bench.json ("times").

Memory: each (scene, device) runs in its own Python process unless --in-process, so the peak host
resident size (getrusage ru_maxrss) and Warp's CUDA mempool high-water mark are that scene's own
(they include the ~0.2 GB of the interpreter with Warp and NumPy; the gradient's figure is the
maximum of its forward and gradient, i.e. the gradient's). With --in-process both are process-wide
high-water marks (labelled so). The gradient's own model of its peak (GradientResult.
peak_bytes_estimate) is reported beside them.

Deepwave: when it is installed the same scenes run through it in the same worker, after ours (our
rows are printed first, so a Deepwave that kills the worker does not lose them); otherwise the rates
recorded in reference.md (H200 and a 2-core CPU VM) are printed as reference anchors, labelled as
recorded figures. A Deepwave run that fails (out of memory, torch or Deepwave broken, any exception,
the worker killed) is reported in the table as "reference failed: <reason>" and does not change the
exit status: only a failure of ours exits 1.

Elastic scenes run through ``adseismic.elastic`` (:func:`run_elastic`: a vertical line force, vz
recorded, gradient with respect to vp, vs and rho).

Outputs in -o DIR (each written atomically): bench.json (rows + machine), bench.md (table),
bench.png (Gcell/s per scene and device with the Deepwave anchors), bench.log. ``--suite
speed-accuracy`` or ``all`` runs the sweep of :mod:`adseismic.speed_accuracy` (speed_accuracy.json,
speed_accuracy.md, speed_accuracy_<device>.png).
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import logging
import math
import os
import pathlib
import platform
import resource
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from types import SimpleNamespace

import numpy as np
import yaml

from adseismic.bench import physics
from adseismic.data.atomic import write_text_atomic
from adseismic.runs import EXIT_ERROR, EXIT_OK, CommandError, RunLog, version

log = logging.getLogger("adseismic.bench")

DX, DT, PEAK_FREQUENCY, PML = 10.0, 1e-3, 15.0, 20  # m, s, Hz, cells
MODES = ("forward", "gradient")
ORDERS = (2, 4, 8)
SUITES = ("scenes", "speed-accuracy", "all")
EST_RATE = {"cpu": 2.5e7, "cuda": 3.0e10}  # forward cell updates/s for time estimates (as scene.EST_RATE)
EST_GRADIENT_FACTOR = 4.0  # forward+gradient time / forward time (docs/benchmarks.md: 3.6)
EST_KIND_FACTOR = {"elastic": 3.0, "elastic3d": 5.0, "viscoacoustic": 2.0, "vti": 1.5, "acoustic_vd": 1.3}  # cell update / acoustic's
WORKER_MARK = "ADSEISMIC_BENCH_ROWS "  # prefix of the worker's result line on stdout


@dataclass(frozen=True)
class SceneSpec:
    """A standard scene. shape: physical cells (z, [y,] x); nt: steps of dt = 1 ms; kind:
    "acoustic" (two layers, 1500 m/s above 2000 m/s) or "elastic" (homogeneous)."""

    name: str
    kind: str
    shape: tuple
    shots: int
    nt: int
    cpu_default: bool
    description: str
    family: str = "standard"  # "standard" (the default selection, `--scenes all`) or "physics" (`--physics`, physics.py)
    gpu_default: bool = True  # in the default selection of its family on a GPU


SCENES = {s.name: s for s in (
    SceneSpec("S600", "acoustic", (600, 600), 1, 1000, True, "600x600 two-layer, 1 shot"),
    SceneSpec("S600x4", "acoustic", (600, 600), 4, 1000, True, "600x600 two-layer, 4 shots"),
    SceneSpec("S600x16", "acoustic", (600, 600), 16, 1000, False, "600x600 two-layer, 16 shots"),
    SceneSpec("S4000", "acoustic", (4000, 4000), 1, 500, False, "4000x4000 two-layer, 1 shot"),
    SceneSpec("S3D400", "acoustic", (400, 400, 400), 1, 500, False, "400^3 two-layer 3D, 1 shot"),
    SceneSpec("E2000", "elastic", (2000, 2000), 1, 500, False, "elastic 2000x2000, 1 shot"),
    SceneSpec("E600x16", "elastic", (600, 600), 16, 1000, False, "elastic 600x600, 16 shots"),
    SceneSpec("VD1000", "acoustic_vd", (1000, 1000), 1, 1000, False, "variable-density acoustic 1000x1000", "physics"),
    SceneSpec("Q1000", "viscoacoustic", (1000, 1000), 1, 1000, False, "visco-acoustic 1000x1000", "physics"),
    SceneSpec("VTI1000", "vti", (1000, 1000), 1, 1000, False, "acoustic VTI 1000x1000", "physics"),
    SceneSpec("E3D200", "elastic3d", (200, 200, 200), 1, 500, False, "elastic 3D 200^3", "physics"),
    SceneSpec("VD40", "acoustic_vd", (40, 40), 1, 30, True, "variable-density acoustic 40x40 (CPU test)", "physics", False),
    SceneSpec("Q40", "viscoacoustic", (40, 40), 1, 30, True, "visco-acoustic 40x40 (CPU test)", "physics", False),
    SceneSpec("VTI40", "vti", (40, 40), 1, 30, True, "acoustic VTI 40x40 (CPU test)", "physics", False),
    SceneSpec("E3D16", "elastic3d", (16, 16, 16), 1, 30, True, "elastic 3D 16^3 (CPU test)", "physics", False),
)}  # fmt: skip


@dataclass(frozen=True)
class Anchor:
    """Deepwave 0.1.0 rates recorded in reference.md section 6 (cell updates/s; bytes)."""

    scene: str
    order: int
    device_kind: str  # "cpu" (2-core VM) or "cuda" (H200)
    forward: float
    gradient: float
    gradient_peak_bytes: float

    @property
    def where(self) -> str:
        return "reference.md, H200" if self.device_kind == "cuda" else "reference.md, 2-core CPU"

    @property
    def label(self) -> str:
        return f"Deepwave ({self.where})"


ANCHORS = (
    Anchor("S600", 4, "cpu", 2.08e9, 0.20e9, 1.96e9),
    Anchor("S600x4", 4, "cpu", 2.16e9, 0.115e9, 6.8e9),
    Anchor("S600", 8, "cpu", 1.58e9, 0.118e9, 1.99e9),
    Anchor("S600", 4, "cuda", 29.7e9, 13.7e9, 1.6e9),
    Anchor("S600x16", 4, "cuda", 87.5e9, 31.5e9, 25.9e9),
    Anchor("S4000", 4, "cuda", 109.6e9, 37.1e9, 32.9e9),
    Anchor("S4000", 8, "cuda", 104.3e9, 30.8e9, 33.0e9),
    Anchor("E2000", 4, "cuda", 19.8e9, 8.4e9, 16.8e9),
    Anchor("E600x16", 4, "cuda", 21.3e9, 8.9e9, 51.6e9),
)
ANCHOR_CPU_CORES = 2  # the CPU anchors ran on a 2-core VM


def anchor_for(scene: str, order: int, device_kind: str) -> Anchor | None:
    return next((a for a in ANCHORS if (a.scene, a.order, a.device_kind) == (scene, order, device_kind)), None)


def device_kind(device: str) -> str:
    return "cuda" if device.startswith("cuda") else "cpu"


def padded_cells(spec: SceneSpec, order: int) -> int:
    """Cells of one shot's padded grid: PML on every side plus the stencil halo order/2 per side."""
    return math.prod(n + 2 * PML + order for n in spec.shape)


def estimate_seconds(spec: SceneSpec, nt: int, device: str, modes, repeat: int) -> float:
    """Rough wall time of one scene on a device (all modes, repeats and a warm-up), from EST_RATE."""
    rate = EST_RATE[device_kind(device)] / EST_KIND_FACTOR.get(spec.kind, 1.0)
    once = padded_cells(spec, 4) * nt * spec.shots / rate
    per_mode = {"forward": 1.0, "gradient": EST_GRADIENT_FACTOR}
    return once * (repeat * sum(per_mode[m] for m in modes) + 1)  # + 1: the untimed forward a gradient needs


# --------------------------------------------------------------------------------- scenes

@dataclass
class SceneArrays:
    """Inputs of one scene. model: {"velocity"} (m/s) or {"vp", "vs" (m/s), "rho" (kg/m^3)}, each
    of spec.shape; sources (shots, 1, ndim) m; receivers (shots, n_rec, ndim) m (axis order z,[y,]x);
    amplitudes (shots, 1, nt), a Ricker wavelet."""

    spec: SceneSpec
    nt: int
    model: dict
    sources: np.ndarray
    receivers: np.ndarray
    amplitudes: np.ndarray


def build_arrays(spec: SceneSpec, nt: int | None = None) -> SceneArrays:
    """Model and acquisition of a scene: sources 20 m deep spread along x (one at the centre for a
    single shot; y = centre in 3D), receivers 20 m deep at every second cell along x."""
    from adseismic.wavelets import ricker

    nt = spec.nt if nt is None else int(nt)
    shape, shots = spec.shape, spec.shots
    amp = np.broadcast_to(ricker(PEAK_FREQUENCY, nt, DT), (shots, 1, nt)).copy()
    if spec.family == "physics":  # on-node sources and receivers (bench/physics.py)
        return SceneArrays(spec, nt, *physics.scene(spec.kind, shape, DX), amp)
    nx = shape[-1]
    if spec.kind == "acoustic":
        v = np.full(shape, 1500.0)
        v[shape[0] // 2:] = 2000.0
        model = {"velocity": v}
    else:
        vp = np.full(shape, 2000.0)
        model = {"vp": vp, "vs": vp / 1.8, "rho": np.full(shape, 2200.0)}
    xs = np.linspace(100.0, (nx - 11) * DX, shots) if shots > 1 else np.array([nx * DX / 2])
    xr = np.linspace(0.0, (nx - 1) * DX, nx // 2)
    mid = [(shape[1] - 1) * DX / 2] if len(shape) == 3 else []
    src = np.array([[[20.0, *mid, x]] for x in xs])
    rec = np.broadcast_to(np.array([[20.0, *mid, x] for x in xr]), (shots, len(xr), len(shape))).copy()
    return SceneArrays(spec, nt, model, src, rec, amp)


def small_version(spec: SceneSpec) -> SceneSpec:
    """A 1-shot scene of the same kind and dimension, at most 40 cells an axis and 20 steps (kernel compile warm-up)."""
    return SceneSpec(spec.name + "-warmup", spec.kind, tuple(min(40, n) for n in spec.shape), 1, min(20, spec.nt), True, "warm-up",
                     spec.family)  # fmt: skip


# --------------------------------------------------------------------------------- engines

def run_elastic(mode: str, a: SceneArrays, device: str, order: int, memory_budget, observed=None):
    """adseismic.elastic on an elastic scene: a vertical line force, vz recorded (the receiver data
    and the gradient's misfit use vz only). vp, vs, rho in a.model: NumPy or Warp arrays (run_job passes
    float32 device arrays on a GPU, as for the acoustic velocity). Returns an object with
    receiver_amplitudes (forward) or the ElasticGradient (gradient, wrt vp, vs, rho)."""
    from adseismic.solve import elastic as api

    m = a.model
    force = np.broadcast_to([1.0, 0.0], (*a.sources.shape[:2], 2))
    args = (m["vp"], m["vs"], m["rho"], DX, DT, a.amplitudes, a.sources, a.receivers)
    kw = dict(source_type="force", source_components=force, order=order, pml_width=PML, device=device)
    if mode == "forward":
        return SimpleNamespace(receiver_amplitudes=api.forward_elastic(*args, **kw).vz)
    return api.gradient_elastic(*args, {"vz": observed}, components=("vz",), memory_budget=memory_budget, **kw)


def run_acoustic(mode: str, a: SceneArrays, device: str, order: int, memory_budget, observed=None, segment_length=None):
    """adseismic.forward or adseismic.gradient (wrt velocity, L2 misfit against ``observed``)."""
    from adseismic.solve.acoustic import forward, gradient

    args = (a.model["velocity"], DX, DT, a.amplitudes, a.sources, a.receivers)
    kw = dict(order=order, pml_width=PML, device=device)
    if mode == "forward":
        return forward(*args, **kw)
    return gradient(*args, observed, memory_budget=memory_budget, segment_length=segment_length, **kw)


def run_deepwave(mode: str, a: SceneArrays, device: str, order: int):
    """The same scene through Deepwave (scalar or elastic; a physics scene's counterpart, physics_reference),
    returning a callable that runs it once (forward, or forward + backward of the summed squared receiver data) and
    synchronises."""
    import torch

    dev = torch.device(device)
    grad = mode == "gradient"
    if a.spec.family == "physics":
        call = physics_reference(a, device, order, grad)
    else:
        call = _standard_reference(a, dev, order, grad)

    def once():
        out = call()
        if grad:
            sum((o**2).sum() for o in out).backward()
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    return once


def _standard_reference(a: SceneArrays, dev, order: int, grad: bool):
    """Deepwave's scalar (acoustic scenes) or 2D elastic run of a standard scene on torch device dev: a callable
    returning its receiver tensors, the models requiring grad when `grad`."""
    import deepwave
    import torch

    def tensor(x, requires_grad=False):
        return torch.tensor(np.asarray(x), dtype=torch.float32, device=dev, requires_grad=requires_grad)

    def index(loc):  # metres -> nearest grid index (Deepwave takes integer cell locations)
        return torch.tensor(np.rint(np.asarray(loc) / DX).astype(np.int64), device=dev)

    amp, src, rec = tensor(a.amplitudes), index(a.sources), index(a.receivers)
    if a.spec.kind == "acoustic":
        v = tensor(a.model["velocity"], grad)

        def call():
            return deepwave.scalar(v, DX, DT, source_amplitudes=amp, source_locations=src,
                                   receiver_locations=rec, accuracy=order, pml_width=PML)[-1:]
    else:
        vp, vs, rho = (tensor(a.model[k], grad) for k in ("vp", "vs", "rho"))

        def call():
            lamb, mu, buoyancy = deepwave.common.vpvsrho_to_lambmubuoyancy(vp, vs, rho)
            return deepwave.elastic(lamb, mu, buoyancy, DX, DT, source_amplitudes_y=amp, source_locations_y=src,
                                    receiver_locations_y=rec, accuracy=order, pml_width=PML)[-3:]
    return call


def physics_reference(a: SceneArrays, device: str, order: int, grad: bool):
    """Deepwave's counterpart of a physics scene (physics.deepwave_call): a callable returning (receiver tensor,)."""
    return physics.deepwave_call(a.spec.kind, grad, a.model, DX, DT, a.amplitudes, a.sources, a.receivers, device=device,
                                 order=order, pml_width=PML, f_peak=PEAK_FREQUENCY)  # fmt: skip


def deepwave_available() -> bool:
    """Whether Deepwave is installed (found, not imported: an installation that fails to import
    is run anyway and reported as "reference failed: ImportError: ..." in its rows)."""
    import importlib.util

    try:
        return importlib.util.find_spec("deepwave") is not None
    except (ImportError, ValueError):
        return False


# --------------------------------------------------------------------------------- rows

@dataclass
class BenchRow:
    """One (scene, engine, device, mode) measurement. seconds: best of ``times`` (s); rate: padded
    cell updates per second; rate_per_core: cell updates per CPU-second (CPU only); peaks in bytes;
    peak_estimate_bytes: the gradient's own model of its peak (adseismic only); status "ok",
    "skipped: why", "failed: why" (ours) or "reference failed: why" (a Deepwave row). A physics scene's Deepwave
    forward row: reference_l2, the relative L2 difference of our receiver data from Deepwave's, and reference_scale,
    the least-squares a of ours ~ a Deepwave (physics.difference), or reference_note why they are missing."""

    scene: str
    kind: str
    engine: str
    device: str
    device_name: str
    mode: str
    order: int
    shape: tuple
    shots: int
    nt: int
    nt_reference: int
    padded_cells: int
    status: str = "ok"
    seconds: float | None = None
    times: list = field(default_factory=list)
    rate: float | None = None
    cpu_seconds: float | None = None
    rate_per_core: float | None = None
    peak_host_rss_bytes: int | None = None
    peak_device_bytes: int | None = None
    device_memory_source: str = ""
    memory_scope: str = ""
    peak_estimate_bytes: int | None = None
    segments: str = ""
    reference_l2: float | None = None
    reference_scale: float | None = None
    reference_note: str = ""

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def cell_updates(self) -> int:
        return self.padded_cells * self.nt * self.shots


@dataclass
class BenchJob:
    """One (scene, device) unit of work, run in a worker process or in-process."""

    scene: str
    device: str
    modes: tuple
    order: int
    nt: int
    repeat: int
    memory_budget: float | None
    deepwave: bool
    memory_scope: str


def _host_peak() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB


def _cpu_time() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _device_pool_peak(device: str) -> int | None:
    """Warp's CUDA mempool high-water mark (bytes, process-wide), or None (CPU, no mempool)."""
    import warp as wp

    if device_kind(device) != "cuda":
        return None
    try:
        return int(wp.get_mempool_used_mem_high(device)) if wp.is_mempool_enabled(device) else None
    except (RuntimeError, ValueError):
        return None


def _timed(fn, repeat: int, sync):
    """(best seconds, all times, CPU seconds of the best run, last result) of ``repeat`` calls of fn."""
    times, cpus, out = [], [], None
    for _ in range(repeat):
        sync()
        c0, t0 = _cpu_time(), time.perf_counter()
        out = fn()
        sync()
        times.append(time.perf_counter() - t0)
        cpus.append(_cpu_time() - c0)
    best = int(np.argmin(times))
    return times[best], times, cpus[best], out


def _failure(exc: BaseException, prefix: str = "failed") -> str:
    text = str(exc).strip()
    return (f"{prefix}: {type(exc).__name__}" + (f": {text.splitlines()[0]}" if text else ""))[:300]


REFERENCE_FAILED = "reference failed"  # status of a Deepwave row that did not run: never our failure


def _reference_failure(exc: BaseException) -> str:
    return _failure(exc, REFERENCE_FAILED)


def is_our_failure(row) -> bool:
    """A failed measurement of ours (exit status 1); a failed reference (Deepwave) is reported only."""
    return row.engine == "adseismic" and row.status.startswith("failed")


def run_job(job: BenchJob, emit=None) -> list[BenchRow]:
    """Warm up, then time every mode of one scene on one device (and through Deepwave when asked).
    emit(rows), when given, gets our rows before Deepwave runs (a worker prints them, so that a
    reference that kills the process does not take our measurements with it)."""
    import warp as wp

    from adseismic.solve.common import resolve_device

    device = resolve_device(job.device)
    spec = SCENES[job.scene]
    name = wp.get_device(device).name
    base = dict(scene=spec.name, kind=spec.kind, device=device, device_name=name, order=job.order, shape=tuple(spec.shape),
                shots=spec.shots, nt=job.nt, nt_reference=spec.nt, padded_cells=padded_cells(spec, job.order))  # fmt: skip
    rows = []

    def engine(mode, a, observed=None, segment_length=None):
        if spec.family == "physics":
            return physics.run_ours(spec.kind, mode, a.model, DX, DT, a.amplitudes, a.sources, a.receivers, device=device,
                                    order=job.order, pml_width=PML, f_peak=PEAK_FREQUENCY, memory_budget=job.memory_budget,
                                    observed=observed, segment_length=segment_length)  # fmt: skip
        if spec.kind == "elastic":
            return run_elastic(mode, a, device, job.order, job.memory_budget, observed)
        return run_acoustic(mode, a, device, job.order, job.memory_budget, observed, segment_length)

    def sync():
        wp.synchronize_device(device)

    a = build_arrays(spec, job.nt)
    ours = a
    if device_kind(device) == "cuda":  # the model (velocity; vp, vs, rho) on the device, as Deepwave's tensors are
        ours = replace(a, model={k: wp.array(v, dtype=wp.float32, device=device) for k, v in a.model.items()})
    try:  # compile (or load from Warp's kernel cache) every kernel outside the timings
        w = build_arrays(small_version(spec))
        fw = engine("forward", w)
        if "gradient" in job.modes:
            engine("gradient", w, np.zeros_like(fw.receiver_amplitudes), segment_length=None if spec.kind == "elastic" else 5)
    except Exception as exc:  # a broken engine fails its rows, not the whole benchmark
        rows = [BenchRow(engine="adseismic", mode=m, status=_failure(exc), **base) for m in job.modes]
        return rows + (_deepwave_rows_guarded(job, a, base, emit, rows) if job.deepwave else [])

    def zero_data(shape):
        # the gradient's observed data: on a GPU's acoustic and acoustic_vd scenes a device array, as an FWI keeps them (the
        # misfit is then formed on the device, as Deepwave's loss is; a host array would add its copies)
        if device_kind(device) == "cuda" and spec.kind in ("acoustic", "acoustic_vd"):
            return wp.zeros(shape, dtype=wp.float64, device=device)
        return np.zeros(shape)

    observed = traces = None  # traces: our forward's receiver data of a physics scene (the accuracy against Deepwave)
    for mode in job.modes:
        row = BenchRow(engine="adseismic", mode=mode, memory_scope=job.memory_scope, **base)
        rows.append(row)
        try:
            if mode == "gradient" and observed is None:
                observed = zero_data(engine("forward", ours).receiver_amplitudes.shape)
            row.seconds, row.times, row.cpu_seconds, out = _timed(lambda: engine(mode, ours, observed), job.repeat, sync)
        except Exception as exc:
            row.status = _failure(exc)
            log.error("%s %s on %s: %s", spec.name, mode, device, row.status)
            continue
        if mode == "forward":
            observed = zero_data(out.receiver_amplitudes.shape)
            traces = out.receiver_amplitudes if spec.family == "physics" else None
        else:
            est = getattr(out, "peak_bytes_estimate", None)
            row.peak_estimate_bytes = int(est) if est else None
            if getattr(out, "n_segments", None):
                row.segments = f"{out.n_segments} x {out.segment_length}"
        row.rate = row.cell_updates / row.seconds
        if device_kind(device) == "cpu" and row.cpu_seconds > 0:
            row.rate_per_core = row.cell_updates / row.cpu_seconds
        row.peak_host_rss_bytes = _host_peak()
        row.peak_device_bytes = _device_pool_peak(device)
        row.device_memory_source = "Warp CUDA mempool high-water mark" if row.peak_device_bytes is not None else ""
        log.info("%s %s on %s: %.3f s, %.3g cell updates/s", spec.name, mode, device, row.seconds, row.rate)
    if job.deepwave:
        rows += _deepwave_rows_guarded(job, a, base, emit, rows, traces)
    return rows


def _deepwave_rows_guarded(job, a, base, emit, ours, traces=None) -> list[BenchRow]:
    """run_deepwave_rows after emitting ours; whatever goes wrong becomes "reference failed" rows (Deepwave not
    installed: "reference failed: not installed"). traces: our forward's receiver data of a physics scene, compared
    with Deepwave's (reference_accuracy)."""
    if emit is not None:
        emit(ours)

    def failed(status):
        return [BenchRow(engine="deepwave", mode=m, memory_scope=job.memory_scope, status=status, **base) for m in job.modes]

    if not deepwave_available():
        return failed(f"{REFERENCE_FAILED}: not installed")
    _release_warp_pool(job.device)
    try:
        rows = run_deepwave_rows(job, a, base)
    except Exception as exc:  # e.g. torch missing or broken: the reference failed, not us
        return failed(_reference_failure(exc))
    forward = next((r for r in rows if r.mode == "forward" and r.ok), None)
    if traces is not None and forward is not None:
        reference_accuracy(forward, a, job, traces)
    return rows


def _release_warp_pool(device: str) -> None:
    """Hand the memory Warp's CUDA mempool keeps from our freed arrays back to the driver (release threshold 0 for
    one synchronisation, then restored), so that Deepwave's torch allocator can have it."""
    if device_kind(device) != "cuda":
        return
    import gc

    import warp as wp

    gc.collect()
    try:
        old = wp.get_mempool_release_threshold(device)
        wp.set_mempool_release_threshold(device, 0)
        wp.synchronize_device(device)
        wp.set_mempool_release_threshold(device, old)
    except (RuntimeError, ValueError):  # no mempool on this device: nothing kept
        pass


def reference_accuracy(row: BenchRow, a: SceneArrays, job: BenchJob, traces) -> None:
    """Fill row.reference_l2 and reference_scale: our forward's receiver data of a physics scene against one more
    forward of Deepwave's (physics.difference); a failure is noted in row.reference_note, the timing row stays ok."""
    try:
        (out,) = physics_reference(a, job.device, job.order, False)()
        row.reference_l2, row.reference_scale = physics.difference(traces, out.detach().cpu().numpy())
        if row.reference_l2 is None:
            row.reference_note = "our receiver data are all zero"
    except Exception as exc:  # the comparison failed, not the timing
        row.reference_note = _failure(exc, "comparison failed")
        log.warning("%s on %s: %s", a.spec.name, job.device, row.reference_note)


def run_deepwave_rows(job: BenchJob, a: SceneArrays, base: dict) -> list[BenchRow]:
    """Time the scene through Deepwave (after ours: its host memory is not separable, so only its
    CUDA peak, torch.cuda.max_memory_allocated, is reported). A mode that raises (out of memory,
    Deepwave or torch missing or broken, anything) gets status "reference failed: <reason>"; the
    other modes still run."""
    rows = []
    for mode in job.modes:
        row = BenchRow(engine="deepwave", mode=mode, memory_scope=job.memory_scope, **base)
        rows.append(row)
        once = None
        try:
            once = run_deepwave(mode, a, job.device, job.order)
            once()  # warm-up
            if device_kind(job.device) == "cuda":
                import torch

                torch.cuda.reset_peak_memory_stats(job.device)
            row.seconds, row.times, row.cpu_seconds, _ = _timed(once, job.repeat, lambda: None)
        except Exception as exc:
            row.status = _reference_failure(exc)  # (cmd_bench logs it)
            del once
            _free_torch_memory(job.device)
            continue
        row.rate = row.cell_updates / row.seconds
        if device_kind(job.device) == "cpu" and row.cpu_seconds > 0:
            row.rate_per_core = row.cell_updates / row.cpu_seconds
        else:
            import torch

            row.peak_device_bytes = int(torch.cuda.max_memory_allocated(job.device))
            row.device_memory_source = "torch.cuda.max_memory_allocated"
    return rows


def _free_torch_memory(device: str) -> None:
    """After a failed Deepwave run (e.g. out of memory): give torch's cached CUDA memory back."""
    if device_kind(device) != "cuda":
        return
    try:
        import gc

        import torch

        gc.collect()
        torch.cuda.empty_cache()
    except Exception:  # torch missing or its CUDA state broken: nothing to free
        pass


def run_job_in_subprocess(job: BenchJob) -> list[BenchRow]:
    """run_job in a fresh Python process (own memory high-water marks); failures become rows."""
    cmd = [sys.executable, "-m", "adseismic.bench", "--worker", json.dumps(asdict(job))]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(WORKER_MARK)]
    rows = [row_from_dict(d) for d in json.loads(lines[-1][len(WORKER_MARK):])] if lines else []
    if proc.returncode == 0 and lines:
        return rows
    tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
    why = "killed (out of host memory?)" if proc.returncode < 0 else f"exit code {proc.returncode}"
    if rows and job.deepwave and not any(r.engine == "deepwave" for r in rows):  # ours printed, then Deepwave died
        log.warning("worker for %s on %s died in Deepwave (%s): %s", job.scene, job.device, why, proc.stderr[-2000:])
        base = {k: getattr(rows[0], k) for k in ("scene", "kind", "device", "device_name", "order", "shape", "shots", "nt",
                                                 "nt_reference", "padded_cells")}  # fmt: skip
        return rows + [BenchRow(engine="deepwave", mode=m, memory_scope=job.memory_scope,
                                status=f"{REFERENCE_FAILED}: worker {why} in Deepwave: {tail}"[:300], **base) for m in job.modes]  # fmt: skip
    log.error("worker for %s on %s failed (%s): %s", job.scene, job.device, why, proc.stderr[-2000:])
    spec = SCENES[job.scene]
    base = dict(scene=spec.name, kind=spec.kind, device=job.device, device_name="", order=job.order, shape=tuple(spec.shape),
                shots=spec.shots, nt=job.nt, nt_reference=spec.nt, padded_cells=padded_cells(spec, job.order))  # fmt: skip
    return [BenchRow(engine="adseismic", mode=m, status=f"failed: worker {why}: {tail}"[:300], **base) for m in job.modes]


def row_from_dict(d: dict) -> BenchRow:
    d = dict(d)
    d["shape"] = tuple(d["shape"])
    return BenchRow(**d)


# --------------------------------------------------------------------------------- reports

def cuda_cpu_ratios(rows) -> dict:
    """{(scene, mode, engine, order): CUDA rate / CPU rate} for every measurement that ran on both a
    CUDA device and the CPU (the first of each kind; rates are per cell update, so a CPU run
    shortened by --cpu-steps compares with the full CUDA run)."""
    rates = {}
    for r in rows:
        if r.ok and r.rate:
            rates.setdefault((r.scene, r.mode, r.engine, r.order, device_kind(r.device)), r.rate)
    return {k[:4]: rates[k] / rates[k[:4] + ("cpu",)] for k in rates if k[4] == "cuda" and k[:4] + ("cpu",) in rates}


def machine_info(devices) -> dict:
    """Versions, CPU and device names, date (UTC)."""
    import warp as wp

    cpu_model = platform.processor() or ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            cpu_model = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), cpu_model)
    except OSError:
        pass
    return {
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "adseismic": version(), "warp": wp.config.version, "numpy": np.__version__, "python": platform.python_version(),
        "platform": platform.platform(), "cpu_model": cpu_model, "cpu_count": os.cpu_count(),
        "devices": {d: wp.get_device(d).name for d in devices}, "deepwave": _deepwave_version(),
    }  # fmt: skip


def _deepwave_version():
    try:
        from importlib.metadata import version as _v

        return _v("deepwave")
    except Exception:  # not installed
        return None


def _g(x) -> str:
    return "" if x is None else f"{x / 1e9:.3g}"


def _ratio(x: float) -> str:
    return f"{x:.3g}" if x < 1000 else f"{x:,.0f}"


def _gb(x) -> str:
    return "" if x is None else f"{x / 1e9:.2f}"


def reference_for(row: BenchRow, rows) -> tuple[float | None, str]:
    """(Deepwave rate, where it comes from) for a row of ours: the live Deepwave row of the same
    measurement, else the reference.md anchor of the scene, order and device kind."""
    live = next((r for r in rows if r.engine == "deepwave" and r.ok and (r.scene, r.mode, r.device, r.order, r.nt)
                 == (row.scene, row.mode, row.device, row.order, row.nt)), None)  # fmt: skip
    if live is not None:
        return live.rate, f"live, Deepwave {_deepwave_version() or ''}"
    a = anchor_for(row.scene, row.order, device_kind(row.device))
    return (None, "") if a is None else (getattr(a, row.mode), a.where)


def reference_failure_for(row: BenchRow, rows) -> str | None:
    """The "reference failed: <reason>" status of the live Deepwave row of our row's measurement, if it failed."""
    live = next((r for r in rows if r.engine == "deepwave" and (r.scene, r.mode, r.device, r.order, r.nt)
                 == (row.scene, row.mode, row.device, row.order, row.nt)), None)  # fmt: skip
    return live.status.replace("|", "/") if live is not None and live.status.startswith(REFERENCE_FAILED) else None


def markdown(rows, machine: dict) -> str:
    """The bench.md table: ours, the Deepwave rate and their ratio side by side, CUDA/CPU ratios."""
    ratios = cuda_cpu_ratios(rows)
    dev = ", ".join(f"{k} ({v})" for k, v in machine["devices"].items())
    lines = [
        "# adseismic bench", "",
        f"{machine['date_utc']}; adseismic {machine['adseismic']}, Warp {machine['warp']}; devices: {dev}; "
        f"CPU: {machine['cpu_model']} ({machine['cpu_count']} logical cores); Deepwave: {machine['deepwave'] or 'not installed'}.",
        "",
        "Rates in Gcell/s = padded-grid cell updates per second (cells incl. PML and halo x steps x shots / seconds), best of",
        "the timed runs after a warm-up; gradient = forward + gradient (checkpointed). Per core: cell updates per CPU-second.",
        "Deepwave: measured live in the same worker when installed, otherwise the figures recorded in",
        "../shared/docs/reference.md section 6 (Deepwave 0.1.0 on an H200 and on a 2-core CPU VM), labelled as such.",
        "",
        "| scene | device | mode | nt (of) | seconds | Gcell/s | per core | peak RSS GB | peak device GB | estimate GB | "
        "Deepwave Gcell/s | ours / Deepwave | CUDA / CPU |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]  # fmt: skip
    for r in rows:
        if r.engine != "adseismic":
            continue
        nt = f"{r.nt}" + (f" (of {r.nt_reference})" if r.nt != r.nt_reference else "")
        failed_ref = reference_failure_for(r, rows)
        if not r.ok:
            lines.append(f"| {r.scene} | {r.device} | {r.mode} | {nt} | {r.status} |  |  |  |  |  | {failed_ref or ''} |  |  |")
            continue
        ref, label = reference_for(r, rows)
        refs = "" if ref is None else f"{ref / 1e9:.3g} ({label})"
        vs = "" if ref is None else _ratio(r.rate / ref)
        if failed_ref:  # the live reference failed: say why (a recorded anchor, if any, follows)
            refs = failed_ref + ("" if ref is None else f"; recorded {refs}")
        ratio = ratios.get((r.scene, r.mode, r.engine, r.order))
        lines.append(
            f"| {r.scene} | {r.device} | {r.mode} | {nt} | {r.seconds:.3f} | {_g(r.rate)} | {_g(r.rate_per_core)} | "
            f"{_gb(r.peak_host_rss_bytes)} | {_gb(r.peak_device_bytes)} | {_gb(r.peak_estimate_bytes)} | {refs} | {vs} | "
            f"{'' if device_kind(r.device) == 'cpu' or ratio is None else _ratio(ratio)} |"
        )
    live = [r for r in rows if r.engine == "deepwave"]
    if live:
        lines += ["", "Deepwave rows (live):", "", "| scene | device | mode | seconds | Gcell/s | per core | peak device GB | status |",
                  "|---|---|---|---|---|---|---|---|"]  # fmt: skip
        lines += [f"| {r.scene} | {r.device} | {r.mode} | {'' if r.seconds is None else f'{r.seconds:.3f}'} | {_g(r.rate)} | "
                  f"{_g(r.rate_per_core)} | {_gb(r.peak_device_bytes)} | {r.status.replace('|', '/')} |" for r in live]  # fmt: skip
    lines += physics_accuracy_lines(rows)
    scopes = sorted({r.memory_scope for r in rows if r.memory_scope})
    lines += [
        "",
        f"Memory: peak RSS = host resident high-water mark (getrusage), scope: {', '.join(scopes) or 'n/a'}; it includes",
        "the interpreter with Warp and NumPy (~0.2 GB). Peak device = Warp's CUDA mempool high-water mark. Estimate = the",
        "gradient's own model of its peak (GradientResult.peak_bytes_estimate). Deepwave's peak memory (reference.md) is",
        "its gradient's: " + ", ".join(f"{a.scene} o{a.order} {a.device_kind} {a.gradient_peak_bytes / 1e9:.3g} GB" for a in ANCHORS) + ".",
        f"The CPU anchors used {ANCHOR_CPU_CORES} cores: divide them by {ANCHOR_CPU_CORES} to compare with our per-core rate.",
    ]  # fmt: skip
    return "\n".join(lines) + "\n"


def physics_accuracy_lines(rows) -> list[str]:
    """The bench.md table of the physics scenes' accuracy against Deepwave (none without physics scenes)."""
    ours = [r for r in rows if r.engine == "adseismic" and r.mode == "forward" and r.kind in physics.KINDS]
    if not ours:
        return []
    lines = ["", "Physics family against Deepwave (same grid, steps, order, PML, source and receivers; bench/physics.py says",
             "what is aligned and what differs): relative L2 difference of our receiver data from Deepwave's, and the",
             "least-squares scale a of ours ~ a Deepwave (1 when the conventions are aligned).", "",
             "| scene | physics | device | recorded | rel. L2 difference | scale a | note |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in ours:
        live = next((d for d in rows if d.engine == "deepwave" and (d.scene, d.mode, d.device, d.order, d.nt)
                     == (r.scene, r.mode, r.device, r.order, r.nt)), None)  # fmt: skip
        l2 = "" if live is None or live.reference_l2 is None else f"{live.reference_l2:.3g}"
        scale = "" if live is None or live.reference_scale is None else f"{live.reference_scale:.4g}"
        note = "Deepwave not run (--no-deepwave)" if live is None else (live.reference_note or ("" if live.ok else live.status))
        lines.append(f"| {r.scene} | {r.kind} | {r.device} | {physics.COMPONENT[r.kind]} | {l2} | {scale} | {note.replace('|', '/')} |")
    return lines


def plot_bench(path, rows) -> pathlib.Path:
    """Bar chart of Gcell/s (log) per scene and device, forward and forward+gradient panels, with
    live Deepwave bars (hatched) and the reference.md anchors of the device kinds that ran (ticks)."""
    from adseismic.plotting import _figure, save_figure

    ours = [r for r in rows if r.ok and r.rate]
    scenes = list(dict.fromkeys(r.scene for r in rows))
    series = list(dict.fromkeys((r.engine, r.device) for r in ours))
    kinds = {device_kind(r.device) for r in rows}
    fig = _figure(max(9.0, 2.2 * len(scenes) + 4.0), 5.0)
    width = 0.8 / max(len(series), 1)
    for p, mode in enumerate(MODES):
        ax = fig.add_subplot(1, 2, p + 1)
        values = []
        for k, (eng, dev) in enumerate(series):
            xs, ys = [], []
            for i, s in enumerate(scenes):
                r = next((r for r in ours if (r.scene, r.mode, r.engine, r.device) == (s, mode, eng, dev)), None)
                if r is not None:
                    xs.append(i - 0.4 + width * (k + 0.5))
                    ys.append(r.rate / 1e9)
            ax.bar(xs, ys, width, label=f"{'adseismic' if eng == 'adseismic' else 'Deepwave (live)'} {dev}",
                   hatch="//" if eng == "deepwave" else None, color=f"C{k}")
            for x, y in zip(xs, ys):
                ax.annotate(f"{y:.3g}", (x, y), ha="center", va="bottom", fontsize=7)
            values += ys
        for kind, colour in (("cuda", "black"), ("cpu", "dimgray")):
            pts = [(i, a) for i, s in enumerate(scenes) for a in [anchor_for(s, _order(rows, s), kind)] if a is not None]
            if pts and kind in kinds:
                ys = [getattr(a, mode) / 1e9 for _, a in pts]
                ax.scatter([i for i, _ in pts], ys, marker="_", s=900, c=colour, linewidths=2.5, zorder=5, label=pts[0][1].label)
                values += ys
        if values:
            ax.set_ylim(min(values) / 3, max(values) * 3)
        ax.set_yscale("log")
        ax.set_xticks(range(len(scenes)), scenes)
        ax.set_ylabel("Gcell/s (padded cell updates per second)")
        ax.set_title("forward" if mode == "forward" else "forward + gradient")
        ax.grid(True, axis="y", which="both", alpha=0.3)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(handles), 4), fontsize=8)
    return save_figure(fig, path)


def _order(rows, scene) -> int:
    return next(r.order for r in rows if r.scene == scene)


# --------------------------------------------------------------------------------- command

def register(p: argparse.ArgumentParser) -> None:
    """Options of ``adseismic bench``."""
    p.add_argument("--device", nargs="+", default=["cpu"], help="devices to run on, e.g. cpu cuda:0 (default: cpu)")
    p.add_argument("--scenes", nargs="+", metavar="NAME",
                   help=f"scenes ({', '.join(SCENES)}, or all: the standard ones); default: the standard ones on CUDA, "
                        f"{', '.join(s for s in SCENES if SCENES[s].cpu_default and SCENES[s].family == 'standard')} on the CPU")
    p.add_argument("--physics", action="store_true",
                   help=f"the physics family instead of the standard scenes (issue 26, beside Deepwave): "
                        f"{', '.join(_family('physics', 'cuda'))} on CUDA, {', '.join(_family('physics', 'cpu'))} (tiny) on the CPU")
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES), help="forward and/or gradient (forward + gradient)")
    p.add_argument("--order", type=int, choices=ORDERS, default=4, help="spatial order of every scene (default 4)")
    p.add_argument("--steps", type=int, metavar="N", help="shorten every scene to at most N time steps (quick run; reported)")
    p.add_argument("--cpu-steps", type=int, metavar="N", help="shorten the scenes to at most N time steps on the CPU only")
    p.add_argument("--repeat", type=int, help="timed runs per measurement, best reported (default: scenes 3 on CUDA, 1 on the CPU; sweep 2)")
    p.add_argument("--memory-budget", type=float, metavar="GB", help="gradient memory budget (default: the memory minimum)")
    p.add_argument("--max-minutes", type=float, default=15.0, help="refuse a scene estimated to take longer than this on a device (default 15)")
    p.add_argument("--in-process", action="store_true",
                   help="run every scene in this process (faster start; memory peaks become process-wide high-water marks)")
    p.add_argument("--no-deepwave", action="store_true", help="do not run Deepwave live even if it is installed")
    p.add_argument("--suite", choices=SUITES, default="scenes", help="scenes (default), speed-accuracy (the sweep), or all")
    p.add_argument("--sweep-orders", nargs="+", type=int, choices=ORDERS, default=[2, 4, 8], help="sweep: spatial orders")
    p.add_argument("--sweep-ppw", nargs="+", type=float, metavar="PPW", default=[3, 4, 5, 6, 8, 11, 16],
                   help="sweep: grid points per minimum wavelength (at the Ricker's -20 dB frequency)")
    p.add_argument("--sweep-precisions", nargs="+", choices=("float32", "float64"), default=["float32", "float64"],
                   help="sweep: precisions")
    p.add_argument("--sweep-cfl", nargs="+", type=float, metavar="FRACTION", default=[0.9, 0.4],
                   help="sweep: time steps as fractions of the CFL limit (default 0.9 0.4)")
    p.add_argument("--fwi", action="store_true",
                   help="instead of the scenes: the FWI race (adseismic against Deepwave + torch LBFGS on a Marmousi-II section)")
    p.add_argument("--fwi-shots", type=int, default=32, metavar="N", help="FWI race: shots (default 32)")
    p.add_argument("--fwi-iterations", type=int, default=20, metavar="N", help="FWI race: iterations a band (default 20)")
    p.add_argument("--fwi-inversion", nargs="+", default=[], metavar="KEY=VALUE",
                   help="FWI race: our inversion settings over the defaults, e.g. water_depth=450 preconditioning=depth")
    p.add_argument("--fwi-small", action="store_true",
                   help="FWI race on a 2 km x 1 km crop at 40 m, 1.5 s records, bands 3 and 5 Hz (a CPU check of the race)")
    p.add_argument("-o", "--output", "--outdir", dest="outdir", type=pathlib.Path, required=True, help="output directory")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar, log only warnings to stderr")


def _family(family: str, kind: str | None) -> list[str]:
    """The scenes of a family ("standard", "physics") in the default selection of a device kind ("cpu", "cuda";
    None: every scene of the family)."""
    return [s for s, spec in SCENES.items() if spec.family == family and
            (kind is None or (spec.cpu_default if kind == "cpu" else spec.gpu_default))]  # fmt: skip


def _check_args(args) -> tuple[list[str], dict]:
    """Validate before anything runs or is written: (resolved devices, {device: [BenchJob]})."""
    from adseismic.solve.common import resolve_device

    devices = []
    for d in args.device:
        try:
            devices.append(resolve_device(d))
        except ValueError as e:
            raise CommandError(f"--device: {e}") from None
    if len(set(devices)) != len(devices):
        raise CommandError(f"--device: {' '.join(args.device)} names a device twice; give each once")
    for opt, val, ok, fix in (("--steps", args.steps, lambda v: v >= 2, "use 2 or more"),
                              ("--cpu-steps", args.cpu_steps, lambda v: v >= 2, "use 2 or more"),
                              ("--repeat", args.repeat, lambda v: v >= 1, "use 1 or more"),
                              ("--memory-budget", args.memory_budget, lambda v: v > 0, "give gigabytes > 0"),
                              ("--max-minutes", args.max_minutes, lambda v: v > 0, "give minutes > 0")):  # fmt: skip
        if val is not None and not ok(val):
            raise CommandError(f"{opt}: {val} is invalid; {fix}")
    bad_ppw = [p for p in args.sweep_ppw if p <= 2.0]
    if args.suite != "scenes" and bad_ppw:
        raise CommandError(f"--sweep-ppw: {bad_ppw[0]:g} points per wavelength is at or below the grid's Nyquist limit (2); use > 2")
    bad_cfl = [f for f in args.sweep_cfl if not 0 < f <= 1]
    if args.suite != "scenes" and bad_cfl:
        raise CommandError(f"--sweep-cfl: {bad_cfl[0]:g} is not a fraction of the CFL limit in (0, 1]; e.g. 0.9 0.4")
    names = args.scenes
    if names is not None and "all" in names:
        names = _family("standard", None)
    if names is not None and getattr(args, "physics", False):
        raise CommandError(f"--physics: give it or --scenes {' '.join(args.scenes)}, not both (name physics scenes with --scenes)")
    unknown = [n for n in names or [] if n not in SCENES]
    if unknown:
        raise CommandError(f"--scenes: unknown scene {unknown[0]!r}; choose from {', '.join(SCENES)} (or all)")
    jobs = {}
    budget = None if args.memory_budget is None else args.memory_budget * 1e9
    deepwave = not args.no_deepwave and deepwave_available()
    for dev in devices if args.suite != "speed-accuracy" else []:
        kind = device_kind(dev)
        repeat = args.repeat or (3 if kind == "cuda" else 1)
        chosen = names if names is not None else _family("physics" if getattr(args, "physics", False) else "standard", kind)
        jobs[dev] = []
        for s in dict.fromkeys(chosen):
            spec = SCENES[s]
            limits = [args.steps] + [args.cpu_steps] * (kind == "cpu")
            nt = min([spec.nt] + [n for n in limits if n is not None])
            est = estimate_seconds(spec, nt, dev, args.modes, repeat)
            if est > 60 * args.max_minutes:
                fit = max(2, int(nt * 60 * args.max_minutes / est))
                raise CommandError(
                    f"--scenes: {s} on {dev} would take ~{est / 60:.0f} min (estimate at {EST_RATE[kind]:.2g} cell updates/s, "
                    f"{len(args.modes)} mode(s), {repeat} repeat(s)), above --max-minutes {args.max_minutes:g}; add "
                    f"{'--cpu-steps' if kind == 'cpu' else '--steps'} {fit} "
                    f"(rates stay comparable), raise --max-minutes, or drop the scene")  # fmt: skip
            scope = "process-wide high-water mark (--in-process)" if args.in_process else "scene (own process)"
            reference = deepwave or (spec.family == "physics" and not args.no_deepwave)  # physics: "not installed" rows
            jobs[dev].append(BenchJob(s, dev, tuple(args.modes), args.order, nt, repeat, budget, reference, scope))
    return devices, jobs


def cmd_bench(args) -> int:
    """Run the benchmark suites and write the reports; exit 1 if a measurement of ours failed (a
    failed reference, Deepwave, is reported in the table as "reference failed: <reason>" only)."""
    from tqdm.auto import tqdm

    if getattr(args, "fwi", False):
        return _cmd_fwi_race(args)
    devices, jobs = _check_args(args)
    outdir = args.outdir
    if outdir.exists() and not outdir.is_dir():
        raise CommandError(f"-o: {outdir} exists and is not a directory; choose another output directory")
    outdir.mkdir(parents=True, exist_ok=True)
    written, failed = [], []
    with RunLog(outdir / "bench.log", args.quiet):
        machine = machine_info(devices)
        log.info("adseismic %s bench %s -> %s; machine %s", version(), " ".join(sys.argv[1:]), outdir, json.dumps(machine))
        all_jobs = [j for dev in devices for j in jobs.get(dev, [])]
        if all_jobs:
            rows = []
            bar = tqdm(all_jobs, desc="bench", unit="scene", disable=args.quiet)
            for job in bar:
                bar.set_postfix_str(f"{job.scene} on {job.device}")
                log.info("running %s on %s (nt %d, order %d, modes %s, repeat %d)", job.scene, job.device, job.nt, job.order,
                         "+".join(job.modes), job.repeat)  # fmt: skip
                rows += run_job(job) if args.in_process else run_job_in_subprocess(job)
            failed += [r for r in rows if is_our_failure(r)]
            for r in rows:
                if r.status.startswith(REFERENCE_FAILED):
                    log.warning("%s %s on %s: Deepwave %s (reported, not our failure)", r.scene, r.mode, r.device, r.status)
            payload = {"machine": machine, "command": sys.argv[1:], "rows": [asdict(r) for r in rows],
                       "cuda_cpu_ratios": [dict(zip(("scene", "mode", "engine", "order"), k), ratio=v)
                                           for k, v in cuda_cpu_ratios(rows).items()],
                       "anchors": [asdict(a) | {"label": a.label} for a in ANCHORS]}  # fmt: skip
            write_text_atomic(outdir / "bench.json", json.dumps(payload, indent=1) + "\n")
            text = markdown(rows, machine)
            write_text_atomic(outdir / "bench.md", text)
            plot_bench(outdir / "bench.png", rows)
            written += ["bench.json", "bench.md", "bench.png"]
            if not args.quiet:
                print(text)
        if args.suite != "scenes":
            from adseismic.bench import speed_accuracy

            points = speed_accuracy.sweep(devices, args.sweep_orders, args.sweep_ppw, args.sweep_precisions, args.sweep_cfl,
                                          args.repeat or 2, progress=not args.quiet)  # fmt: skip
            written += [p.name for p in speed_accuracy.write_outputs(outdir, points, machine)]
            failed += [p for p in points if p.status != "ok"]
        for r in failed:
            log.error("failed: %s", r)
    print(f"wrote {outdir}/: {', '.join(written + ['bench.log'])}")
    if failed:
        print(f"adseismic bench: {len(failed)} measurement(s) failed; see {outdir / 'bench.log'}", file=sys.stderr)
        return EXIT_ERROR
    return EXIT_OK


def _cmd_fwi_race(args) -> int:
    """``adseismic bench --fwi``: the FWI race (bench/fwi_race.py); exit 1 only if our run failed."""
    from adseismic.bench import fwi_race
    from adseismic.solve.common import resolve_device

    try:
        device = resolve_device(args.device[0])
    except ValueError as e:
        raise CommandError(f"--device: {e}") from None
    for opt, val in (("--fwi-shots", args.fwi_shots), ("--fwi-iterations", args.fwi_iterations)):
        if val < 1:
            raise CommandError(f"{opt}: {val} is invalid; use 1 or more")
    overrides = {}
    for item in args.fwi_inversion:
        key, eq, value = item.partition("=")
        if not eq or not key:
            raise CommandError(f"--fwi-inversion: {item!r} is not KEY=VALUE; e.g. water_depth=450")
        overrides[key] = yaml.safe_load(value)
    sc = fwi_race.RaceScene(shots=args.fwi_shots, iterations=args.fwi_iterations, device=device, inversion=overrides)
    if args.fwi_small:
        sc = dataclasses.replace(sc, x_range=(5000.0, 7000.0), depth=1000.0, dx=40.0, duration=1.5, bands=(3.0, 5.0))
    from adseismic.config import ConfigError, parse_fwi_config

    try:  # our settings checked before anything runs
        parse_fwi_config(fwi_race.fwi_config(sc))
    except ConfigError as e:
        raise CommandError(f"--fwi-inversion: {e}") from None
    outdir = args.outdir
    if outdir.exists() and not outdir.is_dir():
        raise CommandError(f"-o: {outdir} exists and is not a directory; choose another output directory")
    outdir.mkdir(parents=True, exist_ok=True)
    with RunLog(outdir / "bench.log", args.quiet):
        log.info("adseismic %s bench %s -> %s; machine %s", version(), " ".join(sys.argv[1:]), outdir, json.dumps(machine_info([device])))
        try:
            report = fwi_race.race(sc, outdir / "runs", deepwave=not args.no_deepwave and deepwave_available())
        except Exception as exc:
            log.exception("the FWI race failed on our side")
            print(f"adseismic bench --fwi: our run failed ({type(exc).__name__}: {exc}); see {outdir / 'bench.log'}", file=sys.stderr)
            return EXIT_ERROR
        report["machine"] = machine_info([device])
        written = fwi_race.write(outdir, report)
        if not args.quiet:
            print(fwi_race.markdown(report))
    print(f"wrote {outdir}/: {', '.join(p.name for p in written)}, bench.log, runs/")
    return EXIT_OK


def _worker_main(argv) -> int:
    """``python -m adseismic.bench --worker JOB_JSON``: run one job, print its rows as JSON."""
    job = BenchJob(**json.loads(argv[argv.index("--worker") + 1]))
    job.modes = tuple(job.modes)
    from adseismic.solve.common import init_warp

    init_warp()

    def emit(rows):
        print(WORKER_MARK + json.dumps([asdict(r) for r in rows]), flush=True)

    emit(run_job(job, emit))  # ours first, then ours + Deepwave's: the parent takes the last line
    return 0
