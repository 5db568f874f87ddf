"""Forward-run configuration (``adseismic run``): the schema, its validation and the dataclasses the
planner consumes.

A config file has the top-level sections ``model``, ``geometry``, ``wavelet`` (required),
``physics``, ``source``, ``simulation`` and ``output`` (optional). ``physics: elastic`` (2D or 3D) makes ``model`` a
``{vp, vs, rho}`` section (:func:`adseismic.data.models.load_physics_model`), lets ``source`` choose a force,
moment-tensor or explosive mechanism and ``geometry.receivers`` record ``components`` (vx, vz, pressure; vy in 3D) and
DAS strain rate (``das``, 2D only); those keys are refused with acoustic physics. Every value is checked before any work is done; a
problem raises :class:`ConfigError` whose message starts with the dotted key path (for example
``simulation.order: 3 is not one of 2, 4, 8; ...``), says what was found and how to fix it.
Unknown keys are errors, since a typo would otherwise silently fall back to a default. Keys, types, units,
defaults and ranges of each section are declared in :mod:`adseismic.config.schema` (which checks them); this module
builds the dataclasses and checks what the schema cannot say: the model (load_model), the geometry against the
model's axes and extent, the wavelet's delay against its period and its file.

Units: metres, seconds, m/s and Hz everywhere. Coordinates are world metres in the frame of the
model's ``origin``; arrays use the model axis order (z, [y,] x), z depth positive down.

PyYAML reads ``1e-3`` (no dot, no sign in the exponent) as a string; float fields therefore accept
any string that ``float()`` parses.
"""
from __future__ import annotations

import pathlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from adseismic.config import schema
from adseismic.config.common import ConfigError, _check_keys, _integer, _mapping, _number, _read_yaml, _short
from adseismic.config.parallel import ParallelConfig, parse_parallel
from adseismic.config.schema import given, validate_section
from adseismic.data.models import ElasticModel, Model, ModelError, VTIModel, load_physics_model

__all__ = [
    "GeometryConfig",
    "DasConfig",
    "SourceConfig",
    "WaveletConfig",
    "SimulationConfig",
    "OutputConfig",
    "ForwardConfig",
    "load_config",
    "parse_config",
    "SECTIONS",
    "SIMULATION_KEYS",
    "OUTPUT_KEYS",
]


# ------------------------------------------------------------------------------ dataclasses

@dataclass
class DasConfig:
    """DAS channels at the receiver points (physics elastic): strain rate (1/s) along the unit vector ``direction``
    (dz, dx) over ``gauge_length`` (m) centred on each point (adseismic.solve.receivers.DasOperator)."""

    gauge_length: float
    direction: tuple


@dataclass
class GeometryConfig:
    """Acquisition geometry in world metres, axis order (z, [y,] x).

    sources: (n_shots, ndim); every source point is one shot.
    receivers: (n_receivers, ndim); one spread shared by all shots.
    components: what the receivers record with physics elastic (of vx, vz, pressure; () for acoustic physics);
    das: DAS strain rate at the receivers too (physics elastic), or None.
    """

    sources: np.ndarray
    receivers: np.ndarray
    components: tuple = ()
    das: DasConfig | None = None


@dataclass
class SourceConfig:
    """The source mechanism of physics elastic, the same at every shot: ``type`` force, moment or explosive, and
    ``components`` in the solver's convention (adseismic.solve.elastic): force (f_z, f_x) in N/m, moment and explosive
    (m_xx, m_zz, m_xz) in N m/m; in 3D (adseismic.solve.elastic3d) force (f_z, f_y, f_x) in N, moment and explosive
    (m_zz, m_yy, m_xx, m_yz, m_xz, m_xy) in N m; the source at time t is components x the wavelet s(t)."""

    type: str = "explosive"
    components: tuple = (1.0, 1.0, 0.0)

    @property
    def solver_type(self) -> str:
        """forward_elastic's source_type: an explosive source is the moment tensor (M0, M0, 0)."""
        return "force" if self.type == "force" else "moment"


