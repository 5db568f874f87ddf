"""adseismic.data (traces, geometry, preprocess, read, write): round trips through SU / SEG-Y / MiniSEED + StationXML / SAC, the local
projection, preprocessing onto the simulation time axis, and the bad-input errors."""
import logging
import subprocess
import sys

import numpy as np
import pytest

from adseismic.data.geometry import Reference, check_inside, check_samples, project, unproject
from adseismic.data.model import Model
from adseismic.data.preprocess import preprocess
from adseismic.data.read import read_shot_gathers, read_station_traces
from adseismic.data.traces import ShotGathers, StationTraces, TraceError
from adseismic.data.write import write_shot_gathers_su, write_station_traces

obspy = pytest.importorskip("obspy")
from obspy import UTCDateTime  # noqa: E402


def _gathers(ndim=2, n_shots=3, n_rec=12, nt=400, dt=0.002, t0=0.0, seed=0):
    rng = np.random.default_rng(seed)
    x_src = 100.0 + 1000.0 * np.arange(n_shots) + 0.123
    z_src = np.full(n_shots, 5.007)
    rec = []
    for s in range(n_shots):
        x = 50.0 + 183.457 * np.arange(n_rec) + 10.0 * s
        z = -12.345 + s + 0.001 * np.arange(n_rec)  # above sea level: negative depth
        cols = [z, x] if ndim == 2 else [z, 400.25 + 7.5 * np.arange(n_rec), x]
        rec.append(np.column_stack(cols))
    src = (np.column_stack([z_src, x_src]) if ndim == 2
           else np.column_stack([z_src, np.full(n_shots, -321.5), x_src]))
    data = rng.standard_normal((n_shots, n_rec, nt)).astype(np.float32)
    return ShotGathers(data, dt, t0, src, np.stack(rec))


# ------------------------------------------------------------------------ SEG-Y / SU

@pytest.mark.parametrize("fmt", ["SU", "SEGY"])
def test_shot_gathers_round_trip(tmp_path, fmt):
    g = _gathers(t0=-0.0125)
    path = write_shot_gathers_su(tmp_path / f"shots.{fmt.lower()}", g, fmt=fmt)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no .part left behind
    r = read_shot_gathers(path)
    assert r.data.shape == (3, 12, 400)
    np.testing.assert_array_equal(r.data, g.data)  # float32 exactly
    assert r.dt == pytest.approx(0.002, rel=1e-12) and r.t0 == pytest.approx(-0.0125, abs=1e-12)
    np.testing.assert_allclose(r.sources, g.sources, atol=1e-3)
    np.testing.assert_allclose(r.receivers, g.receivers, atol=1e-3)


def test_shot_gathers_3d_and_several_files(tmp_path):
    g = _gathers(ndim=3)
    parts = []
    for s in range(3):  # one file per shot
        one = ShotGathers(g.data[s:s + 1], g.dt, g.t0, g.sources[s:s + 1], g.receivers[s:s + 1])
        parts.append(write_shot_gathers_su(tmp_path / f"shot{s}.segy", one, fmt="SEGY"))
    r = read_shot_gathers(parts, ndim=3)
    np.testing.assert_array_equal(r.data, g.data)
    np.testing.assert_allclose(r.sources, g.sources, atol=1e-3)
    np.testing.assert_allclose(r.receivers, g.receivers, atol=1e-3)
    # ndim=2 refuses a geometry whose y coordinates vary
    with pytest.raises(TraceError, match="y coordinates vary"):
        read_shot_gathers(parts, ndim=2)


def test_shot_gathers_coordinate_scale_override(tmp_path):
    g = _gathers()
    path = write_shot_gathers_su(tmp_path / "s.su", g)
    r = read_shot_gathers(path, coordinate_scale=1e-3)  # header ints are mm
    np.testing.assert_allclose(r.receivers, g.receivers, atol=1e-3)
    r = read_shot_gathers(path, group_by="record")
    assert r.data.shape == g.data.shape


