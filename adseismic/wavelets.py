"""Source time functions (wavelets) and simple spectral diagnostics.

All wavelets are sampled at ``t_k = k * dt`` (seconds), ``k = 0 .. nt-1``, and returned as
float64 numpy arrays of shape ``(nt,)``. Frequencies are in Hz.

Formulas
--------
* Ricker (Mexican hat): ``w(t) = (1 - 2 pi^2 f^2 tau^2) exp(-pi^2 f^2 tau^2)``, ``tau = t - delay``;
  amplitude spectrum ``|W(f')| ~ (f'/f)^2 exp(-(f'/f)^2)`` peaks at ``f`` (Ricker 1953; see also
  Wang 2015, Geophysics 80(2), A31).  Its -20 dB / -40 dB upper band edges are 2.2113 f and
  2.7638 f (roots of ``x^2 exp(1 - x^2) = 10^(dB/20)``).
* Gaussian derivative: ``w(t) ~ -tau exp(-tau^2 / (2 sigma^2))`` with ``sigma = 1 / (2 pi f)``
  so that its amplitude spectrum ``~ f' exp(-2 pi^2 sigma^2 f'^2)`` peaks at ``f``.

A YAML config selects a wavelet via :func:`make_wavelet` (``kind`` in :data:`WAVELETS`).
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
from scipy.fft import irfft, next_fast_len, rfft

__all__ = [
    "ricker",
    "gaussian_derivative",
    "from_array",
    "spectral_fmax",
    "duration",
    "WAVELETS",
    "make_wavelet",
]


def _time(nt: int, dt: float) -> np.ndarray:
    return np.arange(int(nt), dtype=np.float64) * float(dt)


def ricker(peak_frequency: float, nt: int, dt: float, delay: float | None = None) -> np.ndarray:
    """Ricker wavelet, shape ``(nt,)``, peak value 1 at ``t = delay``.

    ``peak_frequency`` [Hz] is the peak of the amplitude spectrum; ``dt`` [s]; ``delay`` [s]
    defaults to ``1.5 / peak_frequency`` (first sample then ~1e-8 of the peak).
    """
    f = float(peak_frequency)
    if f <= 0:
        raise ValueError("peak_frequency must be > 0")
    delay = 1.5 / f if delay is None else float(delay)
    a = (np.pi * f * (_time(nt, dt) - delay)) ** 2
    return (1.0 - 2.0 * a) * np.exp(-a)


def gaussian_derivative(
    peak_frequency: float, nt: int, dt: float, delay: float | None = None
) -> np.ndarray:
    """First derivative of a Gaussian, shape ``(nt,)``, normalised to ``max|w| = 1``.

    ``w(t) = -(tau / sigma) exp(1/2 - tau^2 / (2 sigma^2))``, ``tau = t - delay``,
    ``sigma = 1 / (2 pi peak_frequency)``: the amplitude spectrum peaks at ``peak_frequency`` [Hz]
    and the extrema are +-1 at ``tau = -+sigma`` (positive lobe first, then negative lobe).
    Default ``delay = 1.0 / peak_frequency`` [s] = 6.3 sigma, where ``|w| ~ 3e-8`` (this pulse
    is shorter than a Ricker of the same peak frequency, so it needs less delay than 1.5/f).
    """
    f = float(peak_frequency)
    if f <= 0:
        raise ValueError("peak_frequency must be > 0")
    delay = 1.0 / f if delay is None else float(delay)
    sigma = 1.0 / (2.0 * np.pi * f)
    x = (_time(nt, dt) - delay) / sigma
    return -x * np.exp(0.5 - 0.5 * x * x)


def from_array(samples, dt_in: float, nt: int, dt: float, max_denominator: int = 10000) -> np.ndarray:
    """Resample a user wavelet from step ``dt_in`` [s] to ``dt`` [s], pad/truncate to ``(nt,)``.

    Band-limited (Fourier) interpolation: the input, zero padded to at least twice its length,
    is treated as one period of a band-limited signal; when downsampling, content above the new
    Nyquist ``1/(2 dt)`` is removed (ideal low-pass).  The input should taper to ~0 at both ends,
    otherwise the implied jump causes Gibbs ringing.  ``dt_in / dt`` must be a rational number
    ``p/q`` with ``q <= max_denominator`` (to relative 1e-9), true for decimal time steps.
    Sample 0 of the output corresponds to sample 0 of the input (t = 0).
    """
    x = np.asarray(samples, dtype=np.float64).ravel()
    nt = int(nt)
    if x.size == 0:
        return np.zeros(nt)
    ratio = float(dt_in) / float(dt)
    frac = Fraction(ratio).limit_denominator(int(max_denominator))
    if abs(float(frac) - ratio) > 1e-9 * ratio:
        raise ValueError(f"dt_in/dt = {ratio!r} is not a simple rational number")
    p, q = frac.numerator, frac.denominator  # n_out = n_in * p / q
    n_in = q * int(np.ceil(max(2 * x.size, nt / ratio + 1) / q))
    n_out = n_in * p // q
    spec = rfft(x, n_in)
    y = irfft(spec, n_out) * (n_out / n_in)
    if n_in % 2 == 0 and n_out > n_in:  # split the input Nyquist bin (it is counted once by rfft)
        y -= spec[-1].real / n_in * np.cos(np.pi * np.arange(n_out) * n_in / n_out)
    out = np.zeros(nt)
    m = min(nt, n_out)
    out[:m] = y[:m]
    return out


def spectral_fmax(wavelet, dt: float, db: float = -20.0) -> float:
    """Highest frequency [Hz] where the amplitude spectrum is >= ``db`` (dB, < 0) below its peak.

    The wavelet is zero padded to >= 2**16 samples (and >= 16x its length) and the crossing is
    linearly interpolated (in dB) between frequency bins.
    """
    w = np.asarray(wavelet, dtype=np.float64).ravel()
    n = next_fast_len(max(16 * w.size, 2**16))
    amp = np.abs(rfft(w, n))
    if amp.max() == 0:
        return 0.0
    level = amp.max() * 10.0 ** (float(db) / 20.0)
    i = int(np.nonzero(amp >= level)[0][-1])
    df = 1.0 / (n * float(dt))
    if i == amp.size - 1:
        return i * df
    a0, a1 = 20 * np.log10(amp[i]), 20 * np.log10(max(amp[i + 1], 1e-300))
    lv = 20 * np.log10(level)
    return (i + (a0 - lv) / (a0 - a1)) * df


def duration(wavelet, dt: float, threshold: float = 1e-3) -> float:
    """Time [s] from t=0 to the last sample with ``|w| > threshold * max|w|`` (0 if all zero)."""
    w = np.abs(np.asarray(wavelet, dtype=np.float64).ravel())
    if w.size == 0 or w.max() == 0:
        return 0.0
    return float(np.nonzero(w > threshold * w.max())[0][-1]) * float(dt)


def _array_kind(nt, dt, samples, dt_in=None):
    return from_array(samples, dt if dt_in is None else dt_in, nt, dt)


#: kind -> constructor ``f(nt=..., dt=..., **params)``.
WAVELETS = {
    "ricker": lambda nt, dt, peak_frequency, delay=None: ricker(peak_frequency, nt, dt, delay),
    "gaussian_derivative": lambda nt, dt, peak_frequency, delay=None: gaussian_derivative(
        peak_frequency, nt, dt, delay
    ),
    "array": _array_kind,
}


def make_wavelet(kind: str, nt: int, dt: float, **params) -> np.ndarray:
    """Build a wavelet of shape ``(nt,)`` by name, e.g. from a YAML config.

    * ``"ricker"`` / ``"gaussian_derivative"``: ``peak_frequency`` [Hz], optional ``delay`` [s].
    * ``"array"``: ``samples`` (sequence), optional ``dt_in`` [s] (default ``dt``).
    """
    key = str(kind).lower()
    if key not in WAVELETS:
        raise ValueError(f"unknown wavelet kind {kind!r}; valid kinds: {sorted(WAVELETS)}")
    return WAVELETS[key](nt=nt, dt=dt, **params)
