"""Full-waveform inversion: multiscale bands, conditioned gradients, journaled optimisation, run directory.

run_fwi(config, rundir) inverts the model (acoustic velocity; with physics elastic any of vp, vs, rho or lambda, mu,
rho; or a neural network's weights) for all shots of the config:
1. plan the grid for the bounds of the inverted quantities (every model the optimiser may visit is stable and
   resolved) and resample the start model onto it;
2. observed data: simulated from `true_model` with the full wavelet (a synthetic study), or read from
   files; stored in RUNDIR/observed.h5 so that a resumed run uses the same data (and, with pyasdf, in ASDF as
   RUNDIR/observed_waveforms.h5 on the simulation's time axis, adseismic.data.asdf's layout; the final model's
   synthetics go to RUNDIR/synthetic_waveforms.h5 at the end);
3. for each band (low to high), on the plan's grid or (inversion.grid per_band) on the coarsest grid and longest
   time step that resolve the band (band_plan; the model moves between grids by slowness interpolation), the
   wavelet and the observed data get the same causal Butterworth filter (band_filter: filtering the source filters the
   synthetics exactly, the data being linear in the source; a zero-phase filter would not, see band_filter),
   optionally a least-squares wavelet estimate, and the optimiser minimises the
   misfit (normalised by its value at the band's start model, summed over the recorded channels) plus
   regularisation over x, the model space's vector (inversion.model_space: x = v / V_REF for acoustic pixels), with
   the per-cell gradient masked, smoothed and preconditioned before the chain rule takes it back to x;
4. every evaluation goes to a journal (RUNDIR/journal_band<k>.h5, atomic) and every iteration to
   RUNDIR/history.h5 (one group appended per iteration) and PNGs; --resume replays the journals and
   continues, reproducing an uninterrupted run. fwi.log gets a time breakdown of every evaluation
   (simulation vs the rest, _EvaluationTimes) and its sums per band.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import warp as wp
from scipy.signal import butter, sosfilt, sosfiltfilt

from adseismic import plotting
from adseismic.data.atomic import write_h5_atomic, write_text_atomic
from adseismic.data.model import Model, interpolate
from adseismic.inversion import conditioning
from adseismic.inversion.model_space import (OWN_QUANTITIES, PARAMETERIZATIONS, PHYSICS_PARAMETERS, REFERENCE, UNITS, ModelSpace,
                                              quantities_of)
from adseismic.inversion.optimize import minimize
from adseismic.inversion.parameterization import MLP
from adseismic.runs import format_band, format_position
from adseismic.scene import attenuation_check, build_scene, p_speeds, plan_scene, qp_min_speed_ratio
from adseismic.solve.acoustic import forward, gradient
from adseismic.solve.batch import shot_slices
from adseismic.solve.distributed import reduce_in_order
from adseismic.solve.pools import check_pool, open_pool, pool_shots_per_batch
from adseismic.solve.acoustic_vd import MODELS as ACOUSTIC_VD_MODELS
from adseismic.solve.acoustic_vd import forward_acoustic_vd, gradient_acoustic_vd
from adseismic.solve.elastic import forward_elastic, gradient_elastic
from adseismic.solve.misfits import misfit as named_misfit
from adseismic.solve.receivers import UNITS as RECORDED_UNITS
from adseismic.solve.viscoacoustic import MODELS as VISCOACOUSTIC_MODELS
from adseismic.solve.viscoacoustic import forward_viscoacoustic, gradient_viscoacoustic
from adseismic.solve.vti import MODELS as VTI_MODELS
from adseismic.solve.vti import forward_vti, gradient_vti

log = logging.getLogger(__name__)

# A low-passed band needs a grid up to BAND_EDGE x its high corner, not the wavelet's full band (band_filter's
# causal order-4 Butterworth is -10 dB there; what its tail beyond costs on a coarse grid, band_grid_holds measures).
BAND_EDGE = 1.33
BAND_ORDER = 4  # band_filter's Butterworth order (order 8 ended the race 0.01 worse, for Deepwave too: docs/fwi.md)
MODELLING_SHARE = 1.0  # a band's own grid: its modelling error at most this fraction of the data residual (band_grid_holds)
PARALLEL_FILTER_SAMPLES = 1_000_000  # band_pass filters arrays of more samples on threads, a first-axis slice each

# The physics whose solvers take the explosive source's moment S(t) (Simulator._moment) and their own parameters:
# (forward, gradient, the solver's model arguments in order).
MOMENT_SOLVERS = {"acoustic_vd": (forward_acoustic_vd, gradient_acoustic_vd, ACOUSTIC_VD_MODELS),
                  "viscoacoustic": (forward_viscoacoustic, gradient_viscoacoustic, VISCOACOUSTIC_MODELS),
                  "vti": (forward_vti, gradient_vti, VTI_MODELS)}


@dataclass
class FWIResult:
    """Inverted vp (nz, [ny,] nx) m/s on the simulation grid (spacing dx m, origin m), the start
    model, per-band optimiser results, and model errors when the true model is known. models / start_models:
    every physical parameter {vp, [vs (m/s), rho (kg/m^3)]}, the same grid."""

    model: np.ndarray
    start_model: np.ndarray
    dx: float
    origin: tuple
    bands: list = field(default_factory=list)
    errors: dict = field(default_factory=dict)
    seconds: float = 0.0
    models: dict = field(default_factory=dict)
    start_models: dict = field(default_factory=dict)


def band_filter(x, dt, band):
    """An FWI band's filter, applied alike to the source wavelet and the observed data (..., nt) sampled at dt s:
    a causal Butterworth of order BAND_ORDER; band = (f_low or None, f_high or None) Hz.

    Causal, because filtering the wavelet then filters the synthetics exactly: a causal filter started from rest
    commutes with the record's cut at its end and with the source starting at t = 0. A zero-phase filter does
    neither: the filtered wavelet's part before t = 0 is lost, and the observed data's backward pass starts from
    the cut end. At the true model that left a residual of 9% (the 4 Hz band of configs/fwi_demo.yaml) to 21%
    (2.5 Hz) of the band's data that no model could explain; the causal filter leaves 0.1% (the PML tuned to the
    band). Both sides are delayed alike (about 0.41 / f_high s at low frequencies), so the misfit is not."""
    return band_pass(x, dt, band, order=BAND_ORDER, causal=True)


def band_pass(x, dt, band, order=4, causal=False):
    """Butterworth band-pass along the last axis, zero-phase (forward and backward: the response squared) or causal
    (forward, from rest); band = (f_low or None, f_high or None) Hz. A large array (a band's observed data,
    (n_shots, n_receivers, nt)) is filtered one first-axis slice a thread (scipy filters without the GIL; the same
    numbers: each trace is filtered alone)."""
    lo, hi = band
    nyq = 0.5 / dt
    if lo is None and hi is None:
        return np.asarray(x, float)
    if hi is not None and hi >= nyq:
        raise ValueError(f"band f_high {hi:g} Hz is at or above the Nyquist frequency {nyq:g} Hz of dt = {dt:g} s")
    if lo is None:
        sos = butter(order, hi, btype="lowpass", fs=1.0 / dt, output="sos")
    elif hi is None:
        sos = butter(order, lo, btype="highpass", fs=1.0 / dt, output="sos")
    else:
        sos = butter(order, [lo, hi], btype="bandpass", fs=1.0 / dt, output="sos")
    x = np.asarray(x, float)
    run = sosfilt if causal else sosfiltfilt
    if x.ndim < 2 or len(x) < 2 or x.size < PARALLEL_FILTER_SAMPLES:
        return run(sos, x, axis=-1)
    out = np.empty_like(x)

    def part(i):
        out[i] = run(sos, x[i], axis=-1)

    with ThreadPoolExecutor(min(len(x), os.cpu_count() or 1)) as pool:
        list(pool.map(part, range(len(x))))
    return out


def band_plan(cfg, plan, bounds, band) -> tuple:
    """(plan, m): band's simulation grid and its time step as a multiple m of plan.dt. inversion.grid per_band: the
    coarsest grid and longest step that resolve the band (plan_scene for BAND_EDGE x its high corner at
    simulation.accuracy, dx and dt unpinned), never finer than `plan` (the simulation's grid, which the history
    and the result keep), dt = m plan.dt so that the data are decimated, not interpolated; else, for a full band
    or where a coarser grid would save less than a fifth of the cells x steps, (plan, 1). bounds: (v_min, v_max) m/s planned for."""
    if cfg.inversion.grid != "per_band" or band[1] is None:
        return plan, 1
    fwd, f_max = cfg.forward, BAND_EDGE * band[1]

    def planned(dx, dt):
        sim = dataclasses.replace(fwd.simulation, dx=dx, dt=dt)
        return plan_scene(dataclasses.replace(fwd, simulation=sim), velocity_range=bounds, f_max=f_max, check_memory_of_run=False)

    free = planned(None, None)
    m = max(1, int(free.dt / plan.dt * (1 + 1e-9)))
    if (max(free.dx, plan.dx) / plan.dx) ** plan.ndim * m < 1.25:  # not worth a second grid: under a fifth less work
        return plan, 1
    for m in range(m, 0, -1):  # dx again for the step taken (dispersion depends on both); a shorter step if it must
        pb = planned(None, m * plan.dt)
        if pb.expected_error <= fwd.simulation.accuracy or m == 1:
            break
    return (pb if pb.dx >= plan.dx else planned(plan.dx, m * plan.dt)), m


def band_grid_holds(sim, scene, p, pb, m: int, v, grid, wavelet, observed, weights, shots_per_batch=None) -> tuple[bool, float, float]:
    """Whether band plan pb (band_plan: dt = m p.dt) reproduces the plan grid's data where the band's misfit looks.
    At the band's start model v (m/s, on plan `grid`), both grids simulate the band's data (wavelet and observed:
    band-passed, on p's time axis; weights: data_weights on p); the coarse grid holds when its modelling error
    |W (d_pb - d_p)| is at most MODELLING_SHARE x the residual |W (d_p - observed)| the band is to explain (L2 on
    pb's samples). A dispersion error below that is mostly a phase shift the band absorbs as a small velocity
    error, which the next, finer band corrects (docs/fwi.md: the tests' tiny inversion at 0.65 and the race's bands
    at 0.22 and 0.95 end at a lower model error than on the plan's grid). What the dispersion planner cannot see is caught
    here: near a free surface the traces within a few cells of a shallow source carry most of a low band's energy
    and depend on the grid (Marmousi-II at 3 Hz: 99% in the 15 traces within 50 m; 0.81 of it missed on a 47 m
    grid, 23x the residual). The shots run shots_per_batch at a time (None: all at once). Returns (holds, modelling,
    residual), the two norms relative to |W observed|."""
    src, rec = scene.source_locations, scene.receiver_locations

    def data(plan, w):
        vv = v if _same_grid(plan, grid) else _regridded(v, grid, plan, velocity=True)
        amp = np.broadcast_to(w, scene.source_amplitudes.shape[:-1] + w.shape).copy()
        return np.concatenate([sim.forward({"vp": vv}, plan.dx, plan.dt, amp[sl], src[sl], rec[sl])["data"]
                               for sl in shot_slices(len(amp), shots_per_batch)])

    wt = _decimated(weights, m, pb.nt)
    fine = wt * _decimated(data(p, wavelet), m, pb.nt)
    coarse = wt * data(pb, _decimated(wavelet, m, pb.nt))
    obs = wt * _decimated(observed, m, pb.nt)
    scale = np.linalg.norm(obs) or 1.0
    modelling, residual = np.linalg.norm(coarse - fine) / scale, np.linalg.norm(fine - obs) / scale
    return bool(modelling <= MODELLING_SHARE * residual), float(modelling), float(residual)


def _decimated(a, m: int, nt: int) -> np.ndarray:
    """Every m-th sample of a (..., time), cut or zero-padded to nt samples."""
    a = np.asarray(a)[..., ::m][..., :nt]
    return a if a.shape[-1] == nt else np.concatenate([a, np.zeros(a.shape[:-1] + (nt - a.shape[-1],), a.dtype)], axis=-1)


def _regridded(values, src, dst, velocity: bool) -> np.ndarray:
    """values (nz, [ny,] nx) on plan src's grid at plan dst's nodes: a velocity (m/s) by Model.resample (slowness,
    anti-aliased when coarsening), anything else (a gradient) by multilinear interpolation; edges replicated."""
    if velocity:
        return Model(np.asarray(values, float), src.dx, src.origin).resample(dst.dx, dst.origin, dst.shape).values
    return interpolate(values, (src.dx,) * len(src.shape), src.origin, dst.dx, dst.origin, dst.shape)


def estimate_wavelet(wavelet, synthetic, observed, damping=1e-3):
    """Least-squares source wavelet in the frequency domain: W' = W sum conj(D) O / (sum |D|^2 + eps),
    D synthetics for wavelet W, O observed; arrays (..., nt); eps = damping x max sum |D|^2."""
    nt = wavelet.shape[-1]
    n = 2 * nt
    W = np.fft.rfft(wavelet, n)
    D = np.fft.rfft(synthetic, n, axis=-1).reshape(-1, n // 2 + 1)
    O = np.fft.rfft(observed, n, axis=-1).reshape(-1, n // 2 + 1)
    num = np.sum(np.conj(D) * O, axis=0)
    den = np.sum(np.abs(D) ** 2, axis=0)
    return np.fft.irfft(W * num / (den + damping * den.max()), n)[:nt]


def relative_error(v, v_true, region):
    return float(np.linalg.norm((v - v_true)[region]) / np.linalg.norm(v_true[region]))


class _History:
    """history.h5: per band and iteration the model (m/s), gradient and misfit, appended.

    Each add() opens the file, writes one group band<b>/iter<i:04d> (datasets model and gradient,
    float32, uncompressed; attr misfit written last, so a group without it is incomplete) and closes
    it: constant cost per iteration (the whole file used to be rewritten with gzip, O(iterations)),
    and between two adds the file is complete on disk, so a reader, or a reader after a kill -9, sees
    every iteration added before. A kill during an add (about a millisecond an iteration) can leave
    that group incomplete (read_history skips it) or, as HDF5 updates its metadata in place, the
    file unreadable (1 in 60 kills aimed inside appends); the journals stay intact and --resume
    rewrites history.h5 from them. The first add of a process
    truncates the file: a resumed run replays its journals from band 0 iteration 1 and calls add
    again for every iteration, rewriting the same history. No SWMR: it cannot create groups, needs
    the newest file format (whose open-for-write flag makes a killed file unreadable until h5clear)
    and swmr=True in every reader. The writer opens with locking=False, so a reader holding the file
    open (a viewer) cannot make the run fail."""

    UNITS = "model m/s; gradient d(misfit/misfit_0)/d(v/1000 m/s)"

    def __init__(self, path: Path, dx, origin, compression=None, units=None):
        self.path, self.dx, self.origin, self.compression = Path(path), dx, origin, compression
        self.units = units or self.UNITS
        self.rows = []  # (band, iteration, misfit): the misfit curve; the arrays are on disk only
        self.seconds = 0.0  # time spent in add(), for the log's time breakdown

    def add(self, band, iteration, model, grad, misfit, dx=None):
        """model, grad: arrays (datasets model, gradient) or {dataset name: array} (elastic: model_vp, ...), on the
        file's grid; dx: the spacing (m) of the grid the band ran on (attribute dx; inversion.grid per_band: coarser
        than the file's, its model and gradient interpolated onto the file's grid)."""
        t0 = time.perf_counter()
        with h5py.File(self.path, "a" if self.rows else "w", locking=False) as f:
            if not self.rows:
                f.attrs["dx"], f.attrs["origin"], f.attrs["units"] = self.dx, self.origin, self.units
                f.attrs["layout"] = "band<b>/iter<i:04d>/{model, gradient} float32, attrs misfit, dx (the band's grid); appended per iteration"
            name = f"band{band}/iter{iteration:04d}"
            if name in f:  # (not in a normal run: the file is truncated by a process's first add)
                del f[name]
            grp = f.create_group(name)
            arrays = {**(model if isinstance(model, dict) else {"model": model}), **(grad if isinstance(grad, dict) else {"gradient": grad})}
            for key, a in arrays.items():
                grp.create_dataset(key, data=np.asarray(a, np.float32), compression=self.compression)
            grp.attrs["misfit"] = float(misfit)
            grp.attrs["dx"] = float(self.dx if dx is None else dx)
        self.rows.append((band, iteration, float(misfit)))
        self.seconds += time.perf_counter() - t0

    def misfits(self):
        return list(self.rows)


def read_history(path) -> list[dict]:
    """The iterations in a history.h5, in (band, iteration) order: dicts with band, iteration, misfit
    and every dataset of the group (float32 arrays): model, gradient (m/s and the conditioned gradient), or for
    elastic physics model_vp, model_vs, model_rho and gradient_<inverted quantity>. An incomplete last group
    (a run killed during its append) is skipped."""
    out = []
    with h5py.File(path, "r") as f:
        for bname in f:
            if not bname.startswith("band"):
                continue
            for iname, g in f[bname].items():
                if "misfit" not in g.attrs or not any(k.startswith("model") for k in g) or not any(k.startswith("gradient") for k in g):
                    continue
                out.append({"band": int(bname[4:]), "iteration": int(iname[4:]), "misfit": float(g.attrs["misfit"]),
                            **{k: d[...] for k, d in g.items()}})  # fmt: skip
    return sorted(out, key=lambda r: (r["band"], r["iteration"]))


class _EvaluationTimes:
    """The time breakdown of each real (not replayed) evaluation of one band, logged to fwi.log:

        band B evaluation K: T s (simulation S s, misfit+weights M s, conditioning C s, journal J s,
        history H s, iteration I s, other O s; non-kernel P%)

    K is the 0-based journal index; T the wall time since the previous evaluation ended (the band's
    start for the first); simulation the time inside solve.acoustic.gradient less its misfit callback
    (kernels, with the setup and device-host copies inside it; on CUDA it ends in the synchronisation
    its host results need, no extra one is added); misfit+weights the rest of the objective before the
    conditioning (weighting, misfit and adjoint source on the host, sums); conditioning: the scale,
    mask, smoothing, preconditioner and regularisation; journal: its save; history: the history.h5
    appends since the previous evaluation (replayed iterations included); iteration: the accepted iterations'
    own work since the previous evaluation, less their history appends (the model decoded, the gradient in cells
    for the history and the figures, the log line); other: the rest (the optimiser, the log). Non-kernel = 1 - simulation / T. After the band, summary() logs the sums, the figures' time
    and the non-kernel fraction. perf_counter only: cheap."""

    PARTS = ("simulation", "misfit+weights", "conditioning", "journal", "history", "iteration", "other")

    def __init__(self, band, history):
        self.band, self.history = band, history
        self.mark, self.history_mark = time.perf_counter(), history.seconds
        self.total = dict.fromkeys(self.PARTS, 0.0)
        self.n, self.wall, self.iteration = 0, 0.0, 0.0
        self.start()

    def start(self):
        """Called as the objective starts: its own parts (s) are accumulated into self.now."""
        self.now = {"gradient": 0.0, "misfit": 0.0, "conditioning": 0.0}

    def __call__(self, index, seconds):
        """minimize's on_evaluation(index, {"objective", "journal"})."""
        t = time.perf_counter()
        wall, self.mark = t - self.mark, t
        hist, self.history_mark = self.history.seconds - self.history_mark, self.history.seconds
        sim = self.now["gradient"] - self.now["misfit"]
        parts = {"simulation": sim, "misfit+weights": seconds["objective"] - sim - self.now["conditioning"],
                 "conditioning": self.now["conditioning"], "journal": seconds["journal"], "history": hist,
                 "iteration": self.iteration}  # fmt: skip
        self.iteration = 0.0
        parts["other"] = wall - sum(parts.values())
        for k, v in parts.items():
            self.total[k] += v
        self.n, self.wall = self.n + 1, self.wall + wall
        log.info("band %d evaluation %d: %.3f s (%s; non-kernel %.0f%%)", self.band, index, wall,
                 ", ".join(f"{k} {v:.3f} s" for k, v in parts.items()), 100 * (1 - sim / wall) if wall > 0 else 0.0)  # fmt: skip

    def summary(self, figures=0.0):
        if not self.n:
            log.info("band %d time: no evaluations run (replayed from the journal); figures %.3f s", self.band, figures)
            return
        log.info("band %d time: %d evaluations in %.3f s (%.3f s each): %s; non-kernel %.0f%%; figures %.3f s", self.band, self.n,
                 self.wall, self.wall / self.n, ", ".join(f"{k} {v:.3f} s" for k, v in self.total.items()),
                 100 * (1 - self.total["simulation"] / self.wall) if self.wall > 0 else 0.0, figures)  # fmt: skip


@dataclass
class Prepared:
    """What an inversion needs before it writes anything: the plan and scene (start model on the
    simulation grid), the vp range (m/s) every visited model stays within, the model space (the optimiser's x
    and its map to the physics, inversion.model_space) and observed data read from files (or None)."""

    plan: object
    scene: object
    bounds: tuple
    observed: np.ndarray | None
    space: ModelSpace | None = None


def _physics(cfg) -> str:
    return getattr(cfg, "physics", None) or "acoustic"


def _start_models(model, physics) -> dict:
    """{vp, [vs, rho]}: the arrays of a Model (acoustic) or an ElasticModel (ElasticModel.materials: vs 0 for
    acoustic_vd)."""
    if physics == "acoustic":
        return {"vp": np.asarray(model.values, float)}
    return model.materials()


def inversion_bounds(cfg) -> dict:
    """{inverted quantity: (min, max)} in its unit: inversion.bounds, else the start model's range +-25%; raises
    ValueError when a box does not contain the start model (the optimiser starts inside it)."""
    inv, physics = cfg.inversion, _physics(cfg)
    q = quantities_of(_start_models(cfg.forward.model, physics), inv.parameterization)
    out = {}
    for name in _inverted(cfg):
        lo, hi = float(np.min(q[name])), float(np.max(q[name]))
        if not np.isfinite(hi):  # (q = inf: lossless)
            raise ValueError(f"inversion.parameters: {name} is inverted but the start model's {name} is infinite (lossless) at "
                             f"{int(np.sum(~np.isfinite(q[name])))} cells; give a finite start Q there (e.g. 1000), or do not invert q")
        given_bounds = inv.bounds.get(name) if isinstance(inv.bounds, dict) else inv.bounds
        net = getattr(cfg, "network", None)
        reach = (lo, hi) if net is None else (net["v0"] - net["scale"], net["v0"] + net["scale"])  # a network: v0 +- scale
        b = tuple(given_bounds) if given_bounds is not None else _default_bounds(name, lo, hi, reach)
        if not (b[0] <= lo and hi <= b[1]):
            key = "inversion.bounds" if not isinstance(inv.bounds, dict) else f"inversion.bounds.{name}"
            raise ValueError(f"{key}: [{b[0]:g}, {b[1]:g}] {UNITS[name]} do not contain the start model's range "
                             f"[{lo:g}, {hi:g}] {UNITS[name]}; widen them")  # fmt: skip
        out[name] = b
    return out


def _default_bounds(name: str, lo: float, hi: float, reach: tuple) -> tuple:
    """The box of an inverted quantity whose inversion.bounds are not given, around the start model's range [lo, hi]
    (reach: the range a network may give): speeds, densities, moduli +-25%; q [5, 1000] (lossy sediments to hard rock)
    widened to hold the start +-25%; epsilon, delta (which may be 0) 0.1 below and 0.2 above the start (Thomsen's rocks
    span about -0.1..0.3), never below -0.45 (the solver needs > -1/2). The start lies inside, not on a bound, where the
    sigmoid transform would hardly move it."""
    if name == "q":
        return (min(5.0, 0.75 * lo), max(1000.0, 1.25 * hi))
    if name in ("epsilon", "delta"):
        return (max(lo - 0.1, min(lo, -0.45)), hi + 0.2)
    return (0.75 * min(lo, reach[0]), 1.25 * max(hi, reach[1]))


def _inverted(cfg) -> tuple:
    """The inverted quantities: inversion.parameters, else every quantity of the parameterisation (acoustic: vp;
    viscoacoustic, vti: vp, their other quantities are opt-in)."""
    inv = cfg.inversion
    if _physics(cfg) == "acoustic":
        return ("vp",)
    if inv.parameters:
        return tuple(inv.parameters)
    if _physics(cfg) in OWN_QUANTITIES:
        return ("vp",)
    return tuple(q for q in PARAMETERIZATIONS[inv.parameterization] if not (q == "vs" and _physics(cfg) == "acoustic_vd"))


def prepare_fwi(cfg) -> Prepared:
    """Plan for the bounds of the inverted quantities and read/check observed data files; raises ValueError (bad
    input) before any output exists."""
    inv, fwd = cfg.inversion, cfg.forward
    physics = _physics(cfg)
    bounds_of = inversion_bounds(cfg)
    probe = ModelSpace(physics, _start_models(fwd.model, physics), _inverted(cfg), inv.parameterization, bounds_of)
    ranges = probe.physical_ranges()
    bounds = wave_speed_range(cfg, ranges)
    highs = [hi for _, hi in inv.bands]
    f_max = None if None in highs else BAND_EDGE * max(highs)
    # the inversion checks its own memory estimate (below), not the planner's forward-run one
    extra = {"vs_range": ranges["vs"]} if "vs" in ranges else {}
    plan = plan_scene(fwd, velocity_range=bounds, f_max=f_max, check_memory_of_run=False, **extra)
    nyq = 0.5 / plan.dt
    for i, (lo, hi) in enumerate(inv.bands):
        for name, f in (("f_low", lo), ("f_high", hi)):
            if f is not None and f >= 0.9 * nyq:
                raise ValueError(f"inversion.bands[{i}]: {name} {f:g} Hz is above 0.9 x the Nyquist frequency {nyq:.3g} Hz of the "
                                 f"simulation (dt = {plan.dt:.4g} s, planned for the wavelet's band up to {plan.f_max:.3g} Hz): the "
                                 f"wavelet has no energy there; use a corner below {0.9 * nyq:.3g} Hz, or null for the full band")  # fmt: skip
    a = plan.attenuation if physics == "viscoacoustic" else None
    for i, (lo, hi) in enumerate(inv.bands if a is not None else []):  # Q is flat over q_band only
        if (hi is not None and hi < a.q_band[0]) or (lo is not None and lo > a.q_band[1]):
            plan.warnings.append(f"inversion.bands[{i}]: {format_band(lo, hi)} lies outside model.q_band {[round(f, 3) for f in a.q_band]} Hz, "
                                 f"where Q is not the constant Q of the model: the Q this band fits is another attenuation; set "
                                 f"model.q_band to cover the inversion's bands")  # fmt: skip
    memory_line = check_fwi_memory(cfg, plan)
    plan.reasons["memory"] = memory_line
    if "density" in plan.reasons and {"rho", "ip"} & set(_inverted(cfg)):  # (acoustic_vd) the start model's contrasts say nothing
        plan.reasons["density"] = (f"inverted ({', '.join(_inverted(cfg))}): whether the result needs the density is for the "
                                   f"inverted model to say, not the start model")
    weights = _check_weights(cfg, plan)
    scene = build_scene(fwd, plan)
    observed = read_observed(cfg.observed, scene, fwd.geometry, bands=inv.bands) if cfg.observed is not None else None
    if observed is not None:
        _check_observed_selected(cfg, observed, weights)
    if getattr(cfg, "parallel", None) is not None:  # scheduler reachable, devices present, not more workers than shots
        check_pool(cfg.parallel, plan.device, fwd.n_shots)
    net = getattr(cfg, "network", None)
    network = None if net is None else MLP(plan.shape, v0=net["v0"], scale=net["scale"], hidden=net["hidden"], seed=net["seed"], zero_output=True)
    space = ModelSpace(physics, _start_models(scene.model, physics), _inverted(cfg), inv.parameterization, bounds_of, network,
                       inv.transform)
    return Prepared(plan, scene, bounds, observed, space)


def wave_speed_range(cfg, ranges: dict) -> tuple:
    """(slowest, fastest) wave speed (m/s) of every model within ranges (ModelSpace.physical_ranges): vp's range, but
    for vti the qP speeds (the slowest at the lowest epsilon and delta, delta <= epsilon; the fastest horizontal,
    vp_max sqrt(1 + 2 epsilon_max)) and for viscoacoustic the P phase velocity at the Q band's low end and the
    unrelaxed speed (the start model's q_band, f_ref and mechanisms, scene.attenuation_check; lower Q disperses more)."""
    physics, vp = _physics(cfg), ranges["vp"]
    if physics == "vti":  # qP speeds grow with epsilon and with delta
        (e0, e1), d0 = ranges["epsilon"], min(ranges["delta"][0], ranges["epsilon"][0])
        return (vp[0] * float(qp_min_speed_ratio(np.array([e0]), np.array([d0]))[0]), vp[1] * float(np.sqrt(1.0 + 2.0 * e1)))
    if physics == "viscoacoustic":
        from adseismic.kernels.viscoacoustic import fit_mechanisms

        fwd = cfg.forward
        a = attenuation_check(fwd.model, np.asarray(fwd.geometry.sources, float), np.asarray(fwd.geometry.receivers, float), fwd.wavelet)
        mech, q = fit_mechanisms(*a.q_band, a.mechanisms), np.array(ranges["q"])
        slow, _ = p_speeds(np.full(2, vp[0]), q, mech, a.f_ref, a.q_band[0])
        _, fast = p_speeds(np.full(2, vp[1]), q, mech, a.f_ref, a.q_band[0])
        return float(slow.min()), float(fast.max())
    return vp


def check_fwi_memory(cfg, plan) -> str:
    """Refuse (ValueError) an inversion whose estimated peak memory exceeds simulation.memory_budget_gb or the
    device's free memory (unless simulation.force), or whose inversion.memory_budget_gb is below the gradient's
    minimum; returns the account of the estimate for the plan. Estimate: the larger of the observed-data simulation
    (every shot at once) and one gradient of a batch of shots_per_batch shots (checkpoints within
    inversion.memory_budget_gb), plus the observed data, its band-passed copy and the weights (float64)."""
    from adseismic.scene import check_memory, forward_memory_bytes, gradient_memory_bytes

    inv, fwd = cfg.inversion, cfg.forward
    n_shots, n_rec = fwd.n_shots, len(fwd.geometry.receivers)
    batch = min(inv.shots_per_batch or n_shots, n_shots)
    budget = None if inv.memory_budget_gb is None else inv.memory_budget_gb * 1e9
    try:
        grad = gradient_memory_bytes(plan, batch, budget)
    except ValueError as e:
        raise ValueError(f"inversion.memory_budget_gb: {inv.memory_budget_gb:g} GB is too small: {e}") from None
    itemsize = 4 if plan.precision == "float32" else 8
    sim_obs = forward_memory_bytes(plan.padded_cells, n_shots, n_rec, plan.nt, itemsize) if cfg.true_model is not None else 0
    need = max(grad, sim_obs) + 3 * 8 * n_shots * n_rec * plan.nt
    return check_memory(need, fwd.simulation, f"inversion: gradients of {batch} shot(s) at once on a "
                        f"{' x '.join(map(str, plan.shape))} grid, {plan.nt:,} steps, and the data of {n_shots} shots",
                        "use fewer shots per batch (inversion.shots_per_batch), a checkpoint budget (inversion.memory_budget_gb), "
                        "a lower highest band or a smaller domain")  # fmt: skip


def _check_weights(cfg, plan):
    """The data weights of inversion.offsets and time_window; refuses (ValueError) a selection that keeps no
    sample, or (synthetic study) a time window that ends before any wave from a source can reach a selected
    receiver at the true model's highest velocity."""
    inv, geo = cfg.inversion, cfg.forward.geometry
    w = data_weights(SimpleNamespace(plan=plan), inv, geo)
    off = np.linalg.norm(geo.receivers[None, :, :] - geo.sources[:, None, :], axis=-1)
    used = w.any(axis=-1)
    if inv.offsets is not None and not ((off >= inv.offsets[0]) & (off <= inv.offsets[1])).any():
        raise ValueError(f"inversion.offsets: [{inv.offsets[0]:g}, {inv.offsets[1]:g}] m selects none of the {off.size} "
                         f"source-receiver pairs (their offsets run {off.min():.4g}..{off.max():.4g} m); widen it or drop it")
    record = (plan.nt - 1) * plan.dt
    if not used.any():
        t0, t1 = inv.time_window
        raise ValueError(f"inversion.time_window: [{t0:g}, {t1:g}] s keeps no sample of the {record:.4g} s record "
                         f"(dt = {plan.dt:.4g} s); give a window inside [0, {record:.4g}] s")
    if inv.time_window is not None and cfg.true_model is not None:
        first = float(off[used].min()) / cfg.true_model.vmax  # no wave is faster than the model's highest velocity
        if inv.time_window[1] <= first:
            raise ValueError(f"inversion.time_window: [{inv.time_window[0]:g}, {inv.time_window[1]:g}] s ends before the "
                             f"earliest possible arrival at the selected receivers ({first:.4g} s: offset {off[used].min():.4g} m "
                             f"at the true model's v_max {cfg.true_model.vmax:.0f} m/s): the window holds no data; move it later")
    return w


def _check_observed_selected(cfg, observed, weights):
    """Refuse observed data that are all zero, or all zero where the offsets and time window keep samples."""
    inv = cfg.inversion
    if not np.any(observed):
        raise ValueError(f"observed: every sample of the observed data is zero ({observed.shape[0]} shots x "
                         f"{observed.shape[1]} receivers x {observed.shape[2]} samples on the simulation's time axis); "
                         f"check the files and their time range against the record")
    if not np.any(weights * observed):
        sel = ", ".join(f"{k} {list(v)}" for k, v in (("offsets (m)", inv.offsets), ("time_window (s)", inv.time_window)) if v)
        raise ValueError(f"inversion: the observed data are zero wherever the selection keeps samples ({sel}); the misfit "
                         f"would be 0: widen inversion.offsets / time_window to where the data are")


def _observed(cfg, prep: Prepared, rundir: Path, progress, sim: Simulator | None = None):
    """The observed data, kept in RUNDIR/observed.h5 for a resumed run: acoustic an array (n_shots, n_receivers,
    nt) (dataset data); elastic {channel: array} (a dataset per recorded channel, vx, vz, pressure, das, with its units
    attribute; simulated from the true model)."""
    path = rundir / "observed.h5"
    if path.exists():
        try:
            with h5py.File(path, "r") as f:
                return f["data"][...] if _physics(cfg) == "acoustic" else {c: f[c][...] for c in sim.channels}
        except (OSError, KeyError) as e:  # written atomically by us, so only damage or a foreign file gets here
            raise ValueError(f"--resume: {path} cannot be read ({type(e).__name__}: {e}); delete it to simulate or read the "
                             f"observed data again, or start a new run directory") from None
    scene, p = prep.scene, prep.plan
    if _physics(cfg) != "acoustic":  # a synthetic study (the config refuses observed files with the elastic solver)
        true = cfg.true_model.resample(p.dx, p.origin, p.shape)
        log.info("simulating observed data from the true model (%d shots, %s)", len(scene.source_amplitudes), _physics(cfg))
        data = sim.forward(_start_models(true, _physics(cfg)), p.dx, p.dt, scene.source_amplitudes, scene.source_locations,
                           scene.receiver_locations, progress=progress)  # fmt: skip
        data = {c: np.asarray(d, float) for c, d in data.items()}

        def fill(f):
            for c, d in data.items():
                f.create_dataset(c, data=d).attrs["units"] = RECORDED_UNITS[c]

        write_h5_atomic(path, fill)
        return data
    if prep.observed is not None:
        data = prep.observed
    else:
        v_true = cfg.true_model.resample(p.dx, p.origin, p.shape).values
        log.info("simulating observed data from the true model (%d shots)", len(scene.source_amplitudes))
        data = forward(v_true, p.dx, p.dt, scene.source_amplitudes, scene.source_locations, scene.receiver_locations,
                       order=p.order, pml_width=p.pml_width, pml_reflection=p.pml_reflection, free_surface=p.free_surface,
                       device=p.device, precision=p.precision, progress=progress).receiver_amplitudes  # fmt: skip
    write_h5_atomic(path, lambda f: f.create_dataset("data", data=data))
    from adseismic.data.asdf import write_forward_asdf  # the same data in ASDF for other tools (pyasdf optional)

    write_forward_asdf(rundir / "observed_waveforms.h5", receiver_data=data, dt=p.dt, source_coordinates=cfg.forward.geometry.sources,
                       receiver_coordinates=cfg.forward.geometry.receivers)
    return data


def _check_band_nyquist(bands, dt_in: float, where: str) -> None:
    """Refuse a band corner at or above the observed data's Nyquist frequency (the data hold nothing there)."""
    nyq = 0.5 / dt_in
    for i, band in enumerate(bands or []):
        for name, f in zip(("f_low", "f_high"), band):
            if f is not None and f >= nyq:
                raise ValueError(f"inversion.bands[{i}]: {name} {f:g} Hz is at or above the Nyquist frequency {nyq:.4g} Hz of the "
                                 f"observed data ({where}, dt = {dt_in:.4g} s): they hold nothing there; use a corner below "
                                 f"{0.8 * nyq:.3g} Hz (recorders cut near 0.8 x Nyquist), or null for the full band")  # fmt: skip


def read_observed(spec, scene, geometry, bands=None):
    """Observed data (n_shots, n_receivers, nt) on the scene's time axis, from our HDF5, ASDF or SEG-Y/SU
    files; the file's shot/receiver counts and coordinates must match the config's geometry. bands: the inversion's
    (f_low, f_high) Hz bands, refused when a corner is at or above the data's Nyquist frequency."""
    p = scene.plan
    if spec["kind"] in ("mseed", "sac"):
        return _read_station_shots(spec, scene, geometry, bands)
    if spec["kind"] == "hdf5":
        from adseismic.data.store import read_forward

        try:
            d = read_forward(spec["path"])
        except ValueError as e:
            raise ValueError(f"observed.path: {e}") from None
        data, dt_in, t0 = d.receiver_data, d.dt, 0.0
        if data.ndim != 3 or data.size == 0 or not (np.isfinite(dt_in) and dt_in > 0):
            raise ValueError(f"observed.path: {spec['path']}: receiver_data of shape {data.shape} with dt = {dt_in:g} s is not "
                             f"(shots, receivers, samples >= 1) data with a positive sample interval; write it with 'adseismic forward'")
        src, rec = d.source_coordinates, np.broadcast_to(d.receiver_coordinates, (len(d.source_coordinates), *d.receiver_coordinates.shape))
    elif spec["kind"] == "asdf":  # shots = waveform tags shot_<k>, receivers = stations (adseismic.data.asdf)
        from adseismic.data.asdf import read_shot_gathers_asdf

        try:
            g = read_shot_gathers_asdf(spec["path"], reference=spec.get("reference"), ndim=scene.model.ndim,
                                       component=spec.get("component"))
        except ValueError as e:
            raise ValueError(f"observed.path: {e}") from None
        data, dt_in, t0, src, rec = g.data, g.dt, g.t0, g.sources, g.receivers
    else:
        from adseismic.data.read import read_shot_gathers

        g = read_shot_gathers([spec["path"]], fmt=spec["kind"].upper(), coordinate_scale=spec.get("coordinate_scale"), ndim=scene.model.ndim,
                              depth_convention=spec.get("depth_convention") or "elevation", model=scene.model)  # fmt: skip
        data, dt_in, t0, src, rec = g.data, g.dt, g.t0, g.sources, g.receivers
    _check_band_nyquist(bands, dt_in, f"observed.path {Path(spec['path']).name}")
    n_shots, n_rec = scene.receiver_locations.shape[:2]
    if data.shape[:2] != (n_shots, n_rec):
        raise ValueError(f"observed.path: the data hold {data.shape[0]} shots x {data.shape[1]} receivers but the geometry "
                         f"has {n_shots} x {n_rec}; make geometry.sources/receivers match the file")  # fmt: skip
    for name, file_pts, cfg_pts in (("sources", src, geometry.sources), ("receivers", rec, np.broadcast_to(geometry.receivers, rec.shape))):
        diff = np.abs(np.asarray(file_pts) - cfg_pts)
        off = diff.max()
        if off > 0.5 * p.dx:
            hint = ""
            if spec["kind"] in ("segy", "su") and diff[..., 0].max() > 0.5 * p.dx >= diff[..., 1:].max():
                hint = (f" (only the depths differ: file z {np.min(np.asarray(file_pts)[..., 0]):.4g}..{np.max(np.asarray(file_pts)[..., 0]):.4g} m; "
                        f"if the file stores depths in its elevation fields, set observed.depth_convention: depth, "
                        f"or elevation for the SEG-Y standard)")  # fmt: skip
            raise ValueError(f"observed.path: the file's {name} coordinates differ from geometry.{name} by up to {off:.3g} m "
                             f"(more than half a cell, {0.5 * p.dx:g} m){hint}; make the config's geometry match the file")  # fmt: skip
    if abs(dt_in - p.dt) > 1e-9 * p.dt or data.shape[2] != p.nt or t0 != 0.0:
        from adseismic.data.preprocess import preprocess

        data = preprocess(data, dt_in, dt=p.dt, nt=p.nt, t_shift=-t0, detrend=False, taper=0.0, fmax_required=p.f_max)
    return data


def _read_station_shots(spec, scene, geometry, bands=None):
    """One MiniSEED/SAC file (or glob) per shot, receivers = stations (coordinates from StationXML or
    SAC headers, projected about spec["reference"]); time zero = spec["shot_times"][i] or the first sample."""
    from obspy import UTCDateTime

    from adseismic.data.geometry import check_offline, check_samples
    from adseismic.data.preprocess import preprocess
    from adseismic.data.read import read_station_traces

    p = scene.plan
    out = []
    for i, path in enumerate(spec["paths"]):
        st = read_station_traces(path, inventory=spec.get("inventory"), reference=spec.get("reference"),
                                 ndim=scene.model.ndim, component=spec.get("component"))  # fmt: skip
        check_offline(st.offline, st.names, scene.model, "observed.reference")
        if len(st.names) != len(geometry.receivers):
            raise ValueError(f"observed.paths[{i}]: {len(st.names)} traces but geometry.receivers has {len(geometry.receivers)}")
        off = np.abs(st.positions - geometry.receivers).max()
        if off > 0.5 * p.dx:
            raise ValueError(f"observed.paths[{i}]: station coordinates differ from geometry.receivers by up to {off:.3g} m "
                             f"(more than half a cell, {0.5 * p.dx:g} m); order the receivers as the traces ({', '.join(st.names[:3])}, ...)")  # fmt: skip
        _check_band_nyquist(bands, st.dt, f"observed.paths[{i}]")
        try:
            shift = 0.0 if spec.get("shot_times") is None else float(UTCDateTime(spec["shot_times"][i]) - st.starttime)
        except Exception:  # noqa: BLE001 - ObsPy raises several kinds for a bad time
            raise ValueError(f"observed.shot_times[{i}]: {spec['shot_times'][i]!r} is not a UTC time; write e.g. 2024-01-01T00:00:00.5") from None
        check_samples(st.data, st.names)
        out.append(preprocess(st.data, st.dt, dt=p.dt, nt=p.nt, t_shift=shift, detrend=False, taper=0.0, fmax_required=p.f_max))
    return np.stack(out)


def data_weights(scene, inv, geometry):
    """Per-sample weights (n_shots, n_receivers, nt) of the offset mute and the time window (1 = used)."""
    p = scene.plan
    w = np.ones((len(geometry.sources), len(geometry.receivers), p.nt))
    if inv.offsets is not None:
        off = np.linalg.norm(geometry.receivers[None, :, :] - geometry.sources[:, None, :], axis=-1)
        w *= ((off >= inv.offsets[0]) & (off <= inv.offsets[1]))[..., None]
    if inv.time_window is not None:
        t = np.arange(p.nt) * p.dt
        t0, t1 = inv.time_window
        ramp = 0.1 * (t1 - t0)
        up = np.clip((t - t0) / ramp, 0.0, 1.0)
        down = np.clip((t1 - t) / ramp, 0.0, 1.0)
        w *= (0.5 - 0.5 * np.cos(np.pi * up)) * (0.5 - 0.5 * np.cos(np.pi * down))
    return w


def run_fwi(cfg, rundir, progress=True, prepared: Prepared | None = None) -> FWIResult:
    """Run (or resume, when rundir holds journals) the inversion described by cfg, an FWIConfig
    (config.load_fwi_config), writing model.h5, history.h5, the log and PNGs into the folder rundir. Returns the
    FWIResult: the inverted model (nz, [ny,] nx) in m/s on the simulation grid (spacing dx m, origin m).
    With a `parallel:` section (cfg.parallel) the shots of every evaluation run on Dask workers or on the threads of
    several devices (solve.pools.open_pool, one batch per worker unless inversion.shots_per_batch says otherwise)."""
    t_start = time.perf_counter()
    prep = prepared or prepare_fwi(cfg)
    if getattr(cfg, "parallel", None) is None:
        return _run_fwi(cfg, rundir, progress, prep, t_start, None)
    with open_pool(cfg.parallel, prep.plan.device, cfg.forward.n_shots, progress) as pool:
        return _run_fwi(cfg, rundir, progress, prep, t_start, pool)


class Simulator:
    """The physics side of the objective: simulate and differentiate one physics on the plan's grid.

    channels: the recorded data's names, each (n_shots, n_receivers, nt): acoustic "data" (the field u); elastic
    recording.names (adseismic.solve.receivers.Recording: vx, vz (m/s), pressure (Pa), das strain rate (1/s)), whose
    solver records at recording.locations (the receiver locations passed in) and maps them to the channels with the
    exact adjoint for the misfit's residuals. kw: the solver's keyword arguments (order, PML, free surface, device,
    precision, memory budget). Elastic: source_type and source_components (n_shots, n_src, 2|3) as solve.elastic takes
    them; n_receivers: the receiver points. physics "acoustic_vd", "viscoacoustic" and "vti" run their own solvers
    (MOMENT_SOLVERS: the explosive moment M0 = source_components[..., 0] x the wavelet), the channels and recording as
    elastic's; viscoacoustic's kw pins q_band, f_ref and mechanisms (the plan's, fixed through the inversion)."""

    def __init__(self, physics: str, kw: dict, recording=None, n_receivers=0, source_type="force", source_components=None):
        self.physics, self.kw, self.recording, self.n = physics, dict(kw), recording, n_receivers
        self.channels = ("data",) if physics == "acoustic" else tuple(recording.names)
        self.source_type, self.source_components = source_type, source_components

    def _elastic_kw(self, sl):
        comp = None if self.source_components is None else self.source_components[sl]
        return dict(self.kw, source_type=self.source_type, source_components=comp)

    def forward(self, physical, dx, dt, amp, src, rec, sl=slice(None), progress=False) -> dict:
        """{channel: (n_shots, n_receivers, nt)} for physical {vp, [vs, rho]} (m/s, kg/m^3) (viscoacoustic {vp, q, rho},
        vti {vp, epsilon, delta, rho})."""
        if self.physics == "acoustic":
            kw = {k: v for k, v in self.kw.items() if k != "memory_budget"}
            return {"data": forward(physical["vp"], dx, dt, amp, src, rec, progress=progress, **kw).receiver_amplitudes}
        if self.physics in MOMENT_SOLVERS:
            solve, _, models = MOMENT_SOLVERS[self.physics]
            kw = {k: v for k, v in self.kw.items() if k != "memory_budget"}
            r = solve(*(physical[k] for k in models), dx, dt, self._moment(amp, sl), src, rec, progress=progress, **kw)
        else:
            kw = {k: v for k, v in self._elastic_kw(sl).items() if k != "memory_budget"}
            r = forward_elastic(physical["vp"], physical["vs"], physical["rho"], dx, dt, amp, src, rec, progress=progress, **kw)
        return self.recording.data({c: np.asarray(getattr(r, c), float) for c in ("vx", "vz", "pressure")}, self.n)

    def _moment(self, amp, sl):
        """MOMENT_SOLVERS' source S(t): the explosive moment M0 (source_components[..., 0]) x the wavelet amp."""
        return amp * self.source_components[sl][:, :, :1]

    def gradient(self, physical, dx, dt, amp, src, rec, misfit, wrt, sl=slice(None), illumination=False):
        """(loss, {name in wrt: dJ/dname (nz, [ny,] nx)}, {channel: synthetic}, illumination or None); misfit: a
        callable {channel: synthetic} -> (J, {channel: dJ/dsynthetic}), or, acoustic only, the resident data
        (observed, weights) as float64 Warp arrays on the device for the weighted "l2" misfit formed there (the
        synthetic is then a Warp array there too)."""
        if self.physics == "acoustic" and isinstance(misfit, tuple):
            r = gradient(physical["vp"], dx, dt, amp, src, rec, misfit[0], weights=misfit[1], illumination=illumination, **self.kw)
            return r.loss, {"vp": r.velocity}, {"data": r.synthetic}, r.illumination
        if self.physics == "acoustic":
            r = gradient(physical["vp"], dx, dt, amp, src, rec, misfit=lambda d: _one(misfit, d), illumination=illumination, **self.kw)
            return r.loss, {"vp": r.velocity}, {"data": r.synthetic}, r.illumination

        def recorded_misfit(syn):  # the solver's vx, vz, pressure -> the channels, and the residuals back (exact adjoint)
            j, adj = misfit(self.recording.data({c: np.asarray(syn[c], float) for c in ("vx", "vz", "pressure")}, self.n))
            return j, self.recording.adjoint(adj, self.n)

        if self.physics in MOMENT_SOLVERS:  # (acoustic_vd: vs stays 0, never inverted: its gradient 0)
            _, differentiate, models = MOMENT_SOLVERS[self.physics]
            r = differentiate(*(physical[k] for k in models), dx, dt, self._moment(amp, sl), src, rec, misfit=recorded_misfit,
                              wrt=tuple(k for k in wrt if k in models), **self.kw)  # fmt: skip
        else:
            models = wrt
            r = gradient_elastic(physical["vp"], physical["vs"], physical["rho"], dx, dt, amp, src, rec, misfit=recorded_misfit,
                                 wrt=tuple(wrt), **self._elastic_kw(sl))  # fmt: skip
        syn = self.recording.data({c: np.asarray(r.synthetic[c], float) for c in ("vx", "vz", "pressure")}, self.n)
        grads = {k: np.asarray(getattr(r, k), float) if k in models else np.zeros(np.shape(physical["vp"])) for k in wrt}
        return r.loss, grads, syn, None


def _one(misfit, d):
    j, adj = misfit({"data": d})
    return j, adj["data"]


def make_objective(space: ModelSpace, sim: Simulator, plan, amp, src, rec, observed: dict, weights, batches, inv,
                   region_mask, depth, scale: dict, scale_path=None, timing=None, last=None, pool=None):
    """The inversion's objective x -> (f, dJ/dx) for one band (x: the model space's vector).

    f = sum over batches and channels of the named misfit of the weighted data, divided by its value at the band's
    start (scale["misfit"], set by the first evaluation and kept in scale_path for a resumed run), plus the
    regularisation of the model space's cells m (tikhonov, tv, inversion settings). The gradient per cell dJ/dm is
    masked, smoothed and preconditioned (conditioning), then pulled back to x by the model space. observed:
    {channel: (n_shots, n_receivers, nt)}; weights (n_shots, n_receivers, nt); amp (n_shots, n_src, nt); src, rec
    (n_shots, n, ndim) m. last: a dict receiving the latest per-cell gradients (for figures) and shot 0's residual."""
    shape, last = space.shape, {} if last is None else last
    wrt = PHYSICS_PARAMETERS[space.physics]  # (elastic: all three, which the chain rule and the vs clamp may mix)
    want_illum = inv.preconditioning == "pseudo_hessian"
    tm = timing or SimpleNamespace(start=lambda: None, now={"gradient": 0.0, "misfit": 0.0, "conditioning": 0.0})
    resident = {}
    if sim.physics == "acoustic" and inv.misfit == "l2" and pool is None:  # the band's data stay on the device
        resident = {sl.start: tuple(wp.array(np.ascontiguousarray(a[sl]), dtype=wp.float64, device=plan.device)
                                    for a in (observed["data"], weights)) for sl in batches}  # fmt: skip

    def objective(xv):
        tm.start()
        pt = space.point(xv)
        loss, illum = 0.0, np.zeros(shape) if want_illum else None
        grads = {k: np.zeros(shape) for k in wrt}
        if pool is not None:  # the batches on the workers or devices (acoustic), summed here in batch order (float64)
            t = time.perf_counter()
            rs = pool.evaluate(pt.physical["vp"], {"dx": plan.dx, "dt": plan.dt, "misfit": inv.misfit, "illumination": want_illum, "kw": sim.kw})
            tm.now["gradient"] += time.perf_counter() - t  # (the workers' misfits counted as simulation)
            loss, grads["vp"], illum = reduce_in_order(rs, shape)
            last["residual"] = weights[0] * (observed["data"][0] - rs[0]["synthetic0"])
        for sl in batches if pool is None else ():
            w_sl = weights[sl]

            def weighted(syn, w_sl=w_sl, sl=sl):  # misfit of the muted, windowed data, summed over channels
                t = time.perf_counter()
                j, adj = 0.0, {}
                for c in sim.channels:
                    jc, a = named_misfit(inv.misfit, w_sl * np.asarray(syn[c], float), w_sl * observed[c][sl], plan.dt)
                    j, adj[c] = j + jc, w_sl * a
                tm.now["misfit"] += time.perf_counter() - t
                return j, adj

            t = time.perf_counter()
            misfit = resident.get(sl.start, weighted)
            loss_b, g_b, syn, il = sim.gradient(pt.physical, plan.dx, plan.dt, amp[sl], src[sl], rec[sl], misfit, wrt, sl, want_illum)
            tm.now["gradient"] += time.perf_counter() - t
            if sl.start == 0:
                c0 = sim.channels[0]
                syn0 = syn[c0][0].numpy() if isinstance(syn[c0], wp.array) else syn[c0][0]
                last["residual"] = weights[0] * (observed[c0][0] - np.asarray(syn0, float))
            loss += loss_b
            for k in wrt:
                grads[k] += g_b[k]
            if illum is not None:
                illum += il
        t = time.perf_counter()
        if "misfit" not in scale:
            scale["misfit"] = loss if loss > 0 else 1.0
            if scale_path is not None:
                write_text_atomic(scale_path, json.dumps(scale))
        f = loss / scale["misfit"]
        gm = {}
        for k, g in space.cells_gradient(pt, grads).items():
            g = conditioning.precondition(conditioning.smooth(g * region_mask, plan.dx, inv.smoothing) * region_mask,
                                          inv.preconditioning, illum, depth) / scale["misfit"]  # fmt: skip
            for fn, w in ((conditioning.tikhonov, inv.tikhonov), (conditioning.total_variation, inv.tv)):
                rv, rg = fn(pt.m[k], w)
                f, g = f + rv, g + rg * region_mask
            gm[k] = g
        last["cells"], last["x"] = gm, np.array(xv, float)
        gx = space.x_gradient(xv, gm)
        tm.now["conditioning"] = time.perf_counter() - t
        return f, gx

    return objective


def _run_fwi(cfg, rundir, progress, prep: Prepared, t_start, pool) -> FWIResult:
    rundir = Path(rundir)
    rundir.mkdir(parents=True, exist_ok=True)
    inv, fwd = cfg.inversion, cfg.forward
    scene, bounds, p, space = prep.scene, prep.bounds, prep.plan, prep.space
    log.info("plan:\n%s", p.describe())
    for key, why in cfg.chosen.items():
        log.info("inversion.%s: %s (%s)", key, getattr(inv, key), why)
    sim = _simulator(cfg, prep, inv, bounds)
    obs = _observed(cfg, prep, rundir, progress, sim)
    obs = obs if isinstance(obs, dict) else {"data": obs}
    region_mask, _ = _masks(p, inv, fwd)  # (the model errors': on the plan's grid)
    history = _History(rundir / "history.h5", p.dx, p.origin, units=_history_units(space))
    per_batch = inv.shots_per_batch
    if per_batch is None and pool is not None:
        per_batch = pool_shots_per_batch(len(scene.source_amplitudes), pool)
        log.info("inversion.shots_per_batch: %d (one batch per worker of the pool; set it for a result that does not depend on "
                 "the number of workers, bit for bit)", per_batch)
    batches = shot_slices(len(scene.source_amplitudes), per_batch)
    x = space.x0()
    start = space.point(x).physical
    results = []
    last = {}  # the latest gradient (accepted iterate) and data residual of shot 0, for the figures
    figures = plotting.Background()  # each band's figures are drawn while the next band runs
    grid, gspace = p, space  # the grid and the model space that x lives on (inversion.grid per_band: the band's)
    for b, band in enumerate(inv.bands):
        pb, m = band_plan(cfg, p, bounds, band)
        wavelet, obs_p = band_filter(scene.wavelet, p.dt, band), {c: band_filter(o, p.dt, band) for c, o in obs.items()}
        if pb is not p:
            holds, modelling, residual = band_grid_holds(sim, scene, p, pb, m, gspace.point(x).physical["vp"], grid, wavelet,
                                                         obs_p["data"], data_weights(SimpleNamespace(plan=p), inv, fwd.geometry),
                                                         inv.shots_per_batch)  # fmt: skip
            log.info("band %d (%s) grid check: on %g m cells the data differ from the plan grid's by %.3g of the observed "
                     "data, against a residual of %.3g at the band's start model (at most %g x it allowed): %s", b,
                     format_band(*band), pb.dx, modelling, residual, MODELLING_SHARE,
                     "the band runs on its own grid" if holds else "the band runs on the plan's grid")  # fmt: skip
            if not holds:
                log.warning("band %d (%s): the %g m grid misses %.0f%% of the plan grid's data where the misfit looks (the "
                            "residual to explain is %.0f%%); this band runs on the plan's grid. Usual causes: a start model "
                            "already close to the data, whose small residual the coarse grid's dispersion error exceeds; "
                            "near a free surface, traces within a few cells of a shallow source (inversion.offsets can mute them)",
                            b, format_band(*band), pb.dx, 100 * modelling, 100 * residual)  # fmt: skip
                pb, m = p, 1
        if not _same_grid(pb, grid):  # the model moves onto the band's grid; L-BFGS starts afresh every band anyway
            gspace = space.around({"vp": _regridded(gspace.point(x).physical["vp"], grid, pb, velocity=True)})
            x, grid = gspace.x0(), pb
        if pb is not p:
            log.info("band %d (%s) grid: %s cells, dx = %g m, dt = %g s (%d x the plan's), %d steps; %s", b, format_band(*band),
                     " x ".join(map(str, pb.shape)), pb.dx, pb.dt, m, pb.nt, "; ".join(pb.warnings) or "no warnings")  # fmt: skip
        mask_b, depth_b = _masks(pb, inv, fwd)
        weights_b = data_weights(SimpleNamespace(plan=pb), inv, fwd.geometry)
        wavelet = _decimated(wavelet, m, pb.nt)
        obs_b = {c: _decimated(o, m, pb.nt) for c, o in obs_p.items()}
        amp = np.broadcast_to(wavelet, scene.source_amplitudes.shape[:-1] + wavelet.shape).copy()
        sim.kw["pml_frequency"] = band[1] / 2 if band[1] else None
        if inv.wavelet_estimation:  # (acoustic: refused for elastic physics by the config)
            syn = sim.forward(gspace.point(x).physical, pb.dx, pb.dt, amp, scene.source_locations, scene.receiver_locations)["data"]
            wavelet = estimate_wavelet(wavelet, syn, obs_b["data"])
            amp = np.broadcast_to(wavelet, amp.shape).copy()
        # The misfit is normalised by its value at the band's start model; that value is kept on disk
        # because a resumed run replays the first evaluations from the journal without calling us.
        scale_path = rundir / f"band{b}_scale.json"
        scale = json.loads(scale_path.read_text()) if scale_path.exists() else {}
        if pool is not None:  # each batch's data stay on a worker for the band; an evaluation sends only the model
            pool.keep([{"amplitudes": amp[sl], "sources": scene.source_locations[sl], "receivers": scene.receiver_locations[sl],
                        "weights": weights_b[sl], "observed": obs_b["data"][sl], "first": sl.start} for sl in batches])  # fmt: skip

        timing = _EvaluationTimes(b, history)
        objective = make_objective(gspace, sim, pb, amp, scene.source_locations, scene.receiver_locations, obs_b, weights_b, batches,
                                   inv, mask_b, depth_b, scale, scale_path, timing, last, pool)  # fmt: skip

        def callback(iteration, xv, f, g, b=b, band=band, gspace=gspace, pb=pb):
            t, appended = time.perf_counter(), history.seconds
            pt = gspace.point(xv)
            cells = _cells_of(gspace, xv, g, last)
            models, grads = _history_models(gspace, pt), _history_gradients(gspace, cells, g)
            if pb is not p:  # (per_band: acoustic pixels) onto the plan's grid, which the history keeps
                models, grads = _regridded(models, pb, p, velocity=True), _regridded(grads, pb, p, velocity=False)
            history.add(b, iteration, models, grads, f, dx=pb.dx)
            last["gradient"] = cells
            log.info("band %d (%s) iteration %d: misfit %.4g", b, format_band(*band), iteration, f)
            timing.iteration += time.perf_counter() - t - (history.seconds - appended)

        res = minimize(objective, x, method=inv.optimizer, bounds=gspace.x_bounds(),
                       max_iterations=inv.iterations[b] if isinstance(inv.iterations, list) else inv.iterations, max_evaluations=inv.evaluations, rel_decrease=inv.rel_decrease, grad_tol=0.0,
                       journal_path=rundir / f"journal_band{b}.h5", callback=callback, on_evaluation=timing,
                       options={"gd": {"step": inv.step}, "adam": {"lr": inv.lr}}.get(inv.optimizer))  # fmt: skip
        log.info("band %d done: %s after %d iterations, %d evaluations", b, res.stop_reason, res.iterations, res.evaluations)
        t_fig = time.perf_counter()
        if "gradient" in last and "residual" in last:  # (a run resumed after its last band has no residual)
            drawn = {"gradient": {k: np.array(v) for k, v in last["gradient"].items()}, "residual": np.array(last["residual"])}
            figures.submit(_figures, rundir, history.misfits(), gspace, gspace.point(res.x), drawn, pb, fwd, b, inv.bands)
        timing.summary(figures=time.perf_counter() - t_fig)
        results.append({"band": format_band(*band), "f_low_hz": band[0], "f_high_hz": band[1], "iterations": res.iterations, "evaluations": res.evaluations,
                        "misfit": res.f, "stop_reason": res.stop_reason})  # fmt: skip
        x = res.x
    final = gspace.point(x).physical
    if not _same_grid(grid, p):
        final = {"vp": _regridded(final["vp"], grid, p, velocity=True)}
    out = FWIResult(model=final["vp"], start_model=start["vp"], dx=p.dx, origin=p.origin, bands=results, seconds=time.perf_counter() - t_start,
                    models=final, start_models=start)  # fmt: skip
    if cfg.true_model is not None:
        out.errors = _model_errors(cfg, space, p, start, final, region_mask)
    if space.physics == "acoustic":
        _write_synthetic_asdf(rundir, fwd, scene, p, final["vp"], progress)
    figures.wait()  # before summary.json, which marks the run complete
    _write_result(rundir, out, fwd, space)
    return out


def _same_grid(a, b) -> bool:
    return a.dx == b.dx and tuple(a.shape) == tuple(b.shape) and tuple(a.origin) == tuple(b.origin)


def _masks(plan, inv, fwd) -> tuple:
    """The gradient's region mask (water depth, source radius) and the depth of each cell (m, + dx) on plan's grid."""
    shape = plan.shape
    mask = conditioning.mask(shape, plan.dx, plan.origin, inv.water_depth, fwd.geometry.sources, inv.source_radius)
    depth = (plan.origin[0] + plan.dx * np.arange(shape[0])).reshape((-1,) + (1,) * (len(shape) - 1)) * np.ones(shape) + plan.dx
    return mask, depth


def _simulator(cfg, prep: Prepared, inv, bounds) -> Simulator:
    p = prep.plan
    budget = None if inv.memory_budget_gb is None else inv.memory_budget_gb * 1e9
    kw = {"order": p.order, "pml_width": p.pml_width, "pml_reflection": p.pml_reflection, "pml_velocity": bounds[1],
          "free_surface": p.free_surface, "device": p.device, "precision": p.precision, "memory_budget": budget}
    if _physics(cfg) == "acoustic":
        return Simulator("acoustic", kw)
    if _physics(cfg) == "viscoacoustic":  # the plan's relaxation mechanisms for every band: the model means one thing
        a = p.attenuation
        kw.update(q_band=a.q_band, f_ref=a.f_ref, mechanisms=a.mechanisms)
    sc = prep.scene
    return Simulator(_physics(cfg), kw, sc.recording, len(cfg.forward.geometry.receivers), sc.source_type, sc.source_components)


def _cells_of(space: ModelSpace, xv, g, last) -> dict:
    """The per-cell gradient {name: (nz, [ny,] nx)} at x: the blocks of g (pixels), or the network's per-cell
    gradient kept by its evaluation (a replayed evaluation has none: zeros)."""
    if space.network is None:
        n = int(np.prod(space.shape))
        return {k: np.asarray(g[i * n:(i + 1) * n]).reshape(space.shape) for i, k in enumerate(space.names)}
    if "x" in last and np.array_equal(last["x"], xv):
        return last["cells"]
    return {"vp": np.zeros(space.shape)}


def _history_units(space: ModelSpace) -> str:
    if space.physics == "acoustic" and space.network is None:
        return _History.UNITS
    grads = "; ".join(f"gradient_{k} d(misfit/misfit_0)/d({k}/{REFERENCE[k]:g} {UNITS[k]})" for k in space.names)
    if space.network is not None:
        return f"model m/s; gradient d(misfit/misfit_0)/d(network weights); {grads} (per cell)"
    models = ", ".join(f"model_{k} {UNITS[k]}" for k in PHYSICS_PARAMETERS[space.physics])
    return f"{models}; {grads}"


def _history_models(space: ModelSpace, pt) -> dict | np.ndarray:
    if space.physics == "acoustic":
        return pt.physical["vp"]
    return {f"model_{k}": v for k, v in pt.physical.items()}


def _history_gradients(space: ModelSpace, cells: dict, g):
    if space.physics == "acoustic":
        return cells["vp"] if space.network is None else {"gradient": np.asarray(g), "gradient_vp": cells["vp"]}
    return {f"gradient_{k}": v for k, v in cells.items()}


def _model_errors(cfg, space: ModelSpace, p, start: dict, final: dict, region_mask) -> dict:
    """Relative model errors (L2 norm of the difference over the norm of the true model) in the region where the
    true model differs from the start by more than 1% (the anomaly) and below the water / masks. Acoustic: of vp;
    elastic: per inverted quantity (<name>_start_anomaly, ...) and, under the plain keys, their root mean square."""
    true = cfg.true_model.resample(p.dx, p.origin, p.shape)
    truth = quantities_of(_start_models(true, space.physics), space.parameterization)
    q0 = quantities_of(start, space.parameterization)
    q1 = quantities_of(final, space.parameterization)
    changed = np.zeros(space.shape, bool)
    for k in space.names:
        changed |= np.abs(truth[k] - q0[k]) > 0.01 * np.abs(truth[k])
    region = changed if changed.any() else np.ones(space.shape, bool)
    below = region_mask > 0
    per = {}
    for k in space.names:
        per[k] = {"start_anomaly": relative_error(q0[k], truth[k], region), "final_anomaly": relative_error(q1[k], truth[k], region),
                  "start_below_water": relative_error(q0[k], truth[k], below), "final_below_water": relative_error(q1[k], truth[k], below)}  # fmt: skip
    if space.physics == "acoustic":
        return per["vp"]
    out = {key: float(np.sqrt(np.mean([per[k][key] ** 2 for k in space.names]))) for key in per[space.names[0]]}
    out.update({f"{k}_{key}": v for k in space.names for key, v in per[k].items()})
    return out


def _write_synthetic_asdf(rundir: Path, fwd, scene, p, model, progress):
    """The final model's synthetics (the full wavelet, every shot) in ASDF, RUNDIR/synthetic_waveforms.h5 beside
    observed_waveforms.h5, for other tools: one forward run, made only where pyasdf is installed."""
    import importlib.util

    if importlib.util.find_spec("pyasdf") is None:
        return
    from adseismic.data.asdf import write_forward_asdf

    syn = forward(model, p.dx, p.dt, scene.source_amplitudes, scene.source_locations, scene.receiver_locations, order=p.order,
                  pml_width=p.pml_width, pml_reflection=p.pml_reflection, free_surface=p.free_surface, device=p.device,
                  precision=p.precision, progress=progress).receiver_amplitudes  # fmt: skip
    write_forward_asdf(rundir / "synthetic_waveforms.h5", receiver_data=syn, dt=p.dt, source_coordinates=fwd.geometry.sources,
                       receiver_coordinates=fwd.geometry.receivers, wavelet=scene.wavelet)


def _write_result(rundir: Path, res: FWIResult, fwd, space: ModelSpace | None = None):
    """model.h5: acoustic the datasets model and start_model (m/s); other physics each solver parameter (elastic and
    acoustic_vd vp, vs (m/s), rho (kg/m^3); viscoacoustic vp, q, rho; vti vp, epsilon, delta, rho) and its start_<name>,
    each with its units attribute, and the attribute inverted (the quantities the inversion changed); summary.json:
    bands, errors, seconds."""
    elastic = space is not None and space.physics != "acoustic"

    def fill(f):
        if elastic:
            for k in res.models:
                f.create_dataset(k, data=res.models[k]).attrs["units"] = UNITS[k]
                f.create_dataset(f"start_{k}", data=res.start_models[k]).attrs["units"] = UNITS[k]
            f.attrs["inverted"], f.attrs["parameterization"] = list(space.names), space.parameterization
        else:
            f.create_dataset("model", data=res.model)
            f.create_dataset("start_model", data=res.start_model)
        f.attrs["dx"], f.attrs["origin"] = res.dx, res.origin
        f.attrs["units"] = "; ".join(f"{k} {UNITS[k]}" for k in res.models) if elastic else "m/s"
        f.attrs["summary"] = json.dumps({"bands": res.bands, "errors": res.errors})

    write_h5_atomic(rundir / "model.h5", fill)
    write_text_atomic(rundir / "summary.json", json.dumps({"bands": res.bands, "errors": res.errors, "seconds": res.seconds}, indent=2))


def _figures(rundir: Path, misfits, space: ModelSpace, pt, last, plan, fwd, b, bands):
    """After band b of bands: the model and the last gradient (acoustic model.png, gradient.png; elastic one
    model_<name>.png and gradient_<name>.png per inverted quantity), residual.png (shot 0, observed - synthetic of
    the first channel, against receiver position in m, a panel per receiver line) and misfit.png (misfits: the
    history's rows). 3D: the x-z slice through the middle of y, sources and receivers projected onto it. Runs on
    the figures' thread (plotting.Background): it logs its own time."""
    t0 = time.perf_counter()
    name = f"band {b} ({format_band(*bands[b])})"
    origin2 = (plan.origin[0], plan.origin[-1])
    mid = (lambda a: a) if len(space.shape) == 2 else (lambda a: a[:, a.shape[1] // 2])
    src, rec = np.asarray(fwd.geometry.sources, float), np.asarray(fwd.geometry.receivers, float)
    for k in space.names:
        suffix = "" if space.physics == "acoustic" else f"_{k}"
        plotting.plot_model(rundir / f"model{suffix}.png", mid(pt.q[k]), plan.dx, origin2, sources=src[:, [0, -1]], receivers=rec[:, [0, -1]],
                            title=f"{'model' if not suffix else k} after {name}", label=f"{'velocity' if k == 'vp' else k} ({UNITS[k]})")  # fmt: skip
        plotting.plot_model(rundir / f"gradient{suffix}.png", mid(last["gradient"][k]), plan.dx, origin2, title=f"last gradient of {name}",
                            label=f"conditioned gradient\nd(misfit / its start value) / d({'v' if k == 'vp' and not suffix else k} / {REFERENCE[k]:g} {UNITS[k]})",
                            cmap="seismic", symmetric=True)  # fmt: skip
    plotting.plot_gather(rundir / "residual.png", last["residual"], plan.dt, rec, source=src[0], quantity="residual",
                         title=f"shot 0 residual (observed - synthetic, muted and windowed), {name}\n"
                               f"source (star) at {format_position(src[0])}")  # fmt: skip
    plotting.plot_misfit(rundir / "misfit.png", misfits, labels={i: format_band(*bb) for i, bb in enumerate(bands)})
    log.info("band %d figures: %.3f s on the figures' thread (beside the run)", b, time.perf_counter() - t0)