def test_shot_with_fewer_receivers(tmp_path):
    g = _gathers()
    a = write_shot_gathers_su(tmp_path / "a.su", ShotGathers(
        g.data[:2], g.dt, g.t0, g.sources[:2], g.receivers[:2]))
    b = write_shot_gathers_su(tmp_path / "b.su", ShotGathers(
        g.data[2:, :11], g.dt, g.t0, g.sources[2:], g.receivers[2:, :11]))
    with pytest.raises(TraceError, match=r"shot 2 .*x=2100.123.*11 receivers, but shot 0 has 12"):
        read_shot_gathers([a, b])


def test_trace_with_other_sampling_interval(tmp_path):
    g = _gathers()
    a = write_shot_gathers_su(tmp_path / "a.segy", g, fmt="SEGY")
    g1 = _gathers(dt=0.001)
    b = write_shot_gathers_su(tmp_path / "b.segy", g1, fmt="SEGY")
    with pytest.raises(TraceError, match=r"b\.segy trace 0 .*sample interval 0\.001 s differs "
                                         r"from 0\.002 s"):
        read_shot_gathers([a, b])


def test_nan_samples_in_gathers(tmp_path):
    g = _gathers()
    g.data[1, 4, 17] = np.nan
    path = write_shot_gathers_su(tmp_path / "nan.su", g)
    with pytest.raises(TraceError, match=r"nan\.su trace 16 .*sample 17 is nan"):
        read_shot_gathers(path)


def test_unknown_extension_and_missing_file(tmp_path):
    with pytest.raises(TraceError, match="fmt:"):
        read_shot_gathers(tmp_path / "x.dat")
    with pytest.raises(TraceError, match="does not exist"):
        read_shot_gathers(tmp_path / "x.su")


# ------------------------------------------------------------------------ projection

REF = Reference(46.5, 8.0, datum=500.0, azimuth=60.0)


def test_projection_round_trip_and_geodesic():
    from obspy.geodetics import gps2dist_azimuth

    rng = np.random.default_rng(1)
    lat = 46.5 + rng.uniform(-0.6, 0.6, 300)
    lon = 8.0 + rng.uniform(-0.9, 0.9, 300)
    elev = rng.uniform(-500, 3000, 300)
    p = project(lat, lon, elev, REF)  # (n, 3) = z, north, east
    assert p.shape == (300, 3) and np.hypot(p[:, 1], p[:, 2]).max() < 100e3
    np.testing.assert_allclose(p[:, 0], 500.0 - elev)
    for i in range(5):  # distance and azimuth from the reference are the geodesic ones
        dist, az, _ = gps2dist_azimuth(REF.latitude, REF.longitude, lat[i], lon[i])
        assert np.hypot(p[i, 1], p[i, 2]) == pytest.approx(dist, abs=1e-4)
        assert np.degrees(np.arctan2(p[i, 2], p[i, 1])) % 360 == pytest.approx(az, abs=1e-8)
    la, lo, el = unproject(p, REF)
    np.testing.assert_allclose(el, elev, rtol=0, atol=1e-9)
    back = project(la, lo, el, REF)
    assert np.abs(back - p).max() < 1e-3
    assert np.max(np.abs(la - lat)) * 111e3 < 1e-3 and np.max(np.abs(lo - lon)) * 78e3 < 1e-3


def test_projection_2d_line():
    # a point 10 km along azimuth 60 deg lands at x = 10 km; 2D points round trip on the line
    la, lo, el = unproject(np.array([[0.0, 10e3]]), REF)
    p3 = project(la, lo, el, REF)[0]
    assert np.degrees(np.arctan2(p3[2], p3[1])) == pytest.approx(60.0, abs=1e-9)
    p2 = project(la, lo, el, REF, ndim=2)
    np.testing.assert_allclose(p2, [[0.0, 10e3]], atol=1e-6)
    assert project(REF.latitude, REF.longitude + 0.1, 500.0, (46.5, 8.0), ndim=2)[1] > 7e3
    with pytest.raises(TraceError, match="reference"):
        project(0, 0, 0, (95.0, 0.0))


