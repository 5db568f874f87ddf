"""Tests for adseismic.wavelets (numbers, not just shapes)."""

import numpy as np
import pytest

from adseismic.wavelets import (
    WAVELETS,
    duration,
    from_array,
    gaussian_derivative,
    make_wavelet,
    ricker,
    spectral_fmax,
)

DT = 1e-3


def test_ricker_peak_and_zero_mean():
    f, nt = 10.0, 1000
    w = ricker(f, nt, DT)
    assert w.shape == (nt,)
    k = int(np.argmax(w))
    assert k * DT == pytest.approx(1.5 / f)  # default delay
    assert w[k] == pytest.approx(1.0, abs=1e-14)
    assert abs(w[0]) < 1e-7  # starts near zero
    assert abs(w.sum() * DT) < 1e-6 * 1.0 * duration(w, DT)
    # explicit delay moves the peak
    w2 = ricker(f, nt, DT, delay=0.3)
    assert int(np.argmax(w2)) == 300


@pytest.mark.parametrize("f", [5.0, 10.0, 25.0])
def test_ricker_spectral_fmax(f):
    w = ricker(f, 2000, DT)
    assert spectral_fmax(w, DT, -20.0) / f == pytest.approx(2.2113, rel=1e-2)
    assert spectral_fmax(w, DT, -40.0) / f == pytest.approx(2.7638, rel=1e-2)
    # tighter: the interpolated crossing is accurate well beyond the 1% requirement
    assert spectral_fmax(w, DT, -20.0) / f == pytest.approx(2.211271, rel=1e-4)


def test_gaussian_derivative():
    f, nt = 10.0, 1000
    w = gaussian_derivative(f, nt, DT)
    assert np.abs(w).max() == pytest.approx(1.0, rel=1e-4)
    assert abs(w[0]) < 1e-7
    assert abs(w.sum()) * DT < 1e-9
    # amplitude spectrum peaks at f
    n = 2**16
    amp = np.abs(np.fft.rfft(w, n))
    assert np.fft.rfftfreq(n, DT)[amp.argmax()] == pytest.approx(f, rel=2e-3)
    # zero crossing at the delay (1/f), positive lobe first
    assert w[int(round(1.0 / f / DT))] == pytest.approx(0.0, abs=1e-12)
    assert np.argmax(w) < np.argmin(w)


def test_from_array_round_trip():
    f, delay = 10.0, 0.2
    coarse = ricker(f, 300, 2e-3, delay=delay)  # band-limited at dt = 2 ms
    fine = from_array(coarse, 2e-3, 2000, 3e-4)  # non-integer ratio 20/3
    assert np.abs(fine - ricker(f, 2000, 3e-4, delay=delay)).max() < 1e-10
    back = from_array(fine, 3e-4, 300, 2e-3)
    assert np.abs(back - coarse).max() < 1e-10
    # truncation / padding to nt
    assert from_array(coarse, 2e-3, 50, 2e-3).shape == (50,)
    padded = from_array(coarse, 2e-3, 500, 2e-3)
    assert np.allclose(padded[:300], coarse, atol=1e-12) and np.abs(padded[300:]).max() < 1e-12


def test_duration():
    w = np.zeros(100)
    w[10], w[40] = 1.0, 0.01
    assert duration(w, 0.5) == pytest.approx(20.0)
    assert duration(w, 0.5, threshold=0.05) == pytest.approx(5.0)
    r = ricker(10.0, 1000, DT)
    # Ricker tail: |w| < 1e-3 for tau > ~0.1 s beyond the 0.15 s delay
    assert 0.24 < duration(r, DT) < 0.26


def test_make_wavelet():
    assert set(WAVELETS) == {"ricker", "gaussian_derivative", "array"}
    assert np.array_equal(make_wavelet("ricker", 500, DT, peak_frequency=8.0), ricker(8.0, 500, DT))
    g = make_wavelet("gaussian_derivative", 500, DT, peak_frequency=8.0, delay=0.2)
    assert np.array_equal(g, gaussian_derivative(8.0, 500, DT, 0.2))
    a = make_wavelet("array", 10, DT, samples=[0.0, 1.0, 0.0])
    assert a.shape == (10,)
    with pytest.raises(ValueError, match="ricker"):
        make_wavelet("boxcar", 10, DT)
