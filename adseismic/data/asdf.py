"""Waveforms in ASDF (the Adaptable Seismic Data Format: HDF5 with waveforms, StationXML and QuakeML
inside; read by ObsPy users through pyasdf, used by SeisFlows / Pyatoa).

pyasdf is the optional extra ``adseismic[asdf]`` (``pip install "adseismic[asdf]"``), imported inside the
functions only: a missing one raises a one-line :class:`~adseismic.data.traces.TraceError` (a ValueError, exit 2
through the CLI) with the pip command, and only where ASDF is asked for.

Layout written by :func:`write_waveforms_asdf` (``adseismic forward`` -> ``waveforms.h5``):

* one ObsPy Trace per shot x receiver. Receivers are **stations**: network ``XX`` (the FDSN code for
  unregistered / synthetic data), station ``R0000``, ``R0001``, ... (``R`` + receiver index, 4 digits or more),
  location ``""``, channel ``<band>DH`` (SEED band code of the sampling rate, ``D`` pressure, ``H`` hydrophone:
  the acoustic wavefield), e.g. ``XX.R0007..CDH``. Shots are ASDF **tags**: ``shot_0000``, ``shot_0001``, ...
  (the waveforms of shot k at receiver i: ``ds.waveforms["XX.R0007"]["shot_0003"]``). Tags rather than one event
  per shot because a synthetic shot has no latitude/longitude for QuakeML and tags need none;
* samples as simulated (float32 or float64, bitwise), ``delta`` = dt (s), ``starttime`` = the shot time, by default
  1970-01-01T00:00:00Z (UTCDateTime(0), the same for every shot: t = 0 at the source's onset of time, as in
  data.h5's ``time``);
* StationXML: one station per receiver with one channel (sample rate, depth). Its latitude / longitude /
  elevation are geographic only when a :class:`~adseismic.data.geometry.Reference` is given (``unproject``);
  otherwise they are 0 / 0 / 0 and the station's description says so;
* auxiliary data ``Coordinates/Receivers`` (n_receivers, ndim) and ``Coordinates/Sources`` (n_shots, ndim):
  the exact local world metres of data.h5 in axis order (z, [y,] x), z depth positive down (parameters
  ``units`` = m, ``axes``, ``geographic`` = whether StationXML holds real coordinates, ``origin_time``). Kept as
  arrays because StationXML has no local Cartesian frame and latitude / longitude would round-trip local metres
  only through a projection; any HDF5 or pyasdf user reads them as ``ds.auxiliary_data.Coordinates.Receivers.data``;
* ``SourceTimeFunctions/wavelet`` (nt,): the wavelet injected at every shot (when given);
* QuakeML events when given (``events``: an ObsPy Catalog or a QuakeML path), e.g. a located earthquake.

:func:`write_event_asdf` (``adseismic locate`` -> ``waveforms.h5``) keeps the stations' own trace ids and StationXML,
with the tags ``observed_processed`` and ``synthetic`` and the located event's QuakeML inside.

Readers: :func:`read_shot_gathers_asdf` (fwi ``observed: {kind: asdf, path}``) and :func:`station_streams` /
:func:`is_asdf` (``adseismic locate``: a ``traces.paths`` entry that is an ASDF file, optionally ``FILE#tag``),
which :func:`adseismic.data.read.read_station_traces` uses.
"""
from __future__ import annotations

import contextlib
import logging
import os
import pathlib
import re

import numpy as np

from adseismic.data.traces import ShotGathers, TraceError

__all__ = ["NETWORK", "PIP", "is_asdf", "read_shot_gathers_asdf", "receiver_code", "shot_tag", "station_inputs", "station_streams",
           "write_event_asdf", "write_forward_asdf", "write_waveforms_asdf"]

log = logging.getLogger(__name__)

NETWORK = "XX"
PIP = 'pip install "adseismic[asdf]"'
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_SHOT = re.compile(r"^shot_(\d+)$")
_RECEIVER = re.compile(r"^R(\d+)$")
_AXES = {2: "z,x", 3: "z,y,x"}


def _pyasdf():
    try:
        import pyasdf
    except ImportError:
        raise TraceError(f"ASDF needs pyasdf, which is not installed; {PIP}") from None
    return pyasdf


def shot_tag(k: int) -> str:
    """The ASDF tag of shot k: shot_0007."""
    return f"shot_{k:04d}"


def receiver_code(i: int) -> str:
    """The station code of receiver i: R0007."""
    return f"R{i:04d}"