# ------------------------------------------------------------------------ stations

def _stations(n=5, nt=600, seed=2):
    rng = np.random.default_rng(seed)
    lat = 35.0 + rng.uniform(-0.4, 0.4, n)
    lon = -117.5 + rng.uniform(-0.4, 0.4, n)
    elev = rng.uniform(0, 2000, n)
    names = [f"XX.S{i:02d}..HHZ" for i in range(n)]
    tr = StationTraces(rng.standard_normal((n, nt)), 0.01, UTCDateTime(2024, 1, 2, 3, 4, 5.5),
                         np.zeros((n, 3)), names)
    return tr, lat, lon, elev


def test_station_traces_round_trip(tmp_path):
    tr, lat, lon, elev = _stations()
    ref = (35.0, -117.5)
    mseed, xml = write_station_traces(tmp_path, tr, lat, lon, elev)
    r = read_station_traces(mseed, inventory=xml, reference=ref, ndim=3, noise_window=(0, 2.0))
    assert r.names == tr.names and r.dt == pytest.approx(0.01) and r.starttime == tr.starttime
    np.testing.assert_array_equal(r.data, tr.data)
    np.testing.assert_allclose(r.positions, project(lat, lon, elev, ref), atol=1e-6)
    la, lo, el = unproject(r.positions, r.reference)
    assert np.max(np.abs(la - lat)) * 111e3 < 1e-3 and np.max(np.abs(lo - lon)) * 92e3 < 1e-3
    np.testing.assert_allclose(el, elev, atol=1e-6)
    np.testing.assert_allclose(r.noise_std, tr.data[:, :201].std(axis=1))
    r2 = read_station_traces(mseed, inventory=xml, reference=(35.0, -117.5, 0.0, 90.0))
    np.testing.assert_allclose(r2.positions[:, 1], r.positions[:, 2], atol=1e-6)  # 2D x = east


def test_station_traces_sac_headers_and_overrides(tmp_path):
    tr, lat, lon, elev = _stations(n=3)
    for i, name in enumerate(tr.names):
        net, sta, loc, cha = name.split(".")
        t = obspy.Trace(tr.data[i].astype(np.float32), {
            "network": net, "station": sta, "location": loc, "channel": cha, "delta": tr.dt,
            "starttime": tr.starttime})
        if i < 2:
            t.stats.sac = obspy.core.AttribDict(stla=lat[i], stlo=lon[i], stel=elev[i])
        t.write(str(tmp_path / f"{name}.sac"), format="SAC")
    paths = sorted(tmp_path.glob("*.sac"))
    with pytest.raises(TraceError, match=r"XX\.S02\.\.HHZ: no coordinates.*local_coordinates"):
        read_station_traces(paths, reference=(35.0, -117.5))
    r = read_station_traces(paths, reference=(35.0, -117.5), ndim=2,
                              local_coordinates={"XX.S02": {"x": 1234.5, "z": -100.0}})
    np.testing.assert_allclose(r.positions[2], [-100.0, 1234.5])
    # SAC stores stla/stlo as float32: ~2e-6 degrees, i.e. up to ~0.2 m of position
    np.testing.assert_allclose(r.positions[:2], project(lat[:2], lon[:2], elev[:2],
                                                          (35.0, -117.5), ndim=2), atol=0.5)
    with pytest.raises(TraceError, match=r"reference: needed.*\(3[45]\.\d{4}, -11[78]\.\d{4}\)"):
        read_station_traces(paths[:2])


