"""Analytic acoustic solutions in a homogeneous medium (for absolute-amplitude validation).

Convention
----------
The scalar wave equation with a point source at ``x_s``::

    (1/c^2) d^2u/dt^2 - laplacian(u) = s(t) delta(x - x_s),      u = 0 and s = 0 for t < 0,

so ``u = s * G`` (time convolution) with the causal free-space Green's functions
(Morse & Feshbach 1953, ch. 7; Aki & Richards 2002, sec. 4.1; Hudson 1980)::

    3D:  G = delta(t - r/c) / (4 pi r)                 ->  u = s(t - r/c) / (4 pi r)
    2D:  G = H(t - r/c) / (2 pi sqrt(t^2 - r^2/c^2))   ->  u = s' * K,  K = H(t - r/c) arccosh(ct/r) / (2 pi)
    1D:  G = (c/2) H(t - |x|/c)                        ->  u = (c/2) int_0^{t-|x|/c} s

(``K`` is the time integral of the 2D ``G``).  In the frequency domain with numpy's FFT sign
(forward transform ``exp(-i w t)``) the equation becomes ``laplacian(U) + k^2 U = -S delta``,
``k = w/c``, whose outgoing (causal) solution is ``G(w) = (-i/4) H0^(2)(k r)`` for ``w > 0``
(``H0^(2)(kr) ~ exp(-ikr)`` is outgoing for ``exp(+iwt)`` synthesis; Abramowitz & Stegun 9.1.3,
9.2.4).  For ``w < 0`` Hermitian symmetry is used (rfft).  Note that the 2D Green's function is
not integrable in time (``G ~ 1/(2 pi t)``), so ``G(w=0)`` is infinite: a source with non-zero
mean produces a response growing like ``log t``.  :func:`acoustic_2d` therefore works at complex
frequency ``w - i eps`` (damped signals), where everything is finite.

Units: times [s], distances [m], velocity [m/s].  The source ``s`` is sampled at ``t_k = k dt``,
``k = 0 .. nt-1``, is taken as 0 for ``t < 0``, and should taper to ~0 at the end of the record
(band-limited interpolation treats it as one period of a zero-padded signal).  A scalar
``distance`` gives an output of shape ``(nt,)``, an array of distances gives ``(n_distances, nt)``.
"""

from __future__ import annotations

import numpy as np
from scipy.fft import irfft, next_fast_len, rfft, rfftfreq
from scipy.signal import fftconvolve
from scipy.special import hankel2

__all__ = ["acoustic_1d", "acoustic_2d", "acoustic_2d_time_domain", "acoustic_3d", "elastic_2d_force", "elastic_2d_force_spectrum",
           "elastic_3d_force", "lamb_2d"]


def _prepare(source, dt, distance, velocity):
    s = np.asarray(source, dtype=np.float64).ravel()
    r = np.atleast_1d(np.asarray(distance, dtype=np.float64)).ravel()
    if float(dt) <= 0 or float(velocity) <= 0:
        raise ValueError("dt and velocity must be > 0")
    return s, r, np.ndim(distance) == 0


def _fft_len(nt: int, t_max: float, dt: float, pad: float) -> int:
    """FFT length covering ``pad`` times (record + largest travel time)."""
    return next_fast_len(int(np.ceil(pad * (nt + t_max / dt))) + 1)


def acoustic_3d(source, dt: float, distance, velocity: float, pad: float = 2.0) -> np.ndarray:
    """3D point-source response ``u(r, t_k) = s(t_k - r/c) / (4 pi r)``.

    The (generally fractional) delay ``r/c`` is applied as a band-limited Fourier phase shift
    on a zero-padded FFT of length ``>= pad * (nt + max(r)/(c dt))`` (no wrap-around).
    ``source`` (nt,), ``dt`` [s], ``distance`` [m] scalar or (n,), ``velocity`` [m/s].
    Returns (nt,) or (n, nt).
    """
    s, r, scalar = _prepare(source, dt, distance, velocity)
    if np.any(r <= 0):
        raise ValueError("distance must be > 0")
    nt, c = s.size, float(velocity)
    n = _fft_len(nt, r.max() / c, dt, pad)
    f = rfftfreq(n, dt)
    phase = np.exp(-2j * np.pi * f[None, :] * (r[:, None] / c))
    if n % 2 == 0:  # Nyquist bin must stay real
        phase[:, -1] = phase[:, -1].real
    u = irfft(rfft(s, n)[None, :] * phase, n)[:, :nt] / (4.0 * np.pi * r[:, None])
    return u[0] if scalar else u