def band_code(sampling_rate: float) -> str:
    """SEED band code of a sampling rate (Hz), the broadband variants (a synthetic has no corner period)."""
    for limit, code in ((5000, "J"), (1000, "F"), (250, "C"), (80, "H"), (10, "B"), (1, "M")):
        if sampling_rate >= limit:
            return code
    return "L"


def _skipped(path, holder: str) -> bool:
    """Whether an optional ASDF copy at ``path`` is skipped for want of pyasdf (an INFO line with the pip command:
    ``holder``, our own file, has the same traces)."""
    import importlib.util

    if importlib.util.find_spec("pyasdf") is not None:
        return False
    log.info("%s not written: ASDF needs pyasdf; %s (%s holds the same traces)", pathlib.Path(path).name, PIP, holder)
    return True


@contextlib.contextmanager
def _new_dataset(path: pathlib.Path, events=None):
    """A new ASDF file at ``path``, written as ``<path>.part`` and renamed into place when the block ends without an
    error; with ``events`` (an ObsPy Catalog or a QuakeML path) inside."""
    pyasdf = _pyasdf()
    import obspy

    from adseismic.data.atomic import atomic_write

    with atomic_write(path) as part:
        part.unlink(missing_ok=True)
        with pyasdf.ASDFDataSet(str(part), mode="w", compression=None) as ds:
            if events is not None:
                ds.add_quakeml(events if isinstance(events, obspy.Catalog) else obspy.read_events(str(events)))
            yield ds


def write_waveforms_asdf(path, receiver_data, dt, source_coordinates, receiver_coordinates, *, starttime=None,
                         reference=None, wavelet=None, events=None, channel=None, units="units of source_wavelet"):
    """Write shot gathers receiver_data (n_shots, n_receivers, nt) at sample interval dt (s) to the ASDF file
    ``path`` atomically (``<path>.part`` renamed into place); source_coordinates (n_shots, ndim) and
    receiver_coordinates (n_receivers, ndim) in world metres, axis order (z, [y,] x). starttime: the time of
    sample 0 of every shot (UTCDateTime or ISO text; default 1970-01-01T00:00:00). reference: a geographic
    :class:`~adseismic.data.geometry.Reference` (or [lat, lon] / dict) for the StationXML latitude / longitude.
    wavelet (nt,): stored as auxiliary data. events: ObsPy Catalog or QuakeML path. Returns ``path``."""
    _pyasdf()  # without it: one line with the pip command, before any work
    import obspy
    from obspy import UTCDateTime
    from obspy.core.inventory import Channel, Inventory, Network, Station

    data = np.asarray(receiver_data)
    src = np.asarray(source_coordinates, dtype=float)
    rec = np.asarray(receiver_coordinates, dtype=float)
    if data.ndim != 3 or src.shape[0] != data.shape[0] or rec.shape[0] != data.shape[1] or src.shape[1:] != rec.shape[1:]:
        raise TraceError(f"receiver_data {data.shape}, sources {src.shape}, receivers {rec.shape}: not (shots, receivers, "
                         f"nt) with (shots, ndim) and (receivers, ndim) coordinates")
    ndim = rec.shape[1]
    t0 = UTCDateTime(0) if starttime is None else UTCDateTime(starttime)
    rate = 1.0 / float(dt)
    cha = channel or f"{band_code(rate)}DH"
    geo = None
    if reference is not None:
        from adseismic.data.geometry import as_reference, unproject

        reference = as_reference(reference)
        geo = np.stack(unproject(rec, reference), axis=-1)  # (n, 3) latitude, longitude, elevation
    stations = []
    for i, r in enumerate(rec):
        where = ", ".join(f"{a}={v:g}" for a, v in zip(_AXES[ndim].split(","), r))
        if geo is not None:
            lat, lon, elev = (float(v) for v in geo[i])
            desc = f"adseismic receiver {i} ({where} m)"
        else:
            lat = lon = elev = 0.0
            desc = (f"adseismic receiver {i} at local {where} m (no geographic reference: latitude/longitude/elevation "
                    f"are placeholders; see auxiliary data Coordinates/Receivers)")
        ch = Channel(code=cha, location_code="", latitude=lat, longitude=lon, elevation=elev,
                     depth=0.0, sample_rate=rate)
        stations.append(Station(code=receiver_code(i), latitude=lat, longitude=lon, elevation=elev, channels=[ch],
                                description=desc, creation_date=t0))
    inv = Inventory(networks=[Network(code=NETWORK, stations=stations, description="adseismic synthetic receivers")],
                    source="adseismic")
    path = pathlib.Path(path)
    with _new_dataset(path, events) as ds:
        ds.add_stationxml(inv)
        for k in range(data.shape[0]):
            st = obspy.Stream([obspy.Trace(data=np.ascontiguousarray(data[k, i]),
                                           header={"network": NETWORK, "station": receiver_code(i), "location": "",
                                                   "channel": cha, "starttime": t0, "delta": float(dt)})
                               for i in range(data.shape[1])])
            ds.add_waveforms(st, tag=shot_tag(k))
        params = {"units": "m", "axes": _AXES[ndim], "geographic": geo is not None, "origin_time": str(t0),
                  "data_units": units}
        if geo is not None:
            params.update(reference_latitude=reference.latitude, reference_longitude=reference.longitude,
                          reference_datum=reference.datum, reference_azimuth=reference.azimuth)
        ds.add_auxiliary_data(data=rec, data_type="Coordinates", path="Receivers", parameters=params)
        ds.add_auxiliary_data(data=src, data_type="Coordinates", path="Sources", parameters=params)
        if wavelet is not None:
            ds.add_auxiliary_data(data=np.asarray(wavelet), data_type="SourceTimeFunctions", path="wavelet",
                                  parameters={"dt": float(dt), "units": units})
    return path


