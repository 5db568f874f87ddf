"""The declarative config schema: one pydantic model per workflow (forward, fwi, locate), every key with its type,
unit, default and a one-line meaning.

Three uses:

- validation of the raw YAML sections (unknown keys, types, ranges): :func:`validate_section` turns pydantic's
  ValidationError into a :class:`ConfigError` in the project's style, ``<dotted.key>: <value> ...; <fix>``
  (the fix is the check's own text or the key's description); the parse functions in forward.py, fwi.py and
  locate.py then build the dataclasses and do what a schema cannot say (cross-field physics checks, files,
  checks against the model's axes and extent);
- the JSON Schema that YAML editors use for completion (``adseismic schema fwi``, :func:`json_schema`);
- docs/config.md (docs/gen_config.py) and the commented templates of ``adseismic init`` (:func:`template`).

The ``model``/``true_model`` spec and ``parallel`` are described here for documentation and editors; they are
validated by ``adseismic.data.models.load_model`` and ``adseismic.config.parallel.parse_parallel``. The geometry's
points depend on the model's dimension: the schema types them, ``forward._parse_geometry`` checks them.

Number fields accept numeric strings (PyYAML reads ``1e-3`` as text), but not true/false. Imports no workflow.
"""
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError
from pydantic_core import PydanticCustomError

from adseismic.config.common import ConfigError, _boolean, _integer, _number, _positive, _short

__all__ = ["SCHEMAS", "FWISchema", "ForwardSchema", "ImageSchema", "LocateSchema", "json_schema", "template", "validate_section"]


# ------------------------------------------------------------------------------ value checks

def _fail(msg: str, index: int | None = None):
    """Refuse a value: ``msg`` is the text after ``<key>: `` (``<key>[index]: `` for an element of a list)."""
    raise PydanticCustomError("adseismic", "{m}", {"m": msg} if index is None else {"m": msg, "index": index})


def _via(fn, value, *args):
    """The common.py validator ``fn`` run without a key: its message body (after ``<key>: ``) on failure."""
    try:
        return fn(value, "", *args)
    except ConfigError as e:
        _fail(str(e).split(": ", 1)[1])


def _opt(check):
    """None passes (the key is 'not given': the default applies), anything else goes through ``check``."""
    return BeforeValidator(lambda v: None if v is None else check(v))


def Num(unit: str = ""):
    return _opt(lambda v: _via(_number, v, unit))


def Pos(unit: str = ""):
    return _opt(lambda v: _via(_positive, v, unit))


def NonNeg(fix: str, unit: str = ""):
    def check(v):
        x = _via(_number, v, unit)
        if x < 0:
            _fail(f"{_short(v)} is negative; {fix}")
        return x
    return _opt(check)


def Between(lo: float, hi: float, fix: str, hi_closed: bool = False, lo_closed: bool = False):
    def check(v):
        x = _via(_number, v)
        ok = (lo <= x if lo_closed else lo < x) and (x <= hi if hi_closed else x < hi)
        if not ok:
            _fail(f"{_short(v)} is not in {'[' if lo_closed else '('}{lo:g}, {hi:g}{']' if hi_closed else ')'}; {fix}")
        return x
    return _opt(check)


def Int(minimum: int | None = None, fix: str = ""):
    def check(v):
        n = _via(_integer, v)
        if minimum is not None and n < minimum:
            _fail(f"{n} < {minimum}; {fix}")
        return n
    return _opt(check)


Bool = _opt(lambda v: _via(_boolean, v))


def OneOf(*choices, fix: str = "pick one of them"):
    def check(v):
        if isinstance(v, bool) or v not in choices:
            _fail(f"{_short(v)} is not one of {', '.join(map(str, choices))}; {fix}")
        return v
    return _opt(check)


def _order(v):
    try:
        n = _integer(v, "")
    except ConfigError:
        n = None
    if n not in (2, 4, 8):
        _fail(f"{_short(v)} is not one of 2, 4, 8; set the spatial finite-difference order (4 is a good default)")
    return n


def _device(v):
    import re

    if not (isinstance(v, str) and re.match(r"^cpu$|^cuda(:\d+)?$", v)):
        _fail(f"{_short(v)} is not a device; write cpu, cuda or cuda:N (N = GPU index)")
    return v


def _pml_width(v):
    n = _via(_integer, v)
    if n < 4:
        _fail(f"{_short(v)} cells is below 4, the half-width of the source/receiver operator; use >= 4 (10-20 absorbs "
              f"well) or null")
    return n


def _text(what: str):
    def check(v):
        if not isinstance(v, str):
            _fail(f"{_short(v)} is not {what}")
        return v
    return _opt(check)


def _pair(unit: str, allow_null=False, increasing=True, what="[start, end]"):
    def check(v):
        if not isinstance(v, list) or len(v) != 2:
            _fail(f"{_short(v)} is not {what} in {unit}")
        out = []
        for i, x in enumerate(v):
            if allow_null and x is None:
                out.append(None)
                continue
            try:
                out.append(_number(x, "", unit))
            except ConfigError as e:
                _fail(str(e).split(": ", 1)[1], i)
        if increasing and None not in out and not out[0] < out[1]:
            _fail(f"[{out[0]:g}, {out[1]:g}] {unit} is not increasing; give {what} with start < end")
        return out
    return _opt(check)


def _meta(unit: str = "", **extra) -> dict:
    return {"unit": unit, **extra} if unit else dict(extra)


def F(default, description: str, unit: str = "", **extra):
    """A field: its default, one-line meaning and unit (in the JSON Schema as ``unit``)."""
    return Field(default, description=description, json_schema_extra=_meta(unit, **extra) or None)


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


# ------------------------------------------------------------------------------ forward sections

class ModelSpec(_Section):
    """The velocity model: generated (constant, layered, gaussian_anomaly) or read from a file (raw, npy, hdf5, segy).
    Checked by adseismic.data.models.load_model."""

    kind: Literal["constant", "layered", "gaussian_anomaly", "raw", "npy", "hdf5", "segy"] = F(
        ..., "constant, layered, gaussian_anomaly (generated) or raw, npy, hdf5, segy (read from a file)")
    shape: list[int] | None = F(None, "generators: nodes per axis [nz, nx] or [nz, ny, nx]; raw: the stored array "
                                         "shape, slowest axis first")
    spacing: float | list[float] | None = F(None, "grid spacing, one number or one per axis (z, [y,] x); "
                                                           "optional for hdf5 with spacing_dataset", "m")
    origin: list[float] | None = F(None, "world coordinates of node 0, (z, [y,] x); default 0", "m")
    name: str | None = F(None, "a name for logs and plots")
    velocity: float | None = F(None, "constant: the velocity", "m/s")
    velocities: list[float] | None = F(None, "layered: layer velocities, top to bottom", "m/s")
    interfaces: list[float] | None = F(None, "layered: depths of the interfaces between the layers", "m")
    background: float | None = F(None, "gaussian_anomaly: the background velocity", "m/s")
    perturbation: float | None = F(None, "gaussian_anomaly: the anomaly's peak (may be negative)", "m/s")
    center: list[float] | None = F(None, "gaussian_anomaly: the anomaly's centre (z, [y,] x)", "m")
    radius: float | None = F(None, "gaussian_anomaly: the anomaly's standard deviation", "m")
    path: str | None = F(None, "files: the model file, relative to the config's folder")
    units: Literal["m/s", "km/s", "s/m", "s2/km2", "s2/m2"] | None = F(None, "files: stored units (default m/s)")
    axes: str | None = F(None, "files: stored axis order, slowest first, e.g. xz (default zx/zyx; xz for SEG-Y)")
    dtype: str | None = F(None, "raw: sample type (default float32)")
    endian: Literal["little", "big"] | None = F(None, "raw: byte order (default little)")
    dataset: str | None = F(None, "hdf5: the dataset holding the model")
    spacing_dataset: str | None = F(None, "hdf5: a dataset holding the spacing (stored axis order)")
    crop: dict[str, list[float]] | None = F(None, "a window of the model, {x: [min, max], z: [min, max]} in world "
                                                     "metres", "m")
    smoothing: float | None = F(None, "Gaussian smoothing of the slowness, standard deviation", "m")


