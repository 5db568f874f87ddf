"""The streaming SEG-Y / SU reader (issue 27): read_shot_gathers(engine="stream") maps the file window by window and
gives exactly what today's ObsPy reader (engine="obspy") gives, for every byte order and sample format it reads;
selecting shots / receivers reads only their samples; a file it cannot map falls back to ObsPy; and its memory stays
at a fixed bound (a few CHUNK_BYTES windows) plus the header index and the data returned, whatever the file's size."""
import importlib.util
import pathlib
import tracemalloc

import numpy as np
import pytest

from adseismic.data import read as rd
from adseismic.data.read import read_shot_gathers
from adseismic.data.traces import ShotGathers, TraceError
from adseismic.data.write import write_shot_gathers_su

obspy = pytest.importorskip("obspy")

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("segy_read_bench", ROOT / "benchmarks" / "segy_read.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _gathers(ndim=2, n_shots=3, n_rec=7, nt=150, seed=0):
    rng = np.random.default_rng(seed)
    x_src = 100.0 + 1000.0 * np.arange(n_shots) + 0.123
    rec = []
    for s in range(n_shots):
        x = 50.0 + 183.457 * np.arange(n_rec) + 10.0 * s
        z = -12.345 + s + 0.001 * np.arange(n_rec)
        rec.append(np.column_stack([z, x] if ndim == 2 else [z, 400.25 + 7.5 * np.arange(n_rec), x]))
    src = (np.column_stack([np.full(n_shots, 5.007), x_src]) if ndim == 2
           else np.column_stack([np.full(n_shots, 5.007), np.full(n_shots, -321.5), x_src]))
    data = rng.standard_normal((n_shots, n_rec, nt)).astype(np.float16).astype(np.float32)  # IBM-exact values
    return ShotGathers(data, 0.002, -0.0125, src, np.stack(rec))


def _rewrite(path, out, **write_kw):
    """Read ``path`` with ObsPy and write it again to ``out`` (other byte order / sample format)."""
    st = obspy.read(str(path))
    st.write(str(out), **write_kw)
    return out


def _same(a, b):
    assert a.data.dtype == b.data.dtype and a.data.shape == b.data.shape
    np.testing.assert_array_equal(a.data, b.data)
    assert (a.dt, a.t0) == (b.dt, b.t0)
    np.testing.assert_array_equal(a.sources, b.sources)
    np.testing.assert_array_equal(a.receivers, b.receivers)


def _result(paths, **kw):
    """read_shot_gathers' result, or its TraceError's message."""
    try:
        return read_shot_gathers(paths, **kw)
    except TraceError as e:
        return str(e)


def test_trace_header_positions_are_obspys():
    from obspy.io.segy.header import TRACE_HEADER_FORMAT

    offsets, off = {}, 0
    for size, name, *_ in TRACE_HEADER_FORMAT:
        offsets[name] = (off, size)
        off += size
    for name, (o, t) in rd.TRACE_FIELDS.items():
        assert offsets[name] == (o, np.dtype(t).itemsize), name


def test_ibm_conversion():
    words = np.array([0xC276A000, 0x42640000, 0x00000000, 0x80000000, 0x41100000, 0x3F100000], dtype=np.uint32)
    np.testing.assert_array_equal(rd._ibm_to_float32(words), np.float32([-118.625, 100.0, 0.0, -0.0, 1.0, 1 / 256]))
    x = np.random.default_rng(3).standard_normal(1000).astype(np.float16).astype(np.float32)
    np.testing.assert_array_equal(rd._ibm_to_float32(_bench().float_to_ibm(x)), x)


@pytest.mark.parametrize("case", ["su-little", "su-big", "segy-ieee-big", "segy-ieee-little", "segy-ibm",
                                  "segy-int32", "segy-feet"])
def test_stream_reads_what_obspy_reads(tmp_path, case):
    g = _gathers()
    if case.startswith("su"):
        path = write_shot_gathers_su(tmp_path / "a.su", g, fmt="SU")  # little-endian
        if case == "su-big":
            path = _rewrite(path, tmp_path / "b.su", format="SU", byteorder=">")
    else:
        path = write_shot_gathers_su(tmp_path / "a.segy", g, fmt="SEGY")  # big-endian IEEE
        kw = {"segy-ieee-little": {"byteorder": "<"}, "segy-ibm": {"data_encoding": 1},
              "segy-int32": {"data_encoding": 2}}.get(case)
        if kw:
            st = obspy.read(str(path))
            if case == "segy-int32":
                for tr in st:
                    tr.data = np.round(tr.data * 1000).astype(np.int32)
            st.write(str(tmp_path / "b.segy"), format="SEGY", **kw)
            path = tmp_path / "b.segy"
        if case == "segy-feet":
            raw = bytearray(path.read_bytes())
            raw[3254:3256] = (2).to_bytes(2, "big")  # measurement_system = feet
            path.write_bytes(bytes(raw))
    assert rd._layout(path, "SU" if case.startswith("su") else "SEGY") is not None  # the streaming path, no fallback
    new, old = read_shot_gathers(path, engine="stream"), read_shot_gathers(path, engine="obspy")
    _same(new, old)
    if case in ("su-little", "segy-ieee-big", "segy-ibm"):
        np.testing.assert_array_equal(new.data, g.data)
        np.testing.assert_allclose(new.receivers, g.receivers, atol=1e-3)
    if case == "segy-feet":
        np.testing.assert_allclose(new.receivers[..., 1], g.receivers[..., 1] * 0.3048, atol=1e-3)


def test_stream_options_match_obspy_3d_several_files_record_grouping_and_depth_convention(tmp_path):
    g = _gathers(ndim=3, n_shots=4)
    parts = [write_shot_gathers_su(tmp_path / f"s{s}.segy",
                                   ShotGathers(g.data[s:s + 1], g.dt, g.t0, g.sources[s:s + 1], g.receivers[s:s + 1]),
                                   fmt="SEGY") for s in range(4)]
    for kw in ({"ndim": 3}, {"ndim": 3, "group_by": "record"}, {"ndim": 3, "depth_convention": "depth"},
               {"ndim": 3, "coordinate_scale": 1e-3}, {"ndim": 3, "shots": [3, 1], "receivers": [0, 6, 2]}):
        new, old = (_result(parts, engine=e, **kw) for e in ("stream", "obspy"))
        if isinstance(old, str):  # the same refusal (one record number in every file here, for group_by="record")
            assert new == old
        else:
            _same(new, old)
    sel = read_shot_gathers(parts, ndim=3, shots=[3, 1], receivers=[0, 6, 2])
    np.testing.assert_array_equal(sel.data, g.data[[3, 1]][:, [0, 6, 2]])
    np.testing.assert_allclose(sel.sources, g.sources[[3, 1]], atol=1e-3)
    for bad in ([4], [], [0.5]):
        with pytest.raises(TraceError, match="shots: .* indices in 0..3"):
            read_shot_gathers(parts, ndim=3, shots=bad)
    with pytest.raises(TraceError, match="engine: 'fast' is not one of auto, stream, obspy"):
        read_shot_gathers(parts, engine="fast")


def test_variable_trace_lengths_fall_back_to_obspy_and_its_message(tmp_path):
    g = _gathers(n_shots=1, n_rec=3)
    st = obspy.read(str(write_shot_gathers_su(tmp_path / "a.segy", g, fmt="SEGY")))
    st[2].data = st[2].data[:100]
    st.write(str(tmp_path / "v.segy"), format="SEGY")
    with pytest.raises(TraceError, match="v.segy trace 2 .*100 samples differ from 150.*cut or pad"):
        read_shot_gathers(tmp_path / "v.segy")
    with pytest.raises(TraceError, match="engine='obspy'"):
        read_shot_gathers(tmp_path / "v.segy", engine="stream")


def test_memory_stays_bounded_whatever_the_file_size(tmp_path, monkeypatch):
    """A ~200 MB SEG-Y file: reading one shot allocates a few windows and the header index only (not the file);
    reading all of it allocates the data returned plus that same bound (no second copy of the data)."""
    monkeypatch.setattr(rd, "CHUNK_BYTES", 4 * 2 ** 20)
    n_shots, n_rec, nt = 94, 500, 1000  # 199 MB, 47,000 traces
    path, shot0 = _bench().write_segy(tmp_path / "big.segy", n_shots, n_rec, nt)
    size = path.stat().st_size
    assert size > 190e6
    bound = 4 * rd.CHUNK_BYTES + 400 * n_shots * n_rec  # windows + header index (~350 B/trace); 35.6 MB here
    tracemalloc.start()
    try:
        one = read_shot_gathers(path, shots=[0])
        _, peak_one = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        whole = read_shot_gathers(path, shots=[n_shots - 1, 0], receivers=list(range(0, n_rec, 2)))
        _, peak_sel = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(one.data[0], shot0)
    np.testing.assert_array_equal(whole.data[1], shot0[::2])
    assert peak_one < bound < size / 5, (peak_one, bound, size)
    assert peak_sel - whole.data.nbytes < bound, (peak_sel, whole.data.nbytes, bound)
    path.unlink()
