"""Velocity models from the YAML ``model:`` section: generated (adseismic.data_synthetic.generators) or read
from raw, .npy, HDF5 and SEG-Y files (ObsPy imported only for SEG-Y), in m/s, cropped and smoothed.
Axis order (z, [y,] x); the `Model` object is adseismic.data.model's. With ``physics: elastic`` the section holds
``{vp, vs, rho}``, each such a spec (or ``vs: {vp_ratio: R}``, ``rho: {gardner: true}``), with ``physics: acoustic_vd``
``{vp, rho}`` (a fluid: vs = 0), loaded by :func:`load_physics_model` into an :class:`ElasticModel`; with ``physics: vti``
``{vp, epsilon, delta, rho}`` (Thomsen's epsilon and delta dimensionless: a number, layers or a file) into a
:class:`VTIModel`."""
from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass, replace

import numpy as np

from adseismic.data.model import AXES, Model, ModelError, check_velocities, per_axis
from adseismic.data_synthetic import generators

# ----------------------------------------------------------------------------------- loading

_UNITS = {  # stored value a -> velocity in m/s
    "m/s": lambda a: a,
    "km/s": lambda a: 1e3 * a,
    "s/m": lambda a: 1.0 / a,
    "s2/km2": lambda a: 1e3 / np.sqrt(a),
    "s2/m2": lambda a: 1.0 / np.sqrt(a),
}
_GENERATOR_KEYS = {
    "constant": {"velocity"},
    "layered": {"velocities", "interfaces"},
    "gaussian_anomaly": {"background", "perturbation", "center", "radius"},
}
_FILE_KEYS = {
    "raw": {"shape", "dtype", "endian"},
    "npy": set(),
    "hdf5": {"dataset", "spacing_dataset"},
    "segy": set(),
}
_COMMON_KEYS = {"kind", "name", "origin", "crop", "smoothing"}


def load_model(spec: dict, base_dir: pathlib.Path | None = None) -> Model:
    """Build the Model described by the parsed YAML ``model:`` section ``spec``.

    Generator kinds (constant, layered, gaussian_anomaly) call `adseismic.data_synthetic.generators`;
    file kinds (raw, npy, hdf5, segy) read ``path`` (relative to ``base_dir``, default the current
    directory), transpose the stored ``axes`` to (z,[y,]x) and convert ``units`` to m/s.
    ``spacing`` and ``origin`` are always given in model axis order (z,[y,]x); an HDF5
    ``spacing_dataset`` is read in the stored axis order (``axes``). Optional ``name`` names the
    model (default: the kind, or the file name). Unknown keys are rejected (typos would otherwise
    be silently ignored). All problems raise ModelError naming ``model.<key>``.
    """
    if not isinstance(spec, dict):
        raise ModelError(f"model: {spec!r} is not a mapping; write the model section as "
                         f"'model: {{kind: ..., ...}}'")
    kind = spec.get("kind")
    kinds = list(_GENERATOR_KEYS) + list(_FILE_KEYS)
    if kind not in kinds:
        raise ModelError(f"model.kind: {kind!r} is not one of {', '.join(kinds)}; "
                         f"set the kind of model to build or read")
    if kind in _GENERATOR_KEYS:
        allowed = _COMMON_KEYS | {"shape", "spacing"} | _GENERATOR_KEYS[kind]
    else:
        allowed = _COMMON_KEYS | {"path", "units", "axes", "spacing"} | _FILE_KEYS[kind]
    unknown = sorted(set(spec) - allowed, key=str)
    if unknown:
        raise ModelError(f"model.{unknown[0]}: {spec[unknown[0]]!r} is not a key of a {kind!r} "
                         f"model; use only {', '.join(sorted(allowed))}")
    if kind in _GENERATOR_KEYS:
        model = _generate(kind, spec)
    else:
        model = _load_file(kind, spec, pathlib.Path.cwd() if base_dir is None else base_dir)
    if spec.get("crop") is not None:
        model = _crop(model, spec["crop"])
    if spec.get("smoothing") is not None:
        model = _smooth(model, spec["smoothing"])
    return replace(model, name=str(spec["name"])) if "name" in spec else model


def _crop(model: Model, crop) -> Model:
    """Nodes whose world coordinates lie in crop = {x: [min, max], z: [min, max], (y: ...)} (m)."""
    names = ("z", "x") if model.ndim == 2 else ("z", "y", "x")
    if not isinstance(crop, dict) or set(crop) - set(names):
        raise ModelError(f"model.crop: {crop!r} is not a mapping of axes {names} to [min, max] in metres")
    index = []
    for a, name in enumerate(names):
        lo, hi = model.extent[a]
        rng = crop.get(name, [lo, hi])
        if not (isinstance(rng, list) and len(rng) == 2
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in rng)
                and rng[0] < rng[1]):
            raise ModelError(f"model.crop.{name}: {rng!r} is not [min, max] with min < max (metres)")
        i0 = int(np.ceil((rng[0] - model.origin[a]) / model.spacing[a] - 1e-9))
        i1 = int(np.floor((rng[1] - model.origin[a]) / model.spacing[a] + 1e-9))
        i0, i1 = max(i0, 0), min(i1, model.shape[a] - 1)
        if i1 <= i0:
            raise ModelError(f"model.crop.{name}: {rng} m does not overlap the model's extent [{lo:g}, {hi:g}] m")
        index.append(slice(i0, i1 + 1))
    origin = tuple(o + sl.start * h for o, sl, h in zip(model.origin, index, model.spacing))
    return replace(model, values=model.values[tuple(index)], origin=origin)


def _smooth(model: Model, sigma) -> Model:
    """Gaussian smoothing of the slowness with standard deviation sigma (m) along every axis."""
    from scipy.ndimage import gaussian_filter

    try:
        sigma = -1.0 if isinstance(sigma, bool) else float(sigma)
    except (TypeError, ValueError, OverflowError):
        sigma = -1.0
    if not (math.isfinite(sigma) and sigma >= 0):
        raise ModelError(f"model.smoothing: {sigma!r} is not a length >= 0 in metres (Gaussian standard deviation)")
    size = max(n * h for n, h in zip(model.shape, model.spacing))
    if sigma > size:
        raise ModelError(f"model.smoothing: {sigma:g} m is larger than the model ({size:g} m across); give a "
                         f"Gaussian standard deviation below it (the result would be constant)")
    slow = gaussian_filter(1.0 / model.values, [sigma / h for h in model.spacing], mode="nearest")
    return replace(model, values=1.0 / slow)


