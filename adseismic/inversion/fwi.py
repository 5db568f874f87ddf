"""Full-waveform inversion: multiscale bands, conditioned gradients, journaled optimisation, run directory.

run_fwi(config, rundir) inverts the velocity model for all shots of the config:
1. plan the grid for the velocity bounds (every model the optimiser may visit is stable and resolved)
   and resample the start model onto it;
2. observed data: simulated from `true_model` with the full wavelet (a synthetic study), or read from
   files; stored in RUNDIR/observed.h5 so that a resumed run uses the same data (and, with pyasdf, in ASDF as
   RUNDIR/observed_waveforms.h5 on the simulation's time axis, adseismic.data.asdf's layout; the final model's
   synthetics go to RUNDIR/synthetic_waveforms.h5 at the end);
3. for each band (low to high), the wavelet and the observed data get the same zero-phase
   Butterworth band-pass (filtering the source filters the synthetics exactly: the data are linear
   in the source), optionally a least-squares wavelet estimate, and the optimiser minimises the
   misfit (normalised by its value at the band's start model) plus regularisation over
   x = v / V_REF, with the gradient masked, smoothed and preconditioned;
4. every evaluation goes to a journal (RUNDIR/journal_band<k>.h5, atomic) and every iteration to
   RUNDIR/history.h5 (one group appended per iteration) and PNGs; --resume replays the journals and
   continues, reproducing an uninterrupted run. fwi.log gets a time breakdown of every evaluation
   (simulation vs the rest, _EvaluationTimes) and its sums per band.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
from scipy.signal import butter, sosfiltfilt

from adseismic.data.atomic import write_h5_atomic, write_text_atomic
from adseismic.inversion import conditioning
from adseismic.inversion.optimize import minimize
from adseismic.runs import format_band, format_position
from adseismic.scene import build_scene, plan_scene
from adseismic.solve.acoustic import forward, gradient
from adseismic.solve.batch import shot_slices
from adseismic.solve.distributed import ShotPool, check_parallel, reduce_in_order
from adseismic.solve.misfits import misfit as named_misfit

log = logging.getLogger(__name__)
V_REF = 1000.0  # m/s: the optimiser works on v / V_REF, O(1) numbers


@dataclass
class FWIResult:
    """Inverted model (nz, [ny,] nx) m/s on the simulation grid (spacing dx m, origin m), the start
    model, per-band optimiser results, and model errors when the true model is known."""

    model: np.ndarray
    start_model: np.ndarray
    dx: float
    origin: tuple
    bands: list = field(default_factory=list)
    errors: dict = field(default_factory=dict)
    seconds: float = 0.0


def band_pass(x, dt, band, order=4):
    """Zero-phase Butterworth band-pass along the last axis; band = (f_low or None, f_high or None) Hz."""
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
    return sosfiltfilt(sos, np.asarray(x, float), axis=-1)


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

    def __init__(self, path: Path, dx, origin, compression=None):
        self.path, self.dx, self.origin, self.compression = Path(path), dx, origin, compression
        self.rows = []  # (band, iteration, misfit): the misfit curve; the arrays are on disk only
        self.seconds = 0.0  # time spent in add(), for the log's time breakdown

    def add(self, band, iteration, model, grad, misfit):
        t0 = time.perf_counter()
        with h5py.File(self.path, "a" if self.rows else "w", locking=False) as f:
            if not self.rows:
                f.attrs["dx"], f.attrs["origin"], f.attrs["units"] = self.dx, self.origin, self.UNITS
                f.attrs["layout"] = "band<b>/iter<i:04d>/{model, gradient} float32, attr misfit; appended per iteration"
            name = f"band{band}/iter{iteration:04d}"
            if name in f:  # (not in a normal run: the file is truncated by a process's first add)
                del f[name]
            grp = f.create_group(name)
            for key, a in (("model", model), ("gradient", grad)):
                grp.create_dataset(key, data=np.asarray(a, np.float32), compression=self.compression)
            grp.attrs["misfit"] = float(misfit)
        self.rows.append((band, iteration, float(misfit)))
        self.seconds += time.perf_counter() - t0

    def misfits(self):
        return list(self.rows)


def read_history(path) -> list[dict]:
    """The iterations in a history.h5, in (band, iteration) order: dicts with band, iteration, misfit
    and model, gradient (float32 arrays, m/s and the conditioned gradient). An incomplete last group
    (a run killed during its append) is skipped."""
    out = []
    with h5py.File(path, "r") as f:
        for bname in f:
            if not bname.startswith("band"):
                continue
            for iname, g in f[bname].items():
                if "misfit" not in g.attrs or "model" not in g or "gradient" not in g:
                    continue
                out.append({"band": int(bname[4:]), "iteration": int(iname[4:]), "misfit": float(g.attrs["misfit"]),
                            "model": g["model"][...], "gradient": g["gradient"][...]})  # fmt: skip
    return sorted(out, key=lambda r: (r["band"], r["iteration"]))


class _EvaluationTimes:
    """The time breakdown of each real (not replayed) evaluation of one band, logged to fwi.log:

        band B evaluation K: T s (simulation S s, misfit+weights M s, conditioning C s, journal J s,
        history H s, other O s; non-kernel P%)

    K is the 0-based journal index; T the wall time since the previous evaluation ended (the band's
    start for the first); simulation the time inside solve.acoustic.gradient less its misfit callback
    (kernels, with the setup and device-host copies inside it; on CUDA it ends in the synchronisation
    its host results need, no extra one is added); misfit+weights the rest of the objective before the
    conditioning (weighting, misfit and adjoint source on the host, sums); conditioning: the scale,
    mask, smoothing, preconditioner and regularisation; journal: its save; history: the history.h5
    appends since the previous evaluation (replayed iterations included); other: the rest (optimiser,
    log). Non-kernel = 1 - simulation / T. After the band, summary() logs the sums, the figures' time
    and the non-kernel fraction. perf_counter only: cheap."""

    PARTS = ("simulation", "misfit+weights", "conditioning", "journal", "history", "other")

    def __init__(self, band, history):
        self.band, self.history = band, history
        self.mark, self.history_mark = time.perf_counter(), history.seconds
        self.total = dict.fromkeys(self.PARTS, 0.0)
        self.n, self.wall = 0, 0.0
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
                 "conditioning": self.now["conditioning"], "journal": seconds["journal"], "history": hist}  # fmt: skip
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
    simulation grid), the velocity bounds (m/s) and observed data read from files (or None)."""

    plan: object
    scene: object
    bounds: tuple
    observed: np.ndarray | None