class VsRatio(_Section):
    """The shear speed from the P speed: vs = vp / vp_ratio."""

    vp_ratio: Annotated[float, Pos()] = F(..., "vp / vs, >= sqrt(2) = 1.414 (Lame lambda >= 0); 1.732 is a Poisson "
                                                 "solid")


class Gardner(_Section):
    """The density from the P speed by Gardner's rule, rho = 310 vp^0.25 (kg/m^3, vp in m/s; Gardner et al. 1974)."""

    gardner: Annotated[bool, Bool] = F(..., "true: rho = 310 vp^0.25 kg/m^3 (vp in m/s)")


class ElasticModelSpec(_Section):
    """physics elastic: the P speed, the S speed and the density, each a model spec (kinds as for an acoustic model;
    the key velocity / velocities / background ... holds the values: m/s for vp and vs, kg/m^3 for rho) on any grid
    (vs and rho are resampled onto vp's). Checked by adseismic.data.models.load_physics_model."""

    vp: ModelSpec = F(..., "the P-wave speed (m/s)", "m/s")
    vs: ModelSpec | VsRatio = F(..., "the S-wave speed (m/s), > 0 everywhere and <= vp / sqrt(2); or {vp_ratio: R}",
                                "m/s")
    rho: ModelSpec | Gardner = F(..., "the density (kg/m^3), > 0; or {gardner: true}", "kg/m^3")


class AcousticVDModelSpec(_Section):
    """physics acoustic_vd: the P speed and the density (a fluid, vs = 0), each a model spec (kinds as for an acoustic
    model; the key velocity / velocities / background ... holds the values: m/s for vp, kg/m^3 for rho) on any grid
    (rho is resampled onto vp's). Checked by adseismic.data.models.load_physics_model."""

    vp: ModelSpec = F(..., "the P-wave speed (m/s)", "m/s")
    rho: ModelSpec | Gardner = F(..., "the density (kg/m^3), >= 100; or {gardner: true}", "kg/m^3")


class FieldSpec(_Section):
    """A dimensionless field on vp's grid (physics vti: Thomsen's epsilon or delta, may be 0 or negative;
    viscoacoustic: the quality factor Q, > 0, .inf lossless): horizontal layers, or read from a file (spacing and origin
    default to vp's). A constant is written as a number. Checked by adseismic.data.models.load_physics_model."""

    kind: Literal["layered", "raw", "npy", "hdf5", "segy"] = F(..., "layered (generated on vp's grid) or raw, npy, hdf5, "
                                                                  "segy (read from a file on vp's grid)")
    name: str | None = F(None, "a name for logs and plots")
    values: list[float] | None = F(None, "layered: the layers' values, top to bottom (dimensionless)")
    interfaces: list[float] | None = F(None, "layered: depths of the interfaces between the layers", "m")
    path: str | None = F(None, "files: the file, relative to the config's folder")
    axes: str | None = F(None, "files: stored axis order, slowest first (default zx; xz for SEG-Y)")
    spacing: float | list[float] | None = F(None, "files: grid spacing (default vp's)", "m")
    origin: list[float] | None = F(None, "files: world coordinates of node 0 (default vp's)", "m")
    shape: list[int] | None = F(None, "raw: the stored array shape, slowest axis first")
    dtype: str | None = F(None, "raw: sample type (default float32)")
    endian: Literal["little", "big"] | None = F(None, "raw: byte order (default little)")
    dataset: str | None = F(None, "hdf5: the dataset holding the field")
    spacing_dataset: str | None = F(None, "hdf5: a dataset holding the spacing (stored axis order)")


class VTIModelSpec(_Section):
    """physics vti (2D pseudo-acoustic VTI, docs/vti.md): the vertical P speed, Thomsen's epsilon and delta and the
    density. epsilon >= delta > -0.5 everywhere (refused otherwise). Checked by adseismic.data.models.load_physics_model."""

    vp: ModelSpec = F(..., "the vertical P-wave speed (m/s)", "m/s")
    epsilon: float | FieldSpec = F(..., "Thomsen's epsilon (dimensionless, >= delta): a number or a field spec")
    delta: float | FieldSpec = F(..., "Thomsen's delta (dimensionless, > -0.5): a number or a field spec")
    rho: ModelSpec | Gardner | None = F(None, "the density (kg/m^3), >= 100; or {gardner: true}; null: 1000 (water)",
                                        "kg/m^3")


class ViscoacousticModelSpec(_Section):
    """physics viscoacoustic (2D visco-acoustic, constant Q over a band, docs/viscoacoustic.md): the P speed, the
    quality factor and the density, and the band of the relaxation mechanisms. Checked by
    adseismic.data.models.load_physics_model."""

    vp: ModelSpec = F(..., "the P-wave phase velocity at f_ref (m/s)", "m/s")
    q: float | FieldSpec = F(..., "the quality factor Q (dimensionless, > 0; .inf: lossless): a number or a field spec")
    rho: ModelSpec | Gardner | None = F(None, "the density (kg/m^3), >= 100; or {gardner: true}; null: 1000 (water)",
                                        "kg/m^3")
    q_band: list[float] | None = F(None, "[f_min, f_max]: the band over which Q is flat; null: the wavelet's dominant "
                                         "frequency / 3 .. x 2.5", "Hz")
    f_ref: float | None = F(None, "the frequency at which vp is the phase velocity; null: the wavelet's dominant "
                                  "frequency", "Hz")
    mechanisms: int | None = F(None, "standard linear solids fitted to the flat Q; null: 3")


PHYSICS = ("acoustic", "elastic", "acoustic_vd", "vti", "viscoacoustic")  # adseismic.data.models.PHYSICS (tests/test_elastic_config.py keeps them equal)


class Point(_Section):
    """A point in world metres: x, z in 2D; x, y, z in 3D (exactly the model's axes)."""

    x: Annotated[float, Num("metres")] = F(..., "horizontal coordinate", "m")
    y: Annotated[float | None, Num("metres")] = F(None, "second horizontal coordinate (3D models only)", "m")
    z: Annotated[float, Num("metres")] = F(..., "depth, positive down", "m")


class Line(_Section):
    """count points evenly spaced from start to end inclusive."""

    start: Point = F(..., "the first point", "m")
    end: Point = F(..., "the last point", "m")
    count: int = F(..., "number of points, >= 1 (1 gives start)", minimum=1)


class Spread(_Section):
    """Points from any of points, line and lines, concatenated in that order."""

    points: list[Point] | None = F(None, "a list of points, e.g. [{x: 500, z: 20}, {x: 1500, z: 20}]", "m")
    line: Line | None = F(None, "{start, end, count}: evenly spaced points")
    lines: list[Line] | None = F(None, "several lines")


COMPONENTS = ("vx", "vy", "vz", "pressure")  # elastic receiver components (solve.elastic's and, vy, solve.elastic3d's)


class Das(_Section):
    """physics elastic: distributed acoustic sensing; each receiver point is the centre of a gauge recording the
    strain rate along the fibre (adseismic.solve.receivers.DasOperator)."""

    gauge_length: Annotated[float, Pos("metres")] = F(..., "the gauge length: the strain rate is the difference of "
                                                            "the particle velocity between the gauge's ends / it", "m",
                                                       exclusiveMinimum=0)
    direction: Any = F(0.0, "the fibre's direction: [dz, dx] (normalised) or an angle in degrees from the +x axis "
                            "towards +z (0: horizontal, 90: vertical well)", "deg")


