"""Gradient conditioning and regularisation for inversion (arrays (nz, [ny,] nx), spacing dx in m).

- masks: zero the gradient in the water layer (z < water_depth) and near sources (distance <
  source_radius, tapered with a cosine over the outer half), where the gradient is dominated by
  the source's own wavefield and not by the data;
- smoothing: Gaussian of standard deviation `smoothing` metres;
- preconditioning: "depth" multiplies by z / z_max (compensates geometrical spreading of surface
  data); "pseudo_hessian" divides by the normalised illumination sum_t u^2 (Shin et al. 2001) with
  1% water level;
- regularisation (value and gradient, added to the misfit): Tikhonov 1/2 w |grad m|^2 and total
  variation w sum sqrt(|grad m|^2 + eps^2), on m = v / v_ref.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter


def mask(shape, dx, origin, water_depth=0.0, sources=None, source_radius=0.0) -> np.ndarray:
    """Weights in [0, 1] of shape `shape`; origin: world metres of node 0; sources (n, ndim) world m."""
    coords = np.meshgrid(*[origin[a] + dx * np.arange(n) for a, n in enumerate(shape)], indexing="ij")
    w = np.ones(shape)
    if water_depth > 0:
        w[coords[0] < water_depth] = 0.0
    if sources is not None and source_radius > 0:
        for s in np.asarray(sources, float):
            r = np.sqrt(sum((c - p) ** 2 for c, p in zip(coords, s)))
            taper = np.clip((r - 0.5 * source_radius) / (0.5 * source_radius), 0.0, 1.0)
            w *= 0.5 - 0.5 * np.cos(np.pi * taper)
    return w


def smooth(g, dx, sigma_m):
    return gaussian_filter(g, sigma_m / dx, mode="nearest") if sigma_m > 0 else g


def precondition(g, kind, illumination=None, depth=None):
    if kind == "depth":
        return g * (depth / depth.max())
    if kind == "pseudo_hessian":
        h = illumination / illumination.max()
        return g / (h + 0.01)
    return g


def _diff(m):
    """Forward differences along every axis: list of arrays m[i+1] - m[i]."""
    return [np.diff(m, axis=a) for a in range(m.ndim)]


def _diff_t(parts, shape):
    """Transpose of _diff."""
    out = np.zeros(shape)
    for a, r in enumerate(parts):
        lo = [slice(None)] * len(shape)
        hi = [slice(None)] * len(shape)
        lo[a], hi[a] = slice(0, -1), slice(1, None)
        out[tuple(lo)] -= r
        out[tuple(hi)] += r
    return out


def tikhonov(m, weight):
    """(value, exact gradient) of 1/2 weight sum |D m|^2 (D: forward differences)."""
    if weight == 0:
        return 0.0, np.zeros_like(m)
    d = _diff(m)
    return 0.5 * weight * sum(float(np.sum(x * x)) for x in d), weight * _diff_t(d, m.shape)


def total_variation(m, weight, eps=1e-3):
    """(value, exact gradient) of weight sum_i sqrt(sum_axes (D m)_i^2 + eps^2), the differences
    taken on the common interior cells so that the norm couples the axes."""
    if weight == 0:
        return 0.0, np.zeros_like(m)
    core = tuple(slice(0, n - 1) for n in m.shape)
    d = [x[core] for x in _diff(m)]
    norm = np.sqrt(sum(x * x for x in d) + eps**2)
    parts = []
    for a, x in enumerate(d):
        full = np.zeros([n - 1 if b == a else n for b, n in enumerate(m.shape)])
        full[core] = x / norm
        parts.append(full)
    return weight * float(np.sum(norm)), weight * _diff_t(parts, m.shape)