@dataclass
class WaveletConfig:
    """``make_wavelet(kind, nt, dt, **params)``; for kind ``array`` the file is already loaded
    into ``params["samples"]`` (and ``params["dt_in"]`` is its sample interval in seconds)."""

    kind: str
    params: dict


@dataclass
class SimulationConfig:
    """Numerical choices and optional pins; ``None`` lets the planner choose."""

    order: int = 4
    accuracy: float = 0.01
    free_surface: bool = False
    device: str = "cpu"
    precision: str = "float32"
    cfl_safety: float = 0.9
    dx: float | None = None
    dt: float | None = None
    duration: float | None = None
    pml_width: int | None = None
    pml_reflection: float | None = None
    margin: float | None = None
    domain: str = "auto"
    memory_budget_gb: float | None = None  # GB (1e9 bytes) the run may use; None: the device's free memory
    force: bool = False  # run even when the planner's memory estimate exceeds the budget / free memory


@dataclass
class OutputConfig:
    snapshot_interval: float = 0.0  # seconds between wavefield snapshots (0: none)


@dataclass
class ForwardConfig:
    model: Model | ElasticModel | VTIModel  # ElasticModel with physics elastic, acoustic_vd; VTIModel with vti
    geometry: GeometryConfig
    wavelet: WaveletConfig
    simulation: SimulationConfig
    output: OutputConfig
    path: Path | None = None  # the YAML file (None when parsed from a dict)
    raw: dict = field(default_factory=dict)  # the parsed YAML, kept for provenance
    physics: str = "acoustic"  # acoustic, elastic, acoustic_vd (an ElasticModel with vs None) or vti (a VTIModel)
    source: SourceConfig | None = None  # physics elastic, acoustic_vd, vti: the mechanism (None for acoustic physics)
    parallel: ParallelConfig | None = None  # a forward file's parallel section (config.parallel): shots over workers

    @property
    def ndim(self) -> int:
        return self.model.ndim

    @property
    def n_shots(self) -> int:
        return int(self.geometry.sources.shape[0])


# ------------------------------------------------------------------------------ key tables

SECTIONS = ("model", "geometry", "wavelet", "physics", "source", "simulation", "output")
REQUIRED_SECTIONS = ("model", "geometry", "wavelet")
SIMULATION_KEYS = tuple(schema.Simulation.model_fields)  # types, units, defaults, ranges: adseismic.config.schema
OUTPUT_KEYS = tuple(schema.Output.model_fields)
GEOMETRY_KEYS = ("sources", "receivers")
RECORDING_KEYS = ("components", "das")  # geometry.receivers: what an elastic spread records
SPREAD_FORMS = ("points", "line", "lines")
LINE_KEYS = ("start", "end", "count")
WAVELET_KEYS = schema.WAVELET_KEYS  # the keys of each kind
AXES = {2: ("z", "x"), 3: ("z", "y", "x")}  # model axis order by dimension
MAX_DELAY_PERIODS = 100.0  # a wavelet delayed by more is a typo (and its sampled band would not fit in memory)
MAX_LINE_POINTS = 1_000_000  # points on one geometry line: more is a typo (and would not fit in memory)

# ------------------------------------------------------------------------------ sections

def _parse_simulation(raw, key="simulation") -> SimulationConfig:
    """The simulation section: keys, types and ranges by the schema (:class:`adseismic.config.schema.Simulation`)."""
    return SimulationConfig(**{**SimulationConfig().__dict__, **given(validate_section(schema.Simulation, raw, key))})


def _parse_output(raw, key="output") -> OutputConfig:
    """The output section (:class:`adseismic.config.schema.Output`)."""
    return OutputConfig(**given(validate_section(schema.Output, raw, key)))


