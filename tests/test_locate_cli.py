"""`adseismic locate` end to end: MiniSEED + StationXML with latitude/longitude -> the same location as
the in-memory data, QuakeML that ObsPy reads back; bad input refused before anything is written."""

import functools
import json

import numpy as np
import pytest
import yaml

from adseismic.cli import main
from adseismic.location.locate import locate

from .conftest import DEVICE
from .test_locate import DT, NT, T0, TRUTH, scene

REF = {"latitude": 46.0, "longitude": 7.0, "datum": 0.0, "azimuth": 90.0}
MODEL = {"kind": "layered", "shape": [61, 111], "spacing": 20.0, "velocities": [1800.0, 2400.0, 3000.0], "interfaces": [300.0, 800.0]}
NOISE_WINDOW = [0.0, 0.15]  # s: before the first arrival (source onset ~0.2 s, nearest station ~0.1 s later)


@functools.lru_cache(maxsize=None)
def observed():
    """The test scene's traces with 1% Gaussian noise (so the pre-event window has noise to measure)."""
    model, rec, clean = scene()
    rng = np.random.default_rng(3)
    return clean + 0.01 * np.abs(clean).max(axis=1, keepdims=True) * rng.standard_normal(clean.shape)


def write_event(directory, data=None, dt=DT, with_inventory=True, rec=None):
    from obspy import UTCDateTime

    from adseismic.data.geometry import Reference
    from adseismic.data.traces import StationTraces
    from adseismic.data.write import write_station_traces

    _, rec0, _ = scene()
    rec = rec0 if rec is None else rec
    st = StationTraces(data=observed() if data is None else data, dt=dt, starttime=UTCDateTime("2026-11-21T04:44:00"),
                       positions=rec, names=[f"XX.S{i:02d}..HHZ" for i in range(len(rec))], reference=Reference(**REF))  # fmt: skip
    mseed, xml = write_station_traces(directory, st)
    if not with_inventory:
        xml.unlink()
    return mseed, xml


def config(directory, mseed, xml=None, **sections):
    cfg = {"model": MODEL,
           "traces": {"paths": [mseed.name], "reference": REF, **({"inventory": xml.name} if xml else {})},
           "preprocess": {"detrend": False, "taper": 0.0, "noise_window": NOISE_WINDOW, "window": [0.0, (NT - 1) * DT]},
           "simulation": {"dx": 20.0, "dt": DT, "order": 4, "pml_width": 10, "device": DEVICE},
           "truth": {"position": {"z": float(TRUTH[0]), "x": float(TRUTH[1])}, "origin_time": T0}}  # fmt: skip
    cfg.update(sections)
    path = directory / "locate.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.mark.slow  # two locations (the command's and the in-memory one): 50 s on 2 cores
