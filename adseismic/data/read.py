"""Reading observed data through ObsPy: SEG-Y / SU shot gathers (:func:`read_shot_gathers` ->
:class:`adseismic.data.traces.ShotGathers`) and event traces with their station coordinates
(:func:`read_station_traces` -> :class:`adseismic.data.traces.StationTraces`; latitude /
longitude / elevation mapped to local metres by :func:`adseismic.data.geometry.project`).

Conventions as in :mod:`adseismic.data.traces`: metres, seconds; coordinates in axis order
(z, [y,] x), z = depth, positive down. Every problem raises
:class:`adseismic.data.traces.TraceError` naming the file / trace / station / shot, the
offending value and the fix. ObsPy is imported inside the functions only.
"""
from __future__ import annotations

import logging
import math
import os
import pathlib

import numpy as np

from adseismic.data.geometry import AXES, as_reference, check_samples, offline_distance, project
from adseismic.data.traces import ShotGathers, StationTraces, TraceError

__all__ = ["read_shot_gathers", "read_station_traces"]

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------- SEG-Y / SU

_EXT_FORMATS = {".su": "SU", ".segy": "SEGY", ".sgy": "SEGY", ".seg-y": "SEGY", ".seg": "SEGY"}


def _scalar(value) -> float:
    """SEG-Y scalar rule: positive multiplies, negative divides, zero means 1."""
    v = int(value)
    return 1.0 if v == 0 else (float(v) if v > 0 else 1.0 / abs(v))


def _read_one(path: pathlib.Path, fmt: str | None):
    import obspy

    if fmt is None:
        fmt = _EXT_FORMATS.get(path.suffix.lower())
        if fmt is None:
            raise TraceError(f"fmt: cannot tell the format of {path} from its extension "
                             f"{path.suffix!r}; pass fmt='SEGY' or fmt='SU'")
    fmt = str(fmt).upper().replace("-", "")
    if fmt not in ("SEGY", "SU"):
        raise TraceError(f"fmt: {fmt!r} is not 'SEGY' or 'SU'")
    if not path.is_file():
        raise TraceError(f"paths: {path} does not exist; give existing SEG-Y / SU files")
    try:
        stream = obspy.read(str(path), format=fmt, unpack_trace_headers=True)
    except Exception as e:  # ObsPy raises assorted types for unreadable files
        raise TraceError(f"{path}: could not be read as {fmt} ({type(e).__name__}: {e}); check "
                         f"the file or the fmt argument") from None
    if len(stream) == 0:
        raise TraceError(f"{path}: holds no traces")
    return stream, fmt


DEPTH_CONVENTIONS = ("auto", "elevation", "depth")


