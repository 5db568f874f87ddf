"""Earthquake location by waveform inversion: accuracy without and with noise, honest uncertainties,
3D, QuakeML, bad input."""

import functools

import numpy as np
import pytest
from scipy.stats import chi2

from adseismic.data_synthetic.generators import constant, layered
from adseismic.location.locate import _peak_time, locate, source_wavelet
from adseismic.solve.acoustic import forward

from .conftest import DEVICE

DX, DT, NT = 20.0, 2.5e-3, 640
TRUTH = np.array([703.7, 1612.3])  # z, x (m): > 1 km from the model's centre (600, 1100) and from any edge start
T0, F0, A0 = 0.4, 6.0, 3.0


@functools.lru_cache(maxsize=None)
def scene():
    model = layered((61, 111), DX, [1800.0, 2400.0, 3000.0], [300.0, 800.0])
    rec = np.array([[10.0, x] for x in np.linspace(100.0, 2100.0, 12)])
    s, _ = source_wavelet(NT, DT, T0, F0, A0)
    clean = forward(model.values, DX, DT, s[None, None], TRUTH[None, None], rec[None], precision="float64", pml_width=10,
                    pml_frequency=F0, pml_velocity=model.vmax, device=DEVICE).receiver_amplitudes[0]  # fmt: skip
    return model, rec, clean


def noisy(clean, level, rng):
    sigma = level * np.abs(clean).max(axis=1)
    return clean + sigma[:, None] * rng.standard_normal(clean.shape), sigma


def run(obs, sigma, **kw):
    model, rec, _ = scene()
    return locate(model, rec, obs, DT, noise_std=sigma, pml_width=10, device=DEVICE, **kw)


@functools.lru_cache(maxsize=None)
def noise_free():
    model, rec, clean = scene()
    return run(clean, 1e-3 * np.abs(clean).max(axis=1))


@pytest.mark.slow
def test_noise_free_event_to_a_tenth_of_a_cell_and_sample():
    r = noise_free()
    assert np.linalg.norm(r.start["position"] - TRUTH) < 3 * DX  # back-projection, from no prior at all
    assert np.linalg.norm(r.position - TRUTH) <= 0.1 * DX
    assert abs(r.origin_time - T0) <= 0.1 * DT
    assert r.peak_frequency == pytest.approx(F0, rel=1e-3) and r.amplitude == pytest.approx(A0, rel=1e-3)


@pytest.mark.slow
def test_ten_percent_noise_within_half_a_cell():
    model, rec, clean = scene()
    obs, sigma = noisy(clean, 0.1, np.random.default_rng(7))
    r = run(obs, sigma)
    assert np.linalg.norm(r.position - TRUTH) <= 0.5 * DX


@pytest.mark.slow
def test_uncertainty_ellipse_coverage_over_20_noise_realisations():
    # The Gauss-Newton covariance (noise from the data, 1 sigma) must be honest: the 68% ellipse
    # (2 dof) contains the truth in 50-85% of realisations (binomial: 13.6 +- 2.1 of 20).
    model, rec, clean = scene()
    base = noise_free()
    inside = 0
    k2 = chi2.ppf(0.68, 2)
    for i in range(20):
        obs, sigma = noisy(clean, 0.1, np.random.default_rng(100 + i))
        r = run(obs, sigma, method="gauss-newton", max_iterations=3,
                start={"position": base.position, "origin_time": base.origin_time})  # fmt: skip
        d = r.position - TRUTH
        inside += float(d @ np.linalg.solve(r.covariance[:2, :2], d)) <= k2
    assert 10 <= inside <= 17