def write_event_asdf(path, names, observed, synthetic, dt, starttime, *, inventory=None, events=None):
    """Write an event's traces to the ASDF file ``path`` atomically (``adseismic locate`` -> ``waveforms.h5``):
    observed and synthetic (n_traces, nt) at sample interval dt (s) from ``starttime`` (UTCDateTime of sample 0)
    under their own trace ids ``names`` ('NET.STA.LOC.CHA'), tagged ``observed_processed`` (the preprocessed data the
    location fitted) and ``synthetic``; inventory: the StationXML path or Inventory of the stations (or None);
    events: the located event (ObsPy Catalog or QuakeML path). Without pyasdf: an INFO line and None."""
    if _skipped(path, "location.h5"):
        return None
    import obspy

    def stream(data):
        traces = []
        for name, row in zip(names, np.asarray(data)):
            net, sta, loc, cha = (name.split(".") + ["", "", "", ""])[:4]
            traces.append(obspy.Trace(data=np.ascontiguousarray(row), header={"network": net, "station": sta, "location": loc,
                                                                              "channel": cha, "starttime": starttime, "delta": float(dt)}))
        return obspy.Stream(traces)

    path = pathlib.Path(path)
    with _new_dataset(path, events) as ds:
        if inventory is not None:
            ds.add_stationxml(inventory if isinstance(inventory, obspy.Inventory) else obspy.read_inventory(str(inventory)))
        ds.add_waveforms(stream(observed), tag="observed_processed")
        ds.add_waveforms(stream(synthetic), tag="synthetic")
    return path


# ------------------------------------------------------------------------------- reading

def _split_tag(path):
    """(file, tag or None) of 'FILE' or 'FILE#tag' (the latter only when FILE#tag itself is not a file)."""
    p = str(path)
    if "#" in p and not os.path.exists(p):
        f, tag = p.rsplit("#", 1)
        return f, tag
    return p, None


def is_asdf(path) -> bool:
    """Whether path (or 'FILE#tag') is an HDF5 file in ASDF format (checked without pyasdf)."""
    f, _ = _split_tag(path)
    try:
        with open(f, "rb") as fh:
            if fh.read(8) != _HDF5_MAGIC:
                return False
    except OSError:
        return False
    import h5py

    try:
        with h5py.File(f, "r") as h:
            fmt = h.attrs.get("file_format")
    except OSError:
        return False
    return (fmt.decode() if isinstance(fmt, bytes) else str(fmt)) == "ASDF"


def _open(path):
    pyasdf = _pyasdf()
    if not is_asdf(path):
        what = "does not exist" if not os.path.exists(path) else "is not an ASDF file (HDF5 with file_format ASDF)"
        raise TraceError(f"{path}: {what}; give an ASDF file such as adseismic forward's waveforms.h5")
    try:
        return pyasdf.ASDFDataSet(str(path), mode="r")
    except Exception as e:  # noqa: BLE001 - pyasdf raises assorted types for a bad file
        raise TraceError(f"{path}: could not be read as ASDF ({type(e).__name__}: {e})") from None


def _aux(ds, name):
    """(data, parameters) of auxiliary data Coordinates/<name>, or None."""
    try:
        item = ds.auxiliary_data["Coordinates"][name]
    except (KeyError, AttributeError):
        return None
    return np.asarray(item.data[()], dtype=float), dict(item.parameters)