def read_shot_gathers(paths, fmt=None, *, coordinate_scale=None, ndim=2,
                      group_by="source", depth_convention="elevation", model=None) -> ShotGathers:
    """Read SEG-Y or SU file(s) into :class:`ShotGathers` (see its docstring for shapes / units).

    paths: one path or a list (traces are taken in file order, then trace order); fmt: "SEGY",
    "SU" or None (from the extension: .su -> SU; .segy/.sgy/.seg -> SEGY).
    Trace headers used (ObsPy names, ``obspy.io.segy.header``):

    * source_coordinate_x/y, group_coordinate_x/y times scalar_to_be_applied_to_all_coordinates
      (negative: divide; 0: 1); coordinate_units must be 0/1 (length);
    * receiver_group_elevation, surface_elevation_at_source, source_depth_below_surface times
      scalar_to_be_applied_to_all_elevations_and_depths: receiver z = -elevation, source
      z = depth - surface elevation (z = depth, m, positive down);
    * ``depth_convention`` says how the file stores depth: "elevation" (the SEG-Y standard, above):
      elevations positive up, receiver z = -receiver_group_elevation, source z =
      source_depth_below_surface - surface_elevation_at_source; "depth": the elevation fields hold
      positive depths (as JUDI.jl / Devito write them, usually with scalar -1000): receiver z =
      receiver_group_elevation, source z = surface_elevation_at_source + source_depth_below_surface;
      "auto": whichever puts every source and receiver inside ``model`` (an
      :class:`adseismic.data.model.Model`) when only one of them does (a warning says so), else
      "elevation". With "elevation" or "depth", a warning names the other convention when every
      position falls inside the model with it but not with the one given;
    * ``coordinate_scale`` (m per header unit) replaces both header scalars when given (files
      with wrong scalars); SEG-Y binary header measurement_system 2 (feet) converts to metres;
    * sample_interval_in_ms_for_this_trace (microseconds) -> dt; number of samples -> nt;
      delay_recording_time (ms) times scalar_to_be_applied_to_times -> t0;
    * original_field_record_number, trace_number_within_the_original_field_record: labels
      (and the shot key for ``group_by="record"``).

    ndim=2: x from the x coordinates (the y coordinates must all be equal, else TraceError:
    use ndim=3); ndim=3 adds y. Shots are formed by equal source coordinates (to 1 mm;
    ``group_by="source"``) or equal field record number (``group_by="record"``), in order of first
    appearance (record numbers are compared across all files, and the traces of one record must
    share one source position); receivers keep their trace order within a shot. Every trace must share one
    sample interval, length and t0, and every shot the same number of receivers (TraceError).
    """
    if ndim not in (2, 3):
        raise TraceError(f"ndim: {ndim!r} is not 2 or 3")
    if group_by not in ("source", "record"):
        raise TraceError(f"group_by: {group_by!r} is not 'source' or 'record'")
    if depth_convention not in DEPTH_CONVENTIONS:
        raise TraceError(f"depth_convention: {depth_convention!r} is not one of {', '.join(DEPTH_CONVENTIONS)}")
    if coordinate_scale is not None and not (math.isfinite(float(coordinate_scale))
                                             and float(coordinate_scale) > 0):
        raise TraceError(f"coordinate_scale: {coordinate_scale!r} is not a positive number of "
                         f"metres per header unit")
    path_list = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not path_list:
        raise TraceError("paths: no files given")
    labels, samples, src, rec, rec_no, dts, t0s = [], [], [], [], [], [], []
    src_z_depth, rec_z_depth = [], []  # z of the "depth" convention (elevation fields hold depths)
    for p in map(pathlib.Path, path_list):
        stream, f = _read_one(p, fmt)
        unit = 1.0
        if f == "SEGY":
            ms = int(getattr(stream.stats.binary_file_header, "measurement_system", 1) or 1)
            if ms == 2:
                unit = 0.3048
                log.info("%s: binary header measurement_system = 2 (feet): coordinates "
                         "converted to metres", p.name)
        for i, tr in enumerate(stream):
            h = tr.stats.segy.trace_header if f == "SEGY" else tr.stats.su.trace_header
            rec_id = int(h.original_field_record_number)
            label = (f"{p.name} trace {i} (0-based; field record {rec_id}, trace "
                     f"{int(h.trace_number_within_the_original_field_record)})")
            cu = int(h.coordinate_units)
            if cu not in (0, 1) and coordinate_scale is None:
                raise TraceError(f"{label}: coordinate_units = {cu} (2: arc seconds, 3: degrees, "
                                 f"4: DMS) are geographic; convert the coordinates to metres "
                                 f"(e.g. UTM) or pass coordinate_scale to force a length scale")
            if coordinate_scale is None:
                cs = _scalar(h.scalar_to_be_applied_to_all_coordinates) * unit
                es = _scalar(h.scalar_to_be_applied_to_all_elevations_and_depths) * unit
            else:
                cs = es = float(coordinate_scale)
            sx, sy = cs * h.source_coordinate_x, cs * h.source_coordinate_y
            gx, gy = cs * h.group_coordinate_x, cs * h.group_coordinate_y
            sz = es * (h.source_depth_below_surface - h.surface_elevation_at_source)
            gz = -es * h.receiver_group_elevation
            src_z_depth.append(es * (h.surface_elevation_at_source + h.source_depth_below_surface))
            rec_z_depth.append(es * h.receiver_group_elevation)
            src.append((sz, sy, sx))
            rec.append((gz, gy, gx))
            rec_no.append(rec_id)
            dts.append((int(h.sample_interval_in_ms_for_this_trace), float(tr.stats.delta)))
            t0s.append(1e-3 * int(h.delay_recording_time) * _scalar(h.scalar_to_be_applied_to_times))
            labels.append(label)
            samples.append(tr.data)
    # --- one sampling, one length, one t0
    first = labels[0]
    for i, lab in enumerate(labels):
        if dts[i][1] != dts[0][1] and abs(dts[i][1] - dts[0][1]) > 1e-9 * dts[0][1]:
            raise TraceError(f"{lab}: sample interval {dts[i][1]:g} s differs from "
                             f"{dts[0][1]:g} s of {first}; resample the traces to one interval")
        if len(samples[i]) != len(samples[0]):
            raise TraceError(f"{lab}: {len(samples[i])} samples differ from {len(samples[0])} of "
                             f"{first}; cut or pad the traces to one length")
        if abs(t0s[i] - t0s[0]) > 1e-9:
            raise TraceError(f"{lab}: delay recording time t0 = {t0s[i]:g} s differs from "
                             f"{t0s[0]:g} s of {first}; shift the traces to one start time")
    dt = dts[0][1]
    if not dt > 0:
        raise TraceError(f"{first}: sample interval {dt!r} s is not positive; set "
                         f"sample_interval_in_ms_for_this_trace (microseconds)")
    src, rec = np.array(src, dtype=float), np.array(rec, dtype=float)
    src, rec = _apply_depth_convention(src, rec, np.array(src_z_depth, float), np.array(rec_z_depth, float),
                                       depth_convention, model, ndim, path_list)
    if ndim == 2:
        ys = np.concatenate([src[:, 1], rec[:, 1]])
        if np.ptp(ys) > 1e-3:
            i = int(np.argmax(np.maximum(np.abs(src[:, 1] - ys[0]), np.abs(rec[:, 1] - ys[0]))))
            raise TraceError(f"{labels[i]}: y coordinates vary (source y {src[i, 1]:g} m, receiver "
                             f"y {rec[i, 1]:g} m, first trace y {ys[0]:g} m; range {np.ptp(ys):g} m) "
                             f"but ndim=2 reads x only; pass ndim=3, or rotate the line onto x")
        src, rec = src[:, [0, 2]], rec[:, [0, 2]]
    # --- group into shots
    keys = (np.round(src * 1e3).astype(np.int64).tolist() if group_by == "source" else rec_no)
    order, members = [], {}
    for i, k in enumerate(map(lambda k: tuple(k) if isinstance(k, list) else k, keys)):
        if k not in members:
            members[k] = []
            order.append(k)
        members[k].append(i)
    shots = [members[k] for k in order]
    counts = [len(m) for m in shots]
    for s, m in enumerate(shots):
        if counts[s] != counts[0]:
            where = ", ".join(f"{a}={v:.3f}" for a, v in zip(AXES[ndim], src[m[0]]))
            raise TraceError(f"shot {s} (source at {where} m; first trace {labels[m[0]]}): "
                             f"{counts[s]} receivers, but shot 0 has {counts[0]}; every shot needs "
                             f"the same number of receivers (pad missing traces with zeros "
                             f"or drop the shot)")
        if group_by == "record" and np.ptp(src[m], axis=0).max() > 1e-3:
            raise TraceError(f"shot {s} (field record {rec_no[m[0]]}): traces have different "
                             f"source coordinates; group_by='source' instead")
    data = np.stack([np.stack([samples[i] for i in m]) for m in shots])
    gathers = ShotGathers(data=data, dt=dt, t0=float(t0s[0]),
                          sources=np.array([src[m[0]] for m in shots]),
                          receivers=np.array([[rec[i] for i in m] for m in shots]))
    check_samples(gathers.data, [labels[i] for m in shots for i in m])
    log.info("read %d shots x %d receivers x %d samples, dt %g s, t0 %g s from %d file(s)",
             gathers.n_shots, gathers.n_receivers, gathers.nt, dt, gathers.t0, len(path_list))
    return gathers


