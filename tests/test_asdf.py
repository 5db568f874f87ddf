"""Waveforms in ASDF (adseismic.data.asdf): forward's waveforms.h5 opened with pyasdf / ObsPy holds data.h5's
samples, times and coordinates; locate reads an ASDF file as it reads MiniSEED + StationXML; fwi reads
`observed: {kind: asdf}` as it reads data.h5; a missing pyasdf is a one-line message with the pip command."""

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from adseismic.cli import main
from adseismic.data.asdf import read_shot_gathers_asdf, station_streams, write_waveforms_asdf
from adseismic.data.store import read_forward
from adseismic.data.traces import TraceError

pyasdf = pytest.importorskip("pyasdf")

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "configs" / "data" / "location_demo"
REF = {"latitude": 46.0, "longitude": 7.0, "datum": 0.0, "azimuth": 90.0}

FORWARD = {  # tests/test_fwi.py's survey on its true model: 3 shots x 42 receivers, a few seconds on a CPU
    "model": {"kind": "gaussian_anomaly", "shape": [31, 41], "spacing": 20.0, "background": 2000.0,
              "perturbation": 200.0, "center": [300.0, 400.0], "radius": 80.0},
    "geometry": {"sources": {"line": {"start": {"x": 100, "z": 20}, "end": {"x": 700, "z": 20}, "count": 3}},
                 "receivers": {"lines": [{"start": {"x": 0, "z": 10}, "end": {"x": 800, "z": 10}, "count": 21},
                                         {"start": {"x": 0, "z": 590}, "end": {"x": 800, "z": 590}, "count": 21}]}},
    "wavelet": {"kind": "ricker", "peak_frequency": 6.0},
    "simulation": {"order": 4, "pml_width": 8, "precision": "float32", "device": "cpu"},
}  # fmt: skip


@pytest.fixture(scope="module")
def forward_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("asdf_forward")
    cfg = d / "forward.yaml"
    cfg.write_text(yaml.safe_dump(FORWARD))
    assert main(["forward", str(cfg), "-o", str(d / "out"), "-q"]) == 0
    return d / "out"


def test_forward_waveforms_h5_holds_data_h5_samples_times_and_coordinates(forward_run):
    from obspy import Inventory, Stream, UTCDateTime

    fwd = read_forward(forward_run / "data.h5")
    n_shots, n_rec, nt = fwd.receiver_data.shape
    with pyasdf.ASDFDataSet(str(forward_run / "waveforms.h5"), mode="r") as ds:
        assert sorted(ds.waveforms.list()) == [f"XX.R{i:04d}" for i in range(n_rec)]
        for i in (0, 17, n_rec - 1):
            sta = ds.waveforms[f"XX.R{i:04d}"]
            assert sorted(sta.get_waveform_tags()) == [f"shot_{k:04d}" for k in range(n_shots)]
            inv = sta.StationXML
            assert isinstance(inv, Inventory) and inv[0][0].code == f"R{i:04d}"
            for k in range(n_shots):
                st = sta[f"shot_{k:04d}"]
                assert isinstance(st, Stream) and len(st) == 1
                tr = st[0]
                assert tr.data.dtype == fwd.receiver_data.dtype == np.float32  # as simulated, bitwise
                assert np.array_equal(tr.data, fwd.receiver_data[k, i])
                assert tr.stats.starttime == UTCDateTime(0) and tr.stats.npts == nt
                assert tr.stats.delta == pytest.approx(fwd.dt, rel=1e-12)
                assert np.allclose(tr.times(), fwd.time, rtol=0, atol=1e-9)
            assert inv[0][0][0].sample_rate == pytest.approx(1.0 / fwd.dt, rel=1e-12)
        coords = ds.auxiliary_data.Coordinates
        assert np.array_equal(coords.Receivers.data[()], fwd.receiver_coordinates)
        assert np.array_equal(coords.Sources.data[()], fwd.source_coordinates)
        assert coords.Receivers.parameters["axes"] == "z,x" and coords.Receivers.parameters["units"] == "m"
        assert np.array_equal(ds.auxiliary_data.SourceTimeFunctions.wavelet.data[()], fwd.source_wavelet)
    g = read_shot_gathers_asdf(forward_run / "waveforms.h5")
    assert np.array_equal(g.data, fwd.receiver_data) and g.t0 == 0.0
    assert np.array_equal(g.receivers[0], fwd.receiver_coordinates) and np.array_equal(g.sources, fwd.source_coordinates)