def _parse_wavelet(raw, base_dir: Path, key="wavelet") -> WaveletConfig:
    w = _mapping(raw, key, "kind and its parameters")
    kind = w.get("kind")
    if not isinstance(kind, str) or kind not in WAVELET_KEYS:
        raise ConfigError(f"{key}.kind: {kind!r} is not one of {', '.join(WAVELET_KEYS)}; "
                          f"set the source time function")
    _check_keys(w, key, WAVELET_KEYS[kind])  # the keys of this kind (the schema lists those of every kind)
    v = given(validate_section(schema.Wavelet, w, key))  # types and ranges
    if kind in ("ricker", "gaussian_derivative"):
        if "peak_frequency" not in v:
            raise ConfigError(f"{key}.peak_frequency: missing; a {kind} wavelet needs its peak "
                              f"frequency in Hz")
        params = {"peak_frequency": v["peak_frequency"]}
        if "delay" in v:
            delay = v["delay"]
            most = MAX_DELAY_PERIODS / params["peak_frequency"]
            if delay > most:
                raise ConfigError(f"{key}.delay: {delay:g} s is more than {MAX_DELAY_PERIODS:g} periods of the "
                                  f"{params['peak_frequency']:g} Hz wavelet ({most:g} s); give the time of its centre, "
                                  f"a few periods (default {1.5 / params['peak_frequency']:g} s), or leave it out")
            params["delay"] = delay
        return WaveletConfig(kind, params)
    # kind: array
    for k, what in (("file", "the path of a .npy file with the samples"),
                    ("dt_in", "the sample interval of the file in seconds")):
        if w.get(k) is None:
            raise ConfigError(f"{key}.{k}: missing; an array wavelet needs {what}")
    dt_in = v["dt_in"]
    path = pathlib.Path(str(w["file"])).expanduser()
    path = path if path.is_absolute() else base_dir / path
    if not path.is_file():
        raise ConfigError(f"{key}.file: {str(w['file'])!r} does not exist (looked for {path}); "
                          f"give an absolute path or one relative to {base_dir}")
    try:
        samples = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as e:
        raise ConfigError(f"{key}.file: {path} is not a readable .npy array ({e}); save the "
                          f"samples with numpy.save") from None
    samples = np.asarray(samples, dtype=np.float64).squeeze()
    if samples.ndim != 1 or samples.size < 2:
        raise ConfigError(f"{key}.file: {path.name} holds an array of shape {samples.shape}; "
                          f"give a 1D array of at least 2 samples")
    if not np.all(np.isfinite(samples)) or not np.any(samples):
        raise ConfigError(f"{key}.file: {path.name} has non-finite samples or only zeros; "
                          f"give a finite, non-zero wavelet")
    return WaveletConfig("array", {"samples": samples, "dt_in": dt_in})


def _point(p, key: str, ndim: int) -> list[float]:
    axes = AXES[ndim]
    allowed = ", ".join(sorted(axes, key="xyz".index))
    p = _mapping(p, key, f"the coordinates {allowed} in metres")
    for k in p:
        if k not in axes:
            raise ConfigError(f"{key}.{k}: unknown key for a {ndim}D model; allowed: {allowed} "
                              f"(world metres)")
    for a in sorted(axes, key="xyz".index):
        if a not in p:
            raise ConfigError(f"{key}.{a}: missing; a point in a {ndim}D model needs {allowed} "
                              f"(world metres)")
    return [_number(p[a], f"{key}.{a}", "metres") for a in axes]