def _apply_depth_convention(src, rec, src_z_depth, rec_z_depth, convention, model, ndim, path_list):
    """(src, rec) (n, 3) with z from the chosen convention (read_shot_gathers' depth_convention), warning when
    only the other one puts every source and receiver inside the model."""
    alt_src, alt_rec = src.copy(), rec.copy()
    alt_src[:, 0], alt_rec[:, 0] = src_z_depth, rec_z_depth
    where = f"{len(path_list)} file(s) from {pathlib.Path(path_list[0]).name}"
    if model is None or getattr(model, "ndim", None) != ndim:
        if convention == "depth":
            return alt_src, alt_rec
        return src, rec

    def inside(s, r):
        pick = [0, 2] if ndim == 2 else [0, 1, 2]
        pts = np.concatenate([s[:, pick], r[:, pick]])
        return bool(np.all(model.contains(pts))), float(pts[:, 0].min()), float(pts[:, 0].max())

    ok = {"elevation": inside(src, rec), "depth": inside(alt_src, alt_rec)}
    z_top, z_bottom = model.extent[0]
    if convention == "auto":
        if ok["depth"][0] and not ok["elevation"][0]:
            log.warning("%s: with the SEG-Y elevation convention (z = -elevation) the sources and receivers lie at z "
                        "%.4g..%.4g m, outside the model (z %.4g..%.4g m); read as depths (elevation fields holding "
                        "positive depths, as JUDI.jl writes them) all are inside (z %.4g..%.4g m): using depth_convention "
                        "'depth' (set it explicitly to silence this warning)", where, ok["elevation"][1],
                        ok["elevation"][2], z_top, z_bottom, ok["depth"][1], ok["depth"][2])
            return alt_src, alt_rec
        return src, rec
    other = "depth" if convention == "elevation" else "elevation"
    if ok[other][0] and not ok[convention][0]:
        log.warning("%s: with depth_convention '%s' the sources and receivers lie at z %.4g..%.4g m, not all inside "
                    "the model (z %.4g..%.4g m); with '%s' all would be inside (z %.4g..%.4g m): set depth_convention: "
                    "%s if the file stores depth that way", where, convention, ok[convention][1], ok[convention][2],
                    z_top, z_bottom, other, ok[other][1], ok[other][2], other)
    return (alt_src, alt_rec) if convention == "depth" else (src, rec)