def station_streams(path, *, ndim=None):
    """(Stream, Inventory, local coordinates {'NET.STA': (z,[y,]x) m} or None) of an ASDF file for
    read_station_traces. path: 'FILE' or 'FILE#tag'; a file with several waveform tags needs the tag. The local
    coordinates come from auxiliary data Coordinates/Receivers (our writer's, stations R<i>) and are returned only
    when its StationXML holds placeholder (not geographic) coordinates; ndim: refuse other dimensions."""
    import obspy

    f, tag = _split_tag(path)
    with _open(f) as ds:
        tags = sorted({t for sta in ds.waveforms for t in sta.get_waveform_tags()})
        if tag is None:
            if len(tags) > 1:
                raise TraceError(f"{f}: holds the waveform tags {', '.join(tags[:6])}{' ...' if len(tags) > 6 else ''}; "
                                 f"choose one as {f}#{tags[0]}")
            tag = tags[0] if tags else None
        elif tag not in tags:
            raise TraceError(f"{f}#{tag}: no waveform tag {tag!r} in the file; it holds {', '.join(tags[:6]) or 'none'}")
        stream, inv = obspy.Stream(), obspy.Inventory()
        for sta in ds.waveforms:
            if tag in sta.get_waveform_tags():
                stream += sta[tag]
            if "StationXML" in sta:
                inv += sta.StationXML
        local = None
        rec = _aux(ds, "Receivers")
        if rec is not None and not bool(rec[1].get("geographic", True)):
            pts = rec[0]
            if ndim is not None and pts.shape[1] != ndim:
                raise TraceError(f"{f}: the receivers' local coordinates are {pts.shape[1]}D but the model is {ndim}D")
            local = {}
            for tr in stream:
                m = _RECEIVER.match(tr.stats.station)
                if m and int(m.group(1)) < len(pts):
                    local[f"{tr.stats.network}.{tr.stats.station}"] = pts[int(m.group(1))]
    if len(stream) == 0:
        raise TraceError(f"{f}: holds no waveforms{' with tag ' + repr(tag) if tag else ''}")
    log.info("%s: %d traces of tag %s, %d stations in its StationXML", f, len(stream), tag, len(inv.get_contents()["stations"]))
    return stream, inv, local