def test_station_trace_with_gap(tmp_path):
    tr, lat, lon, elev = _stations(n=2)
    mseed, xml = write_station_traces(tmp_path, tr, lat, lon, elev)
    st = obspy.read(str(mseed))
    a = st[1].copy().trim(endtime=st[1].stats.starttime + 1.0)
    b = st[1].copy().trim(starttime=st[1].stats.starttime + 2.5)
    st = obspy.Stream([st[0], a, b])
    st.write(str(tmp_path / "gap.mseed"), format="MSEED", encoding="FLOAT64")
    with pytest.raises(TraceError, match=r"XX\.S01\.\.HHZ: gap from 2024-01-02T03:04:06\.5.* "
                                         r"to 2024-01-02T03:04:08\.0.*fill_gaps"):
        read_station_traces(tmp_path / "gap.mseed", inventory=xml, reference=(35, -117.5))
    r = read_station_traces(tmp_path / "gap.mseed", inventory=xml, reference=(35, -117.5),
                              fill_gaps=0.0)
    assert r.data.shape == (2, 600) and np.all(r.data[1, 101:250] == 0)


def test_station_trace_with_other_sampling_rate(tmp_path):
    tr, lat, lon, elev = _stations(n=3)
    mseed, xml = write_station_traces(tmp_path, tr, lat, lon, elev)
    st = obspy.read(str(mseed))
    st[2].stats.sampling_rate = 50.0
    st.write(str(tmp_path / "mixed.mseed"), format="MSEED", encoding="FLOAT64")
    with pytest.raises(TraceError, match=r"XX\.S02\.\.HHZ: sampling rate 50 Hz .* 100 Hz"):
        read_station_traces(tmp_path / "mixed.mseed", inventory=xml, reference=(35, -117.5))


def test_station_misaligned_start(tmp_path):
    tr, lat, lon, elev = _stations(n=2)
    mseed, xml = write_station_traces(tmp_path, tr, lat, lon, elev)
    st = obspy.read(str(mseed))
    st[1].stats.starttime += 0.004
    st.write(str(tmp_path / "shifted.mseed"), format="MSEED", encoding="FLOAT64")
    with pytest.raises(TraceError, match=r"XX\.S01\.\.HHZ: starts at .*0\.004 s .*align=True"):
        read_station_traces(tmp_path / "shifted.mseed", inventory=xml, reference=(35, -117.5))
    r = read_station_traces(tmp_path / "shifted.mseed", inventory=xml, reference=(35, -117.5),
                              align=True)
    assert r.data.shape[0] == 2 and r.starttime == tr.starttime + 0.01


# ------------------------------------------------------------------------ checks

def test_check_inside():
    model = Model(np.full((11, 21), 2000.0), 10.0, (0.0, -100.0))
    check_inside(np.array([[0.0, -100.0], [100.0, 100.0]]), model, "station")
    with pytest.raises(TraceError, match=r"station 1 \(XX\.B\): at \(z=5\.000, x=150\.500\) m "
                                         r"is outside the model \(z 0\.\.100, x -100\.\.100 m\)"):
        check_inside(np.array([[5.0, 0.0], [5.0, 150.5]]), model, "station",
                       names=["XX.A", "XX.B"])
    with pytest.raises(TraceError, match=r"receiver \(1, 2\): at \(z=-1\.000"):
        pts = np.zeros((2, 3, 2))
        pts[1, 2] = (-1.0, 0.0)
        check_inside(pts, model, "receiver")


def test_check_samples(caplog):
    data = np.zeros((3, 100))
    data[0] = np.sin(np.arange(100) * 0.3)
    data[1] = np.clip(5 * np.sin(np.arange(100) * 0.1), -1, 1)
    with caplog.at_level(logging.WARNING, logger="adseismic.data.geometry"):
        check_samples(data, ["a", "b", "c"])
    msgs = " ".join(r.getMessage() for r in caplog.records)
    assert "b: looks clipped" in msgs and "c: all samples are zero" in msgs and "a:" not in msgs
    data[2, 7] = np.inf
    with pytest.raises(TraceError, match=r"c: sample 7 is inf"):
        check_samples(data, ["a", "b", "c"])


# ------------------------------------------------------------------------ preprocess

def _tones(t):
    return np.sin(2 * np.pi * 25 * t) + 0.5 * np.cos(2 * np.pi * 60 * t + 0.3)


