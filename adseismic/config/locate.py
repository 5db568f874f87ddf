"""Event-location configuration (``adseismic locate``): sections model, traces, preprocess,
source, search, simulation and truth; only model and traces are required.

The accepted search methods and source-time-function kinds are :data:`LOCATE_METHODS` and
:data:`STF_KINDS` (kept equal to ``adseismic.location.locate.METHODS`` / ``STFS`` by a test), so
that loading a config imports no workflow.
"""
from __future__ import annotations

import pathlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from adseismic.config import schema
from adseismic.config.common import ConfigError, _check_keys, _mapping, _number, _read_yaml, _short
from adseismic.config.forward import (AXES, SimulationConfig, _check_inside, _load_model, _parse_physics, _parse_simulation, _point,
                                      refuse_elastic3d, refuse_forward_only)
from adseismic.config.schema import given, validate_section
from adseismic.data.models import Model

__all__ = ["LocateConfig", "parse_locate_config", "load_locate_config", "LOCATE_METHODS", "STF_KINDS"]

LOCATE_SECTIONS = ("physics", "model", "traces", "preprocess", "source", "search", "simulation", "truth")
LOCATE_METHODS = schema.LOCATE_METHODS  # adseismic.location.locate.METHODS (a test keeps them equal)
STF_KINDS = schema.STF_KINDS  # adseismic.location.locate.STFS