def acoustic_2d(
    source, dt: float, distance, velocity: float, pad: float = 4.0, wrap_db: float = -200.0
) -> np.ndarray:
    """2D line-source response, computed in the frequency domain.

    ``U(w) = S(w) (-i/4) H0^(2)(w r / c)`` (numpy FFT sign, see module docstring), evaluated at
    complex frequency ``w - i eps`` (damped signals, Kosloff & Kosloff 1983, Geophysics 48(8)):
    the FFT is applied to ``s(t) exp(-eps t)`` and the result multiplied by ``exp(eps t)``.
    This is exact for the causal problem and suppresses the wrap-around of the slowly decaying
    2D tail (``~1/t^3`` for a zero-mean source, ``~log t`` growth otherwise) by
    ``exp(-eps T) = 10^(wrap_db/20)``, ``T`` the FFT period (``>= pad * (nt + max(r)/(c dt))``
    samples).  At ``w = 0`` the transfer function is finite, ``K0(eps r/c) / (2 pi)``, so sources
    with non-zero mean are handled too.  ``source`` (nt,), ``dt`` [s], ``distance`` [m] scalar
    or (n,), ``velocity`` [m/s].  Returns (nt,) or (n, nt).
    """
    s, r, scalar = _prepare(source, dt, distance, velocity)
    if np.any(r <= 0):
        raise ValueError("distance must be > 0")
    nt, c = s.size, float(velocity)
    n = _fft_len(nt, r.max() / c, dt, pad)
    eps = -np.log(10.0) * float(wrap_db) / 20.0 / (n * dt)
    t = np.arange(n) * dt
    w = 2.0 * np.pi * rfftfreq(n, dt) - 1j * eps
    g = -0.25j * hankel2(0, w[None, :] * r[:, None] / c)
    if n % 2 == 0:  # irfft uses only the real part of the Nyquist bin
        g[:, -1] = g[:, -1].real
    u = irfft(rfft(s * np.exp(-eps * t[: s.size]), n)[None, :] * g, n)[:, :nt]
    u *= np.exp(eps * t[:nt])
    return u[0] if scalar else u


def _kernel_antiderivative(t, t0):
    """``Q(t) = int_0^t K``, ``K = H(t - t0) arccosh(t/t0) / (2 pi)``; t0 = r/c > 0."""
    t = np.asarray(t, dtype=np.float64)
    x = np.maximum(t, t0)
    return (x * np.arccosh(x / t0) - np.sqrt((x - t0) * (x + t0))) / (2.0 * np.pi)


def acoustic_2d_time_domain(
    source, dt: float, distance, velocity: float, oversample: int = 4
) -> np.ndarray:
    """2D line-source response from the time-domain form ``u = s(0) K(t) + int s'(tau) K(t - tau)``.

    ``K(t) = H(t - r/c) arccosh(c t / r) / (2 pi)``.  The source is Fourier-interpolated to
    step ``h = dt / oversample`` (``oversample=1``: use the samples as given), taken as
    piecewise linear between fine samples, and ``K`` is integrated analytically over each
    interval via its antiderivative ``Q(t) = [t arccosh(t/t0) - sqrt(t^2 - t0^2)] / (2 pi)``:
    ``u_n = s_0 K(t_n) + sum_k (s_{k+1} - s_k) [Q(t_n - t_k) - Q(t_n - t_{k+1})] / h``.
    The only approximation is the interpolation of ``s`` (error ~ (pi f h)^2 / 3 relative at
    frequency f).  Valid for sources with non-zero mean; with ``oversample > 1`` the source
    must taper to ~0 at both ends (Fourier interpolation), else use ``oversample=1``.
    Cost O(n_distances * nt * oversample * log).  Shapes as in :func:`acoustic_2d`.
    """
    s, r, scalar = _prepare(source, dt, distance, velocity)
    if np.any(r <= 0):
        raise ValueError("distance must be > 0")
    nt, c, m = s.size, float(velocity), int(oversample)
    if m > 1:
        from .wavelets import from_array

        s = from_array(s, dt, nt * m, dt / m)
    h = float(dt) / m
    t = np.arange(s.size + 1) * h
    ds = np.diff(s)
    out = np.empty((r.size, nt))
    for i, ri in enumerate(r):
        t0 = ri / c
        q = _kernel_antiderivative(t, t0)
        wk = np.diff(q) / h  # wk[j-1] = (Q(j h) - Q((j-1) h)) / h, kernel for lag j >= 1
        kern = np.concatenate(([0.0], wk[: s.size - 1]))
        u = fftconvolve(ds, kern)[: s.size]
        u += s[0] * np.arccosh(np.maximum(t[: s.size], t0) / t0) / (2.0 * np.pi)
        out[i] = u[::m][:nt]
    return out[0] if scalar else out