class Receivers(Spread):
    """One receiver spread shared by all shots (points, line, lines as for sources); physics elastic adds what it
    records."""

    components: list[Literal[COMPONENTS]] | None = F(
        None, "physics elastic: any of vx, vz (m/s), pressure (Pa), and vy (m/s) in 3D; null: all of them, or none when "
              "das is given (2D only)")
    das: Das | None = F(None, "physics elastic: record DAS strain rate (1/s) along a fibre at the points")


class Geometry(_Section):
    """Sources and receivers in world metres; every point must lie inside the model."""

    sources: Spread = F(..., "every point is one shot (one source per shot)")
    receivers: Receivers = F(..., "one receiver spread shared by all shots")


SOURCE_TYPES = ("force", "moment", "explosive")  # adseismic.solve.elastic.SOURCE_TYPES


class ElasticSource(_Section):
    """physics elastic: the source mechanism; the amplitude at time t is components x the wavelet s(t)."""

    type: Annotated[Literal[SOURCE_TYPES] | None, OneOf(*SOURCE_TYPES)] = F(
        "explosive", "force (a line force), moment (a moment tensor) or explosive (isotropic moment tensor)")
    components: Any = F(None, "force: [f_z, f_x] in N/m (3D: [f_z, f_y, f_x] in N); moment: [m_xx, m_zz, m_xz] in N m/m "
                              "(3D: [m_zz, m_yy, m_xx, m_yz, m_xz, m_xy] in N m); explosive: the moment M0 in N m/m "
                              "(3D: N m) (default 1)")


class Wavelet(_Section):
    """The source time function: make_wavelet(kind, nt, dt, **params) once the planner has chosen nt and dt."""

    kind: Annotated[Literal["ricker", "gaussian_derivative", "array"], OneOf(
        "ricker", "gaussian_derivative", "array", fix="set the source time function")] = F(
        ..., "ricker, gaussian_derivative or array (samples from a .npy file)")
    peak_frequency: Annotated[float | None, Pos("Hz")] = F(
        None, "ricker, gaussian_derivative: the peak of the amplitude spectrum, > 0", "Hz", exclusiveMinimum=0)
    delay: Annotated[float | None, NonNeg("give the time of the wavelet's centre in seconds (>= 0) or leave it out",
                                             "seconds")] = F(
        None, "ricker, gaussian_derivative: time of the wavelet's centre (default 1.5 / peak_frequency for a Ricker, "
              "1 / peak_frequency for the Gaussian derivative), at most 100 periods", "s", minimum=0)
    file: Any | None = F(None, "array: a .npy file with the samples (1D, starting at t = 0), relative to the config")
    dt_in: Annotated[float | None, Pos("seconds")] = F(
        None, "array: the file's sample interval; resampled band-limited to the simulation's dt", "s", exclusiveMinimum=0)


WAVELET_KEYS = {"ricker": ("kind", "peak_frequency", "delay"), "gaussian_derivative": ("kind", "peak_frequency", "delay"),
                "array": ("kind", "file", "dt_in")}


class Simulation(_Section):
    """Numerical choices and optional pins; null lets the planner choose (adseismic plan prints why)."""

    order: Annotated[Literal[2, 4, 8] | None, _opt(_order)] = F(
        4, "spatial order of the finite-difference Laplacian: 2, 4 or 8")
    accuracy: Annotated[float | None, Between(0, 0.5, "give the target relative group-velocity error, e.g. 0.01 "
                                                         "for 1%")] = F(
        0.01, "target maximum relative group-velocity error at the wavelet's f_max (its -20 dB upper band edge), "
              "in (0, 0.5)", exclusiveMinimum=0, exclusiveMaximum=0.5)
    free_surface: Annotated[bool | None, Bool] = F(
        False, "pressure-release (u = 0) top boundary at the grid's first row instead of an absorbing layer")
    device: Annotated[str | None, _opt(_device)] = F("cpu", "cpu, cuda or cuda:N", pattern=r"^cpu$|^cuda(:\d+)?$")
    precision: Annotated[Literal["float32", "float64"] | None, OneOf("float32", "float64")] = F(
        "float32", "float32 or float64 (locate: default float64)")
    cfl_safety: Annotated[float | None, Between(0, 1, "give the fraction of the exact stability limit to use, "
                                                         "e.g. 0.9", hi_closed=True)] = F(
        0.9, "dt = cfl_safety x the exact stability limit unless dt is pinned; in (0, 1]",
        exclusiveMinimum=0, maximum=1)
    dx: Annotated[float | None, Pos("metres")] = F(None, "grid spacing, > 0; null: planned", "m", exclusiveMinimum=0)
    dt: Annotated[float | None, Pos("seconds")] = F(
        None, "time step, > 0; null: planned; refused (with the limit) if unstable", "s", exclusiveMinimum=0)
    duration: Annotated[float | None, Pos("seconds")] = F(
        None, "record length, > 0; null: the longest straight-ray source-receiver travel time + the wavelet's duration",
        "s", exclusiveMinimum=0)
    pml_width: Annotated[int | None, _opt(_pml_width)] = F(
        None, "absorbing-layer width in cells, integer >= 4; null: 20", "cells", minimum=4)
    pml_reflection: Annotated[float | None, Between(0, 1, "give the target reflection coefficient, e.g. 1e-3, "
                                                             "or null")] = F(
        None, "target reflection coefficient of the absorbing layer, in (0, 1); null: 1e-3 (1e-5 at order 8)",
        exclusiveMinimum=0, exclusiveMaximum=1)
    margin: Annotated[float | None, NonNeg("give the aperture margin around sources and receivers in metres (>= 0) "
                                              "or null", "metres")] = F(
        None, "aperture margin around the sources and receivers, >= 0 (domain auto only); null: v_max T / 2", "m",
        minimum=0)
    domain: Annotated[Literal["auto", "model"] | None, OneOf("auto", "model")] = F(
        "auto", "auto: the sources/receivers box plus margin, cut to the model; model: the whole model")
    memory_budget_gb: Annotated[float | None, Pos("GB")] = F(
        None, "memory the run may use; the planner refuses a run estimated above it (null: the device's free memory)",
        "GB", exclusiveMinimum=0)
    force: Annotated[bool | None, Bool] = F(
        False, "run even when the memory estimate is above the budget / free memory (--force sets it)")


class Output(_Section):
    """What a forward run writes besides data.h5 and the figures."""

    snapshot_interval: Annotated[float | None, NonNeg("give seconds between snapshots, or 0 for none", "seconds")] = F(
        0.0, "seconds between stored wavefield snapshots (rounded to whole time steps); 0: none; more than 8 GiB "
             "of snapshots is refused", "s", minimum=0)


class ForwardSchema(_Section):
    """A forward simulation (adseismic forward): model, geometry, wavelet; optionally simulation and output."""

    physics: Annotated[Literal[PHYSICS] | None, OneOf(*PHYSICS)] = F(
        "acoustic", "acoustic (model: a velocity model), elastic (2D; model: {vp, vs, rho}), acoustic_vd (2D "
                    "or 3D acoustic with variable density; model: {vp, rho}), vti (2D "
                    "pseudo-acoustic VTI, forward only; model: {vp, epsilon, delta, rho}) or viscoacoustic (2D "
                    "constant-Q attenuation, forward only; model: {vp, q, rho})")
    model: ModelSpec | ElasticModelSpec | AcousticVDModelSpec | VTIModelSpec | ViscoacousticModelSpec = F(
        ..., "the velocity model (m/s); physics elastic: {vp, vs, rho}; acoustic_vd: {vp, rho}; vti: {vp, epsilon, "
             "delta, rho}; viscoacoustic: {vp, q, rho}")
    geometry: Geometry = F(..., "sources (one shot each) and receivers, world metres")
    wavelet: Wavelet = F(..., "the source time function")
    source: ElasticSource | None = F(None, "physics elastic: the source mechanism; null: explosive; acoustic_vd, vti, "
                                           "viscoacoustic: explosive only (M0 in N m/m)")
    simulation: Simulation | None = F(None, "numerical settings; null: all planned / defaults")
    output: Output | None = F(None, "extra outputs")


