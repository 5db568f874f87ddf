"""Writing observed data through ObsPy: shot gathers as SU or SEG-Y (:func:`write_shot_gathers_su`)
and event traces as MiniSEED + StationXML (:func:`write_station_traces`), for tests, docs and
synthetic data sets; read back by :mod:`adseismic.data.read`.

Files are written atomically (``<name>.part`` renamed into place, see
:mod:`adseismic.data.atomic`); problems raise :class:`adseismic.data.traces.TraceError`. ObsPy is
imported inside the functions only.
"""
from __future__ import annotations

import logging
import os
import pathlib

import numpy as np

from adseismic.data.atomic import atomic_path
from adseismic.data.geometry import unproject
from adseismic.data.read import _scalar
from adseismic.data.traces import ShotGathers, StationTraces, TraceError

__all__ = ["write_shot_gathers_su", "write_station_traces"]

log = logging.getLogger(__name__)


def _fit_scalar(values, what, lo=-(2 ** 31), hi=2 ** 31 - 1, finest=-1000):
    """Finest SEG-Y scalar (-1000, -100, -10, 1, 10, ...) for which all values fit the int range."""
    v = np.asarray(values, dtype=float)
    for sc in (-1000, -100, -10, 1, 10, 100, 1000, 10000):
        if sc < finest:
            continue
        ints = np.round(v * abs(sc) if sc < 0 else v / sc)
        if ints.size == 0 or (ints.min() >= lo and ints.max() <= hi):
            if sc != finest:
                log.warning("%s: stored with scalar %d (precision %g m)", what, sc,
                            1 / abs(sc) if sc < 0 else sc)
            return sc, ints.astype(np.int64)
    raise TraceError(f"{what}: values up to {np.abs(v).max():g} m do not fit a SEG-Y header")


def write_shot_gathers_su(path, gathers: ShotGathers, fmt="SU") -> pathlib.Path:
    """Write ``gathers`` to an SU (fmt="SU") or SEG-Y rev 1 (fmt="SEGY", IEEE float32) file,
    atomically; returns the path. One trace per (shot, receiver), shot-major. Headers:
    coordinates with scalar_to_be_applied_to_all_coordinates = -1000 (mm) and elevations with
    scalar_to_be_applied_to_all_elevations_and_depths = -1000 (coarser only if mm overflow
    int32), receiver_group_elevation = -z, surface_elevation_at_source = -z_source (depth 0),
    coordinate_units = 1, delay_recording_time = t0 in ms (scalar_to_be_applied_to_times when
    t0 is not whole ms), original_field_record_number = shot + 1,
    trace_number_within_the_original_field_record = receiver + 1, offset (whole m).
    dt must be a whole number of microseconds (the header unit). Samples stored as float32."""
    import obspy
    from obspy.core import AttribDict

    path = pathlib.Path(path)
    fmt = str(fmt).upper().replace("-", "")
    if fmt not in ("SU", "SEGY"):
        raise TraceError(f"fmt: {fmt!r} is not 'SU' or 'SEGY'")
    data = np.asarray(gathers.data)
    if data.ndim != 3:
        raise TraceError(f"gathers.data: shape {data.shape} is not (n_shots, n_receivers, nt)")
    n_shots, n_rec, nt = data.shape
    src, rec = np.asarray(gathers.sources, float), np.asarray(gathers.receivers, float)
    nd = src.shape[-1]
    if src.shape != (n_shots, nd) or rec.shape != (n_shots, n_rec, nd) or nd not in (2, 3):
        raise TraceError(f"gathers: sources {src.shape} / receivers {rec.shape} do not match "
                         f"data {data.shape}: need (n_shots, ndim) and (n_shots, n_receivers, ndim)")
    us = int(round(gathers.dt * 1e6))
    if not (1 <= us <= 65535 and abs(us - gathers.dt * 1e6) < 1e-6 * us):
        raise TraceError(f"gathers.dt: {gathers.dt!r} s is not a whole number of microseconds "
                         f"in 1..65535 (the SEG-Y header unit); resample first")
    delta = us * 1e-6
    while int(delta * 1e6) != us:  # ObsPy's SEG-Y writer truncates delta * 1e6
        delta = np.nextafter(delta, 1.0)
    t0_ms = gathers.t0 * 1e3
    for t_sc in (1, -10, -100, -1000, -10000):  # plainest exact scalar (SU tools ignore it)
        t_int = round(t0_ms * (abs(t_sc) if t_sc < 0 else 1))
        if abs(t_int * _scalar(t_sc) - t0_ms) < 1e-9 * max(1.0, abs(t0_ms)) and abs(t_int) < 32768:
            break
    else:
        raise TraceError(f"gathers.t0: {gathers.t0!r} s cannot be stored as the delay recording "
                         f"time (int16 ms with a scalar down to 1e-4 ms); shift the data to a "
                         f"whole 0.1 microsecond within +-32 s")
    xs = np.concatenate([src[:, -1], rec[..., -1].ravel()] +
                        ([src[:, 1], rec[..., 1].ravel()] if nd == 3 else []))
    c_sc, _ = _fit_scalar(xs, "coordinates")
    e_sc, _ = _fit_scalar(np.concatenate([src[:, 0], rec[..., 0].ravel()]), "elevations")

    def ints(v, sc):
        return int(round(v * abs(sc) if sc < 0 else v / sc))

    traces = []
    key = "su" if fmt == "SU" else "segy"
    for s in range(n_shots):
        for r in range(n_rec):
            n = s * n_rec + r + 1
            sy = src[s, 1] if nd == 3 else 0.0
            gy = rec[s, r, 1] if nd == 3 else 0.0
            h = AttribDict(
                trace_sequence_number_within_line=n, trace_sequence_number_within_segy_file=n,
                original_field_record_number=s + 1,
                trace_number_within_the_original_field_record=r + 1,
                energy_source_point_number=s + 1, trace_identification_code=1,
                scalar_to_be_applied_to_all_coordinates=c_sc,
                scalar_to_be_applied_to_all_elevations_and_depths=e_sc,
                source_coordinate_x=ints(src[s, -1], c_sc), source_coordinate_y=ints(sy, c_sc),
                group_coordinate_x=ints(rec[s, r, -1], c_sc), group_coordinate_y=ints(gy, c_sc),
                surface_elevation_at_source=ints(-src[s, 0], e_sc), source_depth_below_surface=0,
                receiver_group_elevation=ints(-rec[s, r, 0], e_sc), coordinate_units=1,
                distance_from_center_of_the_source_point_to_the_center_of_the_receiver_group=int(
                    round(float(np.hypot(rec[s, r, -1] - src[s, -1], gy - sy)))),
                delay_recording_time=int(t_int), scalar_to_be_applied_to_times=t_sc,
            )
            tr = obspy.Trace(np.ascontiguousarray(data[s, r], dtype=np.float32))
            tr.stats.delta = delta
            tr.stats[key] = AttribDict(trace_header=h)
            traces.append(tr)
    stream = obspy.Stream(traces)
    path.parent.mkdir(parents=True, exist_ok=True)
    part = atomic_path(path)
    try:
        if fmt == "SEGY":
            from obspy.io.segy.segy import SEGYBinaryFileHeader

            bh = SEGYBinaryFileHeader()
            bh.measurement_system = 1
            bh.number_of_data_traces_per_ensemble = n_rec
            bh.trace_sorting_code = 1
            stream.stats = AttribDict(textual_file_header=b"C 1 adseismic shot gathers".ljust(3200),
                                      binary_file_header=bh)
            stream.write(str(part), format="SEGY", data_encoding=5, byteorder=">")
        else:
            stream.write(str(part), format="SU", byteorder="<")
        os.replace(part, path)
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    log.info("wrote %d shots x %d receivers x %d samples to %s (%s)", n_shots, n_rec, nt, path, fmt)
    return path