def _parse_line(raw, key: str, ndim: int) -> np.ndarray:
    line = _mapping(raw, key, "start, end and count")
    _check_keys(line, key, LINE_KEYS)
    for k in LINE_KEYS:
        if k not in line:
            raise ConfigError(f"{key}.{k}: missing; a line needs start, end (points in "
                              f"metres) and count (number of points, >= 1)")
    start = _point(line["start"], f"{key}.start", ndim)
    end = _point(line["end"], f"{key}.end", ndim)
    count = _integer(line["count"], f"{key}.count")
    if count < 1:
        raise ConfigError(f"{key}.count: {line['count']!r} is not >= 1; give the number of "
                          f"evenly spaced points from start to end")
    if count > MAX_LINE_POINTS:
        raise ConfigError(f"{key}.count: {line['count']!r} points is more than {MAX_LINE_POINTS:,} on one line; "
                          f"give the number of sources or receivers on the line (a typo? e.g. 1.4e15 for 140)")
    return np.linspace(start, end, count).reshape(count, ndim)


def _parse_spread(raw, key: str, ndim: int) -> np.ndarray:
    """Points from any of 'points: [...]', 'line: {start, end, count}' and 'lines: [{...}, ...]',
    concatenated in that order."""
    s = _mapping(raw, key, "'points: [...]', 'line: {start, end, count}' or 'lines: [...]'")
    _check_keys(s, key, SPREAD_FORMS)
    if not s:
        raise ConfigError(f"{key}: empty; give 'points: [{{x: .., z: ..}}, ...]', "
                          f"'line: {{start: .., end: .., count: ..}}' or 'lines: [...]'")
    parts = []
    if "points" in s:
        pts = s["points"]
        if not isinstance(pts, list) or not pts:
            raise ConfigError(f"{key}.points: {pts!r} is not a non-empty list; give a list of "
                              f"points like {{x: 100, z: 10}}")
        parts.append(np.array([_point(p, f"{key}.points[{i}]", ndim) for i, p in enumerate(pts)]))
    if "line" in s:
        parts.append(_parse_line(s["line"], f"{key}.line", ndim))
    if "lines" in s:
        if not isinstance(s["lines"], list) or not s["lines"]:
            raise ConfigError(f"{key}.lines: {s['lines']!r} is not a non-empty list of lines")
        parts += [_parse_line(ln, f"{key}.lines[{i}]", ndim) for i, ln in enumerate(s["lines"])]
    return np.concatenate(parts)


def _check_inside(points: np.ndarray, key: str, model: Model) -> None:
    inside = model.contains(points)
    if not inside.all():
        i = int(np.argmin(inside))
        axes = AXES[model.ndim]
        where = ", ".join(f"{a}={v:g}" for a, v in zip(axes, points[i]))
        box = ", ".join(f"{a} [{lo:g}, {hi:g}]" for a, (lo, hi) in zip(axes, model.extent))
        raise ConfigError(f"{key}: point {i} ({where}) m lies outside the model ({box} m); "
                          f"{int((~inside).sum())} of {len(points)} points are outside: move "
                          f"them inside or change the model's origin")


def _parse_geometry(raw, model: Model | ElasticModel, physics: str = "acoustic", key="geometry") -> GeometryConfig:
    g = _mapping(raw, key, "sources and receivers")
    _check_keys(g, key, GEOMETRY_KEYS)
    arrays, recording = {}, {}
    for k in GEOMETRY_KEYS:
        if k not in g:
            raise ConfigError(f"{key}.{k}: missing; give 'points: [...]' or 'line: {{...}}' "
                              f"in world metres")
        spread = g[k]
        if k == "receivers" and isinstance(spread, dict):
            recording = {r: spread[r] for r in RECORDING_KEYS if r in spread}
            spread = {r: v for r, v in spread.items() if r not in RECORDING_KEYS}
        arrays[k] = _parse_spread(spread, f"{key}.{k}", model.ndim)
        _check_inside(arrays[k], f"{key}.{k}", model)
    components, das = _parse_recording(recording, arrays["receivers"], model, physics, f"{key}.receivers")
    return GeometryConfig(arrays["sources"], arrays["receivers"], components, das)