@pytest.mark.slow
def test_3d_event_within_one_cell():
    h = 30.0
    model = constant((17, 17, 17), h, 2000.0)
    truth = np.array([262.3, 240.8, 301.1])
    rec = np.array([[10.0, y, x] for y in (30.0, 240.0, 450.0) for x in (30.0, 240.0, 450.0)] + [[470.0, 240.0, 240.0]])
    nt, dt = 240, 3e-3
    s, _ = source_wavelet(nt, dt, 0.25, 5.0, 1.0)
    obs = forward(model.values, h, dt, s[None, None], truth[None, None], rec[None], precision="float64", pml_width=6,
                  pml_frequency=5.0, pml_velocity=2000.0, device=DEVICE).receiver_amplitudes[0]  # fmt: skip
    r = locate(model, rec, obs, dt, noise_std=1e-3 * np.abs(obs).max(axis=1), pml_width=6, max_iterations=20, device=DEVICE)
    assert np.linalg.norm(r.position - truth) <= h


@pytest.mark.slow
def test_quakeml_of_a_location_reads_back(tmp_path):
    from obspy import UTCDateTime, read_events

    from adseismic.data.geometry import Reference, project
    from adseismic.location.quakeml import read_quakeml_origin, write_quakeml

    r = noise_free()
    ref = Reference(46.0, 7.0, azimuth=90.0)
    t0 = UTCDateTime("2026-11-21T04:44:00") + r.origin_time
    cov = r.covariance
    write_quakeml(tmp_path / "event.xml", position=r.position, origin_time=t0, covariance=cov, reference=ref, ndim=2)
    ev = read_events(str(tmp_path / "event.xml"))[0]
    o = read_quakeml_origin(tmp_path / "event.xml")
    assert abs(ev.preferred_origin().time - t0) < 1e-6
    back = project(o["latitude"], o["longitude"], -o["depth"], ref, ndim=2)
    assert np.linalg.norm(np.asarray(back) - r.position) < 1e-3


@pytest.mark.slow
def test_free_source_time_function_and_multi_start():
    # A source-time function a Ricker cannot fit (phase rotated by 60 degrees): the Ricker fit is
    # biased by more than a quarter cell, the free STF (variable projection) recovers the position
    # to a tenth of a cell and the STF's peak time to a tenth of a sample, noise-free. Two starts
    # (the two best back-projection maxima) are both run; the lower misfit wins.
    from scipy.signal import hilbert

    model, rec, _ = scene()
    r0, _ = source_wavelet(NT, DT, T0, F0, A0)
    g = np.cos(np.pi / 3) * r0 + np.sin(np.pi / 3) * np.imag(hilbert(r0))
    obs = forward(model.values, DX, DT, g[None, None], TRUTH[None, None], rec[None], precision="float64", pml_width=10,
                  pml_frequency=F0, pml_velocity=model.vmax, device=DEVICE).receiver_amplitudes[0]  # fmt: skip
    r = run(obs, 1e-3 * np.abs(obs).max(axis=1), stf="free", multi_start=2)
    assert len(r.candidates) == 2 and r.candidates[0]["misfit"] <= r.candidates[1]["misfit"]
    assert np.linalg.norm(r.candidates[0]["position"] - r.candidates[1]["position"]) >= 4 * 2 * DX - 1e-9  # separated starts
    ricker_error = np.linalg.norm(r.candidates[0]["final_position"] - TRUTH)
    assert ricker_error > 0.25 * DX
    assert np.linalg.norm(r.position - TRUTH) <= 0.1 * DX
    assert abs(r.origin_time - _peak_time(g, DT)[0]) <= 0.1 * DT
    assert np.corrcoef(r.stf, g)[0, 1] > 0.999


def test_bad_input_is_refused():
    model, rec, clean = scene()
    with pytest.raises(ValueError, match="noise_std or noise_window"):
        locate(model, rec, clean, DT)
    with pytest.raises(ValueError, match="noise window"):
        locate(model, rec, clean, DT, noise_window=(0.0, 0.01))
    bad = clean.copy()
    bad[3, 100] = np.nan
    with pytest.raises(ValueError, match="NaN|non-finite"):
        locate(model, rec, bad, DT, noise_std=np.ones(len(rec)))
    with pytest.raises(ValueError, match="outside"):
        locate(model, rec + np.array([0.0, 5000.0]), clean, DT, noise_std=np.ones(len(rec)))