def test_miniseed_stationxml_round_trip_gives_the_in_memory_location(tmp_path, capsys):
    from obspy import UTCDateTime, read_events

    from adseismic.data.geometry import Reference, project
    from adseismic.location.quakeml import read_quakeml_origin

    mseed, xml = write_event(tmp_path)
    out = tmp_path / "run"
    assert main(["locate", str(config(tmp_path, mseed, xml)), "-o", str(out), "--misfit-map", "3", "-q"]) == 0
    for name in ("event.xml", "location.h5", "traces.png", "location.png", "summary.json", "config.yaml", "locate.log"):
        assert (out / name).is_file(), name
    assert not list(out.glob("*.part"))
    s = json.loads((out / "summary.json").read_text())

    model, rec, _ = scene()
    # the command measures the noise's autocorrelation time in the window (~1 for this white noise)
    # and inflates the covariance by it: give the in-memory run the same factor
    mem = locate(model, rec, observed(), DT, noise_window=tuple(NOISE_WINDOW), pml_width=10, device=DEVICE,
                 noise_correlation=s["noise_correlation_samples"])
    pos = np.array([s["position_m"]["z"], s["position_m"]["x"]])
    # identical samples (float64 MiniSEED, same dt, no filter) and station positions through
    # latitude/longitude to < 1e-6 m: the same optimisation path, so the same answer to rounding
    assert np.abs(pos - mem.position).max() < 1e-3
    assert abs(s["origin_time_after_record_start_s"] - mem.origin_time) < 1e-6
    assert np.allclose([s["position_error_m_1sigma"]["z"], s["origin_time_error_s_1sigma"]],
                       [np.sqrt(mem.covariance[0, 0]), np.sqrt(mem.covariance[2, 2])], rtol=1e-4)
    assert s["truth_position_error_m"] <= 0.1 * 20.0  # 1% noise: well inside a tenth of a cell
    ev = read_events(str(out / "event.xml"))[0]
    o = ev.preferred_origin()
    assert abs(o.time - (UTCDateTime("2026-11-21T04:44:00") + mem.origin_time)) < 1e-5
    q = read_quakeml_origin(out / "event.xml")
    back = project(q["latitude"], q["longitude"], -q["depth"], Reference(**REF), ndim=2)
    assert np.linalg.norm(np.asarray(back) - pos) < 1e-2
    import pyasdf  # the event's traces, its stations and the located event in one ASDF file (issue 27)

    with pyasdf.ASDFDataSet(str(out / "waveforms.h5"), mode="r") as ds:
        assert len(ds.events) == 1 and len(ds.waveforms) == len(rec)
        sta = ds.waveforms[ds.waveforms.list()[0]]
        assert sorted(sta.get_waveform_tags()) == ["observed_processed", "synthetic"] and "StationXML" in sta
    printed = capsys.readouterr().out
    assert "event at z =" in printed
    wrote = [line for line in printed.splitlines() if line.startswith("wrote ")]
    assert len(wrote) == 1 and all(p.name in wrote[0] for p in out.iterdir() if p.is_file()), wrote
    log = (out / "locate.log").read_text().splitlines()
    assert " locate " in log[0] and str(out) in log[0]  # the banner first, then the preprocessing it did before OUTDIR
    plan = [line for line in log if "plan: grid" in line]
    assert len(plan) == 1  # the plan once
    text = "\n".join(log)
    # one event per evaluation (not the search box's corners as shots); nt from the trimmed window, not "pinned"
    assert "x 1 shot(s)" in text and "why: the simulated window" in text.split("plan: nt", 1)[1].split("\n", 2)[1]


def run_bad(tmp_path, capsys, cfg_path):
    out = tmp_path / "bad_run"
    code = main(["locate", str(cfg_path), "-o", str(out), "-q"])
    return code, capsys.readouterr().err, out


def test_traces_without_coordinates_are_refused(tmp_path, capsys):
    mseed, _ = write_event(tmp_path, with_inventory=False)
    code, err, out = run_bad(tmp_path, capsys, config(tmp_path, mseed))
    assert code == 2 and "no coordinates" in err and "inventory" in err
    assert not out.exists()


def test_station_outside_the_model_is_refused(tmp_path, capsys):
    _, rec, _ = scene()
    far = rec.copy()
    far[2, 1] = 5000.0
    mseed, xml = write_event(tmp_path, rec=far)
    code, err, out = run_bad(tmp_path, capsys, config(tmp_path, mseed, xml))
    assert code == 2 and "XX.S02..HHZ" in err and "outside the model" in err
    assert not out.exists()


def test_sampling_too_coarse_for_the_simulation_is_refused(tmp_path, capsys):
    coarse = observed()[:, ::10]  # dt 25 ms: Nyquist 20 Hz, below the Ricker's -20 dB edge (~15 Hz) x margin
    mseed, xml = write_event(tmp_path, data=coarse, dt=10 * DT)
    cfg = config(tmp_path, mseed, xml, simulation={"order": 4, "pml_width": 10, "device": DEVICE},
                 preprocess={"noise_window": NOISE_WINDOW, "window": "auto"}, source={"peak_frequency": 12.0})  # fmt: skip
    code, err, out = run_bad(tmp_path, capsys, cfg)
    assert code == 2 and "too coarse" in err
    assert not out.exists()


@pytest.mark.parametrize("what", ["nan"])
def test_nan_samples_are_refused(tmp_path, capsys, what):
    data = observed().copy()
    data[4, 300] = np.nan
    mseed, xml = write_event(tmp_path, data=data)
    code, err, out = run_bad(tmp_path, capsys, config(tmp_path, mseed, xml))
    assert code == 2 and "XX.S04..HHZ" in err
    assert not out.exists()


def test_config_errors_name_the_key(tmp_path, capsys):
    mseed, xml = write_event(tmp_path)
    cfg = config(tmp_path, mseed, xml, search={"method": "newton"})
    code, err, out = run_bad(tmp_path, capsys, cfg)
    assert code == 2 and "search.method" in err and not out.exists()
    cfg = config(tmp_path, mseed, xml, preprocess={"detrend": False})
    code, err, out = run_bad(tmp_path, capsys, cfg)
    assert code == 2 and "preprocess.noise_window: missing" in err and not out.exists()
