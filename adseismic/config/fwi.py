"""Full-waveform-inversion configuration (``adseismic fwi``): the forward sections (``model`` is the
start model) plus ``inversion`` and exactly one of ``true_model`` or ``observed``.

The accepted misfit names are :data:`MISFIT_NAMES` (kept equal to
``adseismic.solve.misfits.MISFITS`` by a test), so that loading a config imports no workflow.
"""
from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from adseismic.config import schema
from adseismic.config.common import ConfigError, _check_keys, _choice, _mapping, _positive, _read_yaml, _short
from adseismic.config.forward import AXES, ForwardConfig, parse_config, refuse_elastic3d
from adseismic.config.parallel import ParallelConfig, parse_parallel
from adseismic.config.schema import given, validate_section
from adseismic.data.models import ElasticModel, Model, ModelError, load_physics_model

__all__ = ["InversionConfig", "FWIConfig", "parse_fwi_config", "load_fwi_config", "MISFIT_NAMES", "OPTIMIZERS",
           "PRECONDITIONERS"]

INVERSION_KEYS = tuple(schema.Inversion.model_fields)  # types, units, defaults, ranges: adseismic.config.schema
FWI_SECTIONS = ("true_model", "observed", "inversion", "parallel")
OPTIMIZERS = schema.OPTIMIZERS
PRECONDITIONERS = schema.PRECONDITIONERS
MISFIT_NAMES = schema.MISFIT_NAMES  # adseismic.solve.misfits.MISFITS (a test keeps them equal)
OBSERVED_KEYS = ("kind", "path", "paths", "coordinate_scale", "inventory", "reference", "component", "shot_times",
                 "depth_convention")
DEPTH_CONVENTIONS = ("auto", "elevation", "depth")  # adseismic.data.read.DEPTH_CONVENTIONS