@dataclass
class LocateConfig:
    """An event location (``adseismic locate``). Times in the config are seconds after the traces'
    first common sample, or UTC strings (origin times); positions are world metres, axis order
    (z,[y,]x).

    traces: paths (list of file paths / globs), inventory (StationXML path or None), reference
    (dict latitude, longitude[, datum, azimuth] or None), local_coordinates, component, fill_gaps,
    align (see adseismic.data.read.read_station_traces). preprocess: detrend, taper (fraction at each end), band
    ((fmin or None, fmax or None) Hz or None), noise_window (start, end) s, window "auto" (trim
    around the expected arrivals) or (start, end) s. source: stf ("ricker" or "free"),
    peak_frequency (Hz start or None: the data's dominant frequency), frequency_range (factors),
    smoothness (free STF), bounds ([(lo, hi)] per axis, m, or None: the model less 2 cells), start
    ({position, origin_time} or None: back-projection). search: method, scaled, iterations,
    multi_start, grid_spacing (back-projection candidates, m, or None). truth: optional known
    {position, origin_time} of a synthetic event, reported beside the result. physics: acoustic (model a
    Model, source.type pressure) or elastic (model an ElasticModel, 2D; source.type moment with
    source.constraint none, deviatoric or double_couple; traces Z (vertical, up) and X (along the line) per station).
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
    physics: str = "acoustic"


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


def _check_local_coordinates(local, ndim: int) -> None:
    """traces.local_coordinates: one [z, (y,) x] in metres per station (the schema cannot know the model's dimension)."""
    if local is None:
        return
    if not isinstance(local, dict):
        raise ConfigError(f"traces.local_coordinates: {_short(local)} is not a mapping of station (NET.STA or "
                          f"NET.STA.LOC.CHA) to [{', '.join(AXES[ndim])}] in metres")
    for k, v in local.items():
        pts = list(v.values()) if isinstance(v, dict) else v
        if not isinstance(k, str) or not isinstance(pts, list) or len(pts) != ndim:
            raise ConfigError(f"traces.local_coordinates.{k}: {_short(v)} is not [{', '.join(AXES[ndim])}] in metres")
        for i, x in enumerate(pts):
            _number(x, f"traces.local_coordinates.{k}[{i}]", "m")


def _check_mechanism(src: dict, physics: str) -> None:
    """source.type / source.constraint against the physics: a moment tensor needs elastic physics, elastic locates a
    moment tensor; fills the default constraint (none)."""
    if physics == "acoustic":
        if src["type"] == "moment":
            raise ConfigError("source.type: 'moment' (a moment-tensor source) needs elastic physics; an acoustic model "
                              "has a pressure source only: set physics: elastic with model {vp, vs, rho}, or drop source.type")
        if src["constraint"] is not None:
            raise ConfigError(f"source.constraint: {src['constraint']!r} constrains a moment tensor, which needs physics: "
                              f"elastic; drop source.constraint for acoustic physics")
        return
    if src["type"] != "moment":
        raise ConfigError(f"source.type: {src['type']!r} with physics elastic; the elastic locator fits a moment tensor: give "
                          f"source.type: moment (or leave it out)")
    src["constraint"] = src["constraint"] or "none"  # a 3D elastic model is refused (forward.refuse_elastic3d)


def parse_locate_config(raw: dict, base_dir: Path | str | None = None, path: Path | None = None) -> LocateConfig:
    """Validate a location config (sections model, traces, preprocess, source, search, simulation,
    truth); only model and traces are required. Raises ConfigError naming the key."""
    base_dir = pathlib.Path.cwd() if base_dir is None else pathlib.Path(base_dir)
    if not isinstance(raw, dict):
        raise ConfigError(f"config: {type(raw).__name__} is not a mapping; a location config has the sections {', '.join(LOCATE_SECTIONS)}")
    if raw.get("parallel") is not None:
        raise ConfigError("parallel: a location simulates one event per evaluation (one forward and one adjoint run of "
                          "a single source), there are no shots to split over workers or devices; drop the section "
                          "(locate runs on simulation.device)")
    _check_keys(raw, "", LOCATE_SECTIONS)
    for k in ("model", "traces"):
        if raw.get(k) is None:
            raise ConfigError(f"{k}: missing; a location config needs model (the velocity model) and traces (the event's files)")
    simulation = _parse_simulation(raw.get("simulation"))
    if (raw.get("simulation") or {}).get("precision") is None:
        simulation.precision = "float64"  # the covariance comes from differences of simulations
    physics = _parse_physics(raw.get("physics"))
    refuse_forward_only(physics, "locate", "locate with physics: acoustic (model: the vp spec) or physics: elastic")
    if physics == "acoustic_vd":  # a location fits travel times (and a source amplitude), not interface amplitudes
        raise ConfigError("physics: acoustic_vd is not available for adseismic locate (an event's location comes from "
                          "travel times, which density does not change); use physics: acoustic with model: the vp spec, "
                          "or physics: elastic for a moment-tensor source")
    model = _load_model(raw["model"], base_dir, physics)
    refuse_elastic3d(model)

    t = given(validate_section(schema.Traces, raw["traces"], "traces"))  # keys and types
    if "paths" not in t:
        raise ConfigError(f"traces.paths: {raw['traces'].get('paths')!r} is not a file path, glob or list of them "
                          f"(relative to the config)")
    traces = {"paths": [str(base_dir / p) for p in t["paths"]], "inventory": None, "reference": t.get("reference"),
              "local_coordinates": t.get("local_coordinates"), "component": t.get("component"),
              "fill_gaps": t.get("fill_gaps"), "align": t.get("align", False)}  # fmt: skip
    if "inventory" in t:
        inv = base_dir / t["inventory"]
        if not inv.exists():
            raise ConfigError(f"traces.inventory: {str(inv)!r} does not exist; give the StationXML file (relative to the config)")
        traces["inventory"] = str(inv)
    _check_local_coordinates(traces["local_coordinates"], model.ndim)

    p = given(validate_section(schema.Preprocess, raw.get("preprocess"), "preprocess"))  # keys, types, ranges
    pre = {"detrend": True, "taper": 0.05, "band": None, "noise_window": None, "window": "auto"}
    pre.update({k: tuple(v) if isinstance(v, list) else v for k, v in p.items()})
    if pre["noise_window"] is None:
        raise ConfigError("preprocess.noise_window: missing; give [start, end] s after the record start of a window "
                          "before the first arrival (the data noise that weights the misfit and sets the uncertainty)")
    if pre["noise_window"][0] < 0:
        raise ConfigError(f"preprocess.noise_window: starts at {pre['noise_window'][0]:g} s, before the record; give times >= 0")

    s = given(validate_section(schema.Source, raw.get("source"), "source"))  # keys, types
    src = {"stf": "ricker", "peak_frequency": None, "frequency_range": (0.3, 3.0), "smoothness": 0.01, "bounds": None, "start": None,
           "type": "moment" if physics == "elastic" else "pressure", "constraint": None}  # fmt: skip
    src.update({k: s[k] for k in ("stf", "peak_frequency", "smoothness", "type", "constraint") if k in s})
    _check_mechanism(src, physics)
    if "frequency_range" in s:
        fr = tuple(s["frequency_range"])
        if not 0 < fr[0] < 1 < fr[1]:
            raise ConfigError(f"source.frequency_range: {list(fr)} must bracket 1, e.g. [0.3, 3]")
        src["frequency_range"] = fr
    if "bounds" in s:
        src["bounds"] = _parse_location_bounds(raw["source"]["bounds"], "source.bounds", model)
    if "start" in s:
        src["start"] = _parse_location_point(raw["source"]["start"], "source.start", model)
        if src["start"]["origin_time"] is None:
            raise ConfigError("source.start.origin_time: missing; give it with the start position (or drop source.start)")

    search = {"method": "lbfgs", "scaled": True, "iterations": 60, "multi_start": 1, "grid_spacing": None}
    search.update(given(validate_section(schema.Search, raw.get("search"), "search")))  # keys, types, ranges
    truth = None if raw.get("truth") is None else _parse_location_point(raw["truth"], "truth", model)
    return LocateConfig(model, traces, pre, src, search, simulation, truth, path, raw, physics)


def load_locate_config(path) -> LocateConfig:
    """Read and validate a location YAML file; relative paths resolve from its folder."""
    raw, path = _read_yaml(path)
    return parse_locate_config(raw, base_dir=path.resolve().parent, path=path)
