"""Gridded P-wave velocity models: the `Model` object and its resampling.

Conventions used throughout:

* Axis order is always (z, x) in 2D and (z, y, x) in 3D; z is depth, positive down.
* Velocities are in m/s, coordinates and spacings in metres.
* Node ``i`` along an axis sits at ``origin + i * spacing``; the model covers the closed box
  between its first and last node (`Model.extent`).

This module imports neither Warp nor ObsPy; loading models from YAML specs and files is
adseismic.data.models'.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

AXES = {2: "zx", 3: "zyx"}  # model axis order by dimension


class ModelError(ValueError):
    """A velocity model or its ``model:`` spec is invalid; the message names the key and the fix."""


def per_axis(value, ndim: int, key: str) -> tuple[float, ...]:
    """Expand a scalar or length-``ndim`` sequence to a tuple of ``ndim`` finite floats."""
    def is_bool(v):
        return isinstance(v, (bool, np.bool_)) or (isinstance(v, (list, tuple)) and any(map(is_bool, v)))

    try:
        arr = None if isinstance(value, (str, bytes)) or is_bool(value) else np.atleast_1d(np.asarray(value, float))
    except (TypeError, ValueError, OverflowError):
        arr = None
    if arr is None or arr.ndim != 1 or arr.size not in (1, ndim) or not np.all(np.isfinite(arr)):
        text = repr(value) if len(repr(value)) <= 80 else repr(value)[:77] + "..."
        hint = " (true/false are not numbers)" if is_bool(value) else ""
        raise ModelError(f"{key}: {text} is not a number or a list of {ndim} numbers{hint} "
                         f"in axis order {AXES[ndim]}; give one value per axis (metres)")
    return tuple(float(v) for v in np.broadcast_to(arr, (ndim,)))


def check_velocities(values: np.ndarray, key: str, note: str = "") -> None:
    """Raise ModelError naming ``key`` if any velocity is non-finite or <= 0."""
    bad = ~(np.isfinite(values) & (values > 0))
    if bad.any():
        first = np.unravel_index(int(np.argmax(bad)), values.shape)
        where = ", ".join(f"{a}={i}" for a, i in zip(AXES[values.ndim], first))
        raise ModelError(f"{key}: {int(bad.sum())} of {values.size} velocities{note} are "
                         f"non-finite or <= 0; the first is {float(values[first])} m/s at index "
                         f"({where}); every velocity must be a positive finite number (m/s)")


def interpolate(values: np.ndarray, spacing, origin, new_spacing: float, new_origin, shape) -> np.ndarray:
    """values (axis order z,[y,]x) on the grid of per-axis ``spacing`` (m) with node 0 at ``origin`` (m), by
    (multi)linear interpolation at the ``shape`` nodes of spacing ``new_spacing`` from ``new_origin``; nodes outside
    the input extent take the nearest edge node's value."""
    out = np.asarray(values, float)
    for axis, (o_new, n_new, o, d, n) in enumerate(zip(new_origin, shape, origin, spacing, out.shape)):
        idx = np.clip((o_new + new_spacing * np.arange(n_new) - o) / d, 0, n - 1)
        i0 = np.minimum(np.floor(idx).astype(int), n - 1)
        w = (idx - i0).reshape([-1 if a == axis else 1 for a in range(out.ndim)])
        i1 = np.minimum(i0 + 1, n - 1)
        out = (1 - w) * out.take(i0, axis) + w * out.take(i1, axis)
    return out


