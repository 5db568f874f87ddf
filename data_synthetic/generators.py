"""Synthetic velocity models (pure numpy) and small example model files.

All generators return an `adseismic.models.Model` with values of shape ``shape`` = (nz, nx) or
(nz, ny, nx) nodes, axis order (z,[y,]x), z depth positive down; ``spacing`` (m) is a scalar or
one value per axis, ``origin`` (m) is the world coordinate of node 0 (default zeros). Velocities
are in m/s. Invalid parameters raise `ModelError` whose message starts with the parameter name
(which is also the key of the YAML ``model:`` section, see `adseismic.models.load_model`).
"""
from __future__ import annotations

import copy
import pathlib

import numpy as np

from adseismic.data.model import Model, ModelError, per_axis


def _grid(shape, spacing, origin) -> tuple[tuple[int, ...], tuple[float, ...], tuple[float, ...]]:
    """Validated (shape, spacing, origin) tuples."""
    if not (isinstance(shape, (list, tuple)) and len(shape) in (2, 3)
            and all(isinstance(n, (int, np.integer)) and n > 0 for n in shape)):
        raise ModelError(f"shape: {shape!r} is not [nz, nx] or [nz, ny, nx] positive integers; "
                         f"give the number of grid nodes per axis")
    ndim = len(shape)
    return (tuple(int(n) for n in shape), per_axis(spacing, ndim, "spacing"),
            per_axis(0.0 if origin is None else origin, ndim, "origin"))


def _positive(value, key: str) -> float:
    if not (isinstance(value, (int, float, np.number)) and np.isfinite(value) and value > 0):
        hint = " (YAML reads 1.5e3 as text: write 1500.0 or 1.5e+3)" if isinstance(value, str) else ""
        raise ModelError(f"{key}: {value!r} is not a positive velocity; give it in m/s{hint}")
    return float(value)


def _coords(shape, spacing, origin, axis: int) -> np.ndarray:
    """World coordinate (m) of every node along ``axis``, shaped to broadcast over the grid."""
    c = origin[axis] + spacing[axis] * np.arange(shape[axis])
    return c.reshape([-1 if a == axis else 1 for a in range(len(shape))])


def constant(shape, spacing, velocity, origin=None) -> Model:
    """Homogeneous model: every node has ``velocity`` (m/s)."""
    shape, spacing, origin = _grid(shape, spacing, origin)
    return Model(np.full(shape, _positive(velocity, "velocity")), spacing, origin, "constant")


def layered(shape, spacing, velocities, interfaces, origin=None) -> Model:
    """Horizontal layers: ``velocities`` (m/s, top to bottom) separated by ``interfaces``
    (world depths z in m, strictly increasing, one fewer than velocities). A node exactly on an
    interface belongs to the layer below it."""
    shape, spacing, origin = _grid(shape, spacing, origin)
    if not (isinstance(velocities, (list, tuple)) and velocities):
        raise ModelError(f"velocities: {velocities!r} is not a non-empty list; give the layer "
                         f"velocities in m/s, top to bottom")
    v = np.array([_positive(x, "velocities") for x in velocities])
    z_if = np.asarray(interfaces, dtype=float) if isinstance(interfaces, (list, tuple)) else None
    if z_if is None or z_if.shape != (len(v) - 1,) or not np.all(np.isfinite(z_if)):
        raise ModelError(f"interfaces: {interfaces!r} is not a list of {len(v) - 1} depths; give "
                         f"one depth (m) between each pair of the {len(v)} velocities")
    if np.any(np.diff(z_if) <= 0):
        raise ModelError(f"interfaces: {interfaces!r} is not strictly increasing; list the "
                         f"interface depths (m) from top to bottom")
    layer = np.searchsorted(z_if, _coords(shape, spacing, origin, 0), side="right")
    return Model(np.broadcast_to(v[layer], shape), spacing, origin, "layered")