# ------------------------------------------------------------------------------ fwi sections

MISFIT_NAMES = ("l2", "correlation", "traveltime", "envelope")  # fwi.MISFIT_NAMES (a test keeps them equal)
OPTIMIZERS = ("lbfgs", "gd", "adam")
PRECONDITIONERS = ("none", "depth", "pseudo_hessian")


class Band(_Section):
    """A band-pass: fmin and/or fmax in Hz."""

    fmin: Annotated[float | None, Pos("Hz")] = F(None, "low corner; null: none", "Hz", exclusiveMinimum=0)
    fmax: Annotated[float | None, Pos("Hz")] = F(None, "high corner; null: none", "Hz", exclusiveMinimum=0)


def _band(v):
    if v is None or isinstance(v, dict):
        return v
    if isinstance(v, (int, float, str)) and not isinstance(v, bool):
        return {"fmax": _via(_positive, v, "Hz")}
    _fail(f"{_short(v)} is not a band; give fmax in Hz (e.g. 5), {{fmin: 2, fmax: 5}} or null (full band)")


def _nonempty_list(example: str):
    def check(v):
        if not isinstance(v, list) or not v:
            _fail(f"{_short(v)} is not a non-empty list; e.g. {example}")
        return v
    return _opt(check)


def _iterations(v):
    if isinstance(v, list):
        out = []
        for i, n in enumerate(v):
            try:
                out.append(_integer(n, ""))
            except ConfigError as e:
                _fail(str(e).split(": ", 1)[1], i)
    else:
        out = _via(_integer, v)
    if min(out if isinstance(out, list) else [out], default=1) < 1:
        _fail(f"{out} has a value < 1; give at least 1 iteration per band")
    return out


_NONNEG = "give 0 (off) or a positive value"
# each parameterisation's quantities: adseismic.inversion.model_space.PARAMETERIZATIONS (a test keeps them equal)
PARAMETERIZATION_QUANTITIES = {"vp-vs-rho": ("vp", "vs", "rho"), "lambda-mu-rho": ("lambda", "mu", "rho"),
                               "ip-rho": ("ip", "rho")}
PARAMETERIZATIONS = tuple(PARAMETERIZATION_QUANTITIES)
# physics viscoacoustic and vti invert their solver's own parameters (adseismic.inversion.model_space.PHYSICS_PARAMETERS)
OWN_QUANTITIES = {"viscoacoustic": ("vp", "q", "rho"), "vti": ("vp", "epsilon", "delta", "rho")}
INVERTED_QUANTITIES = ("vp", "vs", "rho", "lambda", "mu", "ip", "q", "epsilon", "delta")
_BOUND_UNITS = {"vp": "m/s", "vs": "m/s", "rho": "kg/m^3", "lambda": "Pa", "mu": "Pa", "ip": "kg/(m^2 s)", "q": "(dimensionless)",
                "epsilon": "(dimensionless)", "delta": "(dimensionless)"}


def _bounds(v):
    """inversion.bounds: [min, max] m/s, or {quantity: [min, max]} in the quantity's unit."""
    if not isinstance(v, dict):
        return _pair("m/s", what="[v_min, v_max]").func(v)
    out = {}
    for k, pair in v.items():
        if k not in _BOUND_UNITS:
            _fail(f"{_short(k)} is not an invertible quantity; bounds are keyed by {', '.join(_BOUND_UNITS)}")
        unit = _BOUND_UNITS[k]
        if not isinstance(pair, list) or len(pair) != 2:
            _fail(f"{k}: {_short(pair)} is not [min, max] in {unit}")
        lo, hi = (_via(_number, x, unit) for x in pair)
        if not lo < hi:
            _fail(f"{k}: [{lo:g}, {hi:g}] {unit} has min >= max; give [min, max] with min < max")
        out[k] = [lo, hi]
    return out