def read_shot_gathers_asdf(path, *, reference=None, ndim=2, component=None) -> ShotGathers:
    """Shot gathers from an ASDF file: shots = waveform tags shot_<k> (by k), receivers = stations (R<i> by i, other
    codes sorted by NET.STA), coordinates from auxiliary data Coordinates/Sources and /Receivers (world m, z down)
    or, for receivers, StationXML latitude/longitude projected about reference. Every shot must hold the same
    stations with the same dt and length; t0 = first sample - origin_time (0 for our writer). component: keep
    channels ending in this letter. Samples keep the file's type."""
    from obspy import UTCDateTime

    with _open(path) as ds:
        tags = {}
        for name in ds.waveforms.list():
            for t in ds.waveforms[name].get_waveform_tags():
                m = _SHOT.match(t)
                if m is None:
                    raise TraceError(f"{path}: waveform tag {t!r} of {name} is not shot_<k>; fwi reads one tag "
                                     f"per shot (shot_0000, shot_0001, ... in the order of geometry.sources)")
                tags[int(m.group(1))] = t
        if not tags:
            raise TraceError(f"{path}: holds no waveforms")
        shots = sorted(tags)
        if shots != list(range(len(shots))):
            raise TraceError(f"{path}: shot tags {[tags[k] for k in shots][:6]} are not shot_0000 .. shot_{len(shots) - 1:04d}")

        def key(name):
            m = _RECEIVER.match(name.split(".")[1])
            return (0, int(m.group(1)), name) if m else (1, 0, name)

        names = sorted(ds.waveforms.list(), key=key)
        traces = {}
        for name in names:
            sta = ds.waveforms[name]
            for k in shots:
                st = sta[tags[k]] if tags[k] in sta.get_waveform_tags() else []
                if component is not None:
                    st = st.select(component=component)
                if len(st) != 1:
                    raise TraceError(f"{path}: station {name}, tag {tags[k]}: {len(st)} traces"
                                     f"{' of component ' + component if component else ''}; every shot needs one trace per "
                                     f"station{' (set observed.component)' if len(st) > 1 else ''}")
                traces[k, name] = st[0]
        first = traces[0, names[0]]
        dt, nt, start = float(first.stats.delta), int(first.stats.npts), first.stats.starttime
        for (k, name), tr in traces.items():
            if abs(tr.stats.delta - dt) > 1e-9 * dt or tr.stats.npts != nt or abs(tr.stats.starttime - start) > 0.01 * dt:
                raise TraceError(f"{path}: {tr.id} of {tags[k]} has dt {tr.stats.delta:g} s, {tr.stats.npts} samples from "
                                 f"{tr.stats.starttime}, unlike {first.id} of {tags[0]} ({dt:g} s, {nt} from {start}); "
                                 f"give every trace one time axis")
        data = np.stack([np.stack([traces[k, n].data for n in names]) for k in shots])
        rec_aux, src_aux = _aux(ds, "Receivers"), _aux(ds, "Sources")
        if src_aux is None:
            raise TraceError(f"{path}: no auxiliary data Coordinates/Sources (n_shots, ndim) world m; write the file with "
                             f"adseismic.data.asdf.write_waveforms_asdf or add it")
        src, params = src_aux
        origin = params.get("origin_time")
        t0 = 0.0 if origin is None else float(start - UTCDateTime(str(origin)))
        if rec_aux is not None and (not bool(rec_aux[1].get("geographic", True)) or reference is None):
            idx = [key(n)[1] if key(n)[0] == 0 else -1 for n in names]
            if min(idx) < 0 or max(idx) >= len(rec_aux[0]):
                raise TraceError(f"{path}: station codes {names[:3]} do not index Coordinates/Receivers; name them R<i>")
            rec = rec_aux[0][idx]
        else:
            from adseismic.data.geometry import as_reference, project

            if reference is None:
                raise TraceError(f"{path}: the receivers' coordinates are latitude/longitude; give observed.reference")
            inv = ds.waveforms[names[0]].StationXML
            for n in names[1:]:
                inv += ds.waveforms[n].StationXML
            geo = np.array([[c["latitude"], c["longitude"], c["elevation"] - (c.get("local_depth") or 0.0)]
                            for c in (inv.get_coordinates(traces[0, n].id, start) for n in names)])
            rec = project(geo[:, 0], geo[:, 1], geo[:, 2], as_reference(reference), ndim=ndim)
    if src.shape != (len(shots), ndim) or rec.shape != (len(names), ndim):
        raise TraceError(f"{path}: coordinates of {src.shape} sources and {rec.shape} receivers are not {ndim}D for "
                         f"{len(shots)} shots x {len(names)} stations")
    log.info("%s: %d shots x %d receivers x %d samples, dt %g s", path, len(shots), len(names), nt, dt)
    return ShotGathers(data=data, dt=dt, t0=t0, sources=src, receivers=np.broadcast_to(rec, (len(shots), *rec.shape)).copy())


def station_inputs(paths, inventory, local_coordinates, ndim):
    """read_station_traces' inputs with every ASDF file among paths replaced by its Stream: (paths, inventory,
    local_coordinates), the files' StationXML added to inventory and their local receiver coordinates (files of
    our writer without a geographic reference) under local_coordinates (whose own entries win). Unchanged when no
    path is an ASDF file, so pyasdf is needed only for ASDF input."""
    path_list = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not any(isinstance(p, (str, os.PathLike)) and is_asdf(p) for p in path_list):
        return paths, inventory, local_coordinates
    import obspy

    out, inv, local = [], obspy.Inventory(), {}
    for p in path_list:
        if isinstance(p, (str, os.PathLike)) and is_asdf(p):
            st, i, loc = station_streams(p, ndim=ndim)
            out.append(st)
            inv += i
            local.update(loc or {})
        else:
            out.append(p)
    if isinstance(inventory, obspy.Inventory):
        inv += inventory
    elif inventory is not None:
        for ip in [inventory] if isinstance(inventory, (str, os.PathLike)) else inventory:
            try:
                inv += obspy.read_inventory(str(ip))
            except Exception as e:  # noqa: BLE001 - ObsPy raises assorted types
                raise TraceError(f"inventory: {ip} could not be read ({type(e).__name__}: {e}); give StationXML") from None
    local.update(local_coordinates or {})
    return out, (inv if inv.networks else None), (local or None)


def write_forward_asdf(path, **kw):
    """:func:`write_waveforms_asdf` for ``adseismic forward``: without pyasdf (optional), an INFO line with the pip
    command and None instead of the file (data.h5 holds the same samples)."""
    if _skipped(path, "data.h5"):
        return None
    out = write_waveforms_asdf(path, **kw)
    log.info("wrote %s (ASDF: tags shot_<k>, stations %s.R<i>)", out, NETWORK)
    return out
