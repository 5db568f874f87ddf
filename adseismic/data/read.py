"""Reading observed data: SEG-Y / SU shot gathers (:func:`read_shot_gathers` ->
:class:`adseismic.data.traces.ShotGathers`; streamed window by window through numpy memory maps, with only the
header fields it needs and the samples of the shots / receivers asked for held in memory, ObsPy for files of
variable trace length) and event traces with their station coordinates through ObsPy
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
from dataclasses import dataclass

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

    fmt = _file_format(path, fmt)
    try:
        stream = obspy.read(str(path), format=fmt, unpack_trace_headers=True)
    except Exception as e:  # ObsPy raises assorted types for unreadable files
        raise TraceError(f"{path}: could not be read as {fmt} ({type(e).__name__}: {e}); check "
                         f"the file or the fmt argument") from None
    if len(stream) == 0:
        raise TraceError(f"{path}: holds no traces")
    return stream, fmt


# ------------------------------------------------------------------------------- streaming SEG-Y / SU

#: trace header fields the streaming reader takes: ObsPy's name -> (0-based byte offset in the 240-byte trace header,
#: type). SEG-Y rev 1 positions, the same in SU; tests/test_segy.py holds them to ``obspy.io.segy.header``.
TRACE_FIELDS = {
    "original_field_record_number": (8, "i4"),
    "trace_number_within_the_original_field_record": (12, "i4"),
    "receiver_group_elevation": (40, "i4"),
    "surface_elevation_at_source": (44, "i4"),
    "source_depth_below_surface": (48, "i4"),
    "scalar_to_be_applied_to_all_elevations_and_depths": (68, "i2"),
    "scalar_to_be_applied_to_all_coordinates": (70, "i2"),
    "source_coordinate_x": (72, "i4"),
    "source_coordinate_y": (76, "i4"),
    "group_coordinate_x": (80, "i4"),
    "group_coordinate_y": (84, "i4"),
    "coordinate_units": (88, "i2"),
    "delay_recording_time": (108, "i2"),
    "number_of_samples_in_this_trace": (114, "u2"),
    "sample_interval_in_ms_for_this_trace": (116, "u2"),
    "scalar_to_be_applied_to_times": (214, "i2"),
}
#: SEG-Y data sample format code -> (sample type in the file, numpy type returned); 1 = IBM float (converted)
SAMPLE_FORMATS = {1: ("u4", np.float32), 2: ("i4", np.int32), 3: ("i2", np.int16), 5: ("f4", np.float32),
                  8: ("i1", np.int8)}
#: bytes of the file mapped at a time; the reader's working memory is a few of these (sample conversion) plus the
#: header index (~350 bytes per trace at its peak) and the traces selected, whatever the file's size
CHUNK_BYTES = 8 * 2**20

# IBM float: sign (1 bit), base-16 exponent biased by 64 (7 bits), 24-bit fraction: value = +-fraction/2^24 * 16^(e-64)
_IBM_SCALE = np.array([(-1.0 if b & 0x80 else 1.0) * 16.0 ** ((b & 0x7F) - 64) / 2.0 ** 24 for b in range(256)])


def _ibm_to_float32(u):
    """IBM single-precision floats given as native uint32 words -> float32 (exact where float32 can hold the value)."""
    with np.errstate(over="ignore"):
        return ((u & 0xFFFFFF).astype(np.float64) * _IBM_SCALE[u >> 24]).astype(np.float32)


@dataclass
class _Layout:
    """A SEG-Y / SU file of fixed-length traces as the streaming reader maps it."""

    path: pathlib.Path
    fmt: str
    endian: str  # ">" or "<"
    code: int  # data sample format code (SU: 5)
    start: int  # byte offset of the first trace header
    nt: int
    n_traces: int
    unit: float  # m per header length unit (0.3048 for SEG-Y measurement_system 2)
    binary_dt: float  # s, the binary header's sample interval (0 if unset; SU: 0)

    @property
    def itemsize(self) -> int:
        return 240 + self.nt * np.dtype(SAMPLE_FORMATS[self.code][0]).itemsize

    def windows(self, first: int = 0):
        """(a, b): consecutive runs of traces of about CHUNK_BYTES each, from trace ``first``."""
        per = max(1, CHUNK_BYTES // self.itemsize)
        for a in range(first, self.n_traces, per):
            yield a, min(a + per, self.n_traces)

    def map(self, dtype, a, b):
        return np.memmap(self.path, dtype=dtype, mode="r", offset=self.start + a * self.itemsize, shape=(b - a,))


def _layout(path: pathlib.Path, fmt: str):
    """The :class:`_Layout` of a file of fixed-length traces in a sample format numpy reads, or None (then ObsPy reads
    it, and reports what is wrong with it)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(3600 if fmt == "SEGY" else 240)

    def num(buf, off, t):
        return int(np.frombuffer(buf, dtype=t, count=1, offset=off)[0])

    if fmt == "SU":
        fits = [e for e in "<>" if len(head) == 240 and num(head, 114, e + "i2") > 0
                and size % (240 + 4 * num(head, 114, e + "i2")) == 0]
        if len(fits) != 1:
            return None
        nt = num(head, 114, fits[0] + "i2")
        return _Layout(path, fmt, fits[0], 5, 0, nt, size // (240 + 4 * nt), 1.0, 0.0)
    if len(head) < 3600:
        return None
    endian = next((e for e in "><" if num(head, 3224, e + "i2") in (1, 2, 3, 4, 5, 8)), None)
    if endian is None or num(head, 3224, endian + "i2") not in SAMPLE_FORMATS:
        return None
    n_ext = num(head, 3504, endian + "i2")
    start = 3600 + 3200 * n_ext
    if n_ext < 0 or size < start + 240:
        return None
    with open(path, "rb") as f:
        f.seek(start + 114)
        nt = num(f.read(2), 0, endian + "u2")
    lay = _Layout(path, fmt, endian, num(head, 3224, endian + "i2"), start, nt, 0,
                  0.3048 if num(head, 3254, endian + "i2") == 2 else 1.0, num(head, 3216, endian + "u2") * 1e-6)
    if nt < 1 or (size - start) % lay.itemsize:
        return None
    lay.n_traces = (size - start) // lay.itemsize
    return lay


def _scan_headers(lay: _Layout):
    """{field: (n_traces,) array} of :data:`TRACE_FIELDS`, read window by window; None if the traces' lengths differ
    (not a fixed-length file: ObsPy reads it)."""
    names = list(TRACE_FIELDS)
    dtype = np.dtype({"names": names, "formats": [lay.endian + TRACE_FIELDS[k][1] for k in names],
                      "offsets": [TRACE_FIELDS[k][0] for k in names], "itemsize": lay.itemsize})
    out = {k: np.empty(lay.n_traces, dtype=TRACE_FIELDS[k][1]) for k in names}
    for a, b in lay.windows():
        mm = lay.map(dtype, a, b)
        for k in names:
            out[k][a:b] = mm[k]
        del mm
    if np.any(out["number_of_samples_in_this_trace"] != lay.nt):
        return None
    return out


def _read_samples(lay: _Layout, traces, out, rows) -> None:
    """Copy the samples of traces ``traces`` (sorted file indices) of ``lay`` into ``out[rows]``, window by window."""
    ftype, _ = SAMPLE_FORMATS[lay.code]
    dtype = np.dtype({"names": ["s"], "formats": [(lay.endian + ftype, (lay.nt,))], "offsets": [240],
                      "itemsize": lay.itemsize})
    per = max(1, CHUNK_BYTES // lay.itemsize)
    i = 0
    while i < len(traces):
        a = int(traces[i])
        j = int(np.searchsorted(traces, a + per, side="left"))
        mm = lay.map(dtype, a, min(a + per, lay.n_traces))
        sel = traces[i:j] - a
        raw = mm["s"][sel[0]:sel[-1] + 1] if np.all(np.diff(sel) == 1) else mm["s"][sel]  # the selected traces only
        samples = _ibm_to_float32(raw.astype(np.uint32)) if lay.code == 1 else raw
        r = rows[i:j]
        if np.all(np.diff(r) == 1):
            out[r[0]:r[-1] + 1] = samples
        else:
            out[r] = samples
        del mm, raw, samples
        i = j


DEPTH_CONVENTIONS = ("auto", "elevation", "depth")
ENGINES = ("auto", "stream", "obspy")


def _one_sampling(files, h, file_of, first_of, label):
    """(dt s, t0 s, nt) shared by every trace of read_shot_gathers' files (TraceError naming the first trace that
    differs): the trace header's sample interval, else the binary header's; one length; one delay recording time."""
    iv = h["sample_interval_in_ms_for_this_trace"].astype(np.float64) * 1e-6
    fallback = np.array([fh.get("dt", 0.0) if lay is None else lay.binary_dt for _, lay, fh, _ in files])[file_of]
    dts = np.where(iv > 0, iv, fallback)
    bad = np.flatnonzero((dts != dts[0]) & (np.abs(dts - dts[0]) > 1e-9 * dts[0]))
    if bad.size:
        raise TraceError(f"{label(bad[0])}: sample interval {dts[bad[0]]:g} s differs from "
                         f"{dts[0]:g} s of {label(0)}; resample the traces to one interval")
    lengths = [lay.nt if lay is not None else fh["nt"] for _, lay, fh, _ in files]
    bad = [k for k, m in enumerate(lengths) if m != lengths[0]]
    if bad:
        raise TraceError(f"{label(first_of[bad[0]])}: {lengths[bad[0]]} samples differ from {lengths[0]} of "
                         f"{label(0)}; cut or pad the traces to one length")
    t0s = 1e-3 * h["delay_recording_time"] * _scalars(h["scalar_to_be_applied_to_times"])
    bad = np.flatnonzero(np.abs(t0s - t0s[0]) > 1e-9)
    if bad.size:
        raise TraceError(f"{label(bad[0])}: delay recording time t0 = {t0s[bad[0]]:g} s differs from "
                         f"{t0s[0]:g} s of {label(0)}; shift the traces to one start time")
    dt = float(dts[0])
    if not dt > 0:
        raise TraceError(f"{label(0)}: sample interval {dt!r} s is not positive; set "
                         f"sample_interval_in_ms_for_this_trace (microseconds)")
    return dt, float(t0s[0]), lengths[0]


def _group_shots(src, h, group_by, ndim, label):
    """(n_shots, n_receivers) trace indices of read_shot_gathers: shots by equal source position (to 1 mm) or field
    record number, in order of first appearance, receivers in trace order (TraceError: unequal shots, or a record
    with several source positions)."""
    rec_no = h["original_field_record_number"].astype(np.int64)
    keys = np.round(src * 1e3).astype(np.int64) if group_by == "source" else rec_no[:, None]
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    shot_of = np.argsort(np.argsort(first))[inverse.reshape(-1)]
    order = np.argsort(shot_of, kind="stable")
    counts = np.bincount(shot_of)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    odd = np.flatnonzero(counts != counts[0])
    if odd.size:
        s = int(odd[0])
        m0 = int(order[starts[s]])
        where = ", ".join(f"{a}={v:.3f}" for a, v in zip(AXES[ndim], src[m0]))
        raise TraceError(f"shot {s} (source at {where} m; first trace {label(m0)}): "
                         f"{counts[s]} receivers, but shot 0 has {counts[0]}; every shot needs "
                         f"the same number of receivers (pad missing traces with zeros "
                         f"or drop the shot)")
    grid = order.reshape(len(counts), int(counts[0]))
    if group_by == "record":
        spread = (src[grid].max(axis=1) - src[grid].min(axis=1)).max(axis=1)
        bad = np.flatnonzero(spread > 1e-3)
        if bad.size:
            s = int(bad[0])
            raise TraceError(f"shot {s} (field record {rec_no[grid[s, 0]]}): traces have different "
                             f"source coordinates; group_by='source' instead")
    return grid


def read_shot_gathers(paths, fmt=None, *, coordinate_scale=None, ndim=2, group_by="source",
                      depth_convention="elevation", model=None, shots=None, receivers=None,
                      engine="auto") -> ShotGathers:
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
    sample interval, length and t0, and every shot the same number of receivers (TraceError);
    the sample interval is the trace header's, else the binary header's.

    shots: indices of the shots to keep (0-based, in the order above; default all); receivers: indices of the
    receivers to keep within every shot (default all). Only the kept traces' samples are read.

    engine: "stream" maps the files window by window (numpy memmap of CHUNK_BYTES at a time) and reads the header
    fields above for every trace and the samples of the kept traces only, so memory stays at a few windows plus
    ~350 bytes per trace (the header index) plus the kept data whatever the file's size; it reads fixed-length traces in sample
    formats 1 (IBM float, converted to float32), 2, 3, 5 (IEEE float) and 8, either byte order. "obspy" reads
    every trace through ObsPy (the whole file in memory); "auto" (default) streams where it can and uses ObsPy
    otherwise (variable trace lengths, other sample formats, unreadable headers; ObsPy then names the problem).
    """
    if ndim not in (2, 3):
        raise TraceError(f"ndim: {ndim!r} is not 2 or 3")
    if group_by not in ("source", "record"):
        raise TraceError(f"group_by: {group_by!r} is not 'source' or 'record'")
    if depth_convention not in DEPTH_CONVENTIONS:
        raise TraceError(f"depth_convention: {depth_convention!r} is not one of {', '.join(DEPTH_CONVENTIONS)}")
    if engine not in ENGINES:
        raise TraceError(f"engine: {engine!r} is not one of {', '.join(ENGINES)}")
    if coordinate_scale is not None and not (math.isfinite(float(coordinate_scale))
                                             and float(coordinate_scale) > 0):
        raise TraceError(f"coordinate_scale: {coordinate_scale!r} is not a positive number of "
                         f"metres per header unit")
    path_list = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not path_list:
        raise TraceError("paths: no files given")
    files = []  # per file: (name, layout or None, header dict, samples or None)
    for p in map(pathlib.Path, path_list):
        f = _file_format(p, fmt)
        lay = _layout(p, f) if engine != "obspy" else None
        hdr = _scan_headers(lay) if lay is not None else None
        if hdr is None:
            if engine == "stream":
                raise TraceError(f"{p}: not a file of fixed-length traces in sample format 1, 2, 3, 5 or 8 that the "
                                 f"streaming reader maps; pass engine='obspy' (reads the whole file into memory)")
            lay, (hdr, samples) = None, _obspy_headers(p, f)
        else:
            samples = None
            if lay.unit != 1.0:
                log.info("%s: binary header measurement_system = 2 (feet): coordinates converted to metres", p.name)
        files.append((p.name, lay, hdr, samples))
    h = {k: np.concatenate([np.asarray(fh[k]) for _, _, fh, _ in files]) for k in TRACE_FIELDS}
    n = len(h["source_coordinate_x"])
    file_of = np.repeat(np.arange(len(files)), [len(fh["source_coordinate_x"]) for _, _, fh, _ in files])
    first_of = np.concatenate([[0], np.cumsum(np.bincount(file_of, minlength=len(files)))[:-1]])
    unit = np.array([fh["unit"] if lay is None else lay.unit for _, lay, fh, _ in files])[file_of]

    def label(i):
        i = int(i)
        return (f"{files[file_of[i]][0]} trace {i - first_of[file_of[i]]} (0-based; field record "
                f"{int(h['original_field_record_number'][i])}, trace "
                f"{int(h['trace_number_within_the_original_field_record'][i])})")

    cu = h["coordinate_units"].astype(np.int64)
    bad = np.flatnonzero((cu != 0) & (cu != 1))
    if bad.size and coordinate_scale is None:
        raise TraceError(f"{label(bad[0])}: coordinate_units = {cu[bad[0]]} (2: arc seconds, 3: degrees, "
                         f"4: DMS) are geographic; convert the coordinates to metres "
                         f"(e.g. UTM) or pass coordinate_scale to force a length scale")
    if coordinate_scale is None:
        cs = _scalars(h["scalar_to_be_applied_to_all_coordinates"]) * unit
        es = _scalars(h["scalar_to_be_applied_to_all_elevations_and_depths"]) * unit
    else:
        cs = es = np.full(n, float(coordinate_scale))
    g = {k: h[k].astype(np.float64) for k in ("source_coordinate_x", "source_coordinate_y", "group_coordinate_x",
                                              "group_coordinate_y", "receiver_group_elevation",
                                              "surface_elevation_at_source", "source_depth_below_surface")}
    src = np.stack([es * (g["source_depth_below_surface"] - g["surface_elevation_at_source"]),
                    cs * g["source_coordinate_y"], cs * g["source_coordinate_x"]], axis=1)
    rec = np.stack([-es * g["receiver_group_elevation"], cs * g["group_coordinate_y"],
                    cs * g["group_coordinate_x"]], axis=1)
    src_z_depth = es * (g["surface_elevation_at_source"] + g["source_depth_below_surface"])
    rec_z_depth = es * g["receiver_group_elevation"]
    del g
    dt, t0, nt = _one_sampling(files, h, file_of, first_of, label)
    src, rec = _apply_depth_convention(src, rec, src_z_depth, rec_z_depth, depth_convention, model, ndim, path_list)
    if ndim == 2:
        ys = np.concatenate([src[:, 1], rec[:, 1]])
        if np.ptp(ys) > 1e-3:
            i = int(np.argmax(np.maximum(np.abs(src[:, 1] - ys[0]), np.abs(rec[:, 1] - ys[0]))))
            raise TraceError(f"{label(i)}: y coordinates vary (source y {src[i, 1]:g} m, receiver "
                             f"y {rec[i, 1]:g} m, first trace y {ys[0]:g} m; range {np.ptp(ys):g} m) "
                             f"but ndim=2 reads x only; pass ndim=3, or rotate the line onto x")
        src, rec = src[:, [0, 2]], rec[:, [0, 2]]
    grid = _group_shots(src, h, group_by, ndim, label)
    grid = grid[_selection(shots, grid.shape[0], "shots")][:, _selection(receivers, grid.shape[1], "receivers")]
    data = _samples(files, grid, file_of, first_of, nt)
    gathers = ShotGathers(data=data, dt=dt, t0=t0, sources=src[grid[:, 0]], receivers=rec[grid])
    check_samples(gathers.data, _Labels(label, grid.reshape(-1)))
    log.info("read %d shots x %d receivers x %d samples, dt %g s, t0 %g s from %d file(s) (%d traces)",
             gathers.n_shots, gathers.n_receivers, gathers.nt, dt, gathers.t0, len(path_list), n)
    return gathers


class _Labels:
    """names[k] = label(traces[k]), made only when asked for (check_samples names the bad traces only)."""

    def __init__(self, label, traces):
        self.label, self.traces = label, traces

    def __len__(self):
        return len(self.traces)

    def __getitem__(self, k):
        return self.label(self.traces[k])


def _scalars(v):
    """SEG-Y scalar rule, element-wise: positive multiplies, negative divides, zero means 1."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v > 0, v, np.where(v < 0, 1.0 / np.where(v < 0, -v, 1.0), 1.0))


def _selection(pick, n, key):
    """Indices (list) of ``pick`` into range(n), checked; all when None."""
    if pick is None:
        return np.arange(n)
    idx = np.asarray(pick).reshape(-1)
    if idx.size == 0 or idx.dtype.kind not in "iu" or idx.min() < -n or idx.max() >= n:
        raise TraceError(f"{key}: {pick!r} is not a non-empty list of indices in 0..{n - 1} ({n} {key} in the data)")
    return idx % n


def _file_format(path: pathlib.Path, fmt) -> str:
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
    return fmt


def _obspy_headers(path: pathlib.Path, fmt: str):
    """(header dict as :func:`_scan_headers` gives it plus 'nt', 'dt', 'unit'; samples (n, nt) array) of a file read
    whole through ObsPy (today's reader: variable trace lengths, sample format 4, ...)."""
    stream, f = _read_one(path, fmt)
    unit = 1.0
    if f == "SEGY" and int(getattr(stream.stats.binary_file_header, "measurement_system", 1) or 1) == 2:
        unit = 0.3048
        log.info("%s: binary header measurement_system = 2 (feet): coordinates converted to metres", path.name)
    heads = [tr.stats.segy.trace_header if f == "SEGY" else tr.stats.su.trace_header for tr in stream]
    hdr = {k: np.array([int(getattr(hh, k)) for hh in heads], dtype=np.int64) for k in TRACE_FIELDS}
    # ObsPy's delta: the trace header's interval, else its default of 1 s
    hdr["sample_interval_in_ms_for_this_trace"] = np.array([round(tr.stats.delta * 1e6) for tr in stream], np.int64)
    lengths = {len(tr.data) for tr in stream}
    if len(lengths) > 1:
        i = next(k for k, tr in enumerate(stream) if len(tr.data) != len(stream[0].data))
        raise TraceError(f"{path.name} trace {i} (0-based; field record {hdr['original_field_record_number'][i]}, trace "
                         f"{hdr['trace_number_within_the_original_field_record'][i]}): {len(stream[i].data)} samples "
                         f"differ from {len(stream[0].data)} of {path.name} trace 0; cut or pad the traces to one length")
    hdr.update(nt=len(stream[0].data), dt=0.0, unit=unit)
    return hdr, np.stack([tr.data for tr in stream])


def _samples(files, grid, file_of, first_of, nt):
    """(shots, receivers, nt) samples of the traces ``grid`` (global trace indices), read file by file."""
    flat = grid.reshape(-1)
    types = {(SAMPLE_FORMATS[lay.code][1] if lay is not None else samples.dtype) for _, lay, _, samples in files}
    out = np.empty((flat.size, nt), dtype=np.result_type(*types))
    for k, (_, lay, _, samples) in enumerate(files):
        rows = np.flatnonzero(file_of[flat] == k)
        if not rows.size:
            continue
        local = flat[rows] - first_of[k]
        if lay is None:
            out[rows] = samples[local]
            continue
        o = np.argsort(local, kind="stable")
        _read_samples(lay, local[o], out, rows[o])
    return out.reshape(*grid.shape, nt)


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
    """Read event traces (MiniSEED, SAC, ASDF, anything ObsPy reads) into :class:`StationTraces`.

    paths: one path / glob or a list; an ASDF file (``FILE`` or ``FILE#tag`` when it holds several waveform tags)
    brings its StationXML and, for our forward output without a geographic reference, its local coordinates
    (:mod:`adseismic.data.asdf`); inventory: an ObsPy Inventory or StationXML path(s)
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
    from adseismic.data.asdf import station_inputs

    # ASDF files (waveforms + StationXML inside, optionally FILE#tag) -> their Stream, inventory and local coordinates
    paths, inventory, local_coordinates = station_inputs(paths, inventory, local_coordinates, ndim)
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
        stream += p if isinstance(p, obspy.Stream) else _read_checked(p)
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