class Inversion(_Section):
    """Full-waveform inversion settings."""

    bands: Annotated[list[Annotated[Band | float | None, BeforeValidator(_band)]] | None,
                     _nonempty_list("[3, 5, 8] (Hz, low to high)")] = F(
        [None], "pass bands, low to high: a number is a low-pass corner (Hz), {fmin, fmax} a band-pass, null the full "
                "band; each band starts from the previous one's result. The filter, a causal order-4 Butterworth, is "
                "applied to the source wavelet and the observed data alike", "Hz")
    misfit: Annotated[Literal[MISFIT_NAMES] | None, OneOf(*MISFIT_NAMES)] = F("l2", "the data misfit")
    optimizer: Annotated[Literal[OPTIMIZERS] | None, OneOf(*OPTIMIZERS)] = F(
        "lbfgs", "lbfgs (L-BFGS; with transform linear scipy's L-BFGS-B on the bounds), gd (steepest descent, strong-Wolfe line search), adam")
    iterations: Annotated[int | list[int] | None, _opt(_iterations)] = F(
        20, "iterations per band: one number, or a list with one per band", minimum=1)
    evaluations: Annotated[int | None, Int(1, "give at least 1 gradient evaluation per band")] = F(
        None, "cap on misfit + gradient evaluations per band; null: none", minimum=1)
    rel_decrease: Annotated[float | None, Pos()] = F(
        1e-4, "stop a band when an iteration lowers the misfit by less than this fraction", exclusiveMinimum=0)
    parameters: Annotated[list[Literal[INVERTED_QUANTITIES]] | None, _nonempty_list("[vp, vs]")] = F(
        None, "the inverted quantities, any of the parameterization's (vp, vs, rho or lambda, mu, rho or ip, rho; "
              "acoustic: vp; acoustic_vd: vp, rho or ip, rho) or the physics' (viscoacoustic: vp, q, rho; vti: vp, "
              "epsilon, delta, rho); the others stay at the start model; null: all of them (viscoacoustic, vti: vp alone, "
              "the others opt-in)")
    transform: Annotated[Literal["linear", "sigmoid"] | None, OneOf("linear", "sigmoid")] = F(
        "sigmoid", "how the optimiser's x gives each inverted cell: sigmoid (q = lo + (hi - lo) sigmoid(x) inside the "
                   "bounds, x free: Deepwave's FWI recipe; a cell near a bound, such as water near the lower velocity "
                   "bound, moves little; docs/fwi_physics.md) or linear (x = q / reference, the bounds a box "
                   "L-BFGS-B projects onto); pixels only")
    grid: Annotated[Literal["fixed", "per_band"] | None, OneOf("fixed", "per_band")] = F(
        None, "the simulation grid of each band: null (per_band where it applies, acoustic pixel models; else fixed), "
              "fixed (the plan's grid for the highest band, every band) or per_band (each low-passed band on the "
              "coarsest grid and longest time step that resolve it at simulation.accuracy, planned for 1.33 x its high "
              "corner: never finer than the plan's grid, dt a whole multiple of the plan's; the model moves between "
              "grids by slowness interpolation, the history and the result stay on the plan's grid; acoustic pixels "
              "only; docs/fwi.md measures it against fixed)")
    parameterization: Annotated[Literal[PARAMETERIZATIONS] | None, OneOf(*PARAMETERIZATIONS)] = F(
        "vp-vs-rho", "physics elastic: the quantities the optimiser moves, vp-vs-rho (m/s, m/s, kg/m^3) or "
                     "lambda-mu-rho (Lame moduli in Pa, kg/m^3); acoustic_vd: vp-vs-rho (vp and rho move, vs stays 0) "
                     "or ip-rho (impedance ip = rho vp in kg/(m^2 s), and rho); each is scaled by a fixed reference "
                     "(1000 m/s, 1000 kg/m^3, 1 GPa, 1e6 kg/(m^2 s)) so the optimiser sees O(1) numbers")
    bounds: Annotated[list[float] | dict[str, list[float]] | None, _opt(_bounds)] = F(
        None, "[v_min, v_max] (m/s, acoustic vp), or per inverted quantity {vp: [min, max], vs: ..., rho: ..., "
              "lambda: ..., mu: ..., q: ..., epsilon: ..., delta: ...} in its unit (m/s, kg/m^3, Pa; q, epsilon, delta "
              "dimensionless: q > 0, epsilon, delta > -0.5; a delta above epsilon is clamped to epsilon, the VTI "
              "solver's stability); the plan (dt, dx) is made for these ranges; null (or a quantity left out): the "
              "start model's range +-25%; q [5, 1000] widened to hold the start +-25%; epsilon, delta the start's "
              "range -0.1 / +0.2", "m/s, kg/m^3, Pa")
    offsets: Annotated[list[float] | None, _pair("m", what="[min, max]")] = F(
        None, "[min, max] source-receiver distance of the traces used (others muted); null: all", "m")
    time_window: Annotated[list[float] | None, _pair("s", what="[min, max]")] = F(
        None, "[start, end] of the samples used (cosine taper over 10% of the window at each end); null: all", "s")
    water_depth: Annotated[float | None, NonNeg(_NONNEG, "m")] = F(
        0.0, "gradient mask: no update above this depth (cosine taper)", "m", minimum=0)
    source_radius: Annotated[float | None, NonNeg(_NONNEG, "m")] = F(
        0.0, "gradient mask: no update within this distance of a source (cosine taper)", "m", minimum=0)
    smoothing: Annotated[float | None, NonNeg(_NONNEG, "m")] = F(
        0.0, "Gaussian smoothing of the gradient, standard deviation", "m", minimum=0)
    preconditioning: Annotated[Literal[PRECONDITIONERS] | None, OneOf(*PRECONDITIONERS)] = F(
        None, "none, depth (the gradient x z / z_max: it falls with depth under a surface acquisition) or "
              "pseudo_hessian (divide by the normalised illumination, 1% water level); null: depth for acoustic pixels "
              "under a surface acquisition (every source and receiver in the model's top tenth), else none")
    tikhonov: Annotated[float | None, NonNeg(_NONNEG)] = F(
        0.0, "Tikhonov weight on m = v / 1000 m/s (the misfit is normalised by its value at each band's start)",
        minimum=0)
    tv: Annotated[float | None, NonNeg(_NONNEG)] = F(0.0, "total-variation weight on m = v / 1000 m/s", minimum=0)
    wavelet_estimation: Annotated[bool | None, Bool] = F(
        False, "least-squares wavelet estimate per band from the start model's synthetics")
    shots_per_batch: Annotated[int | None, Int(1, "give at least 1 shot per batch")] = F(
        None, "shots simulated together (memory); null: all, or one batch per worker with a parallel section", minimum=1)
    memory_budget_gb: Annotated[float | None, Pos("GB")] = F(
        None, "memory for checkpoints + one taped segment per gradient (trades recomputation for memory; null: the minimum, "
              "~sqrt(nt) segments; one that holds every step skips the recomputation)", "GB", exclusiveMinimum=0)
    step: Annotated[float | None, Pos()] = F(
        1.0, "gd: first trial step, in units of v / 1000 m/s", exclusiveMinimum=0)
    lr: Annotated[float | None, Pos()] = F(0.01, "adam: learning rate, in units of v / 1000 m/s", exclusiveMinimum=0)


class Observed(_Section):
    """Observed data files (instead of true_model); checked in fwi.parse_fwi_config."""

    kind: Literal["hdf5", "segy", "su", "mseed", "sac", "asdf"] = F(
        ..., "hdf5 (an adseismic forward data.h5), segy, su (shot gathers), mseed, sac (station traces) or asdf")
    path: str | None = F(None, "hdf5, segy, su: the data file, relative to the config")
    paths: list[str] | None = F(None, "mseed, sac: one file or glob per shot, in the order of geometry.sources")
    coordinate_scale: float | None = F(None, "segy, su: metres per header coordinate unit", "m", exclusiveMinimum=0)
    depth_convention: Literal["auto", "elevation", "depth"] | None = F(
        None, "segy, su: how the headers store depth: elevation (SEG-Y standard), depth, or auto (default)")
    inventory: str | None = F(None, "mseed: the StationXML file with the station coordinates")
    reference: list[float] | dict[str, float] | None = F(
        None, "mseed, sac: the local frame's origin, [latitude, longitude] or {latitude, longitude, datum, azimuth}",
        "deg")
    component: str | None = F(None, "mseed, sac: the component letter, e.g. Z")
    shot_times: list[str] | None = F(None, "mseed, sac: UTC time of each shot (default: each shot's first sample)")


class Parallel(_Section):
    """fwi, forward: the shots of every evaluation (fwi) or of the run (forward) spread over workers: Dask worker
    processes (engine dask; pip install "adseismic[dask]"), here or on a cluster, or one thread and one Warp stream
    per device in this process (engine threads, e.g. every GPU of this host); the results are summed or gathered in
    shot order, independent of the number of workers (docs/parallel.md). Checked by
    adseismic.config.parallel.parse_parallel. No section: one process, one device."""

    engine: Literal["dask", "threads"] | None = F(
        "dask", "dask (worker processes: a LocalCluster or a running scheduler) or threads (one thread per device in "
                "this process, no Dask; takes no scheduler and no workers)")
    scheduler: str | None = F("local", "dask: local (a LocalCluster on this host) or a running scheduler's address, "
                                          "tcp://host:8786")
    devices: Literal["all"] | list[str] | None = F(
        None, "one worker per entry (cpu, cuda, cuda:N) or all (every GPU, else one CPU worker per core); at most one "
              "per shot; null: all for a CUDA simulation.device, else [cpu]")
    workers: int | None = F(None, "dask: the number of workers (worker i on devices[i % len(devices)]); null: one "
                                     "per device", minimum=1)


class NNModelSpec(_Section):
    """fwi: a velocity model represented by a neural network, v(z, x) = v0 + scale x f_theta(z, x), f_theta an MLP
    (two tanh layers of `hidden` units) of the cell coordinates scaled to [-1, 1]; the inversion moves the network's
    weights theta (adseismic.inversion.parameterization.MLP). Acoustic physics only."""

    kind: Literal["nn"] = F(..., "nn")
    shape: list[int] = F(..., "nodes per axis [nz, nx] or [nz, ny, nx] of the grid the start model is given on")
    spacing: float | list[float] = F(..., "grid spacing, one number or one per axis (z, [y,] x)", "m")
    origin: list[float] | None = F(None, "world coordinates of node 0, (z, [y,] x); default 0", "m")
    v0: float = F(..., "the network's offset velocity", "m/s", exclusiveMinimum=0)
    scale: float = F(..., "the velocity scale of the network's output (v0 +- scale is its typical reach)", "m/s",
                     exclusiveMinimum=0)
    hidden: int | None = F(8, "units per hidden layer", minimum=1)
    seed: int | None = F(0, "the random initial weights' seed")