def test_write_read_float64_bitwise_and_geographic_stationxml(tmp_path):
    from adseismic.data.geometry import unproject

    rng = np.random.default_rng(1)
    data = rng.standard_normal((2, 4, 50))
    src = np.array([[10.0, 100.0], [10.0, 300.0]])
    rec = np.stack([np.full(4, 5.0), 100.0 * np.arange(4)], axis=1)
    from obspy.core.event import Catalog, Event, Origin

    event = Event(origins=[Origin(time="2024-01-01T00:00:00.2", latitude=46.0, longitude=7.0, depth=500.0)])
    path = write_waveforms_asdf(tmp_path / "w.h5", data, 0.004, src, rec, reference=REF, starttime="2024-01-01T00:00:00",
                                events=Catalog([event]))
    assert not list(tmp_path.glob("*.part"))
    with pyasdf.ASDFDataSet(str(path), mode="r") as ds:
        tr = ds.waveforms["XX.R0002"]["shot_0001"][0]
        assert tr.data.dtype == np.float64 and np.array_equal(tr.data, data[1, 2])
        assert str(tr.stats.starttime) == "2024-01-01T00:00:00.000000Z" and tr.stats.delta == 0.004
        c = ds.waveforms["XX.R0002"].coordinates
        assert len(ds.events) == 1 and ds.events[0].origins[0].depth == 500.0  # QuakeML inside
    lat, lon, elev = unproject(rec[2], REF)
    assert (c["latitude"], c["longitude"], c["elevation_in_m"]) == pytest.approx((lat, lon, elev), abs=1e-9)
    g = read_shot_gathers_asdf(path, reference=REF)  # receivers through StationXML latitude/longitude
    assert np.array_equal(g.data, data) and g.t0 == 0.0
    assert np.abs(g.receivers[0] - rec).max() < 1e-3


def test_locate_reads_asdf_like_miniseed_plus_stationxml(tmp_path):
    import obspy

    from adseismic.data.read import read_station_traces

    path = tmp_path / "event.h5"
    with pyasdf.ASDFDataSet(str(path), mode="w") as ds:
        ds.add_waveforms(obspy.read(str(DEMO / "event.mseed")), tag="raw_recording")
        ds.add_stationxml(obspy.read_inventory(str(DEMO / "event.xml")))
    a = read_station_traces([str(path)], reference=REF, ndim=2)
    b = read_station_traces([str(DEMO / "event.mseed")], inventory=str(DEMO / "event.xml"), reference=REF, ndim=2)
    assert a.names == b.names and a.dt == b.dt and a.starttime == b.starttime
    assert np.array_equal(a.data, b.data) and np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.offline, b.offline)
    # a second tag: the file needs FILE#tag
    with pyasdf.ASDFDataSet(str(path), mode="a") as ds:
        ds.add_waveforms(obspy.read(str(DEMO / "event.mseed")), tag="processed")
    with pytest.raises(TraceError, match="#processed|#raw_recording"):
        read_station_traces([str(path)], reference=REF, ndim=2)
    c = read_station_traces([f"{path}#raw_recording"], reference=REF, ndim=2)
    assert np.array_equal(c.data, b.data) and np.array_equal(c.positions, b.positions)