@pytest.mark.parametrize("dt, t_shift", [(0.7e-3, 0.0), (0.7e-3, 0.014), (0.71234e-3, 0.0123),
                                         (2.1234e-3, 0.0)])
def test_preprocess_resamples_band_limited_signal(dt, t_shift):
    t = np.arange(3000) * 1e-3
    nt = int(2.9 / dt)
    y = preprocess(np.stack([_tones(t), 2 * _tones(t)]), 1e-3, dt=dt, nt=nt, t_shift=t_shift,
                     detrend=False, taper=0.0)
    assert y.shape == (2, nt)
    to = t_shift + dt * np.arange(nt)
    m = (to > 0.3) & (to < 2.6)
    ref = _tones(to[m])
    assert np.abs(y[0, m] - ref).max() / np.abs(ref).max() < 1e-3
    assert np.abs(y[1, m] - 2 * ref).max() / np.abs(2 * ref).max() < 1e-3


def test_preprocess_band_pass_attenuates_out_of_band():
    dt = 1e-3
    t = np.arange(4000) * dt
    inband, low, high = (np.sin(2 * np.pi * f * t) for f in (35.0, 5.0, 150.0))
    y = preprocess(inband + low + high, dt, dt=dt, nt=4000, band=(20.0, 60.0), taper=0.1)
    m = slice(1000, 3000)
    spec = lambda s, f: abs(np.dot(s[m], np.exp(-2j * np.pi * f * t[m])))  # noqa: E731
    x = inband + low + high
    for f in (5.0, 150.0):
        assert 20 * np.log10(spec(y, f) / spec(x, f)) < -40
    assert 20 * np.log10(spec(y, 35.0) / spec(x, 35.0)) == pytest.approx(0.0, abs=0.5)
    lp = preprocess(x, dt, dt=dt, nt=4000, band=(None, 60.0))
    assert spec(lp, 150.0) / spec(x, 150.0) < 1e-2 and spec(lp, 5.0) / spec(x, 5.0) > 0.9


@pytest.mark.parametrize("dt, t_shift", [(1e-3, 0.05), (0.5e-3, 0.05), (1e-3, -0.02),
                                         (0.5e-3, 0.0)])
def test_preprocess_trim_aligns_impulse(dt, t_shift):
    x = np.zeros(500)
    x[100] = 1.0  # impulse at t = 0.1 s (dt_in 1 ms)
    y = preprocess(x, 1e-3, dt=dt, nt=400, t_shift=t_shift, detrend=False, taper=0.0)
    assert int(np.argmax(y)) == round((0.1 - t_shift) / dt)
    if t_shift < 0:
        assert np.all(y[:round(-t_shift / dt)] == 0)  # zero-padded before the record


def test_preprocess_refuses_coarse_sampling_and_bad_band():
    x = np.random.default_rng(0).standard_normal((2, 300))
    with pytest.raises(TraceError, match=r"dt_in = 0\.01 s \(Nyquist 50 Hz\).*fmax_required = 60 Hz"):
        preprocess(x, 0.01, dt=0.001, nt=3000, fmax_required=60.0)
    preprocess(x, 0.01, dt=0.001, nt=3000, fmax_required=30.0)
    with pytest.raises(TraceError, match=r"band: fmax = 80"):
        preprocess(x, 0.01, dt=0.001, nt=100, band=(1.0, 80.0))
    with pytest.raises(TraceError, match="NaN"):
        preprocess(np.array([0.0, np.nan, 1.0]), 0.01, dt=0.01, nt=3)


def test_module_imports_without_obspy():
    code = ("import sys; sys.modules['obspy'] = None; import adseismic.data.traces; "
            "import adseismic.data.geometry as g, adseismic.data.preprocess as p; "
            "import adseismic.data.read, adseismic.data.write, adseismic.data.atomic, adseismic.data.store; "
            "import numpy as np; p.preprocess(np.ones(10), 0.01, dt=0.01, nt=5); "
            "g.project(46.1, 7.1, 0.0, (46.0, 7.0)); print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr
