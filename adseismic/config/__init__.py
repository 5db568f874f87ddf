"""YAML run configuration: loading, validation and the dataclasses the planner consumes.

A config file has the top-level sections ``model``, ``geometry``, ``wavelet`` (required),
``simulation`` and ``output`` (optional). Every value is checked before any work is done; a
problem raises :class:`ConfigError` whose message starts with the dotted key path (for example
``simulation.order: 3 is not one of 2, 4, 8; ...``), says what was found and how to fix it.
Unknown keys are errors, since a typo would otherwise silently fall back to a default.

Units: metres, seconds, m/s and Hz everywhere. Coordinates are world metres in the frame of the
model's ``origin``; arrays use the model axis order (z, [y,] x), z depth positive down.

PyYAML reads ``1e-3`` (no dot, no sign in the exponent) as a string; float fields therefore accept
any string that ``float()`` parses.
"""
from __future__ import annotations

import math
import pathlib
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from adseismic.data.models import Model, ModelError, load_model

__all__ = [
    "ConfigError",
    "GeometryConfig",
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


class ConfigError(ValueError):
    """An invalid config; the message starts with the dotted key path and names the fix."""


# ------------------------------------------------------------------------------ dataclasses

@dataclass
class GeometryConfig:
    """Acquisition geometry in world metres, axis order (z, [y,] x).

    sources: (n_shots, ndim); every source point is one shot.
    receivers: (n_receivers, ndim); one spread shared by all shots.
    """

    sources: np.ndarray
    receivers: np.ndarray


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


@dataclass
class OutputConfig:
    snapshot_interval: float = 0.0  # seconds between wavefield snapshots (0: none)


@dataclass
class ForwardConfig:
    model: Model
    geometry: GeometryConfig
    wavelet: WaveletConfig
    simulation: SimulationConfig
    output: OutputConfig
    path: Path | None = None  # the YAML file (None when parsed from a dict)
    raw: dict = field(default_factory=dict)  # the parsed YAML, kept for provenance

    @property
    def ndim(self) -> int:
        return self.model.ndim

    @property
    def n_shots(self) -> int:
        return int(self.geometry.sources.shape[0])


# ------------------------------------------------------------------------------ key tables

SECTIONS = ("model", "geometry", "wavelet", "simulation", "output")
REQUIRED_SECTIONS = ("model", "geometry", "wavelet")
SIMULATION_KEYS = ("order", "accuracy", "free_surface", "device", "precision", "cfl_safety",
                   "dx", "dt", "duration", "pml_width", "pml_reflection", "margin", "domain")
OUTPUT_KEYS = ("snapshot_interval",)
GEOMETRY_KEYS = ("sources", "receivers")
SPREAD_FORMS = ("points", "line", "lines")
LINE_KEYS = ("start", "end", "count")
WAVELET_KEYS = {
    "ricker": ("kind", "peak_frequency", "delay"),
    "gaussian_derivative": ("kind", "peak_frequency", "delay"),
    "array": ("kind", "file", "dt_in"),
}
ORDERS = (2, 4, 8)
PRECISIONS = ("float32", "float64")
DOMAINS = ("auto", "model")
DEVICE_RE = re.compile(r"^cpu$|^cuda(:\d+)?$")
MIN_PML_WIDTH = 4  # half-width of the sinc source/receiver operator (kernels.acoustic.HICKS_RADIUS)
AXES = {2: ("z", "x"), 3: ("z", "y", "x")}  # model axis order by dimension


# ------------------------------------------------------------------------------ primitives

def _mapping(value, key: str, what: str) -> dict:
    if not isinstance(value, dict):
        raise ConfigError(f"{key}: {value!r} is not a mapping; write it as '{key.split('.')[-1]}: "
                          f"{{...}}' with {what}")
    return value


def _check_keys(section: dict, key: str, allowed) -> None:
    for k in section:
        if k not in allowed:
            name = f"{key}.{k}" if key else str(k)
            raise ConfigError(f"{name}: unknown key; allowed: {', '.join(allowed)}")


def _number(value, key: str, unit: str = "") -> float:
    """A finite float; numeric strings (PyYAML reads 1e-3 as text) are accepted."""
    u = f" {unit}" if unit else ""
    if isinstance(value, bool) or value is None:
        x = None
    elif isinstance(value, (int, float, np.number)):
        x = float(value)
    elif isinstance(value, str):
        try:
            x = float(value.strip())
        except ValueError:
            x = None
    else:
        x = None
    if x is None or not math.isfinite(x):
        raise ConfigError(f"{key}: {value!r} is not a finite number; give a number{u}")
    return x


def _positive(value, key: str, unit: str = "") -> float:
    x = _number(value, key, unit)
    if x <= 0:
        raise ConfigError(f"{key}: {value!r} is not > 0; give a positive number" +
                          (f" of {unit}" if unit else ""))
    return x


def _integer(value, key: str) -> int:
    """An int; integral floats and integer strings are accepted, bools are not."""
    if isinstance(value, bool):
        ok = False
    elif isinstance(value, (int, np.integer)):
        return int(value)
    else:
        try:
            x = _number(value, key)
            ok = x == int(x)
        except ConfigError:
            ok = False
    if not ok:
        raise ConfigError(f"{key}: {value!r} is not an integer; give a whole number")
    return int(x)


def _boolean(value, key: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{key}: {value!r} is not true or false; write true or false")
    return value


def _choice(value, key: str, choices) -> object:
    if value not in choices:
        raise ConfigError(f"{key}: {value!r} is not one of {', '.join(map(str, choices))}; "
                          f"pick one of them")
    return value


def _optional(section: dict, name: str, fn, *args):
    value = section.get(name)
    return None if value is None else fn(value, *args)


# ------------------------------------------------------------------------------ sections

def _parse_simulation(raw, key="simulation") -> SimulationConfig:
    s = _mapping({} if raw is None else raw, key, "the numerical settings")
    _check_keys(s, key, SIMULATION_KEYS)
    d = SimulationConfig()
    out = {}
    if s.get("order") is not None:
        try:
            order = _integer(s["order"], f"{key}.order")
        except ConfigError:
            order = None
        if order not in ORDERS:
            raise ConfigError(f"{key}.order: {s['order']!r} is not one of 2, 4, 8; set the "
                              f"spatial finite-difference order (4 is a good default)")
        out["order"] = order
    if s.get("accuracy") is not None:
        acc = _number(s["accuracy"], f"{key}.accuracy")
        if not 0 < acc < 0.5:
            raise ConfigError(f"{key}.accuracy: {s['accuracy']!r} is not in (0, 0.5); give the "
                              f"target relative group-velocity error, e.g. 0.01 for 1%")
        out["accuracy"] = acc
    if s.get("free_surface") is not None:
        out["free_surface"] = _boolean(s["free_surface"], f"{key}.free_surface")
    if s.get("device") is not None:
        dev = s["device"]
        if not (isinstance(dev, str) and DEVICE_RE.match(dev)):
            raise ConfigError(f"{key}.device: {dev!r} is not a device; write cpu, cuda or "
                              f"cuda:N (N = GPU index)")
        out["device"] = dev
    if s.get("precision") is not None:
        out["precision"] = _choice(s["precision"], f"{key}.precision", PRECISIONS)
    if s.get("cfl_safety") is not None:
        c = _number(s["cfl_safety"], f"{key}.cfl_safety")
        if not 0 < c <= 1:
            raise ConfigError(f"{key}.cfl_safety: {s['cfl_safety']!r} is not in (0, 1]; give "
                              f"the fraction of the exact stability limit to use, e.g. 0.9")
        out["cfl_safety"] = c
    for name, unit in (("dx", "metres"), ("dt", "seconds"), ("duration", "seconds")):
        v = _optional(s, name, _positive, f"{key}.{name}", unit)
        if v is not None:
            out[name] = v
    if s.get("pml_width") is not None:
        w = _integer(s["pml_width"], f"{key}.pml_width")
        if w < MIN_PML_WIDTH:
            raise ConfigError(f"{key}.pml_width: {s['pml_width']!r} cells is below "
                              f"{MIN_PML_WIDTH}, the half-width of the source/receiver "
                              f"operator; use >= {MIN_PML_WIDTH} (10-20 absorbs well) or null")
        out["pml_width"] = w
    if s.get("pml_reflection") is not None:
        r = _number(s["pml_reflection"], f"{key}.pml_reflection")
        if not 0 < r < 1:
            raise ConfigError(f"{key}.pml_reflection: {s['pml_reflection']!r} is not in (0, 1); "
                              f"give the target reflection coefficient, e.g. 1e-3, or null")
        out["pml_reflection"] = r
    if s.get("margin") is not None:
        m = _number(s["margin"], f"{key}.margin", "metres")
        if m < 0:
            raise ConfigError(f"{key}.margin: {s['margin']!r} is negative; give the aperture "
                              f"margin around sources and receivers in metres (>= 0) or null")
        out["margin"] = m
    if s.get("domain") is not None:
        out["domain"] = _choice(s["domain"], f"{key}.domain", DOMAINS)
    return SimulationConfig(**{**d.__dict__, **out})


def _parse_output(raw, key="output") -> OutputConfig:
    o = _mapping({} if raw is None else raw, key, "the output settings")
    _check_keys(o, key, OUTPUT_KEYS)
    out = OutputConfig()
    if o.get("snapshot_interval") is not None:
        v = _number(o["snapshot_interval"], f"{key}.snapshot_interval", "seconds")
        if v < 0:
            raise ConfigError(f"{key}.snapshot_interval: {o['snapshot_interval']!r} is negative; "
                              f"give seconds between snapshots, or 0 for none")
        out.snapshot_interval = v
    return out


def _parse_wavelet(raw, base_dir: Path, key="wavelet") -> WaveletConfig:
    w = _mapping(raw, key, "kind and its parameters")
    kind = w.get("kind")
    if kind not in WAVELET_KEYS:
        raise ConfigError(f"{key}.kind: {kind!r} is not one of {', '.join(WAVELET_KEYS)}; "
                          f"set the source time function")
    _check_keys(w, key, WAVELET_KEYS[kind])
    if kind in ("ricker", "gaussian_derivative"):
        if w.get("peak_frequency") is None:
            raise ConfigError(f"{key}.peak_frequency: missing; a {kind} wavelet needs its peak "
                              f"frequency in Hz")
        params = {"peak_frequency": _positive(w["peak_frequency"], f"{key}.peak_frequency", "Hz")}
        if w.get("delay") is not None:
            delay = _number(w["delay"], f"{key}.delay", "seconds")
            if delay < 0:
                raise ConfigError(f"{key}.delay: {w['delay']!r} is negative; give the time of the "
                                  f"wavelet's centre in seconds (>= 0) or leave it out")
            params["delay"] = delay
        return WaveletConfig(kind, params)
    # kind: array
    for k, what in (("file", "the path of a .npy file with the samples"),
                    ("dt_in", "the sample interval of the file in seconds")):
        if w.get(k) is None:
            raise ConfigError(f"{key}.{k}: missing; an array wavelet needs {what}")
    dt_in = _positive(w["dt_in"], f"{key}.dt_in", "seconds")
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


def _parse_geometry(raw, model: Model, key="geometry") -> GeometryConfig:
    g = _mapping(raw, key, "sources and receivers")
    _check_keys(g, key, GEOMETRY_KEYS)
    arrays = {}
    for k in GEOMETRY_KEYS:
        if k not in g:
            raise ConfigError(f"{key}.{k}: missing; give 'points: [...]' or 'line: {{...}}' "
                              f"in world metres")
        arrays[k] = _parse_spread(g[k], f"{key}.{k}", model.ndim)
        _check_inside(arrays[k], f"{key}.{k}", model)
    return GeometryConfig(arrays["sources"], arrays["receivers"])


# ------------------------------------------------------------------------------ public API

def parse_config(raw: dict, base_dir: Path | str | None = None, path: Path | None = None,
                 extra_sections: tuple = ()) -> ForwardConfig:
    """Validate a parsed YAML config and build the :class:`ForwardConfig`.

    ``base_dir`` (default: current directory) resolves relative file paths (model and wavelet
    files). Cheap checks run first (sections, simulation, output, wavelet), then the model is
    loaded with :func:`adseismic.models.load_model` (whose ModelError is re-raised as
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
    simulation = _parse_simulation(raw.get("simulation"))
    output = _parse_output(raw.get("output"))
    wavelet = _parse_wavelet(raw["wavelet"], base_dir)
    try:
        model = load_model(raw["model"], base_dir=base_dir)
    except ModelError as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith("model") else f"model.{msg}") from e
    geometry = _parse_geometry(raw["geometry"], model)
    return ForwardConfig(model, geometry, wavelet, simulation, output, path, raw)


def _read_yaml(path) -> tuple[dict, Path]:
    import yaml

    path = pathlib.Path(path).expanduser()
    if not path.is_file():
        raise ConfigError(f"config: {str(path)!r} does not exist; give the path of a YAML file")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"config: {path} is not valid YAML: {e}") from None
    return raw, path


def load_config(path) -> ForwardConfig:
    """Read and validate the YAML file ``path``; relative paths inside resolve from its folder."""
    raw, path = _read_yaml(path)
    return parse_config(raw, base_dir=path.resolve().parent, path=path)


# ------------------------------------------------------------------------------ inversion

INVERSION_KEYS = ("bands", "misfit", "optimizer", "iterations", "evaluations", "rel_decrease", "offsets", "time_window", "bounds", "water_depth",
                  "source_radius", "smoothing", "preconditioning", "tikhonov", "tv", "wavelet_estimation",
                  "shots_per_batch", "memory_budget_gb", "step", "lr")
FWI_SECTIONS = ("true_model", "observed", "inversion")
OPTIMIZERS = ("lbfgs", "gd", "adam")
PRECONDITIONERS = ("none", "depth", "pseudo_hessian")


@dataclass
class InversionConfig:
    """Full-waveform inversion settings (units: Hz, m/s, m). bands: list of (f_low or None, f_high or
    None) pass bands, inverted in order; iterations / evaluations: limits per band (an evaluation is
    one misfit + gradient over all shots); bounds: (v_min, v_max) m/s or None (start model range
    +-25%); water_depth / source_radius: gradient masks (m, 0 = off); smoothing: Gaussian sigma of
    the gradient (m); tikhonov / tv: regularisation weights (relative to the band's initial misfit);
    offsets: (min, max) source-receiver distance (m) of the traces used (others muted); time_window:
    (start, end) s of the samples used (cosine taper over 10% of the window at each end)."""

    bands: list = field(default_factory=lambda: [(None, None)])
    misfit: str = "l2"
    optimizer: str = "lbfgs"
    iterations: int | list = 20
    evaluations: int | None = None
    rel_decrease: float = 1e-4
    bounds: tuple | None = None
    water_depth: float = 0.0
    source_radius: float = 0.0
    smoothing: float = 0.0
    preconditioning: str = "none"
    tikhonov: float = 0.0
    tv: float = 0.0
    wavelet_estimation: bool = False
    shots_per_batch: int | None = None
    memory_budget_gb: float | None = None
    step: float = 1.0
    lr: float = 0.01
    offsets: tuple | None = None
    time_window: tuple | None = None


@dataclass
class FWIConfig:
    """An inversion: `forward.model` is the START model; observed data come from `true_model`
    (a synthetic study) or from `observed` (files: {kind: hdf5|segy|su, path: ...})."""

    forward: ForwardConfig
    inversion: InversionConfig
    true_model: Model | None = None
    observed: dict | None = None


def _parse_band(b, key: str) -> tuple:
    if b is None:  # the full band of the wavelet
        return (None, None)
    if isinstance(b, (int, float, str)):
        return (None, _positive(b, key, "Hz"))
    if isinstance(b, dict):
        _check_keys(b, key, ("fmin", "fmax"))
        lo = None if b.get("fmin") is None else _positive(b["fmin"], f"{key}.fmin", "Hz")
        hi = None if b.get("fmax") is None else _positive(b["fmax"], f"{key}.fmax", "Hz")
        if lo is not None and hi is not None and lo >= hi:
            raise ConfigError(f"{key}: fmin {lo:g} Hz >= fmax {hi:g} Hz; give fmin < fmax")
        return (lo, hi)
    raise ConfigError(f"{key}: {b!r} is not a band; give fmax in Hz (e.g. 5), {{fmin: 2, fmax: 5}} or null (full band)")


def _parse_inversion(raw, key="inversion") -> InversionConfig:
    from adseismic.inversion.misfits import MISFITS

    sec = _mapping(raw or {}, key, "inversion settings")
    _check_keys(sec, key, INVERSION_KEYS)
    out = InversionConfig()
    if sec.get("bands") is not None:
        if not isinstance(sec["bands"], list) or not sec["bands"]:
            raise ConfigError(f"{key}.bands: {sec['bands']!r} is not a non-empty list; e.g. [3, 5, 8] (Hz, low to high)")
        out.bands = [_parse_band(b, f"{key}.bands[{i}]") for i, b in enumerate(sec["bands"])]
    for name, choices in (("misfit", MISFITS), ("optimizer", OPTIMIZERS), ("preconditioning", PRECONDITIONERS)):
        if sec.get(name) is not None:
            setattr(out, name, _choice(sec[name], f"{key}.{name}", choices))
    if sec.get("iterations") is not None:
        its = sec["iterations"]
        its = [_integer(n, f"{key}.iterations[{i}]") for i, n in enumerate(its)] if isinstance(its, list) else _integer(its, f"{key}.iterations")
        if isinstance(its, list) and len(its) != len(out.bands):
            raise ConfigError(f"{key}.iterations: {len(its)} values for {len(out.bands)} bands; give one per band or a single number")
        if min(its if isinstance(its, list) else [its]) < 1:
            raise ConfigError(f"{key}.iterations: {its} has a value < 1; give at least 1 iteration per band")
        out.iterations = its
    if sec.get("evaluations") is not None:
        out.evaluations = _integer(sec["evaluations"], f"{key}.evaluations")
        if out.evaluations < 1:
            raise ConfigError(f"{key}.evaluations: {out.evaluations} < 1; give at least 1 gradient evaluation per band")
    for name in ("rel_decrease", "step", "lr"):
        if sec.get(name) is not None:
            setattr(out, name, _positive(sec[name], f"{key}.{name}"))
    for name, unit in (("water_depth", "m"), ("source_radius", "m"), ("smoothing", "m"), ("tikhonov", ""), ("tv", "")):
        if sec.get(name) is not None:
            val = _number(sec[name], f"{key}.{name}", unit)
            if val < 0:
                raise ConfigError(f"{key}.{name}: {val:g} is negative; give 0 (off) or a positive value")
            setattr(out, name, val)
    if sec.get("bounds") is not None:
        b = sec["bounds"]
        if not isinstance(b, list) or len(b) != 2:
            raise ConfigError(f"{key}.bounds: {b!r} is not [v_min, v_max] in m/s")
        lo, hi = _positive(b[0], f"{key}.bounds[0]", "m/s"), _positive(b[1], f"{key}.bounds[1]", "m/s")
        if lo >= hi:
            raise ConfigError(f"{key}.bounds: v_min {lo:g} >= v_max {hi:g} m/s; give v_min < v_max")
        out.bounds = (lo, hi)
    for name, unit in (("offsets", "m"), ("time_window", "s")):
        if sec.get(name) is not None:
            r = sec[name]
            if not isinstance(r, list) or len(r) != 2:
                raise ConfigError(f"{key}.{name}: {r!r} is not [min, max] in {unit}")
            lo, hi = _number(r[0], f"{key}.{name}[0]", unit), _number(r[1], f"{key}.{name}[1]", unit)
            if not 0 <= lo < hi:
                raise ConfigError(f"{key}.{name}: [{lo:g}, {hi:g}] {unit} is not 0 <= min < max")
            setattr(out, name, (lo, hi))
    if sec.get("wavelet_estimation") is not None:
        out.wavelet_estimation = _boolean(sec["wavelet_estimation"], f"{key}.wavelet_estimation")
    if sec.get("shots_per_batch") is not None:
        out.shots_per_batch = _integer(sec["shots_per_batch"], f"{key}.shots_per_batch")
        if out.shots_per_batch < 1:
            raise ConfigError(f"{key}.shots_per_batch: {out.shots_per_batch} < 1")
    if sec.get("memory_budget_gb") is not None:
        out.memory_budget_gb = _positive(sec["memory_budget_gb"], f"{key}.memory_budget_gb", "GB")
    return out


def parse_fwi_config(raw: dict, base_dir: Path | str | None = None, path: Path | None = None) -> FWIConfig:
    """Validate an inversion config: the forward sections (model = start model) plus `inversion`
    and exactly one of `true_model` (synthetic study) or `observed` (data files)."""
    base_dir = pathlib.Path.cwd() if base_dir is None else pathlib.Path(base_dir)
    forward = parse_config(raw, base_dir, path, extra_sections=FWI_SECTIONS)
    inversion = _parse_inversion(raw.get("inversion"))
    has_true, has_obs = raw.get("true_model") is not None, raw.get("observed") is not None
    if has_true == has_obs:
        raise ConfigError("true_model/observed: give exactly one: true_model (a model spec, for a synthetic study) "
                          "or observed (data files: {kind: hdf5|segy|su, path: ...})")
    true_model = None
    if has_true:
        try:
            true_model = load_model(raw["true_model"], base_dir=base_dir)
        except ModelError as e:
            raise ConfigError(f"true_{e}" if str(e).startswith("model") else f"true_model.{e}") from e
        if true_model.ndim != forward.model.ndim:
            raise ConfigError(f"true_model: {true_model.ndim}D but the start model is {forward.model.ndim}D")
    observed = None
    if has_obs:
        observed = dict(_mapping(raw["observed"], "observed", "observed-data settings"))
        _check_keys(observed, "observed", ("kind", "path", "paths", "coordinate_scale", "inventory", "reference", "component", "shot_times"))
        observed["kind"] = _choice(observed.get("kind"), "observed.kind", ("hdf5", "segy", "su", "mseed", "sac"))
        if observed["kind"] in ("mseed", "sac"):  # station traces: one file (or glob) per shot, in geometry order
            paths = observed.get("paths")
            if not isinstance(paths, list) or len(paths) != forward.n_shots:
                raise ConfigError(f"observed.paths: {paths!r} is not a list of {forward.n_shots} files (one per shot of geometry.sources, in order)")
            observed["paths"] = [str((base_dir / str(p)).resolve()) for p in paths]
            if observed.get("inventory") is not None:
                observed["inventory"] = str((base_dir / str(observed["inventory"])).resolve())
            if observed.get("shot_times") is not None and len(observed["shot_times"]) != forward.n_shots:
                raise ConfigError(f"observed.shot_times: {len(observed['shot_times'])} times for {forward.n_shots} shots")
        else:
            if observed.get("path") is None:
                raise ConfigError("observed.path: missing; give the data file (relative to the config)")
            observed["path"] = (base_dir / str(observed["path"])).resolve()
            if not observed["path"].exists():
                raise ConfigError(f"observed.path: {str(observed['path'])!r} does not exist")
    return FWIConfig(forward, inversion, true_model, observed)


def load_fwi_config(path) -> FWIConfig:
    """Read and validate an inversion YAML file."""
    raw, path = _read_yaml(path)
    return parse_fwi_config(raw, base_dir=path.resolve().parent, path=path)


# ------------------------------------------------------------------------------ location

LOCATE_SECTIONS = ("model", "traces", "preprocess", "source", "search", "simulation", "truth")
TRACES_KEYS = ("paths", "inventory", "reference", "local_coordinates", "component", "fill_gaps", "align")
PREPROCESS_KEYS = ("detrend", "taper", "band", "noise_window", "window")
SOURCE_KEYS = ("stf", "peak_frequency", "frequency_range", "smoothness", "bounds", "start")
SEARCH_KEYS = ("method", "scaled", "iterations", "multi_start", "grid_spacing")


@dataclass
class LocateConfig:
    """An event location (``adseismic locate``). Times in the config are seconds after the traces'
    first common sample, or UTC strings (origin times); positions are world metres, axis order
    (z,[y,]x).

    traces: paths (list of file paths / globs), inventory (StationXML path or None), reference
    (dict latitude, longitude[, datum, azimuth] or None), local_coordinates, component, fill_gaps,
    align (see traces.read_station_traces). preprocess: detrend, taper (fraction at each end), band
    ((fmin or None, fmax or None) Hz or None), noise_window (start, end) s, window "auto" (trim
    around the expected arrivals) or (start, end) s. source: stf ("ricker" or "free"),
    peak_frequency (Hz start or None: the data's dominant frequency), frequency_range (factors),
    smoothness (free STF), bounds ([(lo, hi)] per axis, m, or None: the model less 2 cells), start
    ({position, origin_time} or None: back-projection). search: method, scaled, iterations,
    multi_start, grid_spacing (back-projection candidates, m, or None). truth: optional known
    {position, origin_time} of a synthetic event, reported beside the result.
    """

    model: Model
    traces: dict
    preprocess: dict
    source: dict
    search: dict
    simulation: SimulationConfig
    truth: dict | None = None
    path: Path | None = None
    raw: dict = field(default_factory=dict)


def _pair(value, key: str, unit: str, allow_none=False) -> tuple:
    if not isinstance(value, list) or len(value) != 2:
        raise ConfigError(f"{key}: {value!r} is not [start, end] in {unit}")
    out = tuple(None if (allow_none and v is None) else _number(v, f"{key}[{i}]", unit) for i, v in enumerate(value))
    if None not in out and not out[0] < out[1]:
        raise ConfigError(f"{key}: [{out[0]:g}, {out[1]:g}] {unit} is not increasing; give [start, end] with start < end")
    return out


def _time(value, key: str):
    """Seconds after the record start (a number) or a UTC time string, checked later against the traces."""
    if isinstance(value, str):
        try:
            return _number(value, key)
        except ConfigError:
            return value
    return _number(value, key, "s")


def _parse_location_point(raw, key: str, model: Model) -> dict:
    p = _mapping(raw, key, "position (m) and origin_time (s after the record start, or UTC)")
    _check_keys(p, key, ("position", "origin_time"))
    if p.get("position") is None:
        raise ConfigError(f"{key}.position: missing; give [{', '.join(AXES[model.ndim])}] in world metres")
    pos = np.asarray(_point(p["position"], f"{key}.position", model.ndim))
    _check_inside(pos[None], f"{key}.position", model)
    return {"position": pos, "origin_time": None if p.get("origin_time") is None else _time(p["origin_time"], f"{key}.origin_time")}


def _parse_location_bounds(raw, key: str, model: Model):
    b = _mapping(raw, key, f"one [lo, hi] range in metres per axis ({', '.join(AXES[model.ndim])})")
    _check_keys(b, key, AXES[model.ndim])
    out = []
    for a, (lo_m, hi_m) in zip(AXES[model.ndim], model.extent):
        lo, hi = (lo_m, hi_m) if b.get(a) is None else _pair(b[a], f"{key}.{a}", "m")
        if lo < lo_m - 1e-6 or hi > hi_m + 1e-6:
            raise ConfigError(f"{key}.{a}: [{lo:g}, {hi:g}] m reaches outside the model ({lo_m:g}..{hi_m:g} m); keep the search inside it")
        out.append((lo, hi))
    return out


def parse_locate_config(raw: dict, base_dir: Path | str | None = None, path: Path | None = None) -> LocateConfig:
    """Validate a location config (sections model, traces, preprocess, source, search, simulation,
    truth); only model and traces are required. Raises ConfigError naming the key."""
    from adseismic.location.locate import METHODS, STFS

    base_dir = pathlib.Path.cwd() if base_dir is None else pathlib.Path(base_dir)
    if not isinstance(raw, dict):
        raise ConfigError(f"config: {type(raw).__name__} is not a mapping; a location config has the sections {', '.join(LOCATE_SECTIONS)}")
    _check_keys(raw, "", LOCATE_SECTIONS)
    for k in ("model", "traces"):
        if raw.get(k) is None:
            raise ConfigError(f"{k}: missing; a location config needs model (the velocity model) and traces (the event's files)")
    simulation = _parse_simulation(raw.get("simulation"))
    if (raw.get("simulation") or {}).get("precision") is None:
        simulation.precision = "float64"  # the covariance comes from differences of simulations
    try:
        model = load_model(raw["model"], base_dir=base_dir)
    except ModelError as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith("model") else f"model.{msg}") from e

    t = _mapping(raw["traces"], "traces", "paths (MiniSEED, SAC, ...) and station metadata")
    _check_keys(t, "traces", TRACES_KEYS)
    paths = t.get("paths")
    paths = [paths] if isinstance(paths, str) else paths
    if not isinstance(paths, list) or not paths or not all(isinstance(p, str) for p in paths):
        raise ConfigError(f"traces.paths: {t.get('paths')!r} is not a file path, glob or list of them (relative to the config)")
    traces = {"paths": [str(base_dir / p) for p in paths], "inventory": None, "reference": t.get("reference"),
              "local_coordinates": t.get("local_coordinates"), "component": t.get("component"),
              "fill_gaps": t.get("fill_gaps"), "align": False}  # fmt: skip
    if t.get("inventory") is not None:
        inv = base_dir / str(t["inventory"])
        if not inv.exists():
            raise ConfigError(f"traces.inventory: {str(inv)!r} does not exist; give the StationXML file (relative to the config)")
        traces["inventory"] = str(inv)
    if t.get("align") is not None:
        traces["align"] = _boolean(t["align"], "traces.align")

    p = _mapping(raw.get("preprocess") or {}, "preprocess", "detrend, taper, band, noise_window, window")
    _check_keys(p, "preprocess", PREPROCESS_KEYS)
    pre = {"detrend": True, "taper": 0.05, "band": None, "noise_window": None, "window": "auto"}
    if p.get("detrend") is not None:
        pre["detrend"] = _boolean(p["detrend"], "preprocess.detrend")
    if p.get("taper") is not None:
        pre["taper"] = _number(p["taper"], "preprocess.taper")
        if not 0 <= pre["taper"] <= 0.5:
            raise ConfigError(f"preprocess.taper: {pre['taper']:g} is not a fraction in [0, 0.5] of the record at each end")
    if p.get("band") is not None:
        pre["band"] = _pair(p["band"], "preprocess.band", "Hz", allow_none=True)
    if p.get("noise_window") is None:
        raise ConfigError("preprocess.noise_window: missing; give [start, end] s after the record start of a window "
                          "before the first arrival (the data noise that weights the misfit and sets the uncertainty)")
    pre["noise_window"] = _pair(p["noise_window"], "preprocess.noise_window", "s")
    if pre["noise_window"][0] < 0:
        raise ConfigError(f"preprocess.noise_window: starts at {pre['noise_window'][0]:g} s, before the record; give times >= 0")
    if p.get("window") is not None and p["window"] != "auto":
        pre["window"] = _pair(p["window"], "preprocess.window", "s")

    s = _mapping(raw.get("source") or {}, "source", "the source-time function and search region")
    _check_keys(s, "source", SOURCE_KEYS)
    src = {"stf": "ricker", "peak_frequency": None, "frequency_range": (0.3, 3.0), "smoothness": 0.01, "bounds": None, "start": None}
    if s.get("stf") is not None:
        src["stf"] = _choice(s["stf"], "source.stf", STFS)
    if s.get("peak_frequency") is not None:
        src["peak_frequency"] = _positive(s["peak_frequency"], "source.peak_frequency", "Hz")
    if s.get("frequency_range") is not None:
        fr = _pair(s["frequency_range"], "source.frequency_range", "(factors of the start peak frequency)")
        if not 0 < fr[0] < 1 < fr[1]:
            raise ConfigError(f"source.frequency_range: {list(fr)} must bracket 1, e.g. [0.3, 3]")
        src["frequency_range"] = fr
    if s.get("smoothness") is not None:
        src["smoothness"] = _number(s["smoothness"], "source.smoothness")
        if src["smoothness"] < 0:
            raise ConfigError(f"source.smoothness: {src['smoothness']:g} is negative; give 0 (none) or a positive weight")
    if s.get("bounds") is not None:
        src["bounds"] = _parse_location_bounds(s["bounds"], "source.bounds", model)
    if s.get("start") is not None:
        src["start"] = _parse_location_point(s["start"], "source.start", model)
        if src["start"]["origin_time"] is None:
            raise ConfigError("source.start.origin_time: missing; give it with the start position (or drop source.start)")

    q = _mapping(raw.get("search") or {}, "search", "the optimiser settings")
    _check_keys(q, "search", SEARCH_KEYS)
    search = {"method": "lbfgs", "scaled": True, "iterations": 60, "multi_start": 1, "grid_spacing": None}
    if q.get("method") is not None:
        search["method"] = _choice(q["method"], "search.method", METHODS)
    if q.get("scaled") is not None:
        search["scaled"] = _boolean(q["scaled"], "search.scaled")
    for name in ("iterations", "multi_start"):
        if q.get(name) is not None:
            search[name] = _integer(q[name], f"search.{name}")
            if search[name] < 1:
                raise ConfigError(f"search.{name}: {search[name]} < 1; give at least 1")
    if q.get("grid_spacing") is not None:
        search["grid_spacing"] = _positive(q["grid_spacing"], "search.grid_spacing", "m")
    truth = None if raw.get("truth") is None else _parse_location_point(raw["truth"], "truth", model)
    return LocateConfig(model, traces, pre, src, search, simulation, truth, path, raw)


def load_locate_config(path) -> LocateConfig:
    """Read and validate a location YAML file; relative paths resolve from its folder."""
    raw, path = _read_yaml(path)
    return parse_locate_config(raw, base_dir=path.resolve().parent, path=path)