def _require(spec: dict, key: str, what: str):
    if key not in spec:
        raise ModelError(f"model.{key}: missing; a {spec['kind']!r} model needs {what}")
    return spec[key]


def _short(value, limit: int = 80) -> str:
    r = repr(value)
    return r if len(r) <= limit else r[: limit - 3] + "..."


def _real(value, key: str, what: str) -> float:
    """A finite real number (not a bool, not text)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        hint = (" (YAML reads 1.5e3 as text: write 1500.0 or 1.5e+3)" if isinstance(value, str)
                else " (true/false are not numbers)" if isinstance(value, (bool, np.bool_)) else "")
        raise ModelError(f"{key}: {_short(value)} is not a number{hint}; give {what}")
    try:
        x = float(value)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise ModelError(f"{key}: {_short(value)} is not a finite number; give {what}")
    return x


def check_shape(shape, key: str = "model.shape", itemsize: int = 8) -> tuple:
    """[nz, nx] or [nz, ny, nx] positive integers (not bools) whose float64 array fits in memory."""
    ok = (isinstance(shape, (list, tuple)) and len(shape) in (2, 3)
          and all(isinstance(n, (int, np.integer)) and not isinstance(n, (bool, np.bool_)) and n > 0 for n in shape))
    if not ok:
        raise ModelError(f"{key}: {_short(shape)} is not [nz, nx] or [nz, ny, nx] positive integers; give the number "
                         f"of grid nodes per axis")
    shape = tuple(int(n) for n in shape)
    nbytes = math.prod(shape) * itemsize
    from adseismic.data.memory import available_bytes

    free = available_bytes("cpu")
    if nbytes > MAX_MODEL_BYTES or (free is not None and 2 * nbytes > free):
        raise ModelError(f"{key}: {list(shape)} is {math.prod(shape):,} nodes = {nbytes / 2**30:.3g} GiB as float64, "
                         f"more than this machine can hold ({'free memory ' + format(free / 2**30, '.3g') + ' GiB, ' if free else ''}"
                         f"the model needs about twice its size while loading); give fewer nodes (a coarser spacing or a "
                         f"crop), and check the numbers")
    return shape


MAX_MODEL_BYTES = 2**40  # 1 TiB: above this a node count is a typo, whatever the machine


def _generate(kind: str, spec: dict) -> Model:
    params = {k: _require(spec, k, "this value") for k in ("shape", "spacing") + tuple(
        sorted(_GENERATOR_KEYS[kind]))}
    # check types here: the generators assume numbers and lists of numbers
    check_shape(params["shape"])
    ndim = len(params["shape"])
    for k in ("spacing", "center"):
        if k in params:
            per_axis(params[k], ndim, f"model.{k}")
    if spec.get("origin") is not None:
        per_axis(spec["origin"], ndim, "model.origin")
    for k in ("velocity", "background", "perturbation", "radius"):
        if k in params:
            _real(params[k], f"model.{k}", "a number (m/s for velocities, m for radius)")
    for k in ("velocities", "interfaces"):
        if k in params:
            v = params[k]
            if not isinstance(v, (list, tuple)):
                raise ModelError(f"model.{k}: {_short(v)} is not a list; give "
                                 f"{'the layer velocities in m/s, top to bottom' if k == 'velocities' else 'the interface depths in m, top to bottom'}")
            for i, x in enumerate(v):
                _real(x, f"model.{k}[{i}]", "a number (m/s)" if k == "velocities" else "a depth in m")
    try:
        return getattr(generators, kind)(origin=spec.get("origin"), **params)
    except ModelError as e:  # generator messages start with the parameter (= key) name
        raise ModelError(f"model.{e}") from None


def _load_file(kind: str, spec: dict, base_dir: pathlib.Path) -> Model:
    units = spec.get("units", "m/s")
    if not isinstance(units, str) or units not in _UNITS:
        raise ModelError(f"model.units: {units!r} is not one of {', '.join(_UNITS)}; "
                         f"set the units the file stores")
    data, spacing, path = _read_grid(kind, spec, base_dir)
    with np.errstate(divide="ignore", invalid="ignore"):
        values = _UNITS[units](data)
    check_velocities(values, f"model.path ({path.name})", f" (converted from {units})")
    try:
        return Model(values, spacing, spec.get("origin"), path.stem)
    except ModelError as e:
        raise ModelError(f"model.{e}") from None


def _read_grid(kind: str, spec: dict, base_dir: pathlib.Path) -> tuple[np.ndarray, tuple, pathlib.Path]:
    """(values float64 in axis order (z, [y,] x) as stored (no unit conversion), spacing (m) per axis, the file's path)
    of a file spec (raw, npy, hdf5, segy); ModelError naming ``model.<key>``."""
    # --- validate the spec and the file before reading anything
    raw_path = _require(spec, "path", "the path of the file to read")
    path = pathlib.Path(raw_path).expanduser()
    path = path if path.is_absolute() else pathlib.Path(base_dir) / path
    if not path.is_file():
        raise ModelError(f"model.path: {str(raw_path)!r} does not exist (looked for {path}); "
                         f"give an absolute path or one relative to {base_dir}")
    if "spacing" in spec and "spacing_dataset" in spec:
        raise ModelError(f"model.spacing_dataset: {spec['spacing_dataset']!r} given together "
                         f"with model.spacing; keep only one of them")
    if "spacing" not in spec and not (kind == "hdf5" and "spacing_dataset" in spec):
        alt = " or spacing_dataset (name of an HDF5 dataset holding it)" if kind == "hdf5" else ""
        raise ModelError(f"model.spacing: missing; give the grid spacing in metres (a number "
                         f"or one per axis, z,[y,]x){alt}")

    # --- read the stored array
    if kind == "raw":
        data = _read_raw(spec, path)
    elif kind == "npy":
        if path.stat().st_size == 0:
            raise ModelError(f"model.path: {path} is an empty file (0 bytes); save the model with numpy.save")
        try:
            data = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise ModelError(f"model.path: {path} is not a readable .npy array ({type(e).__name__}: {e}); the file "
                             f"may be truncated or of another format; save it with numpy.save") from None
        if not isinstance(data, np.ndarray):  # an .npz archive
            names = ", ".join(getattr(data, "files", [])[:5])
            raise ModelError(f"model.path: {path} is an .npz archive ({names}), not one .npy array; save the model "
                             f"alone with numpy.save")
    elif kind == "hdf5":
        data, spacing_stored = _read_hdf5(spec, path)
    else:
        data = _read_segy(path)
    data = _check_stored(data, path)

    # --- reorder axes to (z,[y,]x), convert units, check values
    axes = spec.get("axes", "xz" if kind == "segy" else AXES[data.ndim])
    if not isinstance(axes, str) or sorted(axes) != sorted(AXES[data.ndim]):
        raise ModelError(f"model.axes: {axes!r} is not an ordering of {AXES[data.ndim]!r} for "
                         f"the {data.ndim}D stored array of shape {data.shape}; name the stored "
                         f"axes slowest first, e.g. {AXES[data.ndim][::-1]!r}")
    order = [axes.index(a) for a in AXES[data.ndim]]
    if "spacing" in spec:
        spacing = per_axis(spec["spacing"], data.ndim, "model.spacing")
    else:
        spacing = tuple(np.asarray(per_axis(spacing_stored, data.ndim,
                                             f"model.spacing_dataset ({spec['spacing_dataset']})"))[order])
    return np.transpose(data, order).astype(np.float64), spacing, path


def _check_stored(data, path: pathlib.Path) -> np.ndarray:
    """The stored array as read: real numbers, 2 or 3 axes, not empty (ModelError naming the file)."""
    data = np.asarray(data)
    kind = data.dtype.kind
    if kind == "c":
        im = float(np.max(np.abs(data.imag))) if data.size else 0.0
        raise ModelError(f"model.path: {path} holds complex numbers ({data.dtype}, largest |imaginary part| {im:g}); "
                         f"a velocity model is real: save numpy.real(v) (or numpy.abs(v)) in m/s")
    if kind not in "fiu" or data.dtype.names:
        raise ModelError(f"model.path: {path} holds {data.dtype} values, not numbers; save the velocities as "
                         f"float32 or float64")
    if data.ndim not in (2, 3):
        raise ModelError(f"model.path: {path} holds an array of shape {data.shape}; "
                         f"a velocity model needs 2 or 3 axes")
    if data.size == 0:
        raise ModelError(f"model.path: {path} holds an empty array of shape {data.shape}; save the model's "
                         f"values (at least 1 node per axis)")
    return data


def _read_raw(spec: dict, path: pathlib.Path) -> np.ndarray:
    """Headerless binary array: ``shape`` in stored axis order, ``dtype``, ``endian``."""
    shape = _require(spec, "shape", "the stored array shape (slowest axis first, as in 'axes')")
    if not (isinstance(shape, (list, tuple)) and shape
            and all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in shape)):
        raise ModelError(f"model.shape: {_short(shape)} is not a list of positive integers; give the "
                         f"stored array shape, slowest axis first")
    try:
        dtype = np.dtype(spec.get("dtype", "float32")) if isinstance(spec.get("dtype", "float32"), str) else None
    except (TypeError, ValueError):
        dtype = None
    if dtype is None or dtype.kind not in "fiu" or dtype.names:
        raise ModelError(f"model.dtype: {_short(spec.get('dtype'))} is not a numeric numpy dtype; use e.g. "
                         f"float32 or float64") from None
    endian = spec.get("endian", "little")
    if endian not in ("little", "big"):
        raise ModelError(f"model.endian: {endian!r} is not little or big; set the byte order "
                         f"the file was written with")
    dtype = dtype.newbyteorder("<" if endian == "little" else ">")
    count, need = path.stat().st_size / dtype.itemsize, math.prod(shape)
    if count != need:
        raise ModelError(f"model.shape: {path.name} has {count:g} {dtype.name} values but shape "
                         f"{shape} needs {need}; fix shape (stored order) or dtype")
    return np.fromfile(path, dtype=dtype).reshape(shape)


def _read_hdf5(spec: dict, path: pathlib.Path) -> tuple[np.ndarray, object]:
    """Dataset ``dataset`` and, if ``spacing_dataset`` is given, that dataset's values."""
    import h5py

    name = _require(spec, "dataset", "the name of the HDF5 dataset holding the model")
    for key in ("dataset", "spacing_dataset"):
        if key in spec and not isinstance(spec[key], str):
            raise ModelError(f"model.{key}: {_short(spec[key])} is not a dataset name; give the name (text) of an "
                             f"HDF5 dataset, e.g. 'velocity' or 'group/vp'")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        size = path.stat().st_size
        raise ModelError(f"model.path: {path} ({size:,} bytes) is not a readable HDF5 file ({e}); it may be empty, "
                         f"truncated or another format: write it again (h5py) or give kind: npy / raw") from None
    try:
        with f:
            found = []
            f.visititems(lambda n, obj: found.append(n) if isinstance(obj, h5py.Dataset) else None)
            for key in ("dataset", "spacing_dataset"):
                if key in spec and spec[key] not in found:
                    raise ModelError(f"model.{key}: {spec[key]!r} is not a dataset in {path.name}; "
                                     f"it has {', '.join(found) or 'no datasets'}")
            spacing = f[spec["spacing_dataset"]][()] if "spacing_dataset" in spec else None
            return f[name][()], spacing
    except (OSError, RuntimeError, KeyError, TypeError, ValueError) as e:
        if isinstance(e, ModelError):
            raise
        raise ModelError(f"model.path: {path}: dataset {name!r} could not be read ({type(e).__name__}: {e}); the file "
                         f"may be truncated or corrupt: write it again") from None


def _read_segy(path: pathlib.Path) -> np.ndarray:
    """SEG-Y with one trace per x position, samples along z: array (ntraces, nsamples)."""
    import obspy

    try:
        stream = obspy.read(str(path), format="SEGY", unpack_trace_headers=False)
    except Exception as e:  # ObsPy raises assorted types for unreadable files
        raise ModelError(f"model.path: {path} could not be read as SEG-Y ({e}); "
                         f"check the file or choose another kind") from None
    if len(stream) == 0:
        raise ModelError(f"model.path: {path} holds no traces; give a SEG-Y file with one trace per x position")
    lengths = {len(tr.data) for tr in stream}
    if len(lengths) != 1:
        raise ModelError(f"model.path: {path.name} has traces of {len(lengths)} different "
                         f"lengths {sorted(lengths)}; a gridded model needs equal-length traces")
    return np.stack([tr.data for tr in stream])


# ----------------------------------------------------------------------------------- elastic models

PHYSICS = ("acoustic", "elastic", "acoustic_vd", "vti", "viscoacoustic")
ELASTIC_SOLVER = ("elastic", "acoustic_vd")  # the physics the elastic solver runs (acoustic_vd: vs = 0, a fluid)
ELASTIC_KEYS = ("vp", "vs", "rho")
ACOUSTIC_VD_KEYS = ("vp", "rho")
MIN_SHEAR = 10.0  # m/s: below this a shear speed is a unit error (km/s typed as m/s), as for P speeds (scene.MIN_VELOCITY)
MIN_DENSITY = 100.0  # kg/m^3: below this a density is a unit error (g/cm^3 typed as kg/m^3), not a rock or a fluid
GARDNER = (310.0, 0.25)  # rho = 310 vp^0.25 kg/m^3 with vp in m/s (Gardner, Gardner & Gregory 1974, Geophysics 39)


class _OnVpGrid:
    """The Model-like grid of a model of several fields on vp's grid: ``ndim``, ``shape``, ``spacing``, ``origin``,
    ``extent``, ``name``, ``contains`` are vp's grid's, ``values`` vp's (m/s)."""

    ndim = property(lambda self: self.vp.ndim)
    shape = property(lambda self: self.vp.shape)
    spacing = property(lambda self: self.vp.spacing)
    origin = property(lambda self: self.vp.origin)
    extent = property(lambda self: self.vp.extent)
    name = property(lambda self: self.vp.name)
    values = property(lambda self: self.vp.values)

    def contains(self, points) -> np.ndarray:
        """:meth:`Model.contains` of the grid."""
        return self.vp.contains(points)


@dataclass(frozen=True, eq=False)
class ElasticModel(_OnVpGrid):
    """An isotropic elastic model: ``vp``, ``vs`` (m/s) and ``rho`` (kg/m^3), three :class:`Model` objects on one grid
    (shape (nz, [ny,] nx), spacing and origin in m, axis order (z, [y,] x); 3D with vs only); 0 < vs <= vp / sqrt(2)
    (Lame lambda >= 0).
    ``vs`` None: a fluid everywhere (vs = 0), the variable-density acoustic model of ``physics: acoustic_vd``, which
    the elastic solver runs (``physics`` says which; :meth:`materials` gives the solver's three arrays).

    Model-like for the planner and the config: ``ndim``, ``shape``, ``spacing``, ``origin``, ``extent``, ``name``,
    ``contains`` are the grid's; ``values``, ``vmin``, ``vmax`` are vp's (the fastest wave: the domain's margin, the
    CFL limit and the plots); ``resample`` resamples all three.
    """

    vp: Model
    vs: Model | None
    rho: Model

    def __post_init__(self):
        for name in ("vs", "rho"):
            m = getattr(self, name)
            if m is None:
                continue
            if m.shape != self.vp.shape or m.spacing != self.vp.spacing or m.origin != self.vp.origin:
                raise ModelError(f"model.{name}: its grid (shape {list(m.shape)}, spacing {list(m.spacing)} m, origin "
                                 f"{list(m.origin)} m) differs from model.vp's (shape {list(self.vp.shape)}, spacing "
                                 f"{list(self.vp.spacing)} m, origin {list(self.vp.origin)} m); give the three on one grid")
        if self.vs is not None:
            check_shear(self.vp.values, self.vs.values, "model.vs")

    @property
    def physics(self) -> str:
        """elastic, or acoustic_vd when vs is None (a fluid)."""
        return "acoustic_vd" if self.vs is None else "elastic"

    def materials(self) -> dict:
        """{vp, vs, rho}: float64 arrays (nz, [ny,] nx) in m/s, m/s, kg/m^3 as the elastic solver takes them (vs zeros for
        acoustic_vd)."""
        vs = np.zeros(self.shape) if self.vs is None else self.vs.values
        return {"vp": np.asarray(self.vp.values, float), "vs": np.asarray(vs, float), "rho": np.asarray(self.rho.values, float)}

    vmin = property(lambda self: self.vp.vmin)
    vmax = property(lambda self: self.vp.vmax)

    def resample(self, spacing: float, origin: tuple, shape: tuple) -> ElasticModel:
        """The three models on the regular grid of :meth:`Model.resample` (spacing m, origin m, shape nodes), each by
        its inverse: slowness for vp and vs, buoyancy (which the velocity update reads) for rho. vp and vs get the
        same weights at every node, so each new vp / vs lies between old ones (a weighted mediant): vs <= vp / sqrt(2)
        holds on the new grid wherever it held on the old."""
        return ElasticModel(*(None if m is None else m.resample(spacing, origin, shape) for m in (self.vp, self.vs, self.rho)))


def check_shear(vp: np.ndarray, vs: np.ndarray, key: str) -> None:
    """Refuse (ModelError naming ``key``) vs > vp / sqrt(2) anywhere (a negative Lame lambda: vs >= vp in particular)."""
    ratio = vs / vp
    bad = ratio > (1.0 + 1e-12) / math.sqrt(2.0)
    if bad.any():
        i = tuple(int(k) for k in np.unravel_index(int(np.argmax(ratio)), ratio.shape))
        where = ", ".join(f"{a}={k}" for a, k in zip(AXES[vp.ndim], i))
        what = "S faster than P" if ratio[i] >= 1 else "a negative Lame lambda"
        raise ModelError(f"{key}: vs = {vs[i]:g} m/s > vp / sqrt(2) = {vp[i] / math.sqrt(2):g} m/s at index ({where}) "
                         f"(vp {vp[i]:g} m/s; {int(bad.sum())} of {vs.size} nodes): {what}, no elastic solid; give vs <= "
                         f"vp / sqrt(2) (vp/vs >= 1.414; rocks: 1.5-2.0) everywhere")


def _sub_spec(spec, key: str, vp: Model | None) -> dict:
    """``spec`` of ``model.<key>``, a generator kind filling shape, spacing and origin from vp's grid when left out."""
    if not isinstance(spec, dict):
        raise ModelError(f"model.{key}: {_short(spec)} is not a mapping; give a model spec {{kind: ..., ...}}"
                         + (" or {vp_ratio: R}" if key == "vs" else " or {gardner: true}" if key == "rho" else ""))
    if vp is not None and spec.get("kind") in _GENERATOR_KEYS:
        grid = {"shape": list(vp.shape), "spacing": list(vp.spacing), "origin": list(vp.origin)}
        spec = {**{k: v for k, v in grid.items() if k not in spec}, **spec}
    return spec


def _load_part(spec, key: str, base_dir, vp: Model | None) -> Model:
    """load_model of ``model.<key>``, its messages naming ``model.<key>.<field>``."""
    try:
        return load_model(_sub_spec(spec, key, vp), base_dir)
    except ModelError as e:
        msg = str(e)
        msg = f"model.{key}{msg[5:]}" if msg.startswith("model") else f"model.{key}.{msg}"
        if key == "vs" and ("<= 0" in msg or "not > 0" in msg or "not a positive" in msg):
            msg += ("; vs must be > 0 everywhere in an elastic model from a config (fluid regions are not supported "
                    "there); if vs is 0 everywhere, the medium is a fluid: use physics: acoustic with model: the vp spec, or "
                    "physics: acoustic_vd with model: {vp, rho} where the density varies")
        if key == "rho":  # the message after the key speaks of velocities: here they are densities
            where, _, text = msg.partition(": ")
            text = text.replace("velocities", "densities").replace("velocity", "density").replace("m/s", "kg/m^3")
            msg = f"{where}: {text}"
        raise ModelError(msg) from None


def load_physics_model(spec, physics: str = "acoustic", base_dir: pathlib.Path | None = None) -> Model | ElasticModel:
    """The ``model:`` section ``spec`` for ``physics``: acoustic, a :class:`Model` (:func:`load_model`); elastic, an
    :class:`ElasticModel` from ``{vp, vs, rho}``: vp a model spec (m/s); vs a model spec (m/s) or ``{vp_ratio: R}``
    (vs = vp / R, R >= sqrt(2)); rho a model spec (kg/m^3: the key velocity / velocities / background holds the
    densities) or ``{gardner: true}`` (rho = 310 vp^0.25); acoustic_vd, an ElasticModel with vs None (a fluid) from
    ``{vp, rho}``. Generator specs of vs and rho may leave out shape, spacing and origin (vp's are used). elastic: 2D
    or 3D ([nz, ny, nx], adseismic.solve.elastic3d); acoustic_vd: 2D or 3D (adseismic.solve.acoustic_vd).
    Raises ModelError naming ``model.<part>.<key>``, the value and the fix."""
    if physics not in PHYSICS:
        raise ModelError(f"physics: {_short(physics)} is not one of {', '.join(PHYSICS)}; pick one of them")
    is_elastic_spec = isinstance(spec, dict) and bool(set(spec) & set(ELASTIC_KEYS))
    if physics == "vti":
        return _load_vti(spec, base_dir)
    if physics == "viscoacoustic":
        return _load_viscoacoustic(spec, base_dir)
    if physics == "acoustic":
        if is_elastic_spec:
            raise ModelError(f"model: {', '.join(k for k in ELASTIC_KEYS if k in spec)} are the keys of an elastic model "
                             f"(physics elastic), but physics is acoustic; set physics: elastic (or acoustic_vd for "
                             f"{{vp, rho}}), or give one velocity model (model: {{kind: ..., ...}}) for acoustic physics")
        return load_model(spec, base_dir)
    keys = ELASTIC_KEYS if physics == "elastic" else ACOUSTIC_VD_KEYS
    what = ("vp (m/s), vs (m/s, or {vp_ratio: R}) and rho (kg/m^3, or {gardner: true})" if physics == "elastic" else
            "vp (m/s) and rho (kg/m^3, or {gardner: true})")
    if not is_elastic_spec:
        raise ModelError(f"model: {_short(spec)} is one velocity model, but physics {physics} needs "
                         f"{'three' if physics == 'elastic' else 'two'}, {{{', '.join(keys)}}}: write model: {{vp: {{kind: ...}}, "
                         + ("vs: {kind: ...} or {vp_ratio: 1.8}, " if physics == "elastic" else "")
                         + "rho: {kind: ...} or {gardner: true}} (m/s, kg/m^3), or set physics: acoustic")
    if physics == "acoustic_vd" and "vs" in spec:
        raise ModelError(f"model.vs: {_short(spec['vs'])} given with physics acoustic_vd, a fluid (vs = 0 everywhere); "
                         f"drop vs (model: {{vp, rho}}), or set physics: elastic for a solid with shear waves")
    unknown = sorted(set(spec) - set(keys), key=str)
    if unknown:
        kind = "an elastic" if physics == "elastic" else "an acoustic_vd"
        raise ModelError(f"model.{unknown[0]}: unknown key of {kind} model; allowed: {', '.join(keys)} "
                         f"(each a model spec)")
    missing = [k for k in keys if spec.get(k) is None]
    if missing:
        raise ModelError(f"model.{missing[0]}: missing; a physics {physics} model needs {what}")
    vp = _load_part(spec["vp"], "vp", base_dir, None)
    rho = _load_density(spec["rho"], base_dir, vp)
    if physics == "acoustic_vd":
        return ElasticModel(vp, None, rho)
    vs_spec = spec["vs"]
    if isinstance(vs_spec, dict) and "vp_ratio" in vs_spec:
        if set(vs_spec) != {"vp_ratio"}:
            raise ModelError(f"model.vs: {_short(vs_spec)} mixes vp_ratio with a model spec; give either {{vp_ratio: R}} "
                             f"or a model spec")
        r = _real(vs_spec["vp_ratio"], "model.vs.vp_ratio", "vp / vs, a number >= 1.414")
        if not r >= math.sqrt(2.0):
            raise ModelError(f"model.vs.vp_ratio: {r:g} is below sqrt(2) = 1.414: vs = vp / {r:g} > vp / sqrt(2) gives a "
                             f"negative Lame lambda{' (S faster than P)' if r <= 1 else ''}; give vp/vs >= 1.414 "
                             f"(1.732 for a Poisson solid)")
        vs = replace(vp, values=vp.values / r, name=f"vp / {r:g}")
    else:
        vs = _load_part(vs_spec, "vs", base_dir, vp)
        if vs.vmin < MIN_SHEAR:
            raise ModelError(f"model.vs: shear speeds down to {vs.vmin:.4g} m/s, below {MIN_SHEAR:g} m/s (no rock is that "
                             f"slow, and the grid would need cells of millimetres); km/s? multiply by 1000 (speeds are in m/s)")
    return ElasticModel(vp, vs, rho)


def _load_density(rho_spec, base_dir, vp: Model) -> Model:
    """``model.rho``: a model spec (kg/m^3) on vp's grid or ``{gardner: true}``; refuses densities below MIN_DENSITY."""
    if isinstance(rho_spec, dict) and "gardner" in rho_spec:
        if set(rho_spec) != {"gardner"} or rho_spec["gardner"] is not True:
            raise ModelError(f"model.rho: {_short(rho_spec)} is not {{gardner: true}}; give {{gardner: true}} "
                             f"(rho = 310 vp^0.25 kg/m^3) or a model spec of the density")
        a, b = GARDNER
        return replace(vp, values=a * vp.values ** b, name="Gardner")
    rho = _load_part(rho_spec, "rho", base_dir, vp)
    if rho.vmin < MIN_DENSITY:
        raise ModelError(f"model.rho: densities down to {rho.vmin:g} kg/m^3, below {MIN_DENSITY:g} kg/m^3 (water: "
                         f"1000, rocks 1500-3000); g/cm^3? multiply by 1000 (densities are in kg/m^3)")
    return rho


# ----------------------------------------------------------------------------------- VTI models

VTI_KEYS = ("vp", "epsilon", "delta", "rho")
WATER_DENSITY = 1000.0  # kg/m^3: physics vti's density when model.rho is left out
_FIELD_KEYS = {"layered": {"values", "interfaces"}, **{k: v | {"axes", "spacing", "origin", "path"} for k, v in _FILE_KEYS.items()}}
# the dimensionless fields on vp's grid (_load_field): key -> (what it is, an example value, whether +inf is a value)
_FIELDS = {"epsilon": ("Thomsen's epsilon (dimensionless)", "0.1", False),
           "delta": ("Thomsen's delta (dimensionless)", "0.05", False),
           "q": ("the quality factor Q (dimensionless, > 0; .inf: lossless)", "30", True)}


@dataclass(frozen=True, eq=False)
class VTIModel(_OnVpGrid):
    """A 2D VTI model for the pseudo-acoustic solver (adseismic.solve.vti, docs/vti.md): ``vp`` the vertical P speed
    (m/s) and ``rho`` (kg/m^3), :class:`Model` objects on one grid (shape (nz, nx), axis order (z, x)), and Thomsen's
    ``epsilon`` and ``delta`` (dimensionless) as read-only float64 arrays (nz, nx) on that grid; epsilon >= delta and
    delta > -1/2 everywhere (refused otherwise: the solver's thomsen_check). Model-like as :class:`ElasticModel`:
    ``values`` and ``vmin`` are vp's, ``vmax`` the fastest speed, max of the horizontal vp sqrt(1 + 2 epsilon)."""

    vp: Model
    epsilon: np.ndarray
    delta: np.ndarray
    rho: Model

    physics = "vti"

    def __post_init__(self):
        from adseismic.kernels.vti import thomsen_check

        if self.rho.shape != self.vp.shape or self.rho.spacing != self.vp.spacing or self.rho.origin != self.vp.origin:
            raise ModelError(f"model.rho: its grid (shape {list(self.rho.shape)}, spacing {list(self.rho.spacing)} m) differs "
                             f"from model.vp's (shape {list(self.vp.shape)}, spacing {list(self.vp.spacing)} m); give both on one grid")
        for name in ("epsilon", "delta"):
            a = np.array(getattr(self, name), dtype=np.float64)
            if a.shape != self.vp.shape:
                raise ModelError(f"model.{name}: shape {list(a.shape)} differs from model.vp's {list(self.vp.shape)} (z, x); "
                                 f"give {name} on vp's grid")
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        try:
            thomsen_check(self.epsilon, self.delta)
        except ValueError as e:
            raise ModelError(f"model.epsilon, model.delta: {e}") from None

    vmin = property(lambda self: self.vp.vmin)
    vmax = property(lambda self: float(self.horizontal_speed().max()))

    def horizontal_speed(self) -> np.ndarray:
        """vp sqrt(1 + 2 epsilon) (m/s, (nz, nx)): the horizontal P speed, the fastest of the medium."""
        return self.vp.values * np.sqrt(1.0 + 2.0 * self.epsilon)

    def materials(self) -> dict:
        """{vp, epsilon, delta, rho}: float64 arrays (nz, nx) as forward_vti takes them (m/s, 1, 1, kg/m^3)."""
        return {"vp": np.asarray(self.vp.values, float), "epsilon": np.asarray(self.epsilon, float),
                "delta": np.asarray(self.delta, float), "rho": np.asarray(self.rho.values, float)}

    def resample(self, spacing: float, origin: tuple, shape: tuple) -> VTIModel:
        """The model on the regular grid of :meth:`Model.resample` (spacing m, origin m, shape nodes): vp by its
        slowness, rho by its buoyancy (as ElasticModel), epsilon and delta linearly, with the same anti-alias filter
        and interpolation weights (Model.resample of 1 / (1 + 2 t), a positive field whose inverse is linear in t);
        equal weights at every node keep epsilon >= delta."""
        return VTIModel(self.vp.resample(spacing, origin, shape), _resample_linear(self.vp, self.epsilon, spacing, origin, shape),
                        _resample_linear(self.vp, self.delta, spacing, origin, shape), self.rho.resample(spacing, origin, shape))


def _resample_linear(grid: Model, t: np.ndarray, spacing: float, origin: tuple, shape: tuple) -> np.ndarray:
    """A field ``t`` > -1/2 on ``grid``'s nodes (same shape) resampled linearly in t with the anti-alias filter and
    interpolation weights of ``grid.resample(spacing, origin, shape)``: Model.resample of 1 / (1 + 2 t), a positive
    field whose inverse is linear in t."""
    m = replace(grid, values=1.0 / (1.0 + 2.0 * t)).resample(spacing, origin, shape)
    return 0.5 * (1.0 / m.values - 1.0)


def _load_vti(spec, base_dir) -> VTIModel:
    """``model: {vp, epsilon, delta, rho}`` of physics vti: vp a model spec (m/s), epsilon and delta Thomsen fields
    (:func:`_load_field`), rho a model spec (kg/m^3), ``{gardner: true}`` or left out (WATER_DENSITY)."""
    if not (isinstance(spec, dict) and set(spec) & set(VTI_KEYS)):
        raise ModelError(f"model: {_short(spec)} is one velocity model, but physics vti needs {{vp, epsilon, delta}} (and "
                         f"optionally rho): write model: {{vp: {{kind: ...}}, epsilon: 0.1, delta: 0.05}} (vp in m/s, "
                         f"Thomsen's epsilon and delta dimensionless), or set physics: acoustic")
    unknown = sorted(set(spec) - set(VTI_KEYS), key=str)
    if unknown:
        raise ModelError(f"model.{unknown[0]}: unknown key of a vti model; allowed: {', '.join(VTI_KEYS)} (vp, rho model "
                         f"specs; epsilon, delta a number or a Thomsen field spec)")
    for k in VTI_KEYS[:3]:
        if spec.get(k) is None:
            raise ModelError(f"model.{k}: missing; a physics vti model needs vp (m/s), epsilon and delta (Thomsen, "
                             f"dimensionless: a number or {{kind: layered | npy | hdf5 | raw | segy, ...}}) and optionally "
                             f"rho (kg/m^3, {{gardner: true}}, default {WATER_DENSITY:g})")
    base_dir = pathlib.Path.cwd() if base_dir is None else base_dir
    vp = _load_part(spec["vp"], "vp", base_dir, None)
    if vp.ndim != 2:
        raise ModelError(f"model.vp: a 3D model (shape {list(vp.shape)}) with physics vti; the VTI solver is 2D (3D is not "
                         f"built yet): give a 2D model [nz, nx], or use physics: acoustic in 3D")
    eps, delta = (_load_field(spec[k], k, base_dir, vp) for k in ("epsilon", "delta"))
    rho = (replace(vp, values=np.full(vp.shape, WATER_DENSITY), name="water density") if spec.get("rho") is None
           else _load_density(spec["rho"], base_dir, vp))
    return VTIModel(vp, eps, delta, rho)


def _load_field(spec, key: str, base_dir, vp: Model) -> np.ndarray:
    """``model.<key>``, a dimensionless field of :data:`_FIELDS` (epsilon, delta: may be 0 or negative; q: may be
    .inf) on vp's grid (nz, nx): a number (constant),
    ``{kind: layered, values: [...], interfaces: [...]}`` (depths in m, on vp's grid; a node on an interface belongs to
    the layer below, as the velocity generator) or a file kind (npy, hdf5, raw, segy: spacing and origin default to
    vp's; the grid must be vp's). ModelError naming ``model.<key>.<field>``."""
    k, (what, example, infinite) = f"model.{key}", _FIELDS[key]

    def number(x, where, want):
        return math.inf if infinite and isinstance(x, float) and x == math.inf else _real(x, where, want)

    if not isinstance(spec, dict):
        return np.full(vp.shape, number(spec, k, f"{what}, e.g. {example}, or a spec {{kind: layered | npy | hdf5 | raw | segy, ...}}"))
    kind = spec.get("kind")
    if kind not in _FIELD_KEYS:
        raise ModelError(f"{k}.kind: {_short(kind)} is not one of {', '.join(_FIELD_KEYS)} (a constant {key} is a number: "
                         f"{key}: {example}); {key} is dimensionless, so the velocity generators do not apply")
    allowed = {"kind", "name"} | _FIELD_KEYS[kind]
    unknown = sorted(set(spec) - allowed, key=str)
    if unknown:
        why = {"units": " (it is dimensionless)", "crop": " (give it on vp's final grid)", "smoothing": " (give it smoothed)",
               "shape": " (it takes vp's grid)"}.get(unknown[0], "")
        raise ModelError(f"{k}.{unknown[0]}: {_short(spec[unknown[0]])} is not a key of a {kind!r} {key}{why}; use only "
                         f"{', '.join(sorted(allowed))}")
    if kind == "layered":
        values = _require(spec, "values", f"the layers' {key} values, top to bottom")
        if not isinstance(values, (list, tuple)) or not values:
            raise ModelError(f"{k}.values: {_short(values)} is not a non-empty list; give the layers' {key}, top to bottom")
        t = np.array([number(x, f"{k}.values[{i}]", f"a number: {what}") for i, x in enumerate(values)])
        interfaces = _require(spec, "interfaces", "the interface depths in m, top to bottom")
        try:  # the generator's layers (validation, the node-on-an-interface rule) with the layer numbers 1, 2, ...
            layer = generators.layered(vp.shape, vp.spacing, list(range(1, len(t) + 1)), interfaces, vp.origin).values
        except ModelError as e:
            raise ModelError(f"{k}.{e}".replace("velocities", "values")) from None
        return t[layer.astype(int) - 1]
    grid = {"spacing": list(vp.spacing), "origin": list(vp.origin)}
    spec = {**{g: v for g, v in grid.items() if g not in spec and not (g == "spacing" and "spacing_dataset" in spec)}, **spec}
    try:
        values, spacing, path = _read_grid(kind, spec, base_dir)
        origin = per_axis(spec["origin"], values.ndim, "model.origin")
    except ModelError as e:
        raise ModelError(f"{k}{str(e)[5:]}") from None
    bad = ~(np.isfinite(values) | (infinite & (values == math.inf)))
    if bad.any():
        i = tuple(int(j) for j in np.argwhere(bad)[0])
        raise ModelError(f"{k}.path: {path.name} holds {int(bad.sum())} non-finite values (the first, {values[i]}, at index "
                         f"{i}); give finite {key} values{' (or +inf)' if infinite else ''}")
    if values.shape != vp.shape or not np.allclose(spacing, vp.spacing) or not np.allclose(origin, vp.origin):
        raise ModelError(f"{k}.path: {path.name} holds a grid of shape {list(values.shape)}, spacing {list(spacing)} m, "
                         f"origin {list(origin)} m, not model.vp's (shape {list(vp.shape)}, spacing {list(vp.spacing)} m, "
                         f"origin {list(vp.origin)} m); give {key} on vp's grid (axis order z, x; axes: xz for a stored "
                         f"(x, z) array)")
    return values


# ----------------------------------------------------------------------------------- visco-acoustic models

VISCOACOUSTIC_KEYS = ("vp", "q", "rho", "q_band", "f_ref", "mechanisms")


@dataclass(frozen=True, eq=False)
class ViscoacousticModel(_OnVpGrid):
    """A 2D visco-acoustic model for adseismic.solve.viscoacoustic (docs/viscoacoustic.md): ``vp`` the phase velocity
    (m/s) at ``f_ref`` and ``rho`` (kg/m^3), :class:`Model` objects on one grid (shape (nz, nx), axis order (z, x)),
    ``q`` the quality factor (dimensionless, > 0, inf: lossless) as a read-only float64 array (nz, nx) on that grid;
    ``q_band`` (f_min, f_max) Hz over which Q is flat, ``f_ref`` Hz and ``mechanisms`` (standard linear solids): None
    for the solver's defaults (band and f_ref from the wavelet's dominant frequency, 3 mechanisms), resolved by the
    planner (adseismic.scene.attenuation_check). Model-like as :class:`ElasticModel`: ``values``, ``vmin``, ``vmax``
    are vp's."""

    vp: Model
    q: np.ndarray
    rho: Model
    q_band: tuple | None = None
    f_ref: float | None = None
    mechanisms: int | None = None

    physics = "viscoacoustic"

    def __post_init__(self):
        if self.rho.shape != self.vp.shape or self.rho.spacing != self.vp.spacing or self.rho.origin != self.vp.origin:
            raise ModelError(f"model.rho: its grid (shape {list(self.rho.shape)}, spacing {list(self.rho.spacing)} m) differs "
                             f"from model.vp's (shape {list(self.vp.shape)}, spacing {list(self.vp.spacing)} m); give both on one grid")
        q = np.array(self.q, dtype=np.float64)
        if q.shape != self.vp.shape:
            raise ModelError(f"model.q: shape {list(q.shape)} differs from model.vp's {list(self.vp.shape)} (z, x); give q on "
                             f"vp's grid")
        bad = ~(q > 0)  # NaN too
        if bad.any():
            i = tuple(int(j) for j in np.argwhere(bad)[0])
            z, x = (o + j * h for o, j, h in zip(self.vp.origin, i, self.vp.spacing))
            raise ModelError(f"model.q: {q[i]} at z = {z:g} m, x = {x:g} m (index {i}; {int(bad.sum())} such values); Q must be "
                             f"> 0 (30 is a lossy sediment, 100-1000 rock; .inf: lossless): give positive quality factors")
        q.setflags(write=False)
        object.__setattr__(self, "q", q)

    vmin = property(lambda self: self.vp.vmin)
    vmax = property(lambda self: self.vp.vmax)

    def materials(self) -> dict:
        """{vp, q, rho}: float64 arrays (nz, nx) as forward_viscoacoustic takes them (m/s, 1, kg/m^3)."""
        return {"vp": np.asarray(self.vp.values, float), "q": np.asarray(self.q, float), "rho": np.asarray(self.rho.values, float)}

    def resample(self, spacing: float, origin: tuple, shape: tuple) -> ViscoacousticModel:
        """The model on the regular grid of :meth:`Model.resample` (spacing m, origin m, shape nodes): vp by its
        slowness, rho by its buoyancy (as ElasticModel), q by 1 / Q (the attenuation, 0 where lossless) linearly."""
        with np.errstate(divide="ignore"):
            q = 1.0 / _resample_linear(self.vp, 1.0 / self.q, spacing, origin, shape)
        return replace(self, vp=self.vp.resample(spacing, origin, shape), q=q, rho=self.rho.resample(spacing, origin, shape))


def _load_viscoacoustic(spec, base_dir) -> ViscoacousticModel:
    """``model: {vp, q, rho, q_band, f_ref, mechanisms}`` of physics viscoacoustic: vp a model spec (m/s), q a number
    or a field (:func:`_load_field`; .inf lossless), rho a model spec (kg/m^3), ``{gardner: true}`` or left out
    (WATER_DENSITY); optional q_band [f_min, f_max] Hz, f_ref Hz, mechanisms (an integer >= 1)."""
    if not (isinstance(spec, dict) and set(spec) & set(VISCOACOUSTIC_KEYS)):
        raise ModelError(f"model: {_short(spec)} is one velocity model, but physics viscoacoustic needs {{vp, q}} (and "
                         f"optionally rho): write model: {{vp: {{kind: ...}}, q: 50}} (vp in m/s, the quality factor Q "
                         f"dimensionless), or set physics: acoustic")
    unknown = sorted(set(spec) - set(VISCOACOUSTIC_KEYS), key=str)
    if unknown:
        raise ModelError(f"model.{unknown[0]}: unknown key of a viscoacoustic model; allowed: {', '.join(VISCOACOUSTIC_KEYS)} "
                         f"(vp, rho model specs; q a number or a field spec; q_band [f_min, f_max] Hz, f_ref Hz, mechanisms)")
    for k in ("vp", "q"):
        if spec.get(k) is None:
            raise ModelError(f"model.{k}: missing; a physics viscoacoustic model needs vp (m/s) and q (the quality factor: a "
                             f"number, .inf for lossless, or {{kind: layered | npy | hdf5 | raw | segy, ...}}) and optionally "
                             f"rho (kg/m^3, {{gardner: true}}, default {WATER_DENSITY:g})")
    band = spec.get("q_band")
    if band is not None:
        if not isinstance(band, (list, tuple)) or len(band) != 2:
            raise ModelError(f"model.q_band: {_short(band)} is not [f_min, f_max]; give the band (Hz) over which Q is flat, "
                             f"e.g. [3, 30], or leave it out (the wavelet's dominant frequency / 3 .. x 2.5)")
        band = tuple(_real(f, f"model.q_band[{i}]", "a frequency in Hz") for i, f in enumerate(band))
        if not 0 < band[0] < band[1]:
            raise ModelError(f"model.q_band: {list(band)} Hz is not 0 < f_min < f_max; give the band as [f_min, f_max] Hz")
    f_ref = spec.get("f_ref")
    if f_ref is not None and not (f_ref := _real(f_ref, "model.f_ref", "a frequency in Hz")) > 0:
        raise ModelError(f"model.f_ref: {f_ref:g} Hz is not > 0; give the frequency (Hz) at which vp is the phase velocity, "
                         f"or leave it out (the wavelet's dominant frequency)")
    n = spec.get("mechanisms")
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise ModelError(f"model.mechanisms: {_short(n)} is not an integer >= 1; give the number of standard linear solids "
                         f"(3 keeps Q within 5% of its target over a band of a factor 10; 5 over two decades)")
    base_dir = pathlib.Path.cwd() if base_dir is None else base_dir
    vp = _load_part(spec["vp"], "vp", base_dir, None)
    if vp.ndim != 2:
        raise ModelError(f"model.vp: a 3D model (shape {list(vp.shape)}) with physics viscoacoustic; the visco-acoustic "
                         f"solver is 2D (3D is not built yet): give a 2D model [nz, nx], or use physics: acoustic in 3D")
    q = _load_field(spec["q"], "q", base_dir, vp)
    rho = (replace(vp, values=np.full(vp.shape, WATER_DENSITY), name="water density") if spec.get("rho") is None
           else _load_density(spec["rho"], base_dir, vp))
    return ViscoacousticModel(vp, q, rho, band, f_ref, n)
