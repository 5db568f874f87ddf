"""Finite-difference stencils, stability limits and the scheme's exact dispersion relation.

The acoustic scheme is 2nd order in time (leapfrog) and order 2, 4 or 8 in space on a regular
grid of spacing dx. Its plane-wave dispersion relation is

    sin^2(omega dt / 2) = (C^2 / 4) * sum_d F(k_d dx),   F(xi) = -(a_0 + 2 sum_k a_k cos(k xi)),

with a_k the second-derivative weights and C = v dt / dx the Courant number. Stability needs the
right side <= 1 for every wavenumber, which gives C <= 2 / sqrt(ndim * sum |a|) (Lines, Slawinski &
Bording 1999). Numbers here are checked against ../shared/docs/reference.md sections 1-2.
"""

from __future__ import annotations

import functools
import math

import numpy as np

ORDERS = (2, 4, 8)

# Central second-derivative weights (a_0, a_1, ..., a_R) for u'' ~ (a_0 u_0 + sum a_k (u_k + u_-k)) / dx^2.
SECOND_DERIVATIVE = {
    2: (-2.0, 1.0),
    4: (-5.0 / 2.0, 4.0 / 3.0, -1.0 / 12.0),
    8: (-205.0 / 72.0, 8.0 / 5.0, -1.0 / 5.0, 8.0 / 315.0, -1.0 / 560.0),
}
# Central first-derivative weights (c_1, ..., c_R) for u' ~ sum c_k (u_k - u_-k) / dx (used by the CPML).
FIRST_DERIVATIVE = {
    2: (1.0 / 2.0,),
    4: (2.0 / 3.0, -1.0 / 12.0),
    8: (4.0 / 5.0, -1.0 / 5.0, 4.0 / 105.0, -1.0 / 280.0),
}


def check_order(order: int) -> int:
    if order not in ORDERS:
        raise ValueError(f"spatial order {order!r} is not supported; use one of {ORDERS}")
    return order


def cfl_limit(order: int, ndim: int) -> float:
    """Largest stable Courant number v_max dt / dx of the acoustic scheme (exact, not a rule of thumb)."""
    a = SECOND_DERIVATIVE[check_order(order)]
    total = abs(a[0]) + 2.0 * sum(abs(x) for x in a[1:])
    return 2.0 / math.sqrt(ndim * total)


def _symbol(order: int, xi: np.ndarray) -> np.ndarray:
    """F(xi) = -(a_0 + 2 sum a_k cos(k xi)) and its derivative dF/dxi."""
    a = SECOND_DERIVATIVE[order]
    f = -a[0] - 2.0 * sum(a[k] * np.cos(k * xi) for k in range(1, len(a)))
    df = 2.0 * sum(k * a[k] * np.sin(k * xi) for k in range(1, len(a)))
    return f, df


def _directions(ndim: int) -> np.ndarray:
    """Unit propagation directions covering the symmetry wedge (axis to diagonal)."""
    if ndim == 2:
        th = np.linspace(0.0, np.pi / 4, 19)
        return np.stack([np.cos(th), np.sin(th)], axis=1)
    th, ph = np.meshgrid(np.linspace(0.0, np.pi / 4, 10), np.linspace(0.0, np.arccos(1 / np.sqrt(3)), 10))
    return np.stack([np.sin(ph) * np.cos(th), np.sin(ph) * np.sin(th), np.cos(ph)], axis=-1).reshape(-1, 3)


def dispersion_error(order: int, ndim: int, ppw, courant: float) -> dict:
    """Worst-direction relative phase- and group-velocity errors of the scheme.

    ppw: grid points per wavelength (scalar or array); courant: v dt / dx of the wave considered.
    Returns {"phase": array, "group": array} of max |v_numerical / v - 1| over directions; inf where
    the scheme is unstable or the wave is beyond the grid's Nyquist wavenumber.
    """
    ppw = np.atleast_1d(np.asarray(ppw, dtype=float))
    kdx = 2.0 * np.pi / ppw  # |k| dx
    dirs = _directions(ndim)
    xi = kdx[:, None, None] * dirs[None, :, :]  # (n_ppw, n_dir, ndim)
    f, df = _symbol(order, xi)
    s = np.maximum(f.sum(axis=-1), 0.0)
    x = 0.5 * courant * np.sqrt(s)
    with np.errstate(invalid="ignore", divide="ignore"):
        omega_dt = 2.0 * np.arcsin(np.minimum(x, 1.0))
        # omega dt / (|k| dx C) = v_numerical / v
        phase = omega_dt / (kdx[:, None] * courant)
        # d(omega dt)/d(xi_d) = C^2 F'(xi_d) / (2 sin(omega dt))
        grad = courant**2 * df / (2.0 * np.sin(omega_dt)[..., None])
        group = np.linalg.norm(grad, axis=-1) / courant
    bad = (x >= 1.0) | (kdx[:, None] >= np.pi)
    phase_err = np.where(bad, np.inf, np.abs(phase - 1.0)).max(axis=1)
    group_err = np.where(bad, np.inf, np.abs(group - 1.0)).max(axis=1)
    return {"phase": phase_err, "group": group_err}