def write_station_traces(directory, traces: StationTraces, latitude=None, longitude=None,
                         elevation=None, reference=None, *, stem="event"):
    """Write ``traces`` as MiniSEED (float64 samples) + StationXML into ``directory``; returns
    (mseed path, stationxml path), both written atomically. Station coordinates: per-trace
    ``latitude``, ``longitude`` (degrees) and ``elevation`` (m), or, when they are None,
    ``unproject(traces.positions, reference or traces.reference)``. Trace names must be
    'NET.STA.LOC.CHA'; starttime a UTCDateTime or float seconds (epoch)."""
    import obspy
    from obspy import UTCDateTime
    from obspy.core.inventory import Channel, Inventory, Network, Station

    directory = pathlib.Path(directory)
    data = np.asarray(traces.data, dtype=np.float64)
    n = data.shape[0]
    if latitude is None or longitude is None or elevation is None:
        ref = reference if reference is not None else traces.reference
        if ref is None:
            raise TraceError("latitude/longitude/elevation: not given and no reference to "
                             "unproject traces.positions with; pass either")
        latitude, longitude, elevation = unproject(traces.positions, ref)
    lat, lon, elev = (np.broadcast_to(np.asarray(v, float), (n,)) for v in (latitude, longitude, elevation))
    start = traces.starttime if isinstance(traces.starttime, UTCDateTime) else UTCDateTime(float(traces.starttime))
    stream, nets = obspy.Stream(), {}
    for i, name in enumerate(traces.names):
        parts = str(name).split(".")
        if len(parts) != 4:
            raise TraceError(f"traces.names[{i}]: {name!r} is not 'NET.STA.LOC.CHA'")
        net, sta, loc, cha = parts
        tr = obspy.Trace(np.ascontiguousarray(data[i]),
                         {"network": net, "station": sta, "location": loc, "channel": cha,
                          "delta": float(traces.dt), "starttime": start})
        stream.append(tr)
        stations = nets.setdefault(net, {})
        st = stations.setdefault(sta, Station(sta, float(lat[i]), float(lon[i]), float(elev[i])))
        st.channels.append(Channel(cha, loc, float(lat[i]), float(lon[i]), float(elev[i]), 0.0,
                                   sample_rate=1.0 / float(traces.dt)))
    inv = Inventory(networks=[Network(code, stations=list(st.values())) for code, st in nets.items()],
                    source="adseismic")
    directory.mkdir(parents=True, exist_ok=True)
    mseed, xml = directory / f"{stem}.mseed", directory / f"{stem}.xml"
    parts = [atomic_path(mseed), atomic_path(xml)]
    try:
        stream.write(str(parts[0]), format="MSEED", encoding="FLOAT64")
        inv.write(str(parts[1]), format="STATIONXML")
        os.replace(parts[0], mseed)
        os.replace(parts[1], xml)
    except BaseException:
        for p in parts:
            p.unlink(missing_ok=True)
        raise
    log.info("wrote %d traces to %s and %s", n, mseed, xml)
    return mseed, xml