def acoustic_1d(source, dt: float, distance, velocity: float, pad: float = 2.0) -> np.ndarray:
    """1D plane-source response ``u(x, t) = (c/2) int_0^{t - |x|/c} s(tau) dtau``.

    The source is delayed by ``|x|/c`` (band-limited, as in :func:`acoustic_3d`), then
    integrated with the trapezoid rule (O(dt^2)).  ``distance`` may be 0.  Shapes as in
    :func:`acoustic_3d`.
    """
    s, r, scalar = _prepare(source, dt, distance, velocity)
    r = np.abs(r)
    nt, c = s.size, float(velocity)
    n = _fft_len(nt, r.max() / c, dt, pad)
    phase = np.exp(-2j * np.pi * rfftfreq(n, dt)[None, :] * (r[:, None] / c))
    if n % 2 == 0:
        phase[:, -1] = phase[:, -1].real
    sd = irfft(rfft(s, n)[None, :] * phase, n)[:, :nt]
    u = np.zeros_like(sd)
    u[:, 1:] = np.cumsum(0.5 * (sd[:, 1:] + sd[:, :-1]), axis=1) * dt
    u *= 0.5 * c
    return u[0] if scalar else u


# --- Elastic 2D (plane strain) -------------------------------------------------------------------
#
# rho d2u/dt2 = div(sigma) + F(t) delta(x - x_s) with a line force F (N per metre of line). In the
# frequency domain (numpy sign) the displacement is U_i = G_ij F_j with (derived from the Navier
# equation; cf. Aki & Richards 2002 eq. 4.23 for 3D)
#
#     G_ij = delta_ij g_S / mu + d_i d_j (g_S - g_P) / (rho w^2),   g_c = (-i/4) H0^(2)(w r / c),
#
# g_c the scalar Green's function of laplacian(g) + (w/c)^2 g = -delta (as in acoustic_2d). With
# g(r): d_i d_j g = g'' n_i n_j + (g'/r)(delta_ij - n_i n_j), n = (x - x_s)/r. Evaluated at complex
# frequency w - i eps as acoustic_2d (exact for the causal problem). Velocity = i w U.


def _damped_spectrum(s, dt, n, wrap_db):
    eps = -np.log(10.0) * float(wrap_db) / 20.0 / (n * dt)
    t = np.arange(n) * dt
    w = 2.0 * np.pi * rfftfreq(n, dt) - 1j * eps
    return rfft(s * np.exp(-eps * t[: s.size]), n), w, eps, t


def elastic_2d_force_spectrum(w, offset, vp: float, vs: float, rho: float, direction=(1.0, 0.0)):
    """Displacement spectrum (U_z, U_x) (m per unit force spectrum) of a 2D full space for a line force
    along ``direction`` (f_z, f_x) at the origin, at (complex) angular frequencies ``w`` (nw,) (numpy
    FFT sign) and offsets ``offset`` (n, 2) metres (z, x). Returns (2, n, nw)."""
    w = np.asarray(w, dtype=complex)
    off = np.atleast_2d(np.asarray(offset, dtype=np.float64))
    r = np.linalg.norm(off, axis=1)
    if np.any(r <= 0):
        raise ValueError("offset must be non-zero")
    mu = rho * vs * vs
    f = np.asarray(direction, dtype=np.float64)
    out = np.zeros((2, len(r), w.size), dtype=complex)
    for i, (ri, nvec) in enumerate(zip(r, off / r[:, None])):
        h = {}
        for c in (vp, vs):
            k = w / c
            h0, h1 = hankel2(0, k * ri), hankel2(1, k * ri)
            h[c] = (-0.25j * h0, 0.25j * k * h1, 0.25j * k * k * (h0 - h1 / (k * ri)))  # g, g', g''
        d_g = [h[vs][j] - h[vp][j] for j in range(3)]
        for a in range(2):
            for b in range(2):
                cross = (a == b) - nvec[a] * nvec[b]
                gij = (a == b) * h[vs][0] / mu + (d_g[2] * nvec[a] * nvec[b] + d_g[1] / ri * cross) / (rho * w * w)
                out[a, i] += gij * f[b]
    return out