def _parse_recording(raw: dict, receivers: np.ndarray, model, physics: str, key: str) -> tuple:
    """(components, das) of geometry.receivers: checked by the schema (schema.Receivers), refused with acoustic
    physics; the DAS direction normalised and every gauge's ends inside the model."""
    for k, value in raw.items():
        if physics == "acoustic" and value is not None:
            raise ConfigError(f"{key}.{k}: {_short(value)} needs physics: elastic or acoustic_vd (acoustic receivers "
                              f"record the one wavefield u); set physics: elastic (with model: {{vp, vs, rho}}) or "
                              f"acoustic_vd (with model: {{vp, rho}}), or drop {k}")
    if physics == "acoustic":
        return (), None
    v = given(validate_section(schema.Receivers, raw, key))
    if model.ndim == 3 and "das" in v:
        raise ConfigError(f"{key}.das: {_short(raw['das'])} with a 3D model; DAS strain rate is recorded in 2D only (not "
                          f"built in 3D yet): drop das and record components (vx, vy, vz, pressure), or use a 2D model")
    if model.ndim == 2 and "vy" in v.get("components", ()):
        raise ConfigError(f"{key}.components: {list(v['components'])} names vy with a 2D model (z, x), which has no y "
                          f"velocity; drop vy (2D records vx, vz, pressure), or use a 3D model [nz, ny, nx]")
    das = None
    if "das" in v:
        das = DasConfig(v["das"].gauge_length, _direction(v["das"].direction, f"{key}.das.direction"))
        half = 0.5 * das.gauge_length * np.asarray(das.direction)
        for sign, end in ((-1, "start"), (1, "end")):
            _check_inside(receivers + sign * half, f"{key}.das (the gauges' {end}s, +-gauge_length/2 along the fibre)",
                          model)
    default = (tuple(c for c in schema.COMPONENTS if model.ndim == 3 or c != "vy") if physics == "elastic" else
               ("pressure",))  # acoustic_vd: a hydrophone by default
    components = tuple(v["components"]) if "components" in v else (() if das else default)
    if len(set(components)) != len(components):
        raise ConfigError(f"{key}.components: {list(components)} names a component twice; list each once")
    if not components and das is None:
        raise ConfigError(f"{key}.components: [] records nothing; give any of {', '.join(schema.COMPONENTS)}, or das")
    return components, das


def _direction(value, key: str) -> tuple:
    """A unit vector (dz, dx) from [dz, dx] (normalised) or an angle in degrees from +x towards +z."""
    if isinstance(value, list):
        if len(value) != 2:
            raise ConfigError(f"{key}: {_short(value)} is not [dz, dx]; give the fibre's direction as two numbers or "
                              f"an angle in degrees")
        d = np.array([_number(x, f"{key}[{i}]") for i, x in enumerate(value)])
        if not np.hypot(*d) > 0:
            raise ConfigError(f"{key}: {_short(value)} has length 0; give a direction [dz, dx], e.g. [0, 1] (horizontal)")
        d = d / np.hypot(*d)
    else:
        a = np.radians(_number(value, key, "degrees from the +x axis towards +z (depth)"))
        d = np.array([np.sin(a), np.cos(a)])
    return (float(d[0]), float(d[1]))


# components per mechanism and model dimension (adseismic.solve.elastic.SOURCE_TYPES, solve.elastic3d.SOURCE_TYPES)
SOURCE_SIZES = {2: {"force": 2, "moment": 3}, 3: {"force": 3, "moment": 6}}
SOURCE_WHAT = {2: {"force": "[f_z, f_x] in N/m", "moment": "[m_xx, m_zz, m_xz] in N m/m"},
               3: {"force": "[f_z, f_y, f_x] in N", "moment": "[m_zz, m_yy, m_xx, m_yz, m_xz, m_xy] in N m"}}


