"""Data misfits and their adjoint sources (derivative of the misfit with respect to the synthetics).

Every misfit maps synthetic and observed data of shape (n_shots, n_receivers, nt), sampled at dt,
to a scalar, and returns the exact derivative of that (discrete) scalar with respect to every
synthetic sample; the wave-equation part of the chain rule is done by the adjoint sweep (solve/sweep.py).

- "l2":        J = 1/2 sum (d - o)^2 dt
- "correlation": J = sum over traces of 1 - <d, o> / (|d| |o|)   (normalised zero-lag cross-correlation;
               insensitive to amplitude scaling of the synthetics)
- "traveltime": J = 1/2 sum over traces of dtau^2, dtau = the lag (s) maximising the cross-correlation
               of d and o, found on the band-limited (Fourier-interpolated) correlation and
               differentiated by the implicit function theorem (Luo & Schuster 1991)
- "envelope":  J = 1/2 sum (E(d) - E(o))^2 dt, E(x) = sqrt(x^2 + H(x)^2 + eps^2), H the Hilbert
               transform (Bozdag et al. 2011); eps = 1e-6 max|o| keeps E differentiable where it vanishes
"""

from __future__ import annotations

import numpy as np

MISFITS = ("l2", "correlation", "traveltime", "envelope")


def _hilbert(x: np.ndarray) -> np.ndarray:
    """Discrete periodic Hilbert transform along the last axis (DC and Nyquist removed), an
    antisymmetric linear operator, so its adjoint is -H."""
    n = x.shape[-1]
    h = -1j * np.sign(np.fft.fftfreq(n))
    if n % 2 == 0:
        h[n // 2] = 0.0
    return np.real(np.fft.ifft(np.fft.fft(x, axis=-1) * h, axis=-1))


def _l2(d, o, dt):
    r = np.subtract(d, o, dtype=float)
    flat = r.ravel()
    loss = 0.5 * float(flat @ flat) * dt
    r *= dt  # in place: a temporary of an S4000 record costs as much as 20 time steps
    return loss, r


def _correlation(d, o, dt):
    nd = np.linalg.norm(d, axis=-1, keepdims=True)
    no = np.linalg.norm(o, axis=-1, keepdims=True)
    nd = np.where(nd == 0, 1.0, nd)
    no = np.where(no == 0, 1.0, no)
    c = np.sum(d * o, axis=-1, keepdims=True) / (nd * no)
    return float(np.sum(1.0 - c)), -(o / (nd * no) - c * d / nd**2)


def _traveltime(d, o, dt):
    n = d.shape[-1]
    m = 2 * n  # zero padding: no circular wrap of the correlation
    D = np.fft.rfft(d, m, axis=-1)
    O = np.fft.rfft(o, m, axis=-1)
    w = 2.0 * np.pi * np.fft.rfftfreq(m, dt)
    P = D * np.conj(O)  # spectrum of f(tau) = sum_t d(t + tau) o(t)
    cc = np.fft.irfft(P, m, axis=-1)
    lag = np.argmax(cc, axis=-1)
    tau = np.where(lag > m // 2, lag - m, lag) * dt
    weight = np.full(w.shape, 2.0)
    weight[0] = 1.0
    if m % 2 == 0:
        weight[-1] = 1.0

    def deriv(k, tau):  # k-th derivative of the Fourier-interpolated correlation at tau
        e = np.exp(1j * w * tau[..., None])
        return np.real(np.sum(weight * (1j * w) ** k * P * e, axis=-1)) / m

    for _ in range(30):  # Newton on f'(tau) = 0 from the best integer lag
        step = deriv(1, tau) / deriv(2, tau)
        tau = tau - step
        if np.all(np.abs(step) < 1e-12 * dt):
            break
    f2 = deriv(2, tau)
    # d tau = -d f'(tau) / f''(tau); f'(tau) = sum_t d(t) g(t) with g = o'(t - tau) (band-limited)
    g = np.fft.irfft(-1j * w * O * np.exp(-1j * w * tau[..., None]), m, axis=-1)[..., :n]
    dtau_dd = -g / f2[..., None]
    return 0.5 * float(np.sum(tau**2)), tau[..., None] * dtau_dd


def _envelope(d, o, dt):
    eps2 = (1e-6 * np.abs(o).max()) ** 2 if np.abs(o).max() > 0 else 1e-30
    hd = _hilbert(d)
    ed = np.sqrt(d * d + hd * hd + eps2)
    eo = np.sqrt(o * o + _hilbert(o) ** 2 + eps2)
    r = (ed - eo) * dt
    return 0.5 * float(np.sum((ed - eo) ** 2)) * dt, r * d / ed - _hilbert(r * hd / ed)


_FUNCS = {"l2": _l2, "correlation": _correlation, "traveltime": _traveltime, "envelope": _envelope}


def misfit(name: str, synthetic: np.ndarray, observed: np.ndarray, dt: float):
    """(J, dJ/dsynthetic) for the named misfit; arrays (n_shots, n_receivers, nt), dt in s."""
    if name not in _FUNCS:
        raise ValueError(f"misfit {name!r} is not one of {MISFITS}")
    d = np.asarray(synthetic, dtype=float)
    o = np.asarray(observed, dtype=float)
    if d.shape != o.shape:
        raise ValueError(f"observed data has shape {o.shape} but the synthetics have {d.shape} (n_shots, n_receivers, nt)")
    return _FUNCS[name](d, o, float(dt))


def weighted_l2(d, o, w, dt):
    """The "l2" misfit of weighted data, J = 1/2 sum (w (d - o))^2 dt, and dJ/dd = w^2 (d - o) dt (formed as
    (e dt) w, e = w (d - o), in float64, as accel.reductions.weighted_l2_residual_kernel forms it on the device);
    d, o, w: arrays of one shape (w: 1 keeps a sample, 0 mutes it)."""
    e = np.subtract(d, o, dtype=float)
    e *= w
    flat = e.ravel()
    loss = 0.5 * float(flat @ flat) * dt
    e *= dt
    e *= w
    return loss, e