def prepare_fwi(cfg) -> Prepared:
    """Plan for the velocity bounds and read/check observed data files; raises ValueError (bad input)
    before any output exists."""
    inv, fwd = cfg.inversion, cfg.forward
    bounds = inv.bounds or (0.75 * fwd.model.vmin, 1.25 * fwd.model.vmax)
    if not (bounds[0] <= fwd.model.vmin and fwd.model.vmax <= bounds[1]):
        raise ValueError(f"inversion.bounds: [{bounds[0]:g}, {bounds[1]:g}] m/s do not contain the start model's range "
                         f"[{fwd.model.vmin:g}, {fwd.model.vmax:g}] m/s; widen them")  # fmt: skip
    highs = [hi for _, hi in inv.bands]
    # a low-passed last band needs no grid for the wavelet's full band (Butterworth: -20 dB at 1.33 f_high)
    f_max = None if None in highs else 1.33 * max(highs)
    # the inversion checks its own memory estimate (below), not the planner's forward-run one
    plan = plan_scene(fwd, velocity_range=bounds, f_max=f_max, check_memory_of_run=False)
    nyq = 0.5 / plan.dt
    for i, (lo, hi) in enumerate(inv.bands):
        for name, f in (("f_low", lo), ("f_high", hi)):
            if f is not None and f >= 0.9 * nyq:
                raise ValueError(f"inversion.bands[{i}]: {name} {f:g} Hz is above 0.9 x the Nyquist frequency {nyq:.3g} Hz of the "
                                 f"simulation (dt = {plan.dt:.4g} s, planned for the wavelet's band up to {plan.f_max:.3g} Hz): the "
                                 f"wavelet has no energy there; use a corner below {0.9 * nyq:.3g} Hz, or null for the full band")  # fmt: skip
    memory_line = check_fwi_memory(cfg, plan)
    plan.reasons["memory"] = memory_line
    weights = _check_weights(cfg, plan)
    scene = build_scene(fwd, plan)
    observed = read_observed(cfg.observed, scene, fwd.geometry, bands=inv.bands) if cfg.observed is not None else None
    if observed is not None:
        _check_observed_selected(cfg, observed, weights)
    if getattr(cfg, "parallel", None) is not None:  # scheduler reachable, devices present, not more workers than shots
        check_parallel(cfg.parallel, plan.device, fwd.n_shots)
    return Prepared(plan, scene, bounds, observed)


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