def _parse_source(raw, physics: str, key="source", ndim: int = 2) -> SourceConfig | None:
    """The source section (schema.ElasticSource) for a ``ndim``-D model: physics elastic, or acoustic_vd with type
    explosive only (the pressure source of a fluid); None for acoustic physics. 3D: force (f_z, f_y, f_x) N, moment
    (m_zz, m_yy, m_xx, m_yz, m_xz, m_xy) N m, explosive M0 N m as the moment (M0, M0, M0, 0, 0, 0)."""
    if physics == "acoustic":
        if raw is not None:
            raise ConfigError(f"{key}: {_short(raw)} needs physics: elastic; the acoustic solver injects the wavelet as "
                              f"a pressure (explosive-like) point source: drop the source section, or set physics: "
                              f"elastic (with model: {{vp, vs, rho}}) for force and moment-tensor sources")
        return None
    v = given(validate_section(schema.ElasticSource, raw, key))
    kind, comp = v.get("type", "explosive"), v.get("components")
    if physics in ("acoustic_vd", "vti", "viscoacoustic") and kind != "explosive":
        what = {"vti": "the pseudo-acoustic VTI solver (P waves only)"}.get(physics, "a fluid model")
        raise ConfigError(f"{key}.type: {kind!r} with physics {physics}; {what} takes the explosive (pressure) "
                          f"source only: set type: explosive (components: M0 in N m/m), or physics: elastic for force and "
                          f"moment-tensor sources")
    if kind == "explosive":
        m0 = 1.0 if comp is None else _number(comp, f"{key}.components", "N m/m (the explosive moment M0)")
        return SourceConfig(kind, (m0, m0, 0.0) if ndim == 2 else (m0, m0, m0, 0.0, 0.0, 0.0))
    n, what = SOURCE_SIZES[ndim][kind], SOURCE_WHAT[ndim][kind]
    if not isinstance(comp, list) or len(comp) != n:
        raise ConfigError(f"{key}.components: {_short(comp)} is not {what}; a {kind} source in a {ndim}D model needs its "
                          f"{n} components")
    values = tuple(_number(x, f"{key}.components[{i}]", what) for i, x in enumerate(comp))
    if not any(values):
        raise ConfigError(f"{key}.components: {list(values)} are all 0: the source radiates nothing; give {what}")
    return SourceConfig(kind, values)


def _load_model(spec, base_dir: Path, physics: str = "acoustic") -> Model | ElasticModel:
    """:func:`adseismic.data.models.load_physics_model`, its ModelError re-raised as ConfigError (message
    unchanged when it already starts with ``model`` or ``physics``, else prefixed ``model.``)."""
    try:
        return load_physics_model(spec, physics, base_dir=base_dir)
    except ModelError as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith(("model", "physics")) else f"model.{msg}") from e


def _parse_physics(raw) -> str:
    physics = "acoustic" if raw is None else raw
    if physics not in schema.PHYSICS:
        raise ConfigError(f"physics: {_short(raw)} is not one of {', '.join(schema.PHYSICS)}; pick one of them "
                          f"(default acoustic)")
    return physics


# the physics only adseismic forward runs, by name: fwi, locate and image run the acoustic and elastic solvers, which
# would drop the anisotropy or the attenuation; nor do the parallel workers run them yet
FORWARD_ONLY = {"vti": "VTI", "viscoacoustic": "visco-acoustic (constant Q)"}


def refuse_elastic3d(model) -> None:
    """ConfigError for a 3D elastic model in adseismic fwi, image or locate: 3D elastic is forward modelling only. (A 3D
    acoustic_vd model, vs None, passes: fwi inverts it; image and locate refuse acoustic_vd in any dimension.)"""
    if isinstance(model, ElasticModel) and model.ndim == 3 and model.vs is not None:
        raise ConfigError(f"model.vp: a 3D model (shape {list(model.shape)}) with physics elastic; 3D elastic is forward "
                          f"modelling only (adseismic forward), not available for adseismic fwi, image or locate yet: give "
                          f"a 2D model [nz, nx], or use physics: acoustic in 3D")