@dataclass
class InversionConfig:
    """Full-waveform inversion settings (units: Hz, m/s, m). bands: list of (f_low or None, f_high or
    None) pass bands, inverted in order; iterations / evaluations: limits per band (an evaluation is
    one misfit + gradient over all shots); bounds: (v_min, v_max) m/s, or {quantity: (min, max)} in its unit
    (m/s, kg/m^3, Pa; q, epsilon, delta dimensionless), or None (start model range +-25%; q, epsilon, delta:
    inversion.fwi._default_bounds); parameters: the inverted quantities of parameterization (vp-vs-rho or
    lambda-mu-rho; None: all; acoustic: vp) or of physics viscoacoustic (vp, q, rho) and vti (vp, epsilon, delta, rho)
    (None: vp) (adseismic.inversion.model_space); water_depth / source_radius: gradient masks (m, 0 = off); smoothing: Gaussian sigma of
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
    preconditioning: str | None = None  # None: resolved by default_preconditioning (parse_fwi_config)
    tikhonov: float = 0.0
    tv: float = 0.0
    wavelet_estimation: bool = False
    shots_per_batch: int | None = None
    memory_budget_gb: float | None = None
    step: float = 1.0
    lr: float = 0.01
    offsets: tuple | None = None
    time_window: tuple | None = None
    parameters: tuple | None = None  # the inverted quantities (None: all of the parameterization's)
    parameterization: str = "vp-vs-rho"  # or lambda-mu-rho (physics elastic)
    transform: str = "sigmoid"  # q = lo + (hi - lo) sigmoid(x), or linear (inversion.model_space)
    grid: str | None = None  # fixed or per_band (each band on the coarsest grid that resolves it: inversion.fwi.band_plan); None: resolved by _check_inversion_physics


@dataclass
class FWIConfig:
    """An inversion: `forward.model` is the START model; observed data come from `true_model`
    (a synthetic study) or from `observed` (files: {kind: hdf5|segy|su|asdf, path: ...})."""

    forward: ForwardConfig
    inversion: InversionConfig
    true_model: Model | ElasticModel | None = None  # of forward.physics
    observed: dict | None = None
    parallel: ParallelConfig | None = None  # the shots on Dask workers (config.parallel); None: one process
    network: dict | None = None  # model: {kind: nn}: {v0, scale (m/s), hidden, seed} (inversion.parameterization.MLP)
    chosen: dict = field(default_factory=dict)  # {inversion key left null: why it got its value}, for the run's log

    @property
    def physics(self) -> str:
        return self.forward.physics


def _check_band_order(bands, key: str) -> None:
    """Refuse bands whose upper edges fall (null = the full band, the highest): multiscale inversion goes from
    low to high frequencies, and high first invites cycle skipping that the later low bands cannot undo."""
    def top(b):
        return math.inf if b[1] is None else b[1]

    for i in range(1, len(bands)):
        if top(bands[i]) < top(bands[i - 1]):
            def show(b):
                return "null (full band)" if b[1] is None else f"{b[1]:g} Hz"
            raise ConfigError(f"{key}: band {i} (up to {show(bands[i])}) is lower than band {i - 1} (up to {show(bands[i - 1])}); "
                              f"bands run low to high (each starts from the previous one's model): reorder them, e.g. "
                              f"{sorted((b[1] for b in bands if b[1] is not None))}{' then null' if any(b[1] is None for b in bands) else ''}")


def _parse_inversion(raw, key="inversion") -> InversionConfig:
    """The inversion section: keys, types and ranges by the schema (:class:`adseismic.config.schema.Inversion`);
    here what it cannot say: band order, fmin < fmax, one iteration count per band, v_min < v_max."""
    v = given(validate_section(schema.Inversion, raw, key))
    out = InversionConfig()
    if "bands" in v:
        out.bands = []
        for i, b in enumerate(v["bands"]):
            band = (None, None) if b is None else (b.fmin, b.fmax)
            if None not in band and band[0] >= band[1]:
                raise ConfigError(f"{key}.bands[{i}]: fmin {band[0]:g} Hz >= fmax {band[1]:g} Hz; give fmin < fmax")
            out.bands.append(band)
        _check_band_order(out.bands, f"{key}.bands")
    its = v.get("iterations")
    if isinstance(its, list) and len(its) != len(out.bands):
        raise ConfigError(f"{key}.iterations: {len(its)} values for {len(out.bands)} bands; give one per band or a single number")
    for name in ("offsets", "time_window"):
        if name in v and not 0 <= v[name][0]:
            unit = "m" if name == "offsets" else "s"
            raise ConfigError(f"{key}.{name}: [{v[name][0]:g}, {v[name][1]:g}] {unit} is not 0 <= min < max")
    for name, value in v.items():
        if name != "bands":
            if name == "bounds" and isinstance(value, dict):
                value = {k: tuple(b) for k, b in value.items()}
            elif name in ("bounds", "offsets", "time_window", "parameters"):
                value = tuple(value)
            setattr(out, name, value)
    return out


def _parse_network(raw: dict) -> tuple:
    """model: {kind: nn, ...} (schema.NNModelSpec): (the network's settings, the raw config with model replaced by a
    constant v0 model on the same grid, what the planner and the geometry checks read); else (None, raw)."""
    spec = raw.get("model") if isinstance(raw, dict) else None
    if not (isinstance(spec, dict) and spec.get("kind") == "nn"):
        return None, raw
    v = given(validate_section(schema.NNModelSpec, spec, "model"))
    if raw.get("physics", "acoustic") != "acoustic":
        raise ConfigError(f"model.kind: nn with physics {raw.get('physics')}: a network represents the acoustic velocity "
                          f"only; set physics: acoustic, or give model: {{vp, vs, rho}} for elastic FWI")
    net = {"v0": float(v["v0"]), "scale": float(v["scale"]), "hidden": int(v.get("hidden", 8)), "seed": int(v.get("seed", 0))}
    if net["hidden"] > 64:
        raise ConfigError(f"model.hidden: {net['hidden']} units; the MLP kernel unrolls its layers, use at most 64")
    grid = {k: spec[k] for k in ("shape", "spacing", "origin") if k in spec}
    return net, {**raw, "model": {"kind": "constant", "velocity": net["v0"], **grid}}


def _check_inversion_physics(inv: InversionConfig, physics: str, network, raw) -> None:
    """What the inversion section may ask of the physics: its quantities, parameterisation, bounds and options."""
    if physics == "acoustic":
        if inv.parameterization != "vp-vs-rho" and "parameterization" in (raw.get("inversion") or {}):
            raise ConfigError(f"inversion.parameterization: {inv.parameterization} needs physics: elastic (acoustic physics "
                              f"inverts the velocity vp alone); drop it or set physics: elastic with model: {{vp, vs, rho}}")
        quantities = ("vp",)
    elif physics in schema.OWN_QUANTITIES:  # viscoacoustic, vti: their solver's parameters themselves
        quantities = schema.OWN_QUANTITIES[physics]
        if "parameterization" in (raw.get("inversion") or {}):
            raise ConfigError(f"inversion.parameterization: {inv.parameterization} with physics {physics}, which inverts its own "
                              f"quantities ({', '.join(quantities)}) directly; drop it and list them in inversion.parameters")
    else:
        quantities = schema.PARAMETERIZATION_QUANTITIES[inv.parameterization]
        if physics == "acoustic_vd" and inv.parameterization == "lambda-mu-rho":
            raise ConfigError("inversion.parameterization: lambda-mu-rho with physics acoustic_vd, a fluid (mu = 0); use "
                              "vp-vs-rho (inverts vp and rho; vs stays 0) or ip-rho (impedance and density)")
        if physics == "elastic" and inv.parameterization == "ip-rho":
            raise ConfigError("inversion.parameterization: ip-rho (acoustic impedance) needs physics: acoustic_vd (a "
                              "fluid); use vp-vs-rho or lambda-mu-rho with physics elastic")
        if physics == "acoustic_vd":  # vs stays 0: never inverted
            quantities = tuple(q for q in quantities if q != "vs")
    for q in inv.parameters or ():
        if q not in quantities:
            why = (f"physics {physics} has the one parameter vp" if physics == "acoustic" else
                   "physics acoustic_vd is a fluid: vs stays 0" if q == "vs" and physics == "acoustic_vd" else
                   f"physics {physics} has {', '.join(quantities)}" if physics in schema.OWN_QUANTITIES else
                   f"parameterization {inv.parameterization} moves {', '.join(quantities)}")
            raise ConfigError(f"inversion.parameters: {q} is not a quantity here ({why}); use any of {', '.join(quantities)}")
    if inv.parameters is not None and len(set(inv.parameters)) != len(inv.parameters):
        raise ConfigError(f"inversion.parameters: {list(inv.parameters)} names a quantity twice; list each once")
    inverted = inv.parameters or (("vp",) if physics in schema.OWN_QUANTITIES else quantities)  # (inversion.fwi._inverted)
    if isinstance(inv.bounds, dict):
        for q in inv.bounds:
            if q not in inverted:
                raise ConfigError(f"inversion.bounds.{q}: {list(inv.bounds[q])} bounds a quantity that is not inverted "
                                  f"(inverted: {', '.join(inverted)}); drop it or add {q} to inversion.parameters")
        if "lambda" in inv.bounds and inv.bounds["lambda"][0] < 0:
            raise ConfigError(f"inversion.bounds.lambda: [{inv.bounds['lambda'][0]:g}, {inv.bounds['lambda'][1]:g}] Pa allows "
                              f"lambda < 0 (vs > vp / sqrt(2)), which the elastic solver refuses; give a lower bound >= 0")
        for q, floor, why in (("q", 0.0, "Q > 0 (30 a lossy sediment, 100-1000 rock)"),
                              ("epsilon", -0.5, "the horizontal qP speed vp sqrt(1 + 2 epsilon) needs epsilon > -1/2"),
                              ("delta", -0.5, "the VTI solver needs delta > -1/2")):  # fmt: skip
            if q in inv.bounds and not (inv.bounds[q][0] > floor and math.isfinite(inv.bounds[q][1])):
                raise ConfigError(f"inversion.bounds.{q}: [{inv.bounds[q][0]:g}, {inv.bounds[q][1]:g}] allows {q} <= {floor:g} or "
                                  f"infinite: {why}; give finite bounds above {floor:g}")
    elif inv.bounds is not None and physics != "acoustic":
        example = {"elastic": "{vp: [1500, 3500], vs: [800, 2000]} (m/s)", "viscoacoustic": "{vp: [1500, 3500], q: [10, 500]}",
                   "vti": "{vp: [1500, 3500], epsilon: [0, 0.3]}"}.get(physics, "{vp: [1500, 3500], rho: [1000, 2600]} (m/s, kg/m^3)")
        raise ConfigError(f"inversion.bounds: {list(inv.bounds)} is one [min, max] pair but physics {physics} inverts "
                          f"{', '.join(inverted)}; give one per quantity, e.g. {example}")
    pixels = physics == "acoustic" and network is None
    if inv.grid == "per_band" and not pixels:
        raise ConfigError(f"inversion.grid: per_band with {'a network model' if network is not None else f'physics {physics}'}; "
                          f"the per-band grids move acoustic pixel models only: use grid: fixed")
    if inv.grid is None:  # per_band where it applies: fewer cells and steps for a low band at the same accuracy
        inv.grid = "per_band" if pixels else "fixed"
    if physics != "acoustic":  # the staggered solvers (elastic, acoustic_vd, viscoacoustic, vti)
        for key, bad, why, fix in (("preconditioning", inv.preconditioning == "pseudo_hessian", f"the {physics} gradient has no illumination", "use none or depth"),
                                   ("wavelet_estimation", inv.wavelet_estimation, "the wavelet fit is for one data channel", "set it false")):  # fmt: skip
            if bad:
                raise ConfigError(f"inversion.{key}: {getattr(inv, key)} is acoustic only ({why}); {fix}")
        for section in ("observed", "parallel"):
            if raw.get(section) is not None:
                what = (f"FWI with physics {physics} simulates its observed data from true_model" if section == "observed" else
                        "the parallel shot pools (dask, threads) run acoustic shots only")
                raise ConfigError(f"{section}: given with physics {physics}; {what}: drop {section} (use true_model)"
                                  if section == "observed" else f"{section}: given with physics {physics}; {what}: drop it")


SURFACE_SHARE = 0.1  # an acquisition is at the surface when every source and receiver lies in this top share of the model


def default_preconditioning(forward, network) -> tuple[str, str]:
    """(kind, why) of inversion.preconditioning null: depth for acoustic pixels under a surface acquisition, else none.
    Under surface sources and receivers the gradient's amplitude falls with depth (geometrical spreading of both
    wavefields), so L-BFGS spends its first iterations on the shallow part; z / z_max evens that out (measured,
    docs/fwi.md: the FWI race 0.61 -> 0.49 model error, Marmousi-II 36% -> 41% lower error). Elsewhere (transmission,
    a network model, the staggered physics) it is not measured, so not assumed."""
    if forward.physics != "acoustic" or network is not None:
        return "none", "the default beside a network model or a staggered physics"
    top, bottom = forward.model.extent[0]
    deepest = float(np.concatenate([forward.geometry.sources[:, 0], forward.geometry.receivers[:, 0]]).max()) - top
    where = f"the deepest source or receiver {deepest:g} m below the model's top, of {bottom - top:g} m"
    if deepest <= SURFACE_SHARE * (bottom - top):
        return "depth", f"the default under a surface acquisition: {where}"
    return "none", f"the default with sources or receivers at depth: {where}"


def parse_fwi_config(raw: dict, base_dir: Path | str | None = None, path: Path | None = None) -> FWIConfig:
    """Validate an inversion config: the forward sections (model = start model) plus `inversion`
    and exactly one of `true_model` (synthetic study) or `observed` (data files)."""
    base_dir = pathlib.Path.cwd() if base_dir is None else pathlib.Path(base_dir)
    network, raw_forward = _parse_network(raw)
    forward = parse_config(raw_forward, base_dir, path, extra_sections=FWI_SECTIONS)
    refuse_elastic3d(forward.model)
    forward.raw = raw
    inversion = _parse_inversion(raw.get("inversion"))
    _check_inversion_physics(inversion, forward.physics, network, raw)
    chosen = {}
    if inversion.preconditioning is None:
        inversion.preconditioning, chosen["preconditioning"] = default_preconditioning(forward, network)
    parallel = parse_parallel(raw.get("parallel"), forward.n_shots)
    has_true, has_obs = raw.get("true_model") is not None, raw.get("observed") is not None
    if has_true == has_obs:
        raise ConfigError("true_model/observed: give exactly one: true_model (a model spec, for a synthetic study) "
                          "or observed (data files: {kind: hdf5|segy|su|asdf, path: ...})")
    true_model = None
    if has_true:
        try:
            true_model = load_physics_model(raw["true_model"], forward.physics, base_dir=base_dir)
        except ModelError as e:
            raise ConfigError(f"true_{e}" if str(e).startswith("model") else f"true_model.{e}") from e
        if true_model.ndim != forward.model.ndim:
            raise ConfigError(f"true_model: {true_model.ndim}D but the start model is {forward.model.ndim}D")
        for key in ("q_band", "f_ref", "mechanisms") if forward.physics == "viscoacoustic" else ():  # one physics for both
            mine, start = getattr(true_model, key), getattr(forward.model, key)
            if mine is not None and mine != start:
                raise ConfigError(f"true_model.{key}: {mine} differs from model.{key} ({start}); the observed data and the "
                                  f"inversion use the start model's relaxation mechanisms: give the same or leave it out")
        for name in ("sources", "receivers"):
            pts = getattr(forward.geometry, name)
            inside = true_model.contains(pts)
            if not inside.all():
                i = int(np.argmin(inside))
                where = ", ".join(f"{a}={v:g}" for a, v in zip(AXES[true_model.ndim], pts[i]))
                box = ", ".join(f"{a} [{lo:g}, {hi:g}]" for a, (lo, hi) in zip(AXES[true_model.ndim], true_model.extent))
                raise ConfigError(f"true_model: it covers {box} m, smaller than the geometry: geometry.{name} point {i} "
                                  f"({where}) m and {int((~inside).sum()) - 1} more of {len(pts)} lie outside it; give a "
                                  f"true model that covers every source and receiver (like the start model: "
                                  f"{', '.join(f'{a} [{lo:g}, {hi:g}]' for a, (lo, hi) in zip(AXES[forward.ndim], forward.model.extent))} m)")
    observed = None
    if has_obs:
        observed = dict(_mapping(raw["observed"], "observed", "observed-data settings"))
        _check_keys(observed, "observed", OBSERVED_KEYS)
        observed["kind"] = _choice(observed.get("kind"), "observed.kind", ("hdf5", "segy", "su", "mseed", "sac", "asdf"))
        if observed["kind"] == "asdf":
            import importlib.util

            if importlib.util.find_spec("pyasdf") is None:
                raise ConfigError('observed.kind: asdf needs pyasdf, which is not installed; pip install "adseismic[asdf]"')
        if observed["kind"] in ("mseed", "sac"):  # station traces: one file (or glob) per shot, in geometry order
            paths = observed.get("paths")
            if not isinstance(paths, list) or len(paths) != forward.n_shots or not all(isinstance(p, str) and p for p in paths):
                raise ConfigError(f"observed.paths: {_short(paths)} is not a list of {forward.n_shots} file paths (one per shot "
                                  f"of geometry.sources, in order)")
            observed["paths"] = [str((base_dir / str(p)).resolve()) for p in paths]
            if observed.get("inventory") is not None:
                if not isinstance(observed["inventory"], str):
                    raise ConfigError(f"observed.inventory: {_short(observed['inventory'])} is not a file path; give the StationXML file")
                observed["inventory"] = str((base_dir / str(observed["inventory"])).resolve())
            times = observed.get("shot_times")
            if times is not None:
                if not isinstance(times, list) or not all(isinstance(t, str) for t in times):
                    raise ConfigError(f"observed.shot_times: {_short(times)} is not a list of UTC times (text, e.g. "
                                      f"'2024-01-01T00:00:00'), one per shot")
                if len(times) != forward.n_shots:
                    raise ConfigError(f"observed.shot_times: {len(times)} times for {forward.n_shots} shots; give one per shot")
            if observed.get("reference") is not None and not isinstance(observed["reference"], (list, dict)):
                raise ConfigError(f"observed.reference: {_short(observed['reference'])} is not [latitude, longitude] (degrees) "
                                  f"or {{latitude, longitude, datum, azimuth}}")
            if observed.get("component") is not None and not isinstance(observed["component"], str):
                raise ConfigError(f"observed.component: {_short(observed['component'])} is not a component letter, e.g. Z")
        else:
            if observed.get("path") is None or not isinstance(observed["path"], str):
                raise ConfigError(f"observed.path: {_short(observed.get('path'))}: missing or not a path; give the data file "
                                  f"(relative to the config)")
            observed["path"] = (base_dir / str(observed["path"])).resolve()
            if not observed["path"].is_file():
                raise ConfigError(f"observed.path: {str(observed['path'])!r} does not exist")
        if observed.get("coordinate_scale") is not None:
            observed["coordinate_scale"] = _positive(observed["coordinate_scale"], "observed.coordinate_scale", "m per header unit")
        if observed.get("depth_convention") is not None:
            if observed["kind"] not in ("segy", "su"):
                raise ConfigError(f"observed.depth_convention: only for kind segy or su (trace headers), not {observed['kind']}; "
                                  f"drop it")
            observed["depth_convention"] = _choice(observed["depth_convention"], "observed.depth_convention", DEPTH_CONVENTIONS)
        elif observed["kind"] in ("segy", "su"):
            observed["depth_convention"] = "auto"
    return FWIConfig(forward, inversion, true_model, observed, parallel, network, chosen)


def load_fwi_config(path) -> FWIConfig:
    """Read and validate an inversion YAML file."""
    raw, path = _read_yaml(path)
    return parse_fwi_config(raw, base_dir=path.resolve().parent, path=path)