def elastic_2d_force(source, dt: float, offset, vp: float, vs: float, rho: float, direction=(1.0, 0.0),
                     pad: float = 4.0, wrap_db: float = -200.0):  # fmt: skip
    """Particle velocity (v_z, v_x) (m/s) of a homogeneous 2D full space for a line force
    F(t) = source(t) * direction (N/m; direction (f_z, f_x)) at the origin, at receiver offsets
    ``offset`` (n, 2) metres (z, x) or one (2,). ``source`` (nt,) sampled at t_k = k dt; vp, vs (m/s),
    rho (kg/m^3). Returns two arrays (nt,) or (n, nt)."""
    s = np.asarray(source, dtype=np.float64).ravel()
    r = np.linalg.norm(np.atleast_2d(np.asarray(offset, dtype=np.float64)), axis=1)
    nt = s.size
    n = _fft_len(nt, r.max() / vs, dt, pad)
    spec, w, eps, t = _damped_spectrum(s, dt, n, wrap_db)
    V = 1j * w * elastic_2d_force_spectrum(w, offset, vp, vs, rho, direction) * spec
    if n % 2 == 0:
        V[..., -1] = V[..., -1].real
    vz, vx = irfft(V, n)[..., :nt] * np.exp(eps * t[:nt])
    return (vz[0], vx[0]) if np.ndim(offset) == 1 else (vz, vx)


def elastic_3d_force(source, dt: float, offset, vp: float, vs: float, rho: float, direction=(1.0, 0.0, 0.0),
                     pad: float = 4.0) -> np.ndarray:
    """Stokes' solution (Aki & Richards 2002, eq. 4.23): displacement (u_z, u_y, u_x) (m) of a homogeneous 3D whole
    space for a point force F(t) = source(t) * direction (N; direction (f_z, f_y, f_x)) at the origin, at receiver
    offsets ``offset`` (n, 3) metres (z, y, x) or one (3,), sampled at t_k = k dt. With r = |offset|, g = offset / r:

        u_i = (3 g_i g_j - d_ij) / (4 pi rho r^3) int_{r/vp}^{r/vs} tau F_j(t - tau) dtau
              + g_i g_j / (4 pi rho vp^2 r) F_j(t - r/vp) - (g_i g_j - d_ij) / (4 pi rho vs^2 r) F_j(t - r/vs),

    evaluated in the frequency domain on a zero-padded FFT (length >= pad (nt + r/vs / dt): no wrap-around), the
    near-field integral exactly: int_a^b tau e^{-i w tau} dtau = [e^{-i w tau} (1 + i w tau) / w^2]_a^b ((b^2 - a^2) / 2
    at w = 0), the delays as band-limited phase shifts. vp, vs (m/s), rho (kg/m^3). Returns (3, nt) or (3, n, nt)."""
    s = np.asarray(source, dtype=np.float64).ravel()
    off = np.atleast_2d(np.asarray(offset, dtype=np.float64))
    r = np.linalg.norm(off, axis=1)
    if np.any(r <= 0) or off.shape[1] != 3:
        raise ValueError(f"offset must be non-zero (n, 3) metres (z, y, x); got {np.asarray(offset).tolist()}")
    if not (0 < vs < vp and rho > 0 and dt > 0):
        raise ValueError(f"need 0 < vs < vp, rho > 0, dt > 0; got vp {vp}, vs {vs}, rho {rho}, dt {dt}")
    nt = s.size
    n = _fft_len(nt, r.max() / vs, dt, pad)
    w = 2.0 * np.pi * rfftfreq(n, dt)
    spec = rfft(s, n)
    g = off / r[:, None]
    f = np.asarray(direction, dtype=np.float64)
    gf = g @ f  # g_j f_j
    a, b = (r / vp)[:, None], (r / vs)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        prim = lambda t: np.exp(-1j * w * t) * (1.0 + 1j * w * t) / (w * w)  # noqa: E731
        near = np.where(w > 0, prim(b) - prim(a), 0.5 * (b * b - a * a))
    delay_p, delay_s = np.exp(-1j * w * a), np.exp(-1j * w * b)
    out = np.zeros((3, len(r), nt))
    for i in range(3):
        near_c = (3.0 * g[:, i] * gf - f[i]) / (4.0 * np.pi * rho * r**3)
        p_c = g[:, i] * gf / (4.0 * np.pi * rho * vp * vp * r)
        s_c = (g[:, i] * gf - f[i]) / (4.0 * np.pi * rho * vs * vs * r)
        U = spec[None, :] * (near_c[:, None] * near + p_c[:, None] * delay_p - s_c[:, None] * delay_s)
        if n % 2 == 0:
            U[:, -1] = U[:, -1].real
        out[i] = irfft(U, n)[:, :nt]
    return out[:, 0] if np.ndim(offset) == 1 else out