def refuse_forward_only(physics: str, workflow: str, fix: str) -> None:
    """ConfigError for a FORWARD_ONLY physics in ``adseismic <workflow>``; ``fix``: what to use instead."""
    if isinstance(physics, str) and physics in FORWARD_ONLY:
        raise ConfigError(f"physics: {physics} is not available for adseismic {workflow} yet ({FORWARD_ONLY[physics]} is "
                          f"forward modelling only: adseismic forward); {fix}")


# ------------------------------------------------------------------------------ public API

def parse_config(raw: dict, base_dir: Path | str | None = None, path: Path | None = None,
                 extra_sections: tuple = ()) -> ForwardConfig:
    """Validate a parsed YAML config and build the :class:`ForwardConfig`.

    ``base_dir`` (default: current directory) resolves relative file paths (model and wavelet
    files). Cheap checks run first (sections, simulation, output, wavelet), then the model is
    loaded with :func:`adseismic.data.models.load_model` (whose ModelError is re-raised as
    ConfigError, message unchanged: it already starts with ``model.<key>``), then the geometry
    is checked against the model's axes and extent.
    """
    base_dir = pathlib.Path.cwd() if base_dir is None else pathlib.Path(base_dir)
    if not isinstance(raw, dict):
        raise ConfigError(f"config: {type(raw).__name__} {raw!r:.60} is not a mapping; a config "
                          f"file has the sections {', '.join(SECTIONS)}")
    _check_keys(raw, "", SECTIONS + tuple(extra_sections))
    for k in REQUIRED_SECTIONS:
        if raw.get(k) is None:
            raise ConfigError(f"{k}: missing; a config needs the sections "
                              f"{', '.join(REQUIRED_SECTIONS)} (and optionally simulation, output)")
    physics = _parse_physics(raw.get("physics"))
    simulation = _parse_simulation(raw.get("simulation"))
    output = _parse_output(raw.get("output"))
    if physics != "acoustic" and output.snapshot_interval:
        solver = (f"the {FORWARD_ONLY[physics]} solver" if physics in FORWARD_ONLY else
                  f"the elastic solver (which runs physics {physics})")
        raise ConfigError(f"output.snapshot_interval: {output.snapshot_interval:g} s, but {solver} keeps no wavefield "
                          f"snapshots; set it to 0 (or leave it out) with physics "
                          f"{physics}")
    wavelet = _parse_wavelet(raw["wavelet"], base_dir)
    model = _load_model(raw["model"], base_dir, physics)
    source = _parse_source(raw.get("source"), physics, ndim=model.ndim)
    geometry = _parse_geometry(raw["geometry"], model, physics)
    return ForwardConfig(model, geometry, wavelet, simulation, output, path, raw, physics, source)


def load_config(path) -> ForwardConfig:
    """Read and validate the forward YAML file ``path`` (README, "Config"): a ForwardConfig whose model is in m/s,
    geometry in metres (axis order z, [y,] x) and wavelet in Hz and s; relative paths inside resolve from its
    folder. Raises ConfigError naming the key, the value and the fix."""
    raw, path = _read_yaml(path)
    config = parse_config(raw, base_dir=path.resolve().parent, path=path, extra_sections=("parallel",))
    if config.physics in FORWARD_ONLY and raw.get("parallel") is not None:  # the workers run the acoustic and elastic solvers
        raise ConfigError(f"parallel: given with physics {config.physics}; the shots of a {FORWARD_ONLY[config.physics]} run "
                          f"are not spread over workers yet: drop the parallel section (one process simulates every shot at once)")
    if isinstance(config.model, ElasticModel) and config.ndim == 3 and raw.get("parallel") is not None:  # workers run 2D
        raise ConfigError("parallel: given with a 3D elastic model; the shots of a 3D elastic run are not spread over "
                          "workers yet: drop the parallel section (one process simulates every shot at once)")
    config.parallel = parse_parallel(raw.get("parallel"), config.n_shots)
    return config