class FWISchema(ForwardSchema):
    """A full-waveform inversion (adseismic fwi): the forward sections (model is the START model), inversion and
    exactly one of true_model or observed."""

    model: ModelSpec | ElasticModelSpec | AcousticVDModelSpec | VTIModelSpec | ViscoacousticModelSpec | NNModelSpec = F(
        ..., "the START model (m/s); physics elastic: {vp, vs, rho}; acoustic_vd: {vp, rho}; vti: {vp, epsilon, delta, "
             "rho}; viscoacoustic: {vp, q, rho} (its q_band, f_ref, mechanisms hold for every band); {kind: nn, ...}: "
             "a neural-network velocity")
    inversion: Inversion | None = F(None, "inversion settings; null: all defaults")
    true_model: ModelSpec | ElasticModelSpec | AcousticVDModelSpec | VTIModelSpec | ViscoacousticModelSpec | None = F(
        None, "a model spec (synthetic study: data are simulated from it); exactly one of true_model and observed")
    observed: Observed | None = F(None, "observed data files; exactly one of true_model and observed (acoustic physics "
                                        "only)")
    parallel: Parallel | None = F(None, "the shots over Dask workers or the devices of this process (acoustic physics "
                                        "only); null: one process")


# ------------------------------------------------------------------------------ image sections

IMAGE_METHODS = ("rtm", "lsrtm")  # adseismic.config.image.IMAGE_METHODS


class Imaging(_Section):
    """Imaging settings (adseismic image; docs/imaging.md)."""

    method: Annotated[Literal[IMAGE_METHODS] | None, OneOf(*IMAGE_METHODS)] = F(
        "rtm", "rtm (reverse-time migration: the adjoint of the Born operator applied to the reflection data) or "
               "lsrtm (least-squares RTM: conjugate gradients on the normal equations of the Born operator)")
    iterations: Annotated[int | None, Int(1, "give at least 1 conjugate-gradient iteration")] = F(
        10, "lsrtm: conjugate-gradient iterations (each one Born and one adjoint simulation of every shot)", minimum=1)
    smoothing: Annotated[float | None, NonNeg(_NONNEG, "m")] = F(
        0.0, "the migration background: Gaussian smoothing of the model's slowness, standard deviation", "m", minimum=0)
    water_depth: Annotated[float | None, NonNeg(_NONNEG, "m")] = F(
        0.0, "the background keeps the model unsmoothed above this depth (the water) and the image is zero there", "m",
        minimum=0)
    illumination: Annotated[bool | None, Bool] = F(
        True, "divide the RTM image by the source illumination (sum over time and shots of u^2) + epsilon x its "
              "maximum; lsrtm: precondition with its inverse square root")
    epsilon: Annotated[float | None, Pos()] = F(
        0.001, "the illumination's stabiliser, a fraction of its maximum (the maximum is at the sources: 1e-3 compensates "
                "the decay with depth, 1e-2 half of it)", exclusiveMinimum=0)
    laplacian: Annotated[bool | None, Bool] = F(
        False, "rtm: replace the image by -laplacian(image) (per m^2), removing the low-wavenumber backscatter")


class ImageSchema(ForwardSchema):
    """An image of the reflectors (adseismic image): the forward sections (model is the migration model), image and
    exactly one of true_model or observed."""

    model: ModelSpec | ElasticModelSpec = F(..., "the migration model (m/s), smoothed by image.smoothing into the "
                                                 "background; physics elastic: {vp, vs, rho}")
    image: Imaging | None = F(None, "imaging settings; null: all defaults (RTM)")
    true_model: ModelSpec | ElasticModelSpec | None = F(
        None, "a model spec (synthetic study: data are simulated from it); exactly one of true_model and observed")
    observed: Observed | None = F(None, "observed data files (read as fwi reads them); exactly one of true_model "
                                        "and observed")
    parallel: Parallel | None = F(None, "acoustic RTM: the shots over Dask workers or the devices of this process, "
                                        "reduced in shot order; null: one process")


# ------------------------------------------------------------------------------ locate sections

LOCATE_METHODS = ("lbfgs", "gauss-newton", "gd", "adam")  # locate.LOCATE_METHODS
STF_KINDS = ("ricker", "free")
LOCATE_SOURCE_TYPES = ("pressure", "moment")  # locate: acoustic pressure source, elastic moment tensor
MT_CONSTRAINTS = ("none", "deviatoric", "double_couple")  # adseismic.location.moment_tensor.CONSTRAINTS


def _paths(v):
    v = [v] if isinstance(v, str) else v
    if not isinstance(v, list) or not v or not all(isinstance(p, str) for p in v):
        _fail(f"{_short(v)} is not a file path, glob or list of them (relative to the config)")
    return v


def _reference(v):
    if not isinstance(v, (list, dict)):
        _fail(f"{_short(v)} is not [latitude, longitude(, datum, azimuth)] or {{latitude, longitude, datum, azimuth}} "
              f"(degrees, m, degrees)")
    return v


def _local(v):
    if not isinstance(v, dict):
        _fail(f"{_short(v)} is not a mapping of station (NET.STA or NET.STA.LOC.CHA) to [z, (y,) x] in metres")
    return v


def _fill_gaps(v):
    return v if v == "interpolate" else _via(_number, v)


def _window(v):
    return v if v == "auto" else _pair("s").func(v)


def _origin_time(v):
    """Seconds after the record start (a number) or a UTC time string, checked later against the traces."""
    if isinstance(v, str):
        try:
            return _number(v, "")
        except ConfigError:
            return v
    return _via(_number, v, "s")


class Traces(_Section):
    """The event's trace files and station metadata (adseismic.data.read.read_station_traces)."""

    paths: Annotated[str | list[str] | None, _opt(_paths)] = F(
        ..., "MiniSEED/SAC/... file, glob or list of them, relative to the config")
    inventory: Annotated[str | None, _opt(lambda v: str(v))] = F(
        None, "StationXML file with the station coordinates, relative to the config")
    reference: Annotated[list[float | str] | dict[str, float | str] | None, _opt(_reference)] = F(
        None, "the local frame's origin: [latitude, longitude(, datum, azimuth)] or {latitude, longitude, datum, "
              "azimuth} (degrees, m, degrees); checked when the traces are read", "deg")
    local_coordinates: Annotated[dict[str, Any] | None, _opt(_local)] = F(
        None, "station (NET.STA or NET.STA.LOC.CHA) -> [z, (y,) x] world metres, instead of latitude/longitude", "m")
    component: Annotated[str | None, _text("a component letter, e.g. Z")] = F(None, "the component letter, e.g. Z")
    fill_gaps: Annotated[float | Literal["interpolate"] | None, _opt(_fill_gaps)] = F(
        None, "fill gaps in a trace with this value or interpolate; null: a gap is an error")
    align: Annotated[bool | None, Bool] = F(False, "trim all traces to their common time span")


class Preprocess(_Section):
    """Trace processing before the misfit."""

    detrend: Annotated[bool | None, Bool] = F(True, "remove a linear trend")
    taper: Annotated[float | None, Between(0, 0.5, "give a fraction of the record at each end",
                                              lo_closed=True, hi_closed=True)] = F(
        0.05, "cosine taper, fraction of the record at each end, in [0, 0.5]", minimum=0, maximum=0.5)
    band: Annotated[list[float | None] | None, _pair("Hz", allow_null=True)] = F(
        None, "[fmin, fmax] zero-phase Butterworth band-pass (either may be null); null: none", "Hz")
    noise_window: Annotated[list[float] | None, _pair("s")] = F(
        ..., "[start, end] after the record start of a window before the first arrival (the data noise that weights "
             "the misfit and sets the uncertainty); required", "s")
    window: Annotated[Literal["auto"] | list[float] | None, _opt(_window)] = F(
        "auto", "auto (simulate only around the expected arrivals) or [start, end] after the record start", "s")