# ------------------------------------------------------------------------------- stations

def _gap_message(gaps) -> str:
    parts = []
    for g in gaps[:5]:
        kind = "overlap" if g[6] < 0 else "gap"
        parts.append(f"{'.'.join(g[:4])}: {kind} from {g[4]} to {g[5]} ({abs(g[6]):g} s)")
    more = f" and {len(gaps) - 5} more" if len(gaps) > 5 else ""
    return "; ".join(parts) + more


def _sac_coordinates(tr):
    sac = tr.stats.get("sac")
    if not sac:
        return None
    vals = [sac.get(k) for k in ("stla", "stlo", "stel", "stdp")]
    if vals[0] is None or vals[1] is None or -12345.0 in (vals[0], vals[1]):
        return None
    elev = 0.0 if vals[2] in (None, -12345.0) else float(vals[2])
    depth = 0.0 if vals[3] in (None, -12345.0) else float(vals[3])
    return float(vals[0]), float(vals[1]), elev - depth


def _local_override(local, tr, ndim):
    """(z,[y,]x) from local_coordinates for this trace, or None."""
    s = tr.stats
    for key in (tr.id, f"{s.network}.{s.station}", s.station):
        if key in local:
            v = local[key]
            if isinstance(v, dict):
                axes = AXES[ndim]
                missing = [a for a in axes if a not in v]
                if missing:
                    raise TraceError(f"local_coordinates[{key!r}]: {v!r} lacks {missing}; give "
                                     f"{', '.join(axes)} in metres")
                v = [v[a] for a in axes]
            arr = np.asarray(v, dtype=float)
            if arr.shape != (ndim,) or not np.all(np.isfinite(arr)):
                raise TraceError(f"local_coordinates[{key!r}]: {v!r} is not {ndim} finite "
                                 f"numbers in axis order ({','.join(AXES[ndim])}), metres")
            return arr
    return None