def gaussian_anomaly(shape, spacing, background, perturbation, center, radius,
                     origin=None) -> Model:
    """``background`` (m/s) plus ``perturbation`` (m/s, may be negative) times
    exp(-|p - center|^2 / (2 radius^2)); ``center`` in world metres (z,[y,]x), ``radius`` (m) is
    the Gaussian's standard deviation."""
    shape, spacing, origin = _grid(shape, spacing, origin)
    background = _positive(background, "background")
    if not (isinstance(perturbation, (int, float, np.number)) and np.isfinite(perturbation)):
        raise ModelError(f"perturbation: {perturbation!r} is not a number; give it in m/s")
    center = per_axis(center, len(shape), "center")
    if not (isinstance(radius, (int, float, np.number)) and np.isfinite(radius) and radius > 0):
        raise ModelError(f"radius: {radius!r} is not a positive length; give the Gaussian's "
                         f"standard deviation in metres")
    if background + perturbation <= 0:
        raise ModelError(f"perturbation: {perturbation!r} m/s makes the peak velocity "
                         f"{background + perturbation:g} m/s <= 0; use a perturbation "
                         f"> {-background:g} m/s")
    r2 = sum((_coords(shape, spacing, origin, a) - center[a]) ** 2 for a in range(len(shape)))
    values = background + perturbation * np.exp(-r2 / (2.0 * radius ** 2))
    return Model(np.broadcast_to(values, shape), spacing, origin, "gaussian_anomaly")


# Parameters of the example model written by write_example_files (a `layered` model spec).
EXAMPLE_SPEC = {"kind": "layered", "shape": [12, 20], "spacing": [10.0, 12.5],
                "origin": [0.0, -50.0], "velocities": [1500.0, 2500.0, 3500.0],
                "interfaces": [35.0, 80.0]}


def write_example_files(directory) -> dict[str, dict]:
    """Write the `EXAMPLE_SPEC` layered model (12 x 20 nodes) to ``directory`` in every file
    format and return ``{kind: spec}`` with a ``model:`` spec loading each one (paths relative to
    ``directory``), plus ``"layered"``: the generator spec itself. Formats, chosen to exercise
    the loader options:

    * ``example_xz_kms.f32``: raw little-endian float32, stored (x, z), km/s;
    * ``example.npy``: float64 (z, x), m/s;
    * ``example.h5``: dataset ``m`` stored (x, z) as squared slowness s^2/km^2, and dataset
      ``d`` with the spacing in stored order;
    * ``example.segy``: one IEEE-float trace per x position, samples along z, m/s (needs ObsPy).
    """
    import h5py
    from obspy import Stream, Trace
    from obspy.io.segy.segy import SEGYTraceHeader

    directory = pathlib.Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    params = {k: v for k, v in EXAMPLE_SPEC.items() if k != "kind"}
    v = layered(**params).values  # (nz, nx), m/s
    common = {"spacing": EXAMPLE_SPEC["spacing"], "origin": EXAMPLE_SPEC["origin"]}

    (v.T / 1e3).astype("<f4").tofile(directory / "example_xz_kms.f32")
    np.save(directory / "example.npy", v)
    with h5py.File(directory / "example.h5", "w") as f:
        f["m"] = (1e3 / v.T) ** 2
        f["d"] = EXAMPLE_SPEC["spacing"][::-1]
    traces = [Trace(np.ascontiguousarray(col, dtype=np.float32),  # delta: any valid interval
                    {"delta": 1e-3, "segy": {"trace_header": SEGYTraceHeader()}}) for col in v.T]
    Stream(traces).write(str(directory / "example.segy"), format="SEGY", data_encoding=5)
    return copy.deepcopy({  # callers may edit the specs without touching EXAMPLE_SPEC
        "layered": EXAMPLE_SPEC,
        "raw": {"kind": "raw", "path": "example_xz_kms.f32", "shape": [v.shape[1], v.shape[0]],
                "axes": "xz", "units": "km/s", **common},
        "npy": {"kind": "npy", "path": "example.npy", **common},
        "hdf5": {"kind": "hdf5", "path": "example.h5", "dataset": "m", "spacing_dataset": "d",
                 "axes": "xz", "units": "s2/km2", "origin": EXAMPLE_SPEC["origin"]},
        "segy": {"kind": "segy", "path": "example.segy", **common},
    })
