"""Full-waveform inversion: multiscale bands, conditioned gradients, journaled optimisation, run directory.

run_fwi(config, rundir) inverts the velocity model for all shots of the config:
1. plan the grid for the velocity bounds (every model the optimiser may visit is stable and resolved)
   and resample the start model onto it;
2. observed data: simulated from `true_model` with the full wavelet (a synthetic study), or read from
   files; stored in RUNDIR/observed.h5 so that a resumed run uses the same data;
3. for each band (low to high), the wavelet and the observed data get the same zero-phase
   Butterworth band-pass (filtering the source filters the synthetics exactly: the data are linear
   in the source), optionally a least-squares wavelet estimate, and the optimiser minimises the
   misfit (normalised by its value at the band's start model) plus regularisation over
   x = v / V_REF, with the gradient masked, smoothed and preconditioned;
4. every evaluation goes to a journal (RUNDIR/journal_band<k>.h5, atomic) and every iteration to
   RUNDIR/history.h5 (atomic) and PNGs; --resume replays the journals and continues, reproducing an
   uninterrupted run.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
from scipy.signal import butter, sosfiltfilt

from adseismic.data.atomic import write_h5_atomic, write_text_atomic
from adseismic.inversion import conditioning
from adseismic.inversion.optimize import minimize
from adseismic.scene import build_scene, plan_scene
from adseismic.solve.acoustic import forward, gradient
from adseismic.solve.batch import shot_slices
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
    """history.h5: per band and iteration the model (m/s), gradient and misfit; rewritten atomically."""

    def __init__(self, path: Path, dx, origin):
        self.path, self.dx, self.origin = path, dx, origin
        self.rows = []

    def add(self, band, iteration, model, grad, misfit):
        self.rows.append((band, iteration, model.astype(np.float32), grad.astype(np.float32), float(misfit)))

        def fill(f):
            f.attrs["dx"], f.attrs["origin"] = self.dx, self.origin
            f.attrs["units"] = "model m/s; gradient d(misfit/misfit_0)/d(v/1000 m/s)"
            for b, i, m, g, j in self.rows:
                grp = f.create_group(f"band{b}/iter{i:04d}")
                grp.create_dataset("model", data=m, compression="gzip")
                grp.create_dataset("gradient", data=g, compression="gzip")
                grp.attrs["misfit"] = j

        write_h5_atomic(self.path, fill)

    def misfits(self):
        return [(b, i, j) for b, i, _, _, j in self.rows]


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
    plan = plan_scene(fwd, velocity_range=bounds, f_max=f_max)
    scene = build_scene(fwd, plan)
    nyq = 0.5 / plan.dt
    for i, (lo, hi) in enumerate(inv.bands):
        if hi is not None and hi >= 0.9 * nyq:
            raise ValueError(f"inversion.bands[{i}]: f_high {hi:g} Hz is too close to the Nyquist frequency {nyq:.3g} Hz of dt = {plan.dt:.4g} s")
    observed = read_observed(cfg.observed, scene, fwd.geometry) if cfg.observed is not None else None
    return Prepared(plan, scene, bounds, observed)


def _observed(cfg, prep: Prepared, rundir: Path, progress):
    path = rundir / "observed.h5"
    if path.exists():
        with h5py.File(path, "r") as f:
            return f["data"][...]
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
    return data


def read_observed(spec, scene, geometry):
    """Observed data (n_shots, n_receivers, nt) on the scene's time axis, from our HDF5 or SEG-Y/SU
    files; the file's shot/receiver counts and coordinates must match the config's geometry."""
    p = scene.plan
    if spec["kind"] in ("mseed", "sac"):
        return _read_station_shots(spec, scene, geometry)
    if spec["kind"] == "hdf5":
        from adseismic.data.store import read_forward

        d = read_forward(spec["path"])
        data, dt_in, t0 = d.receiver_data, d.dt, 0.0
        src, rec = d.source_coordinates, np.broadcast_to(d.receiver_coordinates, (len(d.source_coordinates), *d.receiver_coordinates.shape))
    else:
        from adseismic.data.read import read_shot_gathers

        g = read_shot_gathers([spec["path"]], fmt=spec["kind"].upper(), coordinate_scale=spec.get("coordinate_scale"), ndim=scene.model.ndim)
        data, dt_in, t0, src, rec = g.data, g.dt, g.t0, g.sources, g.receivers
    n_shots, n_rec = scene.receiver_locations.shape[:2]
    if data.shape[:2] != (n_shots, n_rec):
        raise ValueError(f"observed.path: the data hold {data.shape[0]} shots x {data.shape[1]} receivers but the geometry "
                         f"has {n_shots} x {n_rec}; make geometry.sources/receivers match the file")  # fmt: skip
    for name, file_pts, cfg_pts in (("sources", src, geometry.sources), ("receivers", rec, np.broadcast_to(geometry.receivers, rec.shape))):
        off = np.abs(np.asarray(file_pts) - cfg_pts).max()
        if off > 0.5 * p.dx:
            raise ValueError(f"observed.path: the file's {name} coordinates differ from geometry.{name} by up to {off:.3g} m "
                             f"(more than half a cell, {0.5 * p.dx:g} m); make the config's geometry match the file")  # fmt: skip
    if abs(dt_in - p.dt) > 1e-9 * p.dt or data.shape[2] != p.nt or t0 != 0.0:
        from adseismic.data.preprocess import preprocess

        data = preprocess(data, dt_in, dt=p.dt, nt=p.nt, t_shift=-t0, detrend=False, taper=0.0, fmax_required=p.f_max)
    return data


def _read_station_shots(spec, scene, geometry):
    """One MiniSEED/SAC file (or glob) per shot, receivers = stations (coordinates from StationXML or
    SAC headers, projected about spec["reference"]); time zero = spec["shot_times"][i] or the first sample."""
    from obspy import UTCDateTime

    from adseismic.data.geometry import check_samples
    from adseismic.data.preprocess import preprocess
    from adseismic.data.read import read_station_traces

    p = scene.plan
    out = []
    for i, path in enumerate(spec["paths"]):
        st = read_station_traces(path, inventory=spec.get("inventory"), reference=spec.get("reference"),
                                 ndim=scene.model.ndim, component=spec.get("component"))  # fmt: skip
        if len(st.names) != len(geometry.receivers):
            raise ValueError(f"observed.paths[{i}]: {len(st.names)} traces but geometry.receivers has {len(geometry.receivers)}")
        off = np.abs(st.positions - geometry.receivers).max()
        if off > 0.5 * p.dx:
            raise ValueError(f"observed.paths[{i}]: station coordinates differ from geometry.receivers by up to {off:.3g} m "
                             f"(more than half a cell, {0.5 * p.dx:g} m); order the receivers as the traces ({', '.join(st.names[:3])}, ...)")  # fmt: skip
        shift = 0.0 if spec.get("shot_times") is None else float(UTCDateTime(spec["shot_times"][i]) - st.starttime)
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
    FWIResult: the inverted model (nz, [ny,] nx) in m/s on the simulation grid (spacing dx m, origin m)."""
    t_start = time.perf_counter()
    prep = prepared or prepare_fwi(cfg)
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
    batches = shot_slices(len(scene.source_amplitudes), inv.shots_per_batch)
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

        def objective(xv, amp=amp, obs_b=obs_b, scale=scale, scale_path=scale_path):
            v = xv.reshape(shape) * V_REF
            loss, grad, illum = 0.0, np.zeros(shape), np.zeros(shape) if inv.preconditioning == "pseudo_hessian" else None
            for sl in batches:
                w_sl, o_sl = weights[sl], weights[sl] * obs_b[sl]

                def weighted(syn, w_sl=w_sl, o_sl=o_sl):  # misfit of the muted, windowed data
                    j, adj = named_misfit(inv.misfit, w_sl * syn, o_sl, p.dt)
                    return j, w_sl * adj

                r = gradient(v, p.dx, p.dt, amp[sl], scene.source_locations[sl], scene.receiver_locations[sl],
                             misfit=weighted, illumination=illum is not None, **kw)  # fmt: skip
                if sl.start == 0:
                    last["residual"] = weights[0] * (obs_b[0] - r.synthetic[0])
                loss += r.loss
                grad += r.velocity
                if illum is not None:
                    illum += r.illumination
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
            return f, g.ravel()

        def callback(iteration, xv, f, g, b=b):
            history.add(b, iteration, xv.reshape(shape) * V_REF, g.reshape(shape), f)
            last["gradient"] = g.reshape(shape)
            log.info("band %d (%s Hz) iteration %d: misfit %.4g", b, band, iteration, f)

        res = minimize(objective, x, method=inv.optimizer, bounds=(bounds[0] / V_REF, bounds[1] / V_REF),
                       max_iterations=inv.iterations[b] if isinstance(inv.iterations, list) else inv.iterations, max_evaluations=inv.evaluations, rel_decrease=inv.rel_decrease, grad_tol=0.0,
                       journal_path=rundir / f"journal_band{b}.h5", callback=callback,
                       options={"gd": {"step": inv.step}, "adam": {"lr": inv.lr}}.get(inv.optimizer))  # fmt: skip
        log.info("band %d done: %s after %d iterations, %d evaluations", b, res.stop_reason, res.iterations, res.evaluations)
        if "gradient" in last and "residual" in last:  # (a run resumed after its last band has no residual)
            _figures(rundir, history, res.x.reshape(shape) * V_REF, last, p, fwd, band)
        results.append({"band": list(band), "iterations": res.iterations, "evaluations": res.evaluations,
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
    _write_result(rundir, out, fwd)
    return out


def _write_result(rundir: Path, res: FWIResult, fwd):
    def fill(f):
        f.create_dataset("model", data=res.model)
        f.create_dataset("start_model", data=res.start_model)
        f.attrs["dx"], f.attrs["origin"], f.attrs["units"] = res.dx, res.origin, "m/s"
        f.attrs["summary"] = json.dumps({"bands": res.bands, "errors": res.errors})

    write_h5_atomic(rundir / "model.h5", fill)
    write_text_atomic(rundir / "summary.json", json.dumps({"bands": res.bands, "errors": res.errors, "seconds": res.seconds}, indent=2))


def _figures(rundir: Path, history: _History, model, last, plan, fwd, band):
    """model.png, gradient.png, residual.png (shot 0, observed - synthetic) and misfit.png."""
    from adseismic import plotting

    origin2 = (plan.origin[0], plan.origin[-1])
    mid = (lambda a: a) if model.ndim == 2 else (lambda a: a[:, a.shape[1] // 2])
    plotting.plot_model(rundir / "model.png", mid(model), plan.dx, origin2, sources=fwd.geometry.sources,
                        receivers=fwd.geometry.receivers, title=f"model after band {band} Hz")  # fmt: skip
    plotting.plot_model(rundir / "gradient.png", mid(last["gradient"]), plan.dx, origin2, title=f"last gradient, band {band} Hz",
                        label="d misfit / d v (conditioned)", cmap="seismic", symmetric=True)  # fmt: skip
    plotting.plot_gather(rundir / "residual.png", last["residual"], plan.dt, title=f"shot 0 residual (observed - synthetic), band {band} Hz")
    plotting.plot_misfit(rundir / "misfit.png", history.misfits())