def lamb_2d(source, dt: float, x, vp: float, vs: float, rho: float, depth: float = 0.0, pad: float = 2.0,
            wrap_db: float = -60.0, k_max_factor: float = 12.0, dk_factor: float = 0.1):  # fmt: skip
    """Lamb's problem: particle velocity (v_z, v_x) (m/s) of a homogeneous half-space z >= 0 with a free
    surface, for a vertical line force F(t) = source(t) (N/m, +z down) on the surface at x = 0, at
    horizontal offsets ``x`` (n,) metres and depth ``depth`` (m).

    Wavenumber integration at complex frequency w - i eps (the Rayleigh pole leaves the real k axis by
    ~eps / c_R; eps from wrap_db as in acoustic_2d). Potentials phi = A exp(-nu_P z + i k x),
    psi = B exp(-nu_S z + i k x) (u_x = phi_x - psi_z, u_z = phi_z + psi_x), sigma_zz(z=0) = -F delta(x),
    sigma_xz(z=0) = 0 give, with R(k) = (2k^2 - k_S^2)^2 - 4 k^2 nu_P nu_S,

        A = -F (2k^2 - k_S^2) / (mu R),  B = 2 i k nu_P F / (mu R).

    The k integral runs over [0, k_max_factor * w_max / vs] with step dk_factor * eps / c_R (trapezoid);
    on the surface the 1/k tail beyond it is added in closed form (sine/cosine integrals); below it the
    integrand decays as exp(-k depth) and the range is extended to 40 / depth if needed.
    """
    from scipy.special import sici

    from adseismic.kernels.numerics import rayleigh_speed

    s = np.asarray(source, dtype=np.float64).ravel()
    xs = np.atleast_1d(np.asarray(x, dtype=np.float64))
    nt = s.size
    n = _fft_len(nt, np.abs(xs).max() / (0.8 * vs), dt, pad)
    spec, w, eps, t = _damped_spectrum(s, dt, n, wrap_db)
    mu = rho * vs * vs
    cr = rayleigh_speed(vp, vs)
    amp = np.abs(spec)
    keep = np.nonzero(amp > 1e-9 * amp.max())[0]
    wmax = float(w[keep[-1]].real)
    k_top = max(k_max_factor * wmax / vs, 40.0 / depth if depth > 0 else 0.0)
    dk = dk_factor * eps / cr
    k = np.arange(0.0, k_top + dk, dk)
    wt = np.full(k.size, dk)
    wt[0] = wt[-1] = dk / 2
    cos_kx, sin_kx = np.cos(np.outer(k, xs)), np.sin(np.outer(k, xs))
    Vz = np.zeros((xs.size, w.size), dtype=complex)
    Vx = np.zeros_like(Vz)
    for j in keep:
        wj = w[j]
        ka2, kb2 = (wj / vp) ** 2, (wj / vs) ** 2
        nua, nub = np.sqrt(k * k - ka2), np.sqrt(k * k - kb2)
        two = 2 * k * k - kb2
        R = two * two - 4 * k * k * nua * nub
        A = -two / (mu * R)
        B = 2j * k * nua / (mu * R)
        ea, eb = np.exp(-nua * depth), np.exp(-nub * depth)
        uz = -nua * A * ea + 1j * k * B * eb  # even in k
        ux_odd = (1j * k * A * ea + nub * B * eb) / 1j  # u_x(k) = i * (odd real-ish part)
        # u(x) = (1/2pi) int U(k) e^{ikx} dk = (1/pi) int_0^inf [Uz cos kx] and -(1/pi) int_0^inf [ux_odd sin kx]
        Iz = (wt * uz) @ cos_kx / np.pi
        Ix = -(wt * ux_odd) @ sin_kx / np.pi
        if depth == 0.0:  # 1/k tails beyond k_top (frequency independent coefficients)
            si, ci = sici(k[-1] * np.abs(xs))
            Iz += vp * vp / (2 * mu * (vp * vp - vs * vs)) * (-ci) / np.pi
            Ix += -(vs * vs) / (2 * mu * (vp * vp - vs * vs)) * np.sign(xs) * (np.pi / 2 - si) / np.pi
        Vz[:, j] = 1j * wj * Iz * spec[j]
        Vx[:, j] = 1j * wj * Ix * spec[j]
    out = []
    for V in (Vz, Vx):
        if n % 2 == 0:
            V[:, -1] = V[:, -1].real
        out.append(irfft(V, n)[:, :nt] * np.exp(eps * t[:nt]))
    return (out[0][0], out[1][0]) if np.ndim(x) == 0 else tuple(out)
