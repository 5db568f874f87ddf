"""Property-based fuzz of the config and model loaders (issue 24): whatever the input, the loaders either return
or raise ConfigError / ModelError with a message; any other exception (a traceback for the user) fails.

Bounded for CI: each property runs at most FUZZ_EXAMPLES examples (ADSEISMIC_FUZZ_EXAMPLES overrides; the
issue's long run was 300 s / 49,891 inputs). No simulation runs: only YAML parsing, validation and model files.
"""
from __future__ import annotations

import copy
import os

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from adseismic.config import ConfigError, parse_config, parse_fwi_config, parse_locate_config
from adseismic.config.common import _read_yaml
from adseismic.data.model import ModelError
from adseismic.data.models import load_model

FUZZ_EXAMPLES = int(os.environ.get("ADSEISMIC_FUZZ_EXAMPLES", "200"))
FUZZ = settings(max_examples=FUZZ_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
EXPECTED = (ConfigError, ModelError)

BASE = {
    "model": {"kind": "layered", "shape": [20, 30], "spacing": 10.0, "velocities": [1500, 2500], "interfaces": [100]},
    "geometry": {
        "sources": {"points": [{"x": 100, "z": 20}]},
        "receivers": {"line": {"start": {"x": 0, "z": 10}, "end": {"x": 290, "z": 10}, "count": 30}},
    },
    "wavelet": {"kind": "ricker", "peak_frequency": 10.0},
    "simulation": {"order": 4, "accuracy": 0.01, "dx": 5.0},
    "output": {"snapshot_interval": 0.0},
}
FWI_EXTRA = {"true_model": {"kind": "constant", "shape": [20, 30], "spacing": 10.0, "velocity": 2000.0},
             "inversion": {"bands": [4.0, None], "iterations": [2, 2], "bounds": [1000, 3000], "offsets": [0, 300],
                           "time_window": [0.0, 1.0]}}
KEYS = ["model", "geometry", "wavelet", "simulation", "output", "kind", "shape", "spacing", "velocity", "velocities",
        "interfaces", "origin", "crop", "smoothing", "path", "units", "axes", "sources", "receivers", "points", "line",
        "lines", "start", "end", "count", "x", "y", "z", "peak_frequency", "delay", "order", "accuracy", "dx", "dt",
        "duration", "device", "precision", "pml_width", "domain", "bands", "fmin", "fmax", "bounds", "iterations",
        "inversion", "true_model", "observed", "traces", "preprocess", "noise_window", "memory_budget", "force"]

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(), st.integers(min_value=-(10**30), max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
    st.sampled_from(["1e3", "1.4e15", "nan", "-inf", "true", "cpu", "cuda:0", "ricker", "array", "layered", "constant",
                     "npy", "hdf5", "raw", "segy", "m/s", "km/s", "xz", "zx", "float32", "auto", "model", "l2", ""]),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.sampled_from(KEYS), inner, max_size=4)),
    max_leaves=12,
)


def _paths(node, prefix=()):
    """Every (path to a value) of a nested dict/list."""
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, prefix + (i,))
    return out


def _replace(raw, path, value):
    if not path:
        return value
    raw = copy.deepcopy(raw)
    node = raw
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return raw


@st.composite
def mutated(draw, base):
    """The base config with one value (leaf or section) replaced by an arbitrary one, or a key added."""
    paths = _paths(base)
    path = draw(st.sampled_from(paths))
    if draw(st.booleans()) or not path:
        return _replace(base, path, draw(values))
    parent = path[:-1]
    node = base
    for k in parent:
        node = node[k]
    if isinstance(node, dict):
        return _replace(base, parent + (draw(st.sampled_from(KEYS)),), draw(values))
    return _replace(base, path, draw(values))


def _call(fn, *args, **kw):
    try:
        fn(*args, **kw)
    except EXPECTED as e:
        assert str(e), "an empty error message"


@FUZZ
@given(raw=mutated(BASE))
def test_forward_config_never_tracebacks(raw, tmp_path_factory):
    _call(parse_config, raw, base_dir=tmp_path_factory.getbasetemp())


@FUZZ
@given(raw=mutated({**BASE, **FWI_EXTRA}))
def test_fwi_config_never_tracebacks(raw, tmp_path_factory):
    _call(parse_fwi_config, raw, base_dir=tmp_path_factory.getbasetemp())


@FUZZ
@given(raw=mutated({**BASE, "inversion": {"bands": [{"fmin": 2, "fmax": 5}, 8]},
                    "observed": {"kind": "mseed", "paths": ["a.mseed"], "shot_times": ["2024-01-01T00:00:00"],
                                 "reference": [45.0, 7.0], "component": "Z"}}))
def test_fwi_observed_config_never_tracebacks(raw, tmp_path_factory):
    _call(parse_fwi_config, raw, base_dir=tmp_path_factory.getbasetemp())


@FUZZ
@given(raw=mutated({"model": BASE["model"], "traces": {"paths": ["none/*.mseed"], "reference": [45.0, 7.0],
                                                    "local_coordinates": {"XX.A": [0, 10]}, "component": "Z", "fill_gaps": 0},
                "preprocess": {"noise_window": [0, 1]}, "source": {"stf": "ricker"}, "search": {"method": "lbfgs"}}))