class LocationPoint(_Section):
    """A position and origin time."""

    position: Point = F(..., "the position, world metres", "m")
    origin_time: Annotated[float | str | None, _opt(_origin_time)] = F(None, "seconds after the record start, or a UTC time", "s")


class Source(_Section):
    """The source-time function, the mechanism and the search region."""

    type: Annotated[Literal[LOCATE_SOURCE_TYPES] | None, OneOf(*LOCATE_SOURCE_TYPES)] = F(
        None, "pressure (acoustic physics) or moment (a moment tensor, physics elastic); null: the physics' own")
    constraint: Annotated[Literal[MT_CONSTRAINTS] | None, OneOf(*MT_CONSTRAINTS)] = F(
        None, "moment tensor: none, deviatoric or double_couple (2D: strike along the section's normal, dip-slip); "
              "null: none")

    stf: Annotated[Literal[STF_KINDS] | None, OneOf(*STF_KINDS)] = F(
        "ricker", "ricker or free (one value per sample, smoothness-regularised)")
    peak_frequency: Annotated[float | None, Pos("Hz")] = F(
        None, "start peak frequency; null: the data's dominant frequency", "Hz", exclusiveMinimum=0)
    frequency_range: Annotated[list[float] | None, _pair("(factors of the start peak frequency)")] = F(
        [0.3, 3.0], "[low, high] factors of the start peak frequency the search may reach; brackets 1")
    smoothness: Annotated[float | None, NonNeg("give 0 (none) or a positive weight")] = F(
        0.01, "smoothness weight of a free source-time function", minimum=0)
    bounds: dict[str, list[float]] | None = F(
        None, "search region {x: [lo, hi], z: [lo, hi]} inside the model; null: the model less 2 cells", "m")
    start: LocationPoint | None = F(None, "start position and origin time; null: envelope back-projection")


class Search(_Section):
    """The optimiser."""

    method: Annotated[Literal[LOCATE_METHODS] | None, OneOf(*LOCATE_METHODS)] = F(
        "lbfgs", "lbfgs, gauss-newton, gd or adam")
    scaled: Annotated[bool | None, Bool] = F(True, "optimise non-dimensional (scaled) parameters")
    iterations: Annotated[int | None, Int(1, "give at least 1")] = F(60, "iteration limit", minimum=1)
    multi_start: Annotated[int | None, Int(1, "give at least 1")] = F(
        1, "number of starts (the best back-projection maxima)", minimum=1)
    grid_spacing: Annotated[float | None, Pos("m")] = F(
        None, "spacing of the back-projection candidates; null: planned", "m", exclusiveMinimum=0)


class LocateSchema(_Section):
    """An event location (adseismic locate): model and traces; optionally preprocess, source, search, simulation
    and truth."""

    physics: Annotated[Literal[PHYSICS] | None, OneOf(*PHYSICS)] = F(
        "acoustic", "acoustic (model: a velocity model) or elastic (2D, a moment-tensor source; model: {vp, vs, rho})")
    model: ModelSpec | ElasticModelSpec = F(..., "the velocity model (m/s); physics elastic: {vp, vs, rho}")
    traces: Traces = F(..., "the event's files")
    preprocess: Preprocess = F(..., "trace processing; noise_window is required")
    source: Source | None = F(None, "source-time function and search region")
    search: Search | None = F(None, "the optimiser")
    simulation: Simulation | None = F(None, "numerical settings (precision default float64)")
    truth: LocationPoint | None = F(None, "the known event of a synthetic study, reported beside the result")


class ForwardFileSchema(ForwardSchema):
    """A forward simulation (adseismic forward): model, geometry, wavelet; optionally simulation, output and parallel."""

    parallel: Parallel | None = F(None, "the shots over Dask workers or the devices of this process, gathered in shot "
                                        "order; null: one process")


SCHEMAS = {"forward": ForwardFileSchema, "fwi": FWISchema, "locate": LocateSchema, "image": ImageSchema}


# ------------------------------------------------------------------------------ validation

def _section_of(cls, loc) -> type | None:
    """The model class reached from ``cls`` along ``loc`` (field names; list indices skipped)."""
    import typing

    for part in loc:
        if isinstance(part, int):
            continue
        field = cls.model_fields.get(part) if isinstance(cls, type) and issubclass(cls, BaseModel) else None
        if field is None:
            return None
        stack, cls = [field.annotation], None
        while stack:
            t = stack.pop()
            if isinstance(t, type) and issubclass(t, BaseModel):
                cls = t
                break
            stack += [a for a in reversed(typing.get_args(t)) if a is not type(None)]  # a union: its first model
        if cls is None:
            return None
    return cls


def _clean(loc) -> tuple:
    """``loc`` without pydantic's union and function tags: field names and list indices."""
    loc = [p if isinstance(p, (int, str)) and not isinstance(p, bool) else str(p) for p in loc]
    return tuple(p for p in loc if isinstance(p, int) or not (
        p.startswith(("function-", "union", "list[", "dict[", "literal[")) or p in ("Band", "float", "none")))


def _where(key: str, loc) -> str:
    out = key
    for part in _clean(loc):
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
    return out


def _message(cls, key: str, err: dict) -> str:
    """One pydantic error as ``<key.path>: <value> ...; <fix>``."""
    typ = err["type"]
    if any(p == "[key]" for p in err["loc"]):  # a mapping's key of the wrong type
        where = _where(key, [p for p in err["loc"] if p != "[key]"][:-1])
        return f"{where}: key {_short(err['input'])} is not text; write the names as text"
    loc = _clean(err["loc"])
    where = _where(key, loc)
    parent = _section_of(cls, loc[:-1])
    if typ == "adseismic":
        index = err["ctx"].get("index")
        return f"{where}{'' if index is None else f'[{index}]'}: {err['ctx']['m']}"
    if typ in ("extra_forbidden", "invalid_key"):
        if typ == "invalid_key":
            parent = _section_of(cls, loc[:-1])
            where = f"{_where(key, loc[:-1])}.{err['input']}"
        allowed = ", ".join(parent.model_fields) if parent is not None else "see adseismic schema"
        return f"{where}: unknown key; allowed: {allowed}"
    field = parent.model_fields.get(loc[-1]) if parent is not None and loc and isinstance(loc[-1], str) else None
    meaning = field.description if field is not None else ""
    if typ == "missing":
        return f"{where}: missing; give {meaning}" if meaning else f"{where}: missing"
    if typ in ("model_type", "dict_type"):
        target = _section_of(cls, loc) if loc else cls
        what = (target.__doc__ or "").strip().splitlines()[0].rstrip(".") if target is not None else meaning
        what = what[:1].lower() + what[1:]
        name = where.split(".")[-1] if where else "config"
        return f"{where or 'config'}: {_short(err['input'])} is not a mapping; write it as '{name}: {{...}}' with {what}"
    fix = f"; give {meaning}" if meaning else ""
    return f"{where}: {_short(err.get('input'))} is not valid ({err['msg']}){fix}"


def validate_section(cls, raw, key: str):
    """``raw`` (a parsed YAML section; None: an empty one) validated by the schema ``cls``: the model instance, or
    ConfigError in the project's style naming ``key.<path>``, the value and the fix (unknown keys first)."""
    try:
        return cls.model_validate({} if raw is None else raw)
    except ValidationError as e:
        errs = sorted(e.errors(include_url=False), key=lambda x: x["type"] != "extra_forbidden")
        raise ConfigError(_message(cls, key, errs[0])) from None
    except RecursionError:
        raise ConfigError(f"{key}: nested too deeply; a config has at most a few levels") from None


def given(section: BaseModel) -> dict:
    """The keys the YAML gave (not null), validated."""
    return {k: getattr(section, k) for k in section.model_fields_set if getattr(section, k) is not None}