@functools.lru_cache(maxsize=1024)
def ppw_for_error(order: int, ndim: int, courant: float, target: float, kind: str = "group") -> float:
    """Fewest grid points per wavelength for which the dispersion error is <= target (bisection; cached, as
    every plan of a scene, e.g. each band's of an FWI, asks for the same Courant numbers)."""
    lo, hi = 2.0, 400.0
    if dispersion_error(order, ndim, hi, courant)[kind][0] > target:
        raise ValueError(f"a {kind}-velocity error of {target:g} is unreachable at order {order} with Courant number {courant:.3f}")
    for _ in range(60):
        mid = math.sqrt(lo * hi)
        if dispersion_error(order, ndim, mid, courant)[kind][0] <= target:
            hi = mid
        else:
            lo = mid
    return hi


# Staggered first-derivative weights (c_1, ..., c_M) for u'(x) ~ sum c_m (u(x + (m - 1/2) dx) - u(x - (m - 1/2) dx)) / dx
# (Levander 1988; Fornberg 1988), used by the velocity-stress elastic scheme. Order 6 serves the
# reduced stencils of order 8 next to a free surface.
STAGGERED_DERIVATIVE = {
    2: (1.0,),
    4: (9.0 / 8.0, -1.0 / 24.0),
    6: (75.0 / 64.0, -25.0 / 384.0, 3.0 / 640.0),
    8: (1225.0 / 1024.0, -245.0 / 3072.0, 49.0 / 5120.0, -5.0 / 7168.0),
}


def staggered_cfl_limit(order: int, ndim: int) -> float:
    """Largest stable Courant number vp_max dt / dx of the staggered velocity-stress scheme,
    1 / (sqrt(ndim) sum |c_m|): 0.707 / 0.606 / 0.548 in 2D for orders 2 / 4 / 8 (reference.md sec. 1)."""
    c = STAGGERED_DERIVATIVE[check_order(order)]
    return 1.0 / (math.sqrt(ndim) * sum(abs(x) for x in c))


def rayleigh_speed(vp: float, vs: float) -> float:
    """Rayleigh-wave speed (m/s) of a homogeneous half-space: the root in (0, vs) of
    (2 - x)^2 - 4 sqrt(1 - x vs^2/vp^2) sqrt(1 - x) = 0 with x = (c / vs)^2 (0 for a fluid)."""
    if vs <= 0.0:
        return 0.0
    q = (vs / vp) ** 2
    f = lambda x: (2.0 - x) ** 2 - 4.0 * math.sqrt(1.0 - x * q) * math.sqrt(1.0 - x)  # noqa: E731
    lo, hi = 1e-6, 1.0 - 1e-15  # f(lo) < 0 < f(hi) for every Poisson's ratio in (-1, 0.5)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if f(mid) > 0.0:
            hi = mid
        else:
            lo = mid
    return vs * math.sqrt(0.5 * (lo + hi))


def staggered_dispersion_error(order: int, ndim: int, ppw, courant: float) -> dict:
    """Worst-direction relative phase- and group-velocity errors of the staggered velocity-stress scheme
    for a P or S wave of Courant number c dt / dx. In a homogeneous medium the discrete P and S modes
    decouple exactly: sin(omega dt / 2) = C sqrt(sum_d S(k_d dx)^2), S(xi) = sum_m c_m sin((m - 1/2) xi).
    Same conventions and return value as :func:`dispersion_error`."""
    c = STAGGERED_DERIVATIVE[check_order(order)]
    ppw = np.atleast_1d(np.asarray(ppw, dtype=float))
    kdx = 2.0 * np.pi / ppw
    xi = kdx[:, None, None] * _directions(ndim)[None, :, :]
    s = sum(cm * np.sin((m + 0.5) * xi) for m, cm in enumerate(c))
    ds = sum(cm * (m + 0.5) * np.cos((m + 0.5) * xi) for m, cm in enumerate(c))
    norm = np.sqrt((s * s).sum(axis=-1))
    x = courant * norm
    with np.errstate(invalid="ignore", divide="ignore"):
        omega_dt = 2.0 * np.arcsin(np.minimum(x, 1.0))
        phase = omega_dt / (kdx[:, None] * courant)
        # d(omega dt)/d(xi_d) = 2 C S_d S'_d / (|S| cos(omega dt / 2))
        grad = 2.0 * courant * s * ds / (norm * np.cos(omega_dt / 2.0))[..., None]
        group = np.linalg.norm(grad, axis=-1) / courant
    bad = (x >= 1.0) | (kdx[:, None] >= np.pi)
    return {"phase": np.where(bad, np.inf, np.abs(phase - 1.0)).max(axis=1), "group": np.where(bad, np.inf, np.abs(group - 1.0)).max(axis=1)}
