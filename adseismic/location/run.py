"""The ``adseismic locate`` workflow: event traces -> preprocessing -> plan -> location -> files.

:func:`prepare_locate` does everything that can fail on bad input before a run directory is
touched: it reads the traces through ObsPy (station coordinates projected about the reference),
checks stations against the model, preprocesses (detrend, taper, band-pass), finds start points by
envelope back-projection, trims the record to the expected arrivals, plans the simulation grid and
time step for the data's frequency content (adseismic.scene), resamples the data onto the
simulation's time axis (anti-aliased) and estimates each trace's noise in the pre-event window.
:func:`run_locate` locates the event (adseismic.locate) and writes, each file complete or not at all:

    event.xml        QuakeML (Event, Origin, OriginUncertainty, and with physics elastic a FocalMechanism with its
                     MomentTensor and nodal planes; only with geographic station coordinates)
    location.h5      the result, its covariance, the data, synthetics, STF, misfit map, iterations (+ moment tensor)
    traces.png       observed against synthetic traces (physics elastic: one column per component, vz and vx)
    beachball.png    physics elastic: the moment tensor's focal sphere (ObsPy's beachball)
    location.png     model, stations, back-projection stack, the event with its 68% ellipse; misfit map
    summary.json     the numbers a person reads first (written last: its presence marks a complete run)

Times: the record starts at the traces' first common sample (UTC); config times are seconds after
it. The simulation's time zero is ``t_shift`` seconds after it (the trimmed pre-event part).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from adseismic.config import ForwardConfig, GeometryConfig, LocateConfig, OutputConfig, WaveletConfig
from adseismic.data.atomic import write_h5_atomic, write_text_atomic
from adseismic.inversion.fwi import band_pass
from adseismic.location.locate import LocationResult, back_projection, locate, misfit_map, noise_from_window, phase_models
from adseismic.runs import format_position
from adseismic.scene import plan_scene, straight_ray_times
from adseismic.solve.common import dominant_frequency

log = logging.getLogger(__name__)
CONFIDENCE = 0.68


@dataclass
class PreparedEvent:
    """Inputs of a location on the simulation grid. stations (n, ndim) world m; observed (n, nt) at
    t = t_shift + k dt after the record start; noise_std (n,); starts: start dicts (position m,
    origin_time s on the simulation's time axis, stack); truth: same axis or None."""

    config: LocateConfig
    traces: object
    plan: object
    model: object
    stations: np.ndarray
    observed: np.ndarray
    noise_std: np.ndarray
    t_shift: float
    f0: float
    bounds: list
    starts: list
    stack: dict | None = None
    truth: dict | None = None
    noise_correlation: float = 1.0
    warnings: list = field(default_factory=list)
    components: list | None = None  # physics elastic: what each trace records (vx, vz), see trace_components


#: channel orientation code -> (component, sign): SEED Z is positive up, the model's vz positive down
ORIENTATIONS = {"Z": ("vz", -1.0), "X": ("vx", 1.0)}


def trace_components(names) -> tuple[list, np.ndarray]:
    """Physics elastic: (components, signs) of traces named NET.STA.LOC.CHA from the channel's orientation code
    (its last letter): Z vertical velocity positive up (= -vz), X horizontal velocity along the line's azimuth (= vx),
    m/s. Every station needs both (the P-SV fit of a moment tensor uses both components). ValueError naming the
    trace or station otherwise."""
    comps, signs, seen = [], [], {}
    for name in names:
        code = str(name)[-1:].upper()
        if code not in ORIENTATIONS:
            raise ValueError(f"traces: channel {name!r} has orientation code {code!r}; physics elastic reads Z (vertical velocity, "
                             f"positive up) and X (horizontal velocity along the line's azimuth), m/s: rotate the horizontals onto "
                             f"the line (X) or leave other channels out (traces.paths)")
        c, sgn = ORIENTATIONS[code]
        comps.append(c)
        signs.append(sgn)
        seen.setdefault(str(name).rsplit(".", 1)[0], set()).add(code)
    lacking = {sta: sorted(set(ORIENTATIONS) - codes) for sta, codes in seen.items() if set(ORIENTATIONS) - codes}
    if lacking:
        sta, miss = next(iter(lacking.items()))
        raise ValueError(f"traces: station {sta} lacks its {'/'.join(miss)} component ({len(lacking)} station(s) lack one); physics "
                         f"elastic fits both Z and X at every station: add the missing channel (X: the horizontal along the line) "
                         f"or leave the station out")
    return comps, np.array(signs)


def _seconds(value, starttime, key: str) -> float:
    """Config time (s after the record start, or a UTC string) -> s after the record start."""
    if not isinstance(value, str):
        return float(value)
    from obspy import UTCDateTime

    try:
        return float(UTCDateTime(value) - starttime)
    except Exception:  # noqa: BLE001 - obspy raises several kinds
        raise ValueError(f"{key}: {value!r} is neither seconds after the record start nor a UTC time (e.g. 2026-11-21T04:44:00.5)") from None


def prepare_locate(cfg: LocateConfig) -> PreparedEvent:
    """Read, check and preprocess the event's traces and plan the simulation (see the module
    docstring). Raises ValueError (ConfigError, TraceError) naming the key, file or station."""
    from adseismic.data.geometry import check_inside, check_offline
    from adseismic.data.preprocess import preprocess
    from adseismic.data.read import read_station_traces

    model, pre, src, sim = cfg.model, cfg.preprocess, cfg.source, cfg.simulation
    t = cfg.traces
    elastic = cfg.physics == "elastic"
    if elastic and t["component"] is not None:
        raise ValueError(f"traces.component: {t['component']!r} keeps one component, but physics elastic fits Z and X at every "
                         f"station: drop traces.component")
    st = read_station_traces(t["paths"], inventory=t["inventory"], reference=t["reference"], ndim=model.ndim,
                             local_coordinates=t["local_coordinates"], component=t["component"],
                             fill_gaps=t["fill_gaps"], align=t["align"])  # fmt: skip
    check_offline(st.offline, st.names, model, "traces.reference")  # 2D: stations the projection would move onto the line
    check_inside(st.positions, model, "station", names=st.names)
    components = None
    if elastic:
        components, signs = trace_components(st.names)
        st = dataclasses.replace(st, data=st.data * signs[:, None])  # Z (up) -> vz (down)
    record = (st.nt - 1) * st.dt
    a, b = pre["noise_window"]
    if b > record:
        raise ValueError(f"preprocess.noise_window: ends at {b:g} s, after the {record:g} s record; give a window inside it")
    filt = dict(detrend=pre["detrend"], taper=pre["taper"], band=pre["band"])
    raw = preprocess(st.data, st.dt, dt=st.dt, nt=st.nt, name="traces", **filt)
    f0 = float(src["peak_frequency"] or dominant_frequency(raw[None], st.dt))
    h = float(model.spacing[0])
    bounds = src["bounds"] or [(lo + 2 * h, hi - 2 * h) for lo, hi in model.extent]
    stack = None
    if src["start"] is not None:
        starts = [{"position": src["start"]["position"], "origin_time": _seconds(src["start"]["origin_time"], st.starttime, "source.start.origin_time")}]
    else:
        spacing = cfg.search["grid_spacing"] or max(2 * h, 0.02 * max(hi - lo for lo, hi in bounds))
        starts = back_projection(phase_models(model), st.positions, raw, st.dt, bounds, spacing, n_best=cfg.search["multi_start"])
        stack = starts[0].pop("grid")
        for s in starts:
            log.info("back-projection start: %s, origin time %.4f s after the record start (stack %.2f)",
                     format_position(s["position"]), s["origin_time"], s["stack"])  # fmt: skip
    times = [s["origin_time"] for s in starts]
    corners = np.array(np.meshgrid(*[np.linspace(lo, hi, 3) for lo, hi in bounds], indexing="ij")).reshape(model.ndim, -1).T
    t_travel = float(straight_ray_times(phase_models(model)[-1], corners, st.positions).max())  # the slowest phase
    if pre["window"] == "auto":  # the pre-event part up to 4 periods before the earliest start, arrivals + 4 periods
        w0, w1 = max(0.0, min(times) - 4.0 / f0), min(record, max(times) + t_travel + 4.0 / f0)
        why = f"the starts' origin times {min(times):.3g}..{max(times):.3g} s - 4 periods, + the longest straight-ray time {t_travel:.3g} s + 4 periods"
    else:
        w0, w1 = pre["window"]
        if w1 > record + 1e-9:
            raise ValueError(f"preprocess.window: ends at {w1:g} s, after the {record:g} s record")
        why = "pinned by the config"
    log.info("simulated window %.4g..%.4g s after the record start (%s)", w0, w1, why)
    sources = np.array(np.meshgrid(*[[lo, hi] for lo, hi in bounds], indexing="ij")).reshape(model.ndim, -1).T
    sim = dataclasses.replace(sim, duration=sim.duration or (w1 - w0))
    fwd = ForwardConfig(model, GeometryConfig(sources, st.positions), WaveletConfig("ricker", {"peak_frequency": f0}), sim, OutputConfig(),
                        physics=cfg.physics)  # fmt: skip
    band_hi = None if pre["band"] is None else pre["band"][1]
    plan = plan_scene(fwd, f_max=None if band_hi is None else 1.33 * band_hi)  # Butterworth: -20 dB near 1.33 f_high
    # the 2^ndim "sources" at the search box's corners only size the domain: the run simulates one event
    # per evaluation, over the window chosen above (not a duration pinned in the config)
    nt_why = plan.reasons["nt"] if cfg.simulation.duration else f"the simulated window {w0:.4g}..{w1:.4g} s ({why})"
    plan = dataclasses.replace(plan, n_shots=1, reasons={**plan.reasons, "nt": nt_why})
    for line in plan.describe().splitlines():
        log.info("plan: %s", line)
    k0 = int(round(w0 / plan.dt))
    n_full = int(math.floor(record / plan.dt)) + 1
    data = preprocess(st.data, st.dt, dt=plan.dt, nt=max(n_full, k0 + plan.nt), fmax_required=plan.f_max, name="traces", **filt)
    try:
        noise = noise_from_window(data, plan.dt, (a, b))
    except ValueError as e:
        raise ValueError(f"preprocess.noise_window: {e}") from None
    if np.any(noise <= 0):
        bad = [st.names[i] for i in np.nonzero(noise <= 0)[0]]
        raise ValueError(f"preprocess.noise_window: traces {', '.join(bad)} are exactly zero there; give a window with recorded noise")
    t_shift = k0 * plan.dt
    tau = integrated_correlation(data[:, int(round(a / plan.dt)) : int(round(b / plan.dt))])
    log.info("noise: std %.3g..%.3g, integrated autocorrelation time %.2f samples (covariance inflated by it)", noise.min(), noise.max(), tau)
    starts = [{**s, "origin_time": s["origin_time"] - t_shift} for s in starts]
    truth = None
    if cfg.truth is not None:
        tt = cfg.truth["origin_time"]
        truth = {"position": cfg.truth["position"], "origin_time": None if tt is None else _seconds(tt, st.starttime, "truth.origin_time") - t_shift}
    return PreparedEvent(config=cfg, traces=st, plan=plan, model=model.resample(plan.dx, plan.origin, plan.shape), stations=st.positions,
                         observed=data[:, k0 : k0 + plan.nt], noise_std=noise, t_shift=t_shift, f0=f0, bounds=bounds, starts=starts,
                         stack=stack, truth=truth, noise_correlation=tau, warnings=list(plan.warnings), components=components)  # fmt: skip


def integrated_correlation(noise) -> float:
    """Integrated autocorrelation time (samples) of noise traces (n, m): 1 + 2 sum_k rho(k) over the
    initial positive lags of the trace-averaged autocorrelation; 1 for white noise."""
    x = noise - noise.mean(axis=1, keepdims=True)
    m = x.shape[1]
    ac = np.mean([np.correlate(r, r, "full")[m - 1 :] / max(float(r @ r), 1e-300) for r in x], axis=0)
    total = 1.0
    for k in range(1, m // 2):
        if ac[k] <= 0:
            break
        total += 2 * ac[k]
    return float(total)


def simulation_options(prep: PreparedEvent) -> dict:
    """locate() keyword arguments of the planned simulation, the data's band-pass for the source-time
    function (synthetics must see the filter the data saw) and the noise correlation."""
    p, band = prep.plan, prep.config.preprocess["band"]
    stf_filter = None if band is None else (lambda x: band_pass(x, p.dt, band))
    return dict(order=p.order, pml_width=p.pml_width, free_surface=p.free_surface, device=p.device, precision=p.precision,
                stf_filter=stf_filter)  # fmt: skip


def locate_event(prep: PreparedEvent, callback=None) -> LocationResult:
    """Locate the prepared event with the config's source and search settings."""
    src, q = prep.config.source, prep.config.search
    if q["method"] in ("gd", "adam"):
        log.warning("search.method %s: first-order methods converge slowly on location problems%s; lbfgs or gauss-newton "
                    "is the default for that reason (docs/location.md, optimiser study)",
                    q["method"], " and fail in raw units (parameters of very different scales)" if not q["scaled"] else "")  # fmt: skip
    return locate(prep.model, prep.stations, prep.observed, prep.plan.dt, components=prep.components, constraint=src["constraint"],
                  noise_std=prep.noise_std, bounds=prep.bounds,
                  start=prep.starts, peak_frequency=prep.f0, frequency_range=src["frequency_range"], stf=src["stf"],
                  smoothness=src["smoothness"], method=q["method"], scaled=q["scaled"], max_iterations=q["iterations"],
                  noise_correlation=prep.noise_correlation, callback=callback, **simulation_options(prep))  # fmt: skip


def summary(prep: PreparedEvent, res: LocationResult) -> dict:
    """The location in numbers: local and geographic position, UTC origin time, 1-sigma errors,
    68% ellipse, fit, cost; the error against the truth when the config gives one."""
    from adseismic.data.geometry import unproject
    from adseismic.location.quakeml import confidence_scale, ellipse_2d, ellipsoid

    ndim = prep.model.ndim
    axes = "zyx" if ndim == 3 else "zx"
    sd = np.sqrt(np.diag(res.covariance))
    out = {
        "position_m": dict(zip(axes, res.position.tolist())),
        "position_error_m_1sigma": dict(zip(axes, sd[:ndim].tolist())),
        "origin_time_after_record_start_s": prep.t_shift + res.origin_time,
        "origin_time_error_s_1sigma": float(sd[ndim]),
        "origin_time_utc": str(prep.traces.starttime + prep.t_shift + res.origin_time),
        "stf": res.stf_kind, "peak_frequency_hz": res.peak_frequency, "amplitude": res.amplitude,
        "misfit": res.misfit, "reduced_chi_square": 2 * res.misfit / res.synthetic.size,
        "covariance_inflation": res.inflation, "noise_correlation_samples": prep.noise_correlation, "iterations": res.iterations,
        "evaluations": res.evaluations, "stop_reason": res.stop_reason,
        "starts": [{"position_m": c["position"].tolist(), "origin_time_s": prep.t_shift + c["origin_time"], "misfit": c["misfit"],
                    "final_position_m": c["final_position"].tolist()} for c in res.candidates],
        "grid": {"dx_m": prep.plan.dx, "dt_s": prep.plan.dt, "nt": prep.plan.nt, "shape": list(prep.plan.shape), "order": prep.plan.order,
                 "device": prep.plan.device, "precision": prep.plan.precision},
        "warnings": prep.warnings,
    }  # fmt: skip
    if ndim == 2:
        a, b, angle = ellipse_2d(res.covariance[:2, :2], CONFIDENCE)
        out["ellipse_68"] = {"semi_major_m": a, "semi_minor_m": b, "angle_deg_from_x_toward_z": angle}
    else:
        out["ellipsoid_68"] = ellipsoid(res.covariance[:3, :3], CONFIDENCE)
    out["confidence_scale_2dof"] = confidence_scale(2, CONFIDENCE)
    if prep.traces.reference is not None:
        lat, lon, elev = (float(v) for v in unproject(res.position, prep.traces.reference))
        out.update(latitude=lat, longitude=lon, depth_m=-elev)
    if res.moment_tensor is not None:
        from adseismic.location.moment_tensor import describe

        out["moment_tensor"] = describe(res.moment_tensor, res.moment_tensor_covariance, res.constraint, section_azimuth(prep))
    if prep.truth is not None:
        out["truth_position_error_m"] = float(np.linalg.norm(res.position - prep.truth["position"]))
        if prep.truth["origin_time"] is not None:
            out["truth_origin_time_error_s"] = float(res.origin_time - prep.truth["origin_time"])
    return out


def section_azimuth(prep: PreparedEvent) -> float:
    """Azimuth (degrees from north) of the model's x axis: the traces' reference azimuth (90, east, without one)."""
    ref = prep.traces.reference
    return 90.0 if ref is None or getattr(ref, "azimuth", None) is None else float(ref.azimuth)


def write_outputs(outdir: Path, prep: PreparedEvent, res: LocationResult, mmap: dict, study: dict | None = None) -> list:
    """Write the run's files (module docstring); summary.json last. Returns the paths."""
    from adseismic.location.quakeml import confidence_scale, write_quakeml
    from adseismic.plotting import plot_location, plot_station_traces

    outdir = Path(outdir)
    ndim = prep.model.ndim
    summ = summary(prep, res)
    written = []
    if prep.traces.reference is not None:
        write_quakeml(outdir / "event.xml", position=res.position, origin_time=prep.traces.starttime + prep.t_shift + res.origin_time,
                      covariance=res.covariance, reference=prep.traces.reference, ndim=ndim, confidence=CONFIDENCE,
                      method=f"adseismic waveform location ({res.stf_kind} STF)", extra={"misfit": res.misfit, "dx_m": prep.plan.dx},
                      focal_mechanism=summ.get("moment_tensor"))  # fmt: skip
        written.append(outdir / "event.xml")
    else:
        log.warning("no QuakeML: the station coordinates were local metres (no traces.reference), so there is no latitude/longitude")

    def fill(f):
        f.attrs.update(axes="z,y,x" if ndim == 3 else "z,x", units="m, s, m/s", origin_time_utc=summ["origin_time_utc"],
                       t_shift=prep.t_shift, dt=prep.plan.dt, record_start_utc=str(prep.traces.starttime), stf=res.stf_kind,
                       misfit=res.misfit, stop_reason=res.stop_reason, confidence=CONFIDENCE)  # fmt: skip
        for name, val in (("position", res.position), ("origin_time", res.origin_time), ("covariance", res.covariance),
                          ("parameter_covariance", res.parameter_covariance), ("stf", res.stf), ("observed", prep.observed),
                          ("synthetic", res.synthetic), ("noise_std", res.noise_std), ("station_positions", prep.stations),
                          ("misfit_map/z", mmap["z"]), ("misfit_map/x", mmap["x"]), ("misfit_map/misfit", mmap["misfit"]),
                          ("history/f", np.array([h["f"] for h in res.history]))):  # fmt: skip
            f.create_dataset(name, data=np.asarray(val))
        f.create_dataset("station_names", data=np.array(prep.traces.names, dtype="S"))
        if res.moment_tensor is not None:  # in-plane (Mxx, Mzz, Mxz), N m per metre of line
            f.create_dataset("moment_tensor", data=res.moment_tensor).attrs.update(components="Mxx,Mzz,Mxz", constraint=res.constraint)
            f.create_dataset("moment_tensor_covariance", data=res.moment_tensor_covariance)
            f.create_dataset("components", data=np.array(res.components, dtype="S"))

    write_h5_atomic(outdir / "location.h5", fill)
    written.append(outdir / "location.h5")
    from adseismic.data.asdf import write_event_asdf

    asdf = write_event_asdf(outdir / "waveforms.h5", prep.traces.names, prep.observed, res.synthetic, prep.plan.dt,
                            prep.traces.starttime + prep.t_shift, inventory=prep.config.traces["inventory"],
                            events=outdir / "event.xml" if (outdir / "event.xml").exists() else None)  # fmt: skip
    if asdf is not None:
        written.append(asdf)
    written.append(plot_station_traces(outdir / "traces.png", prep.observed, res.synthetic, prep.plan.dt, prep.traces.names, t0=prep.t_shift,
                                       components=prep.components))  # fmt: skip
    if res.moment_tensor is not None:
        from adseismic.location.moment_tensor import plot_beachball, tensor_local, to_ned

        mt = summ["moment_tensor"]
        planes = ", ".join(f"{p['strike']:.0f}/{p['dip']:.0f}/{p['rake']:.0f}" for p in mt["nodal_planes"])
        written.append(plot_beachball(outdir / "beachball.png", to_ned(tensor_local(res.moment_tensor, res.constraint), section_azimuth(prep)),
                                      title=f"{res.constraint}: strike/dip/rake {planes}\n2D: {', '.join(mt['unresolved'])} unresolved"))  # fmt: skip
    truth = None if prep.truth is None else prep.truth["position"]
    written.append(plot_location(outdir / "location.png", prep.model, prep.stations, res.position, res.covariance[[0, ndim - 1]][:, [0, ndim - 1]],
                                 confidence_scale(2, CONFIDENCE), mmap, candidates=res.candidates, truth_zx=truth, stack=prep.stack,
                                 title=f"located at {format_position(res.position)}, origin {summ['origin_time_utc']}",
                                 confidence=CONFIDENCE))  # fmt: skip
    if study is not None:
        from adseismic.location.locate import optimizer_table

        write_text_atomic(outdir / "optimizers.md", optimizer_table(study) + "\n")
        write_text_atomic(outdir / "optimizers.json", json.dumps(study, indent=1, default=float))
        written += [outdir / "optimizers.md", outdir / "optimizers.json"]
    write_text_atomic(outdir / "summary.json", json.dumps(summ, indent=1, default=float))
    written.append(outdir / "summary.json")
    return written


def event_misfit_map(prep: PreparedEvent, res: LocationResult, n: int = 11) -> dict:
    """misfit_map() of the located event on the prepared grid."""
    kw = simulation_options(prep)
    kw.pop("stf_filter")  # res.stf is already filtered
    return misfit_map(prep.model, prep.stations, prep.observed, prep.plan.dt, res, n=n, **kw)