def read_station_traces(paths, *, inventory=None, reference=None, ndim=2, local_coordinates=None,
                        component=None, fill_gaps=None, align=False, noise_window=None,
                        starttime=None, endtime=None) -> StationTraces:
    """Read event traces (MiniSEED, SAC, anything ObsPy reads) into :class:`StationTraces`.

    paths: one path / glob or a list; inventory: an ObsPy Inventory or StationXML path(s)
    (read with obspy.read_inventory). Coordinates per trace, first found wins:
    ``local_coordinates`` (dict keyed 'NET.STA.LOC.CHA', 'NET.STA' or 'STA' -> (z,[y,]x) metres
    in model axis order, or a dict with keys 'x', ['y',] 'z'), then the inventory
    (latitude, longitude, elevation - local_depth of the channel at the trace's start), then SAC
    headers stla / stlo / stel (- stdp; float32 in the file, so ~0.2 m horizontal precision),
    then ``trace.stats.coordinates``. Geographic ones are
    mapped by :func:`project` about ``reference`` (required then; see :class:`Reference`).

    component: keep only this component (e.g. "Z"); fill_gaps: None (default) raises TraceError
    on gaps / overlaps (Stream.get_gaps), a number fills them with it, "interpolate" linearly.
    All traces must share one sampling rate; they are cut to their common time window
    (optionally [starttime, endtime], UTCDateTime). Start times off the first trace's sample grid
    by more than 1% of dt raise TraceError unless ``align=True`` (Lanczos interpolation onto the
    grid). noise_window: (start, end) seconds relative to the common start time (or UTCDateTimes)
    -> noise_std, the standard deviation of each trace there (e.g. the pre-event window).
    """
    if ndim not in (2, 3):
        raise TraceError(f"ndim: {ndim!r} is not 2 or 3")
    stream = _merged_stream(paths, component, fill_gaps, starttime, endtime)
    names = [tr.id for tr in stream]
    data, delta, t_start, nt = _common_window(stream, align)
    positions, ref, offline = _positions(stream, inventory, reference, ndim, local_coordinates)
    check_samples(data, names)
    noise = _noise_std(data, noise_window, t_start, delta, nt)
    log.info("read %d traces x %d samples, dt %g s, from %s", len(names), nt, delta, t_start)
    return StationTraces(data=data, dt=delta, starttime=t_start, positions=np.array(positions, float),
                         names=names, noise_std=noise, reference=ref, offline=offline)


def _read_checked(p):
    """obspy.read(p), refusing files ObsPy reads only in part (a truncated or corrupt MiniSEED record) and passing
    ObsPy's other warnings to the log."""
    import warnings

    import obspy

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            st = obspy.read(str(p))
        except Exception as e:  # noqa: BLE001 - ObsPy raises assorted types for unreadable files
            raise TraceError(f"{p}: could not be read by ObsPy ({type(e).__name__}: {e}); check "
                             f"the path and the format") from None
    for w in caught:
        text = str(w.message)
        if "not enough to constitute a full SEED record" in text or "Corrupt" in text or "corrupt" in text:
            size = os.path.getsize(p) if os.path.isfile(p) else 0
            got = ", ".join(f"{tr.id}: {tr.stats.npts} samples to {tr.stats.endtime}" for tr in st[:3])
            raise TraceError(f"{p}: truncated or corrupt ({size:,} bytes; ObsPy: {text.strip()}); only the complete "
                             f"records were readable ({got or 'no samples'}); copy the file again, or keep the complete "
                             f"records explicitly (obspy.read(...).write(..., format='MSEED')) and use that file")
        log.warning("%s: %s", p, text.strip())
    return st