def test_locate_config_never_tracebacks(raw, tmp_path_factory):
    _call(parse_locate_config, raw, base_dir=tmp_path_factory.getbasetemp())


@FUZZ
@given(raw=st.one_of(values, st.dictionaries(st.sampled_from(KEYS), values, max_size=6)))
def test_arbitrary_structures_never_traceback(raw, tmp_path_factory):
    _call(parse_config, raw, base_dir=tmp_path_factory.getbasetemp())
    _call(load_model, raw, base_dir=tmp_path_factory.getbasetemp())


YAML_TEXT = "model: {kind: constant, shape: [20, 30], spacing: 10, velocity: 2000}\n" \
            "geometry:\n  sources: {points: [{x: 100, z: 20}]}\n  receivers: {points: [{x: 10, z: 10}]}\n" \
            "wavelet: {kind: ricker, peak_frequency: 10}\n"


@FUZZ
@given(data=st.one_of(st.binary(max_size=200), st.text(max_size=200).map(lambda t: t.encode("utf-8")),
                 st.tuples(st.integers(0, len(YAML_TEXT)), st.binary(min_size=1, max_size=8)).map(
                     lambda t: YAML_TEXT.encode()[: t[0]] + t[1] + YAML_TEXT.encode()[t[0]:])))
def test_config_bytes_never_traceback(data, tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "c.yaml"
    path.write_bytes(data)
    try:
        raw, _ = _read_yaml(path)
        parse_config(raw, base_dir=path.parent)
    except EXPECTED as e:
        assert str(e)


# ------------------------------------------------------------------------------ model files

@FUZZ
@given(case=st.one_of(
    st.binary(max_size=300),
    st.tuples(st.sampled_from(["<f4", "<f8", "<i2", "<c16", "|b1", "<u1", "|O"]),
              st.lists(st.integers(0, 5), min_size=0, max_size=4), st.integers(0, 2)),
))
def test_npy_model_files_never_traceback(case, tmp_path_factory):
    path = tmp_path_factory.mktemp("npy") / "m.npy"
    if isinstance(case, bytes):
        path.write_bytes(b"\x93NUMPY" + case if case[:1] == b"\x01" else case)
    else:
        dtype, shape, fill = case
        with np.errstate(all="ignore"):
            a = np.full(shape, [0.0, 1500.0, np.nan][fill]).astype(object if dtype == "|O" else dtype)
        np.save(path, a, allow_pickle=True)
    _call(load_model, {"kind": "npy", "path": str(path), "spacing": 10.0})


@FUZZ
@given(junk=st.binary(max_size=400), cut=st.integers(0, 2000))
def test_hdf5_model_files_never_traceback(junk, cut, tmp_path_factory):
    import h5py

    path = tmp_path_factory.mktemp("h5") / "m.h5"
    with h5py.File(path, "w") as f:
        f["v"] = np.full((6, 8), 1500.0)
    data = path.read_bytes()
    path.write_bytes(data[: cut] + junk if junk else data[: cut])  # truncated, corrupted or empty
    _call(load_model, {"kind": "hdf5", "path": str(path), "dataset": "v", "spacing": 10.0})


# ------------------------------------------------------------------------------ the planner

extreme = st.one_of(st.sampled_from([1e-300, 1e-12, 1e-9, 1e-3, 0.5, 1.0, 7.0, 1e3, 1e6, 1e12, 1e300]),
                    st.floats(min_value=1e-12, max_value=1e12))


@settings(max_examples=max(FUZZ_EXAMPLES // 8, 10), deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(edits=st.dictionaries(st.sampled_from([("wavelet", "peak_frequency"), ("wavelet", "delay"), ("model", "spacing"),
                                              ("model", "velocity"), ("simulation", "dx"), ("simulation", "dt"),
                                              ("simulation", "duration"), ("simulation", "margin"), ("simulation", "cfl_safety"),
                                              ("simulation", "accuracy"), ("simulation", "memory_budget_gb")]),
                             extreme, max_size=3))
def test_planner_never_tracebacks(edits, tmp_path_factory):
    """Absurd numbers in the config end in ConfigError / ModelError or the planner's ValueError (a refusal with its
    estimate), never in MemoryError, OverflowError or a negative cell count."""
    from adseismic.scene import plan_scene

    raw = copy.deepcopy(BASE)
    raw["model"] = {"kind": "constant", "shape": [20, 30], "spacing": 10.0, "velocity": 2000.0}
    raw["simulation"] = {"order": 4, "pml_width": 8}
    for (sec, key), v in edits.items():
        raw[sec][key] = v
    try:
        cfg = parse_config(raw, base_dir=tmp_path_factory.getbasetemp())
        plan = plan_scene(cfg)
    except (*EXPECTED, ValueError) as e:
        assert str(e)
        return
    assert plan.padded_cells > 0 and plan.memory_bytes > 0 and plan.nt >= 1