def test_locate_reads_forward_output_with_local_coordinates(forward_run):
    from adseismic.data.read import read_station_traces

    fwd = read_forward(forward_run / "data.h5")
    st = read_station_traces([f"{forward_run / 'waveforms.h5'}#shot_0001"], ndim=2)  # no reference: local metres
    order = [int(n.split(".")[1][1:]) for n in st.names]
    assert np.array_equal(st.positions, fwd.receiver_coordinates[order])
    assert np.array_equal(st.data, fwd.receiver_data[1, order].astype(np.float64))
    stream, _inv, local = station_streams(f"{forward_run / 'waveforms.h5'}#shot_0000")
    assert len(stream) == fwd.receiver_data.shape[1] and len(local) == len(stream)


def test_fwi_observed_asdf_reads_the_same_data_as_data_h5(forward_run, tmp_path):
    from adseismic.config import load_fwi_config
    from adseismic.inversion.fwi import _observed, prepare_fwi

    fwi = {**{k: v for k, v in FORWARD.items() if k != "model"},
           "model": {"kind": "constant", "shape": [31, 41], "spacing": 20.0, "velocity": 2000.0},
           "inversion": {"bands": [4.0, None], "iterations": 1, "bounds": [1700, 2400]}}  # fmt: skip
    obs = {}
    for kind, name in (("asdf", "waveforms.h5"), ("hdf5", "data.h5")):
        cfg = tmp_path / f"fwi_{kind}.yaml"
        cfg.write_text(yaml.safe_dump({**fwi, "observed": {"kind": kind, "path": str(forward_run / name)}}))
        config = load_fwi_config(cfg)
        prep = prepare_fwi(config)
        obs[kind] = prep.observed
    assert obs["asdf"].shape == obs["hdf5"].shape and np.array_equal(obs["asdf"], obs["hdf5"])
    # the run directory's observed data (observed.h5, used by --resume) also as ASDF, on the simulation's time axis
    (tmp_path / "run").mkdir()
    data = _observed(config, prep, tmp_path / "run", False)
    g = read_shot_gathers_asdf(tmp_path / "run" / "observed_waveforms.h5")
    assert np.array_equal(g.data, data) and g.dt == pytest.approx(prep.plan.dt, rel=1e-12)
    assert np.array_equal(g.receivers[0], config.forward.geometry.receivers)
    assert main(["fwi", str(tmp_path / "fwi_asdf.yaml"), "--dry-run", "-q"]) == 0


def test_missing_pyasdf_is_one_line_with_the_pip_command(tmp_path, monkeypatch, forward_run, caplog, capsys):
    from adseismic.data.asdf import write_forward_asdf

    monkeypatch.setitem(sys.modules, "pyasdf", None)  # import pyasdf -> ImportError, find_spec -> None
    caplog.set_level("INFO", logger="adseismic")  # optional: an INFO line, not a warning on every forward run
    with pytest.raises(TraceError, match=r'pip install "adseismic\[asdf\]"') as e:
        read_shot_gathers_asdf(forward_run / "waveforms.h5")
    assert "\n" not in str(e.value)
    assert write_forward_asdf(tmp_path / "waveforms.h5", receiver_data=np.zeros((1, 1, 2)), dt=0.1,
                              source_coordinates=[[0.0, 0.0]], receiver_coordinates=[[0.0, 1.0]]) is None
    assert "adseismic[asdf]" in caplog.text and not (tmp_path / "waveforms.h5").exists()
    cfg = tmp_path / "fwi.yaml"
    cfg.write_text(yaml.safe_dump({**FORWARD, "inversion": {"iterations": 1, "bounds": [1700, 2400]},
                                   "observed": {"kind": "asdf", "path": str(forward_run / "waveforms.h5")}}))
    assert main(["fwi", str(cfg), "--dry-run", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith('observed.kind: asdf needs pyasdf, which is not installed; pip install "adseismic[asdf]"'), err
    assert "\n" not in err and "Traceback" not in err