def _observed(cfg, prep: Prepared, rundir: Path, progress):
    path = rundir / "observed.h5"
    if path.exists():
        try:
            with h5py.File(path, "r") as f:
                return f["data"][...]
        except (OSError, KeyError) as e:  # written atomically by us, so only damage or a foreign file gets here
            raise ValueError(f"--resume: {path} cannot be read ({type(e).__name__}: {e}); delete it to simulate or read the "
                             f"observed data again, or start a new run directory") from None
    scene, p = prep.scene, prep.plan
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
    With a `parallel:` section (cfg.parallel) the shots of every evaluation run on Dask workers
    (solve.distributed.ShotPool, one shot per batch unless inversion.shots_per_batch says otherwise)."""
    t_start = time.perf_counter()
    prep = prepared or prepare_fwi(cfg)
    if getattr(cfg, "parallel", None) is None:
        return _run_fwi(cfg, rundir, progress, prep, t_start, None)
    with ShotPool(cfg.parallel, prep.plan.device, cfg.forward.n_shots) as pool:
        return _run_fwi(cfg, rundir, progress, prep, t_start, pool)


def _run_fwi(cfg, rundir, progress, prep: Prepared, t_start, pool) -> FWIResult:
    rundir = Path(rundir)
    rundir.mkdir(parents=True, exist_ok=True)
    inv, fwd = cfg.inversion, cfg.forward
    scene, bounds, p = prep.scene, prep.bounds, prep.plan
    log.info("plan:\n%s", p.describe())
    obs = _observed(cfg, prep, rundir, progress)
    shape = scene.model.values.shape
    region_mask = conditioning.mask(shape, p.dx, p.origin, inv.water_depth, fwd.geometry.sources, inv.source_radius)
    depth = (p.origin[0] + p.dx * np.arange(shape[0])).reshape((-1,) + (1,) * (len(shape) - 1)) * np.ones(shape) + p.dx
    history = _History(rundir / "history.h5", p.dx, p.origin)
    batches = shot_slices(len(scene.source_amplitudes), inv.shots_per_batch or (1 if pool is not None else None))
    budget = None if inv.memory_budget_gb is None else inv.memory_budget_gb * 1e9
    kw = dict(order=p.order, pml_width=p.pml_width, pml_reflection=p.pml_reflection, pml_velocity=bounds[1],
              free_surface=p.free_surface, device=p.device, precision=p.precision, memory_budget=budget)  # fmt: skip

    x = scene.model.values.ravel() / V_REF
    results = []
    last = {}  # the latest gradient (accepted iterate) and data residual of shot 0, for the figures
    weights = data_weights(scene, inv, fwd.geometry)
    for b, band in enumerate(inv.bands):
        wavelet = band_pass(scene.wavelet, p.dt, band)
        obs_b = band_pass(obs, p.dt, band)
        amp = np.broadcast_to(wavelet, scene.source_amplitudes.shape).copy()
        kw["pml_frequency"] = band[1] / 2 if band[1] else None
        if inv.wavelet_estimation:
            syn = forward(x.reshape(shape) * V_REF, p.dx, p.dt, amp, scene.source_locations, scene.receiver_locations, **{k: v for k, v in kw.items() if k != "memory_budget"}).receiver_amplitudes
            wavelet = estimate_wavelet(wavelet, syn, obs_b)
            amp = np.broadcast_to(wavelet, amp.shape).copy()
        # The misfit is normalised by its value at the band's start model; that value is kept on disk
        # because a resumed run replays the first evaluations from the journal without calling us.
        scale_path = rundir / f"band{b}_scale.json"
        scale = json.loads(scale_path.read_text()) if scale_path.exists() else {}
        if pool is not None:  # each batch's data stay on a worker for the band; an evaluation sends only the model
            pool.keep([{"amplitudes": amp[sl], "sources": scene.source_locations[sl], "receivers": scene.receiver_locations[sl],
                        "weights": weights[sl], "observed": weights[sl] * obs_b[sl], "first": sl.start} for sl in batches])  # fmt: skip

        timing = _EvaluationTimes(b, history)

        def objective(xv, amp=amp, obs_b=obs_b, scale=scale, scale_path=scale_path, tm=timing):
            tm.start()
            v = xv.reshape(shape) * V_REF
            loss, grad, illum = 0.0, np.zeros(shape), np.zeros(shape) if inv.preconditioning == "pseudo_hessian" else None
            if pool is not None:  # the batches on the Dask workers, summed here in batch order (float64) as below
                t = time.perf_counter()
                rs = pool.evaluate(v, {"dx": p.dx, "dt": p.dt, "misfit": inv.misfit, "illumination": illum is not None, "kw": kw})
                tm.now["gradient"] += time.perf_counter() - t  # (the workers' misfits counted as simulation)
                loss, grad, illum = reduce_in_order(rs, shape)
                last["residual"] = weights[0] * (obs_b[0] - rs[0]["synthetic0"])
            for sl in batches if pool is None else ():
                w_sl, o_sl = weights[sl], weights[sl] * obs_b[sl]

                def weighted(syn, w_sl=w_sl, o_sl=o_sl):  # misfit of the muted, windowed data
                    t = time.perf_counter()
                    j, adj = named_misfit(inv.misfit, w_sl * syn, o_sl, p.dt)
                    adj = w_sl * adj
                    tm.now["misfit"] += time.perf_counter() - t
                    return j, adj

                t = time.perf_counter()
                r = gradient(v, p.dx, p.dt, amp[sl], scene.source_locations[sl], scene.receiver_locations[sl],
                             misfit=weighted, illumination=illum is not None, **kw)  # fmt: skip
                tm.now["gradient"] += time.perf_counter() - t
                if sl.start == 0:
                    last["residual"] = weights[0] * (obs_b[0] - r.synthetic[0])
                loss += r.loss
                grad += r.velocity
                if illum is not None:
                    illum += r.illumination
            t = time.perf_counter()
            if "misfit" not in scale:
                scale["misfit"] = loss if loss > 0 else 1.0
                write_text_atomic(scale_path, json.dumps(scale))
            g = conditioning.precondition(conditioning.smooth(grad * region_mask, p.dx, inv.smoothing) * region_mask,
                                          inv.preconditioning, illum, depth)  # fmt: skip
            f = loss / scale["misfit"]
            g = g * V_REF / scale["misfit"]
            m = v / V_REF
            for fn, w in ((conditioning.tikhonov, inv.tikhonov), (conditioning.total_variation, inv.tv)):
                rv, rg = fn(m, w)
                f, g = f + rv, g + rg * region_mask
            tm.now["conditioning"] = time.perf_counter() - t
            return f, g.ravel()

        def callback(iteration, xv, f, g, b=b):
            history.add(b, iteration, xv.reshape(shape) * V_REF, g.reshape(shape), f)
            last["gradient"] = g.reshape(shape)
            log.info("band %d (%s) iteration %d: misfit %.4g", b, format_band(*band), iteration, f)

        res = minimize(objective, x, method=inv.optimizer, bounds=(bounds[0] / V_REF, bounds[1] / V_REF),
                       max_iterations=inv.iterations[b] if isinstance(inv.iterations, list) else inv.iterations, max_evaluations=inv.evaluations, rel_decrease=inv.rel_decrease, grad_tol=0.0,
                       journal_path=rundir / f"journal_band{b}.h5", callback=callback, on_evaluation=timing,
                       options={"gd": {"step": inv.step}, "adam": {"lr": inv.lr}}.get(inv.optimizer))  # fmt: skip
        log.info("band %d done: %s after %d iterations, %d evaluations", b, res.stop_reason, res.iterations, res.evaluations)
        t_fig = time.perf_counter()
        if "gradient" in last and "residual" in last:  # (a run resumed after its last band has no residual)
            _figures(rundir, history, res.x.reshape(shape) * V_REF, last, p, fwd, b, inv.bands)
        timing.summary(figures=time.perf_counter() - t_fig)
        results.append({"band": format_band(*band), "f_low_hz": band[0], "f_high_hz": band[1], "iterations": res.iterations, "evaluations": res.evaluations,
                        "misfit": res.f, "stop_reason": res.stop_reason})  # fmt: skip
        x = res.x
    v = x.reshape(shape) * V_REF
    out = FWIResult(model=v, start_model=scene.model.values, dx=p.dx, origin=p.origin, bands=results, seconds=time.perf_counter() - t_start)
    if cfg.true_model is not None:
        v_true = cfg.true_model.resample(p.dx, p.origin, p.shape).values
        changed = np.abs(v_true - out.start_model) > 0.01 * v_true
        region = changed if changed.any() else np.ones(shape, bool)
        below = region_mask > 0
        out.errors = {
            "start_anomaly": relative_error(out.start_model, v_true, region), "final_anomaly": relative_error(v, v_true, region),
            "start_below_water": relative_error(out.start_model, v_true, below), "final_below_water": relative_error(v, v_true, below),
        }  # fmt: skip
    _write_synthetic_asdf(rundir, fwd, scene, p, v, progress)
    _write_result(rundir, out, fwd)
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


def _write_result(rundir: Path, res: FWIResult, fwd):
    def fill(f):
        f.create_dataset("model", data=res.model)
        f.create_dataset("start_model", data=res.start_model)
        f.attrs["dx"], f.attrs["origin"], f.attrs["units"] = res.dx, res.origin, "m/s"
        f.attrs["summary"] = json.dumps({"bands": res.bands, "errors": res.errors})

    write_h5_atomic(rundir / "model.h5", fill)
    write_text_atomic(rundir / "summary.json", json.dumps({"bands": res.bands, "errors": res.errors, "seconds": res.seconds}, indent=2))


def _figures(rundir: Path, history: _History, model, last, plan, fwd, b, bands):
    """model.png, gradient.png, residual.png (shot 0, observed - synthetic, against receiver position in m, a
    panel per receiver line) and misfit.png after band b of bands. 3D: the x-z slice through the middle of y,
    sources and receivers projected onto it."""
    from adseismic import plotting

    name = f"band {b} ({format_band(*bands[b])})"
    origin2 = (plan.origin[0], plan.origin[-1])
    mid = (lambda a: a) if model.ndim == 2 else (lambda a: a[:, a.shape[1] // 2])
    src, rec = np.asarray(fwd.geometry.sources, float), np.asarray(fwd.geometry.receivers, float)
    plotting.plot_model(rundir / "model.png", mid(model), plan.dx, origin2, sources=src[:, [0, -1]], receivers=rec[:, [0, -1]],
                        title=f"model after {name}")  # fmt: skip
    plotting.plot_model(rundir / "gradient.png", mid(last["gradient"]), plan.dx, origin2, title=f"last gradient of {name}",
                        label="conditioned gradient\nd(misfit / its start value) / d(v / 1000 m/s)", cmap="seismic", symmetric=True)  # fmt: skip
    plotting.plot_gather(rundir / "residual.png", last["residual"], plan.dt, rec, source=src[0], quantity="residual",
                         title=f"shot 0 residual (observed - synthetic, muted and windowed), {name}\n"
                               f"source (star) at {format_position(src[0])}")  # fmt: skip
    plotting.plot_misfit(rundir / "misfit.png", history.misfits(), labels={i: format_band(*bb) for i, bb in enumerate(bands)})