def _merged_stream(paths, component, fill_gaps, starttime, endtime):
    """The ObsPy Stream of the files at paths: one component, gaps merged (or refused), one trace per channel,
    sorted by id, cut to [starttime, endtime]."""
    import obspy
    from obspy import UTCDateTime

    path_list = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not path_list:
        raise TraceError("paths: no files given")
    stream = obspy.Stream()
    for p in path_list:
        stream += _read_checked(p)
    if component is not None:
        stream = stream.select(component=component)
        log.info("kept %d traces of component %s", len(stream), component)
    if len(stream) == 0:
        raise TraceError(f"paths: no traces in {[str(p) for p in path_list]}"
                         f"{' with component ' + repr(component) if component else ''}")
    gaps = stream.get_gaps()
    if gaps:
        if fill_gaps is None:
            raise TraceError(f"{_gap_message(gaps)}; traces with gaps or overlaps cannot be used "
                             f"as they are; pass fill_gaps=0.0 (or 'interpolate') to merge them, "
                             f"or remove the traces")
        stream.merge(method=1, fill_value=fill_gaps)
        log.warning("merged %d gaps/overlaps, filled with %r: %s", len(gaps), fill_gaps,
                    _gap_message(gaps))
    else:
        stream.merge(method=1)
    for tr in stream:
        if np.ma.isMaskedArray(tr.data):
            if np.ma.is_masked(tr.data):
                raise TraceError(f"{tr.id}: still has masked samples after merging; fill the "
                                 f"gaps (fill_gaps=0.0) or remove the trace")
            tr.data = tr.data.filled()
    stream.sort(keys=["network", "station", "location", "channel"])
    ids = [tr.id for tr in stream]
    dups = sorted({i for i in ids if ids.count(i) > 1})
    if dups:
        raise TraceError(f"{dups[0]}: {ids.count(dups[0])} separate traces remain after merging; "
                         f"give one continuous record per channel")
    if starttime is not None or endtime is not None:
        stream.trim(None if starttime is None else UTCDateTime(starttime),
                    None if endtime is None else UTCDateTime(endtime))
        log.info("cut to %s .. %s", starttime, endtime)
    return stream


def _common_window(stream, align):
    """(data (n_traces, nt) float64, dt s, start UTCDateTime, nt) of the traces on one sample grid and their common
    time window."""
    # --- one sampling interval
    delta = float(stream[0].stats.delta)
    for tr in stream:
        if abs(tr.stats.delta - delta) > 1e-6 * delta:
            raise TraceError(f"{tr.id}: sampling rate {tr.stats.sampling_rate:g} Hz (dt "
                             f"{tr.stats.delta:g} s) differs from {stream[0].stats.sampling_rate:g}"
                             f" Hz of {stream[0].id}; resample it (obspy Trace.resample) first")
        if tr.stats.npts < 2:
            raise TraceError(f"{tr.id}: {tr.stats.npts} samples in the window; widen the window "
                             f"or drop the trace")
    # --- common sample grid and window
    t_grid = stream[0].stats.starttime
    for tr in stream:
        frac = ((tr.stats.starttime - t_grid) / delta) % 1.0
        off = min(frac, 1 - frac)
        if off > 0.01:
            if not align:
                raise TraceError(f"{tr.id}: starts at {tr.stats.starttime}, {off * delta:g} s "
                                 f"({off:.3f} samples) off the sample grid of {stream[0].id}; pass "
                                 f"align=True to interpolate it onto that grid")
            k = math.ceil((tr.stats.starttime - t_grid) / delta)
            t_new = t_grid + k * delta
            n_new = int(math.floor((tr.stats.endtime - t_new) / delta + 1e-6)) + 1
            tr.interpolate(1.0 / delta, method="lanczos", a=20, starttime=t_new, npts=n_new)
            log.info("%s: interpolated onto the common sample grid (shift %.3f samples)",
                     tr.id, off)
    t_start = max(tr.stats.starttime for tr in stream)
    t_end = min(tr.stats.endtime for tr in stream)
    if t_end - t_start < delta:
        raise TraceError(f"traces share no common time window (latest start {t_start}, earliest "
                         f"end {t_end}); select traces that overlap in time")
    longest = max(tr.stats.endtime - tr.stats.starttime for tr in stream)
    if t_end - t_start < 0.5 * longest:
        short = min(stream, key=lambda tr: tr.stats.endtime - tr.stats.starttime)
        log.warning("the traces share only %.4g s of the longest record's %.4g s: %s covers %s .. %s (%d samples), a "
                    "truncated file? every trace is cut to the common window", t_end - t_start, longest, short.id,
                    short.stats.starttime, short.stats.endtime, short.stats.npts)
    nt = int(math.floor((t_end - t_start) / delta + 1e-6)) + 1
    rows = []
    for tr in stream:
        k0 = int(round((t_start - tr.stats.starttime) / delta))
        rows.append(np.asarray(tr.data[k0:k0 + nt], dtype=np.float64))
        if k0 or len(tr.data) != nt:
            log.info("%s: cut to the common window (%d of %d samples)", tr.id, nt, len(tr.data))
    return np.stack(rows), delta, t_start, nt


