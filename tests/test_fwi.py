"""Full-waveform inversion workflow: a tiny inversion end to end, kill -9 and --resume reproducing an
uninterrupted run, bad input refused before anything is written, band-pass and wavelet estimation."""

import json
import os
import re
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest
import yaml

from adseismic.cli import main
from adseismic.config import load_fwi_config
from adseismic.inversion.fwi import BAND_EDGE, _decimated, band_filter, band_pass, band_plan, estimate_wavelet, prepare_fwi
from adseismic.inversion.optimize import Journal
from adseismic.solve.acoustic import forward
from adseismic.wavelets import ricker

TINY = {
    "model": {"kind": "constant", "shape": [31, 41], "spacing": 20.0, "velocity": 2000.0},
    "true_model": {"kind": "gaussian_anomaly", "shape": [31, 41], "spacing": 20.0, "background": 2000.0,
                   "perturbation": 200.0, "center": [300.0, 400.0], "radius": 80.0},
    "geometry": {"sources": {"line": {"start": {"x": 100, "z": 20}, "end": {"x": 700, "z": 20}, "count": 3}},
                 "receivers": {"lines": [{"start": {"x": 0, "z": 10}, "end": {"x": 800, "z": 10}, "count": 21},
                                         {"start": {"x": 0, "z": 590}, "end": {"x": 800, "z": 590}, "count": 21}]}},
    "wavelet": {"kind": "ricker", "peak_frequency": 6.0},
    "simulation": {"order": 4, "pml_width": 8, "precision": "float64"},
    "inversion": {"bands": [4.0, None], "iterations": 3, "bounds": [1700, 2400]},
}  # fmt: skip