# ------------------------------------------------------------------------------ JSON Schema, templates

def json_schema(workflow: str) -> dict:
    """The JSON Schema (draft 2020-12) of a workflow's config, for YAML editors (yaml-language-server)."""
    cls = SCHEMAS[workflow]
    s = cls.model_json_schema()
    s["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    s["title"] = f"adseismic {workflow} config"
    return s


_TEMPLATE_VALUES = {
    "forward": {
        "model": {"kind": "layered", "shape": [41, 81], "spacing": 10.0, "velocities": [1800.0, 2500.0],
                  "interfaces": [200.0]},
        "geometry": {"sources": {"points": [{"x": 200.0, "z": 20.0}, {"x": 600.0, "z": 20.0}]},
                     "receivers": {"line": {"start": {"x": 0.0, "z": 10.0}, "end": {"x": 800.0, "z": 10.0},
                                            "count": 41}}},
        "wavelet": {"kind": "ricker", "peak_frequency": 10.0},
        "simulation": {"order": 4, "accuracy": 0.01, "device": "cpu", "precision": "float32", "pml_width": 10},
        "output": {"snapshot_interval": 0.0},
    },
}
_TEMPLATE_VALUES["fwi"] = {
    **{k: v for k, v in _TEMPLATE_VALUES["forward"].items() if k != "output"},
    "model": {"kind": "constant", "shape": [41, 81], "spacing": 10.0, "velocity": 2000.0},
    "true_model": {"kind": "gaussian_anomaly", "shape": [41, 81], "spacing": 10.0, "background": 2000.0,
                   "perturbation": 200.0, "center": [200.0, 400.0], "radius": 60.0},
    "inversion": {"bands": [6.0, None], "misfit": "l2", "optimizer": "lbfgs", "iterations": 10,
                  "source_radius": 30.0},
}
_TEMPLATE_VALUES["locate"] = {
    "model": {"kind": "layered", "shape": [61, 111], "spacing": 20.0, "velocities": [1800.0, 2400.0, 3000.0],
              "interfaces": [300.0, 800.0]},
    "traces": {"paths": ["{demo}/event.mseed"], "inventory": "{demo}/event.xml",
               "reference": {"latitude": 46.0, "longitude": 7.0, "datum": 0.0, "azimuth": 90.0}},
    "preprocess": {"detrend": True, "taper": 0.05, "band": [1.0, 15.0], "noise_window": [0.0, 0.7],
                   "window": "auto"},
    "source": {"stf": "ricker"},
    "search": {"method": "lbfgs", "multi_start": 2},
    "simulation": {"order": 4, "accuracy": 0.003, "device": "cpu"},
}


def _yaml_value(v) -> str:
    import json

    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return v if v.replace("/", "").replace(".", "").replace("_", "").replace("-", "").isalnum() else json.dumps(v)
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, list):
        return "[" + ", ".join(_yaml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_yaml_value(x)}" for k, x in v.items()) + "}"
    return str(v)


def _comment(field) -> str:
    unit = (field.json_schema_extra or {}).get("unit") if isinstance(field.json_schema_extra, dict) else None
    return f"{field.description}" + (f" [{unit}]" if unit else "")


_TEMPLATE_VALUES["image"] = {
    **{k: v for k, v in _TEMPLATE_VALUES["forward"].items() if k != "output"},
    "model": {"kind": "constant", "shape": [41, 81], "spacing": 10.0, "velocity": 1800.0},
    "true_model": {"kind": "layered", "shape": [41, 81], "spacing": 10.0, "velocities": [1800.0, 2400.0],
                   "interfaces": [250.0]},
    "image": {"method": "rtm", "smoothing": 0.0, "illumination": True, "epsilon": 0.001, "laplacian": False},
}
_LIST_OMITTED = ("Simulation", "Output", "Inversion", "Traces", "Preprocess", "Source", "Search", "Wavelet", "Imaging")


def _template_lines(cls, values: dict, indent: int) -> list[str]:
    """YAML lines for ``values`` (a section of ``cls``), each key with its meaning as a comment; the keys left out
    follow as commented lines with their defaults (uncomment to set them)."""
    pad = "  " * indent
    lines = []
    for name, value in values.items():
        field = cls.model_fields[name]
        sub = _section_of(cls, [name])
        if isinstance(value, dict) and sub is not None and sub is not Point and name not in ("sources", "receivers"):
            lines.append(f"{pad}{name}:{' ' * max(1, 40 - len(pad) - len(name))}# {_comment(field)}")
            lines += _template_lines(sub, value, indent + 1)
        else:
            head = f"{pad}{name}: {_yaml_value(value)}"
            lines.append(f"{head}{' ' * max(1, 41 - len(head))}# {_comment(field)}")
    if cls.__name__ in _LIST_OMITTED:
        for name, field in cls.model_fields.items():
            if name in values or (cls is Wavelet and name not in WAVELET_KEYS[values.get("kind", "ricker")]):
                continue
            default = None if field.is_required() else field.default
            head = f"{pad}# {name}: {_yaml_value(default)}"
            lines.append(f"{head}{' ' * max(1, 41 - len(head))}# {_comment(field)}")
    if indent == 0:
        for name, field in cls.model_fields.items():
            if name not in values:
                lines.append(f"# {name}:{' ' * max(1, 37 - len(name))}# optional section: {_comment(field)}")
    return lines


def template(workflow: str, demo_dir: str | None = None, name: str = "THIS.yaml") -> str:
    """A commented YAML config for ``workflow`` that runs as written on a CPU in seconds (locate: the shipped demo
    event at ``demo_dir``, a path relative to the written file or absolute); each key carries its meaning as a
    comment, and the keys left out are listed with their defaults."""
    cls = SCHEMAS[workflow]
    values = _TEMPLATE_VALUES[workflow]
    head = {
        "forward": [("adseismic forward config: a small synthetic 2D scene (two-layer model, 2 shots) that runs on a "
                     "CPU in seconds:"), "  adseismic forward THIS.yaml -o out/forward"],
        "fwi": [("adseismic fwi config: recover a +200 m/s Gaussian anomaly from a constant start model (2 shots, "
                 "two bands, 10 iterations each; about half a minute on a CPU):"), "  adseismic fwi THIS.yaml -o out/fwi"],
        "locate": [("adseismic locate config: the shipped demo event (12 MiniSEED stations + StationXML in "
                    "configs/data/location_demo of the adseismic repository); traces paths are relative to this file:"),
                   "  adseismic locate THIS.yaml -o out/locate",
                   "For your own event: point traces.paths / traces.inventory at your files and set the model."],
        "image": [("adseismic image config: reverse-time migration of a flat reflector at 250 m depth (2 shots, a "
                   "constant migration model; seconds on a CPU):"), "  adseismic image THIS.yaml -o out/image"],
    }[workflow]
    lines = [f"# {h}" for h in head]
    lines.append(f"# yaml-language-server: $schema=adseismic-{workflow}.schema.json  (write it with: adseismic schema "
                 f"{workflow} -o adseismic-{workflow}.schema.json)")
    lines.append("# Units: metres, seconds, m/s, Hz. Every key and its default: docs/config.md.")
    text = "\n".join(lines + _template_lines(cls, values, 0)).replace("THIS.yaml", name) + "\n"
    if workflow == "locate":
        if demo_dir is None:  # not a clone of the repository: the demo data are not next to the package
            demo_dir = "data/location_demo"
            text = ("# The demo traces are not installed with the package: write them next to this file with\n"
                    "#   python -m adseismic.data_synthetic.location data/location_demo\n"
                    "# (a fine-grid simulation, a few minutes on a CPU), or use your own files.\n") + text
        text = text.replace("{demo}", demo_dir)
    return text