def _positions(stream, inventory, reference, ndim, local_coordinates):
    """(positions (n_traces, ndim) metres in model axis order, the Reference used or None) of the traces: local
    coordinates, then the inventory, SAC headers and stats.coordinates projected about reference."""
    import obspy

    # --- coordinates
    inv = None
    if inventory is not None:
        if isinstance(inventory, obspy.Inventory):
            inv = inventory
        else:
            inv = obspy.Inventory()
            for ip in ([inventory] if isinstance(inventory, (str, os.PathLike)) else inventory):
                try:
                    inv += obspy.read_inventory(str(ip))
                except Exception as e:
                    raise TraceError(f"inventory: {ip} could not be read ({type(e).__name__}: "
                                     f"{e}); give StationXML (or another ObsPy inventory format)") from None
    local = dict(local_coordinates or {})
    positions = [None] * len(stream)
    offline = None
    geo, missing = {}, []
    for i, tr in enumerate(stream):
        over = _local_override(local, tr, ndim)
        if over is not None:
            positions[i] = over
            continue
        c = None
        if inv is not None:
            try:
                cc = inv.get_coordinates(tr.id, tr.stats.starttime)
                c = (cc["latitude"], cc["longitude"], cc["elevation"] - (cc.get("local_depth") or 0.0))
            except Exception:
                c = None
        if c is None:
            c = _sac_coordinates(tr)
        if c is None and tr.stats.get("coordinates"):
            cc = tr.stats.coordinates
            if cc.get("latitude") is not None and cc.get("longitude") is not None:
                c = (cc.latitude, cc.longitude, cc.get("elevation", 0.0) or 0.0)
        if c is None:
            missing.append(tr.id)
        else:
            geo[i] = c
    if missing:
        raise TraceError(f"{', '.join(missing)}: no coordinates (not in the inventory, no SAC "
                         f"stla/stlo, no stats.coordinates, not in local_coordinates); pass "
                         f"inventory=<StationXML> or local_coordinates={{'{missing[0]}': "
                         f"({', '.join(AXES[ndim])}) metres}}")
    ref = None
    if geo:
        lat, lon, elev = (np.array([geo[i][k] for i in sorted(geo)], dtype=float) for k in range(3))
        if reference is None:
            raise TraceError(f"reference: needed to map station latitude/longitude to local "
                             f"metres; pass reference=(lat0, lon0) in degrees (the model's "
                             f"x=0{', y=0' if ndim == 3 else ''} point), e.g. the network centre "
                             f"({lat.mean():.4f}, {lon.mean():.4f})")
        ref = as_reference(reference)
        xyz = project(lat, lon, elev, ref, ndim=ndim)
        for j, i in enumerate(sorted(geo)):
            positions[i] = xyz[j]
        if ndim == 2:
            offline = np.zeros(len(stream))
            offline[sorted(geo)] = offline_distance(lat, lon, ref)
        log.info("projected %d stations about (%.6f, %.6f), datum %g m%s", len(geo),
                 ref.latitude, ref.longitude, ref.datum,
                 f", 2D line azimuth {ref.azimuth:g} deg" if ndim == 2 else "")
    return positions, ref, offline


def _noise_std(data, noise_window, t_start, delta, nt):
    """The standard deviation of each trace in noise_window ((start, end) s after t_start, or UTCDateTimes), or None."""
    from obspy import UTCDateTime

    noise = None
    if noise_window is not None:
        try:
            a, b = (float(w - t_start) if isinstance(w, UTCDateTime) else float(w)
                    for w in noise_window)
        except (TypeError, ValueError):
            raise TraceError(f"noise_window: {noise_window!r} is not (start, end) in seconds "
                             f"relative to the start {t_start}") from None
        i0, i1 = max(int(math.ceil(a / delta - 1e-9)), 0), min(int(math.floor(b / delta + 1e-9)), nt - 1)
        if i1 - i0 + 1 < 2:
            raise TraceError(f"noise_window: ({a:g}, {b:g}) s after {t_start} holds {max(i1 - i0 + 1, 0)} "
                             f"samples of the {nt * delta:g} s record; give a window of at least "
                             f"two samples inside it (before the first arrival)")
        noise = data[:, i0:i1 + 1].std(axis=1)
        log.info("noise std from %g..%g s (%d samples)", i0 * delta, i1 * delta, i1 - i0 + 1)
    return noise