def write(tmp_path, cfg=TINY, name="fwi.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_tiny_inversion_end_to_end(tmp_path, capsys):
    cfg = write(tmp_path)
    out = tmp_path / "run"
    assert main(["fwi", str(cfg), "-o", str(out), "-q"]) == 0
    for name in ("model.h5", "history.h5", "summary.json", "model.png", "gradient.png", "residual.png", "misfit.png", "fwi.log", "config.yaml", "observed.h5"):
        assert (out / name).exists(), name
    wrote = [line for line in capsys.readouterr().out.splitlines() if line.startswith("wrote ")]
    assert len(wrote) == 1  # the final line names every file of the run directory, journals included
    assert all(p.name in wrote[0] for p in out.iterdir() if p.is_file()), wrote[0]
    log = (out / "fwi.log").read_text()
    assert log.splitlines()[0].endswith(f"fwi {cfg} -> {out}")
    assert "inversion.preconditioning: none (the default with sources or receivers at depth: the deepest source or receiver 590 m" in log
    import pyasdf  # observed and final synthetic data in ASDF for other tools (issue 27)

    for name in ("observed_waveforms.h5", "synthetic_waveforms.h5"):
        with pyasdf.ASDFDataSet(str(out / name), mode="r") as ds:
            assert len(ds.waveforms) == 42 and sorted(ds.waveforms.list()[0:1]) == ["XX.R0000"]
            assert ds.waveforms["XX.R0000"].get_waveform_tags() == ["shot_0000", "shot_0001", "shot_0002"]  # the banner first, then the checks made before OUTDIR existed
    assert not list(out.glob("*.part"))
    summary = json.loads((out / "summary.json").read_text())
    assert [b["iterations"] for b in summary["bands"]] == [3, 3]
    assert all(b["misfit"] < 1.0 for b in summary["bands"])  # normalised by each band's start
    assert summary["errors"]["final_anomaly"] < summary["errors"]["start_anomaly"]
    with h5py.File(out / "history.h5") as f, h5py.File(out / "model.h5") as m:
        assert sorted(f) == ["band0", "band1"] and len(f["band1"]) == 3
        assert f["band0/iter0001/model"].shape == m["model"].shape  # the planner's grid


def test_per_band_grid_is_coarser_where_a_band_allows_and_still_accurate(tmp_path, capsys):
    """inversion.grid per_band (the default here): the low band runs on a coarser grid and a longer step that meet simulation.accuracy
    (its data match the plan grid's within the travel-time error that accuracy allows), the full band on the plan's
    grid; the history and the result stay on the plan's grid; a resumed run replays the coarse band's journal and
    reproduces the run bit for bit (float64 on a CPU). The anomaly is wider than TINY's (160 m): the 4 Hz residual at
    the start model, 0.114 of the band's data, must exceed the 45 m grid's modelling error, 0.071 (band_grid_holds;
    TINY's own 80 m anomaly leaves a residual of 0.042, and its band runs on the plan's grid)."""
    wide = dict(TINY, true_model=dict(TINY["true_model"], radius=160.0))
    config = load_fwi_config(write(tmp_path, wide))  # the default for acoustic pixels
    assert config.inversion.grid == "per_band"
    prep = prepare_fwi(config)
    p, sc = prep.plan, prep.scene
    low, full = config.inversion.bands
    pb, m = band_plan(config, p, prep.bounds, low)
    assert pb.dx > 2 * p.dx and m >= 2 and pb.dt == m * p.dt and pb.origin == p.origin
    assert pb.expected_error <= config.forward.simulation.accuracy and not pb.warnings
    assert band_plan(config, p, prep.bounds, full) == (p, 1)
    fixed = load_fwi_config(write(tmp_path, dict(TINY, inversion=dict(TINY["inversion"], grid="fixed")), "fixed.yaml"))
    assert band_plan(fixed, p, prep.bounds, low) == (p, 1)

    # the low band's data on its grid against the plan grid's: a relative difference below the phase error that the
    # planned group-velocity error allows over the longest path, 2 pi f_edge err t (f_edge: the band's grid edge)
    kw = {"order": p.order, "pml_width": p.pml_width, "precision": "float64"}
    w = band_filter(sc.wavelet, p.dt, low)

    def traces(plan, wavelet):
        v = config.true_model.resample(plan.dx, plan.origin, plan.shape).values
        amp = np.broadcast_to(wavelet, sc.source_amplitudes.shape[:-1] + wavelet.shape).copy()
        return forward(v, plan.dx, plan.dt, amp, sc.source_locations, sc.receiver_locations, **kw).receiver_amplitudes

    fine, coarse = _decimated(traces(p, w), m, pb.nt), traces(pb, _decimated(w, m, pb.nt))
    geo = config.forward.geometry
    t_max = np.linalg.norm(geo.receivers[None] - geo.sources[:, None], axis=-1).max() / config.true_model.vmin
    allowed = 2 * np.pi * BAND_EDGE * low[1] * pb.expected_error * t_max
    assert np.linalg.norm(coarse - fine) / np.linalg.norm(fine) < allowed

    out = tmp_path / "run"
    assert main(["fwi", str(tmp_path / "fwi.yaml"), "-o", str(out), "-q"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["errors"]["final_anomaly"] < 0.5 * summary["errors"]["start_anomaly"]
    assert f"band 0 (<= 4 Hz) grid: {' x '.join(map(str, pb.shape))} cells, dx = {pb.dx:g} m" in (out / "fwi.log").read_text()
    with h5py.File(out / "history.h5") as f, h5py.File(out / "model.h5") as mf:
        assert {f[f"band{b}/iter0003/model"].shape for b in (0, 1)} == {mf["model"].shape} == {p.shape}
        assert (f["band0/iter0001"].attrs["dx"], f["band1/iter0001"].attrs["dx"]) == (pb.dx, p.dx)
        whole = mf["model"][...]
    for name in ("model.h5", "summary.json", "journal_band1.h5"):  # killed after band 0: its journal replays
        (out / name).unlink()
    assert main(["fwi", str(tmp_path / "fwi.yaml"), "-o", str(out), "--resume", "-q"]) == 0
    with h5py.File(out / "model.h5") as mf:
        np.testing.assert_array_equal(mf["model"][...], whole)


def test_a_band_grid_that_misses_the_data_runs_on_the_plan_grid(tmp_path):
    """band_grid_holds: a band's own grid must reproduce the plan grid's data to within the residual it is to explain.
    With a wider anomaly, the 4 Hz grid does (test above). Under a free surface, with sources 20 m and receivers 10 m deep,
    the near-source traces carry most of the data and depend on the grid, so band 0 runs on the plan's grid, and
    fwi.log says why. (Its forward runs go shots_per_batch at a time.)"""
    cfg = dict(TINY, simulation=dict(TINY["simulation"], free_surface=True), inversion=dict(TINY["inversion"], iterations=1, shots_per_batch=2))
    config = load_fwi_config(write(tmp_path, cfg))
    prep = prepare_fwi(config)
    p = prep.plan
    pb, m = band_plan(config, p, prep.bounds, config.inversion.bands[0])
    assert pb.dx > p.dx  # planned coarser, refused by the check
    out = tmp_path / "run"
    assert main(["fwi", str(tmp_path / "fwi.yaml"), "-o", str(out), "-q"]) == 0
    log = (out / "fwi.log").read_text()
    check = re.search(r"band 0 \(<= 4 Hz\) grid check: on ([\d.]+) m cells the data differ from the plan grid's by ([\d.e-]+) of the "
                      r"observed data, against a residual of ([\d.e-]+) .*: the band runs on the plan's grid", log)
    assert check and float(check[1]) == pb.dx and float(check[2]) > float(check[3]) > 0, log
    assert "WARNING" in log and "this band runs on the plan's grid" in log and "band 0 (<= 4 Hz) grid: " not in log
    with h5py.File(out / "history.h5") as f:
        assert f["band0/iter0001"].attrs["dx"] == p.dx


@pytest.mark.slow
def test_kill_9_then_resume_equals_uninterrupted_run(tmp_path):
    cfg = write(tmp_path)
    whole, broken = tmp_path / "whole", tmp_path / "broken"
    assert main(["fwi", str(cfg), "-o", str(whole), "-q"]) == 0
    proc = subprocess.Popen([sys.executable, "-m", "adseismic.cli", "fwi", str(cfg), "-o", str(broken), "-q"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    journal = broken / "journal_band1.h5"
    deadline = time.time() + 300
    while time.time() < deadline:  # kill during band 1, after its second evaluation
        if journal.exists() and len(Journal.load(journal)) >= 2:
            break
        assert proc.poll() is None, "the run finished before it could be killed; make the test problem bigger"
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (broken / "model.h5").exists()
    for h5 in broken.glob("*.h5"):  # nothing corrupted by the kill
        with h5py.File(h5) as f:
            list(f)
    assert main(["fwi", str(cfg), "-o", str(broken), "--resume", "-q"]) == 0
    with h5py.File(whole / "model.h5") as a, h5py.File(broken / "model.h5") as b:
        np.testing.assert_array_equal(a["model"][...], b["model"][...])  # float64 on a CPU: bitwise
    with h5py.File(whole / "history.h5") as a, h5py.File(broken / "history.h5") as b:
        assert sorted(a["band1"]) == sorted(b["band1"])


@pytest.mark.slow
def test_resume_guards(tmp_path, capsys):
    cfg = write(tmp_path)
    out = tmp_path / "run"
    assert main(["fwi", str(cfg), "-o", str(out), "--resume", "-q"]) == 2
    assert "no run to resume" in capsys.readouterr().err
    assert main(["fwi", str(cfg), "-o", str(out), "-q"]) == 0
    assert main(["fwi", str(cfg), "-o", str(out), "-q"]) == 2
    assert "already holds a run" in capsys.readouterr().err
    changed = dict(TINY, inversion=dict(TINY["inversion"], iterations=5))
    assert main(["fwi", str(write(tmp_path, changed, "changed.yaml")), "-o", str(out), "--resume", "-q"]) == 2
    assert "config differs" in capsys.readouterr().err


def test_observed_file_with_wrong_shot_count_writes_nothing(tmp_path, capsys):
    # observed data from our own forward run with 2 shots, while the inversion's geometry has 3
    fwd = {k: TINY[k] for k in ("model", "wavelet", "simulation")}
    fwd["geometry"] = {"sources": {"line": {"start": {"x": 100, "z": 20}, "end": {"x": 700, "z": 20}, "count": 2}},
                       "receivers": TINY["geometry"]["receivers"]}  # fmt: skip
    assert main(["forward", str(write(tmp_path, fwd, "fwd.yaml")), "-o", str(tmp_path / "obs"), "-q"]) == 0
    cfg = {k: v for k, v in TINY.items() if k != "true_model"}
    cfg["observed"] = {"kind": "hdf5", "path": str(tmp_path / "obs" / "data.h5")}
    out = tmp_path / "run"
    assert main(["fwi", str(write(tmp_path, cfg)), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert "observed.path" in err and "2 shots" in err and "3" in err
    assert not out.exists()


def test_band_pass_has_the_butterworth_response():
    dt = 1e-3
    t = np.arange(4000) * dt
    y = band_pass(np.sin(2 * np.pi * 3 * t) + np.sin(2 * np.pi * 20 * t), dt, (None, 6.0))[500:-500]
    tt = t[500:-500]  # away from the edge transients
    # least-squares amplitudes of both tones, fitted jointly (they are not orthogonal over 3 s)
    basis = np.stack([fn(2 * np.pi * f * tt) for f in (3.0, 20.0) for fn in (np.sin, np.cos)], axis=1)
    c = np.linalg.lstsq(basis, y, rcond=None)[0]
    # 4th-order Butterworth, forward and backward: |H(f)|^2 = 1 / (1 + (f / 6 Hz)^8)
    assert np.linalg.norm(c[:2]) == pytest.approx(1 / (1 + 0.5**8), rel=1e-3)
    assert np.linalg.norm(c[2:]) == pytest.approx(1 / (1 + (20 / 6) ** 8), rel=0.05)


def test_band_filter_is_causal_with_the_butterworth_response():
    dt = 1e-3
    impulse = band_filter(np.eye(1, 4000, 2000)[0], dt, (None, 6.0))
    assert not impulse[:2000].any() and impulse[2000:].any()  # nothing before the impulse
    h = np.fft.rfft(band_filter(np.eye(1, 4000)[0], dt, (None, 6.0)))
    f = np.fft.rfftfreq(4000, dt)
    warped = np.tan(np.pi * f * dt) / np.tan(np.pi * 6.0 * dt)  # the bilinear transform's frequency axis
    for fi in (3.0, 6.0, 8.0, 20.0):  # order-4 Butterworth: |H(f)| = 1 / sqrt(1 + (f / 6 Hz)^8), f warped
        i = np.argmin(abs(f - fi))
        assert abs(h[i]) == pytest.approx((1 + warped[i] ** 8) ** -0.5, rel=1e-6)


def test_filtering_the_wavelet_filters_the_synthetics_exactly(tmp_path):
    # fwi filters the source wavelet and the observed data alike and compares the two: at the true model, on the
    # same grid, the filtered synthetics must equal the filtered observed data. A zero-phase filter misses them by
    # 10% of the band (the filtered wavelet's part before t = 0 is cut, the data's backward pass starts at the
    # record's end); the causal band_filter by rounding only.
    cfg = load_fwi_config(write(tmp_path))
    prep = prepare_fwi(cfg)
    sc, p = prep.scene, prep.plan
    v = cfg.true_model.resample(p.dx, p.origin, p.shape).values
    band = cfg.inversion.bands[0]
    kw = {"order": p.order, "pml_width": p.pml_width, "precision": "float64", "pml_frequency": band[1] / 2}  # (as fwi)

    def traces(wavelet):
        amp = np.broadcast_to(wavelet, sc.source_amplitudes.shape).copy()
        return forward(v, p.dx, p.dt, amp, sc.source_locations, sc.receiver_locations, **kw).receiver_amplitudes

    observed = traces(sc.wavelet)
    for name, fn, low, high in (("band_filter", band_filter, 0.0, 1e-9),
                                ("zero-phase", lambda x, dt, b: band_pass(x, dt, b), 0.05, 1.0)):  # fmt: skip
        o = fn(observed, p.dt, band)
        assert low <= np.linalg.norm(traces(fn(sc.wavelet, p.dt, band)) - o) / np.linalg.norm(o) < high, name


def test_band_pass_of_a_large_array_on_threads_is_scipys_bit_for_bit():
    # a band's observed data (n_shots, n_receivers, nt) above PARALLEL_FILTER_SAMPLES is filtered a shot a thread
    from scipy.signal import butter, sosfilt, sosfiltfilt

    from adseismic.inversion import fwi

    x = np.random.default_rng(3).standard_normal((3, 7, fwi.PARALLEL_FILTER_SAMPLES // 20))
    assert x.size > fwi.PARALLEL_FILTER_SAMPLES
    for band in ((None, 6.0), (2.0, 6.0), (2.0, None)):
        sos = butter(4, [f for f in band if f is not None] if None not in band else next(f for f in band if f is not None),
                     btype={(True, False): "lowpass", (False, False): "bandpass", (False, True): "highpass"}[(band[0] is None, band[1] is None)],
                     fs=1e3, output="sos")  # fmt: skip
        np.testing.assert_array_equal(band_pass(x, 1e-3, band), sosfiltfilt(sos, x, axis=-1))
        np.testing.assert_array_equal(band_pass(x, 1e-3, band, causal=True), sosfilt(sos, x, axis=-1))  # (band_filter's)


def test_wavelet_estimation_recovers_scale_and_shift():
    dt, nt = 1e-3, 600
    w0 = ricker(10.0, nt, dt)
    w_true = 2.5 * ricker(10.0, nt, dt, delay=0.17)
    green = np.zeros((4, nt))
    for i, k in enumerate((40, 90, 130, 200)):
        green[i, k] = 1.0 / (i + 1)
    conv = lambda w: np.array([np.convolve(g, w)[:nt] for g in green])  # noqa: E731
    est = estimate_wavelet(w0, conv(w0), conv(w_true), damping=1e-6)
    assert np.linalg.norm(est - w_true) < 1e-3 * np.linalg.norm(w_true)


@pytest.mark.parametrize(
    "inversion, message",
    [
        ({"bounds": [2100, 2400]}, r"inversion\.bounds.*do not contain the start model"),
        ({"bands": [200.0]}, r"inversion\.bands\[0\].*Nyquist"),
        ({"iterations": [3, 3, 3]}, r"inversion\.iterations: 3 values for 2 bands"),
    ],
)
def test_bad_inversion_settings_write_nothing(tmp_path, capsys, inversion, message):
    cfg = dict(TINY, inversion=dict(TINY["inversion"], **inversion))
    out = tmp_path / "run"
    assert main(["fwi", str(write(tmp_path, cfg)), "-o", str(out), "-q"]) == 2
    assert re.search(message, capsys.readouterr().err)
    assert not out.exists()


def test_observed_miniseed_with_stationxml_matches_our_hdf5(tmp_path):
    # the same synthetic shots through both readers: our data.h5, and one MiniSEED + StationXML file
    # per shot with the receivers' latitude/longitude (projected back about the reference point)
    from adseismic.config import parse_fwi_config
    from adseismic.data.geometry import Reference
    from adseismic.data.store import read_forward
    from adseismic.data.traces import StationTraces
    from adseismic.data.write import write_station_traces
    from adseismic.inversion.fwi import prepare_fwi

    fwd = {k: TINY[k] for k in ("model", "wavelet", "simulation", "geometry")}
    assert main(["forward", str(write(tmp_path, fwd, "fwd.yaml")), "-o", str(tmp_path / "obs"), "-q"]) == 0
    d = read_forward(tmp_path / "obs" / "data.h5")
    ref = Reference(46.0, 7.0)
    rec = d.receiver_coordinates
    paths = []
    for i in range(d.receiver_data.shape[0]):
        st = StationTraces(data=d.receiver_data[i].astype(float), dt=d.dt, starttime=1.7e9, positions=rec,
                                  names=[f"XX.R{k:03d}..HHZ" for k in range(len(rec))], reference=ref)  # fmt: skip
        mseed, _ = write_station_traces(tmp_path / f"shot{i}", st, reference=ref, stem=f"shot{i}")
        paths.append(str(mseed))
    base = {k: v for k, v in TINY.items() if k != "true_model"}
    via_h5 = prepare_fwi(parse_fwi_config(dict(base, observed={"kind": "hdf5", "path": str(tmp_path / "obs" / "data.h5")})))
    inventory = str(next((tmp_path / "shot0").glob("*.xml")))
    via_mseed = prepare_fwi(parse_fwi_config(dict(base, observed={"kind": "mseed", "paths": paths, "inventory": inventory,
                                                                     "reference": [46.0, 7.0]})))  # fmt: skip
    np.testing.assert_allclose(via_mseed.observed, via_h5.observed, rtol=0, atol=1e-6 * np.abs(via_h5.observed).max())


def test_preconditioning_defaults_to_depth_under_a_surface_acquisition():
    from adseismic.config import parse_fwi_config

    top_line = {"line": {"start": {"x": 0, "z": 10}, "end": {"x": 800, "z": 10}, "count": 21}}
    surface = dict(TINY, geometry=dict(TINY["geometry"], receivers=top_line))
    cfg = parse_fwi_config(surface)
    assert cfg.inversion.preconditioning == "depth"
    assert cfg.chosen["preconditioning"].startswith("the default under a surface acquisition: the deepest source or receiver 20 m")
    assert parse_fwi_config(TINY).inversion.preconditioning == "none"  # receivers at 590 m of 600 m: transmission
    given = parse_fwi_config(dict(surface, inversion=dict(TINY["inversion"], preconditioning="none")))
    assert given.inversion.preconditioning == "none" and given.chosen == {}
    net = parse_fwi_config(dict(surface, model={"kind": "nn", "shape": [31, 41], "spacing": 20.0, "v0": 2000.0, "scale": 300.0,
                                                           "hidden": 12, "seed": 0}))
    assert net.inversion.preconditioning == "none"  # not measured for a network model


def test_offset_mute_and_time_window_weights():
    from adseismic.config import parse_fwi_config
    from adseismic.inversion.fwi import data_weights, prepare_fwi

    cfg = parse_fwi_config(dict(TINY, inversion=dict(TINY["inversion"], offsets=[0, 300], time_window=[0.1, 0.5])))
    scene = prepare_fwi(cfg).scene
    w = data_weights(scene, cfg.inversion, cfg.forward.geometry)
    g = cfg.forward.geometry
    off = np.linalg.norm(g.receivers[None] - g.sources[:, None], axis=-1)
    t = np.arange(scene.plan.nt) * scene.plan.dt
    assert np.all(w[off > 300] == 0) and np.all(w[..., t < 0.1] == 0) and np.all(w[..., t > 0.5] == 0)
    inside = (off <= 300)[..., None] & ((t > 0.14) & (t < 0.46))[None, None]
    assert np.all(w[inside] == 1.0)
