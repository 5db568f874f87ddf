"""adseismic: differentiable seismic wave propagation in NVIDIA Warp, for full-waveform inversion and
earthquake location.

Units are SI throughout: metres, seconds, m/s, kg/m^3, Hz. Arrays follow the model's axis order (z, [y,] x),
z depth positive down: models (nz, [ny,] nx); locations (n_shots, n_per_shot, ndim) metres; source samples
and receiver data (n_shots, n, nt) at t = k dt. docs/api.md lists the names below; docs/architecture.md
shows the layers behind them. Names are imported on first use, so ``import adseismic`` stays light.
"""

import importlib

_WHERE = {
    # simulation and gradients (adseismic.solve)
    "forward": "adseismic.solve.acoustic",
    "ForwardResult": "adseismic.solve.acoustic",
    "gradient": "adseismic.solve.acoustic",
    "GradientResult": "adseismic.solve.acoustic",
    "born": "adseismic.solve.acoustic",
    "forward_elastic": "adseismic.solve.elastic",
    "ElasticResult": "adseismic.solve.elastic",
    "gradient_elastic": "adseismic.solve.elastic",
    "ElasticGradient": "adseismic.solve.elastic",
    "forward_acoustic_vd": "adseismic.solve.acoustic_vd",
    "gradient_acoustic_vd": "adseismic.solve.acoustic_vd",
    "PropagationError": "adseismic.solve.common",
    # models, wavelets, scenes
    "Model": "adseismic.data.model",
    "load_model": "adseismic.data.models",
    "ricker": "adseismic.wavelets",
    "load_config": "adseismic.config",
    "plan_scene": "adseismic.scene",
    # workflows and data
    "run_fwi": "adseismic.inversion.fwi",
    "minimize": "adseismic.inversion.optimize",
    "locate": "adseismic.location.locate",
    "read_station_traces": "adseismic.data.read",
    "read_shot_gathers": "adseismic.data.read",
}

__all__ = [
    "ElasticGradient",
    "ElasticResult",
    "ForwardResult",
    "GradientResult",
    "Model",
    "PropagationError",
    "born",
    "forward",
    "forward_acoustic_vd",
    "forward_elastic",
    "gradient",
    "gradient_acoustic_vd",
    "gradient_elastic",
    "load_config",
    "load_model",
    "locate",
    "minimize",
    "plan_scene",
    "read_shot_gathers",
    "read_station_traces",
    "ricker",
    "run_fwi",
]


def __getattr__(name):
    if name not in _WHERE:
        raise AttributeError(f"module 'adseismic' has no attribute {name!r}")
    value = getattr(importlib.import_module(_WHERE[name]), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