@dataclass(frozen=True, eq=False)
class Model:
    """Gridded P-wave velocity model.

    values: float64 ndarray, shape (nz, nx) in 2D or (nz, ny, nx) in 3D, m/s (read-only copy).
        Axis order is always (z, [y,] x); z is depth, positive down.
    spacing: tuple of per-axis grid spacing in metres, same axis order (scalar accepted).
    origin: tuple of world coordinates (m) of values[0, ...0], same axis order (default zeros).
    name: str (for logs/plots).
    """

    values: np.ndarray
    spacing: tuple
    origin: tuple = None
    name: str = ""

    def __post_init__(self):
        values = np.array(self.values, dtype=np.float64)
        if values.ndim not in (2, 3):
            raise ModelError(f"values: shape {values.shape} is neither (nz, nx) nor "
                             f"(nz, ny, nx); give a 2D or 3D array")
        spacing = per_axis(self.spacing, values.ndim, "spacing")
        if min(spacing) <= 0:
            raise ModelError(f"spacing: {spacing} has a value <= 0; grid spacings are "
                             f"positive distances in metres")
        origin = per_axis(0.0 if self.origin is None else self.origin, values.ndim, "origin")
        check_velocities(values, "values")
        values.setflags(write=False)
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "spacing", spacing)
        object.__setattr__(self, "origin", origin)

    @classmethod
    def from_array(cls, values, spacing, origin=None, name: str = "") -> "Model":
        """Model from an (nz,[ny,]nx) array in m/s; spacing (m) scalar or per axis; origin (m)."""
        return cls(values, spacing, origin, name)

    @property
    def ndim(self) -> int:
        return self.values.ndim

    @property
    def shape(self) -> tuple[int, ...]:
        return self.values.shape

    @property
    def extent(self) -> tuple[tuple[float, float], ...]:
        """Per axis (z, [y,] x): (min, max) world coordinate (m) of the first and last node."""
        return tuple((o, o + (n - 1) * d) for o, n, d in zip(self.origin, self.shape, self.spacing))

    @property
    def vmin(self) -> float:
        return float(self.values.min())

    @property
    def vmax(self) -> float:
        return float(self.values.max())

    def contains(self, points) -> np.ndarray:
        """Bool array of shape (...) for points (..., ndim) in world metres, axis order (z,[y,]x):
        True where the point lies within [first node, last node] on every axis (with a
        tolerance of 1e-9 spacing for round-off)."""
        p = np.asarray(points, dtype=float)
        if p.shape[-1:] != (self.ndim,):
            raise ModelError(f"points: shape {p.shape} does not end in {self.ndim} coordinates "
                             f"({AXES[self.ndim]}); pass an array of shape (..., {self.ndim})")
        lo, hi = np.array(self.extent).T
        tol = 1e-9 * np.array(self.spacing)
        return np.all((p >= lo - tol) & (p <= hi + tol), axis=-1)

    def resample(self, spacing: float, origin: tuple, shape: tuple) -> "Model":
        """Model on the regular grid with equal ``spacing`` (m) on all axes, node 0 at ``origin``
        (m, axis order z,[y,]x) and ``shape`` nodes.

        Works on slowness 1/v, which interpolates travel times better than velocity:
        1. Anti-alias: along each axis where r = spacing / old_spacing > 1 (coarsening), the
           slowness is smoothed with a Gaussian of sigma = 0.5 * r input cells (edges
           replicated); axes that are refined or kept are not smoothed.
        2. (Multi)linear interpolation of the slowness at the new nodes; new nodes outside the
           input extent take the value of the nearest edge node (crop / edge replication).
        """
        h = float(spacing)
        if not (math.isfinite(h) and h > 0):
            raise ModelError(f"spacing: {spacing!r} is not a positive number of metres")
        origin = per_axis(origin, self.ndim, "origin")
        if len(shape) != self.ndim or min(shape) < 1:
            raise ModelError(f"shape: {tuple(shape)} is not {self.ndim} positive node counts "
                             f"in axis order {AXES[self.ndim]}")
        ratio = np.array([h / d for d in self.spacing])
        slow = ndimage.gaussian_filter(1.0 / self.values, np.where(ratio > 1, 0.5 * ratio, 0.0),
                                       mode="nearest")
        slow = interpolate(slow, self.spacing, self.origin, h, origin, shape)
        return Model(1.0 / slow, h, origin, self.name)
