"""Standard linear solids for a constant Q over a band (host-side numerics, NumPy, done once per run).

L mechanisms with relaxation times tau_l = 1 / (2 pi f_l), f_l log-spaced over [f_min, f_max], give the modulus

    M(w) = M_R m(w),   m(w) = 1 + sum_l y_l i w tau_l / (1 + i w tau_l)        (numpy's e^{+i w t} convention)

(a generalised standard linear solid: y_l = tau_epsilon_l / tau_sigma_l - 1, Emmerich & Korn 1987; Blanch et al.
1995), whose quality factor is Q(w) = Re m / Im m. A flat Q over the band needs Im m = Re m / Q there:

    sum_l y_l (I_l(w) - R_l(w) / Q) = 1 / Q,   I_l = w tau_l / (1 + w^2 tau_l^2),   R_l = w^2 tau_l^2 / (1 + w^2 tau_l^2),

linear in y for one Q. Q varies in space and is differentiated, so y is taken as a power series in 1 / Q,
y_l = sum_k c_kl Q^-(k+1) (k < SERIES_TERMS), each order fitted once by least squares over the band: c_0 . I = 1
(the low-loss fit), c_{k+1} . I = c_k . R. The kernels evaluate the series per cell (Horner). Measured (L = 3, band
3-25 Hz, 500 frequencies): the largest |Q(f) / Q - 1| over the band is 2.6% for Q = 1000, 3.1% for Q = 20, 3.7%
for Q = 10, 4.9% for Q = 5 (tests/test_viscoacoustic.py::test_fitted_q_is_flat_over_the_band).

vp is the phase velocity at f_ref: the relaxed modulus is M_R = rho vp^2 Re(m(w_ref)^(-1/2))^2, the unrelaxed
(w -> infinity, the fastest speed: the one the CFL limit needs) M_U = M_R (1 + sum y_l).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

SERIES_TERMS = 4  # orders of 1/Q in y_l (3 leaves 5.8% at Q = 5 on 3-25 Hz, 4 and more 4.9%)
FIT_FREQUENCIES = 200  # log-spaced frequencies of the least-squares fits


@dataclass(frozen=True)
class Mechanisms:
    """L standard linear solids fitted to a flat Q over [f_min, f_max] Hz: tau (L,) relaxation times (s) and
    series (SERIES_TERMS, L), the coefficients of y_l = sum_k series[k, l] Q^-(k+1)."""

    f_min: float
    f_max: float
    tau: np.ndarray
    series: np.ndarray

    @property
    def count(self) -> int:
        return self.tau.size

    def y(self, q) -> np.ndarray:
        """Mechanism weights y_l (..., L) for quality factors q (any shape; inf: lossless)."""
        iq = 1.0 / np.asarray(q, dtype=float)[..., None]
        return sum(self.series[k] * iq ** (k + 1) for k in range(self.series.shape[0]))

    def modulus_ratio(self, frequency, q) -> np.ndarray:
        """m(w) = M(w) / M_R at frequencies (Hz, shape F) for a scalar q: complex (F,)."""
        wt = 2.0 * math.pi * np.asarray(frequency, dtype=float)[:, None] * self.tau
        return 1.0 + (self.y(q) * (1j * wt) / (1.0 + 1j * wt)).sum(axis=-1)

    def quality(self, frequency, q) -> np.ndarray:
        """The mechanisms' exact Q(f) = Re M / Im M at frequencies (Hz) for the target q (scalar)."""
        m = self.modulus_ratio(frequency, q)
        return m.real / m.imag

    def velocity(self, frequency, q, vp: float, f_ref: float) -> np.ndarray:
        """Complex velocity c(w) = sqrt(M(w) / rho) (m/s) at frequencies (Hz) of a medium of phase velocity vp (m/s)
        at f_ref (Hz) and quality factor q (scalar)."""
        m_ref = self.modulus_ratio(np.array([f_ref]), q)[0]
        relaxed = vp * np.real(m_ref**-0.5)  # sqrt(M_R / rho)
        return relaxed * np.sqrt(self.modulus_ratio(frequency, q))


def fit_mechanisms(f_min: float, f_max: float, count: int = 3) -> Mechanisms:
    """The `count` mechanisms of a flat Q over [f_min, f_max] Hz (module docstring). Raises ValueError on a bad band."""
    if not (0.0 < f_min < f_max and math.isfinite(f_max)):
        raise ValueError(f"q_band [{f_min}, {f_max}] Hz must satisfy 0 < f_min < f_max; e.g. [f_peak / 3, 2.5 f_peak] of the wavelet")
    if int(count) < 1:
        raise ValueError(f"mechanisms = {count}: need at least 1 standard linear solid (3 is the default)")
    tau = 1.0 / (2.0 * math.pi * np.geomspace(f_min, f_max, int(count)))
    wt = 2.0 * math.pi * np.geomspace(f_min, f_max, FIT_FREQUENCIES)[:, None] * tau
    imag, real = wt / (1.0 + wt**2), wt**2 / (1.0 + wt**2)
    series = [np.linalg.lstsq(imag, np.ones(FIT_FREQUENCIES), rcond=None)[0]]
    for _ in range(1, SERIES_TERMS):
        series.append(np.linalg.lstsq(imag, real @ series[-1], rcond=None)[0])
    return Mechanisms(float(f_min), float(f_max), tau, np.array(series))
