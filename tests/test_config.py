"""Tests for adseismic.config: the example configs validate, bad input fails with the key."""
import copy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from adseismic.config import ConfigError, ForwardConfig, SimulationConfig, load_config, parse_config

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
# the clone's copy (data/README.md); no test skips for want of it
MARMOUSI = ROOT / "data" / "marmousi2" / "marmousi2_resampled_1601x401_7.5m_kms.f32"

BASE = {
    "model": {"kind": "layered", "shape": [40, 60], "spacing": 10.0,
              "velocities": [1500, 2500], "interfaces": [200]},
    "geometry": {
        "sources": {"points": [{"x": 100, "z": 20}, {"x": 400, "z": 20}]},
        "receivers": {"line": {"start": {"x": 0, "z": 10}, "end": {"x": 590, "z": 10},
                               "count": 60}},
    },
    "wavelet": {"kind": "ricker", "peak_frequency": 10.0},
    "simulation": {"order": 4},
    "output": {"snapshot_interval": 0.0},
}


def cfg(**edits) -> dict:
    """BASE with dotted-path edits, e.g. cfg(**{"simulation.order": 3}); value ... deletes."""
    raw = copy.deepcopy(BASE)
    for path, value in edits.items():
        *parents, last = path.split(".")
        node = raw
        for p in parents:
            node = node.setdefault(p, {})
        if value is ...:
            del node[last]
        else:
            node[last] = value
    return raw


def error(raw, tmp_path=None) -> str:
    with pytest.raises(ConfigError) as e:
        parse_config(raw, base_dir=tmp_path)
    return str(e.value)


# ------------------------------------------------------------------------------ good configs

@pytest.mark.parametrize("name", ["example_2d", "example_3d", "marmousi_forward"])
def test_example_configs_validate(name):
    path = CONFIGS / f"{name}.yaml"
    c = load_config(path)  # marmousi_forward reads data/marmousi2 in the clone
    assert isinstance(c, ForwardConfig) and c.path == CONFIGS / f"{name}.yaml"
    ndim = c.model.ndim
    assert c.geometry.sources.ndim == 2 and c.geometry.sources.shape[1] == ndim
    assert c.geometry.receivers.shape[1] == ndim
    assert np.all(c.model.contains(c.geometry.sources))
    assert np.all(c.model.contains(c.geometry.receivers))
    assert c.raw == yaml.safe_load(path.read_text())  # the parsed YAML is kept
    if name == "marmousi_forward":
        assert c.model.shape == (401, 1601) and c.model.spacing == (7.5, 7.5)
        assert 1000 < c.model.vmin < 1100 and 4600 < c.model.vmax < 4800  # km/s -> m/s


def test_marmousi_fwi_config_reads_the_clones_model():
    # configs/marmousi_fwi.yaml reads data/marmousi2 (in the clone): a 6 km crop (x 3000-9000 m: 801 columns at 7.5 m)
    # of the 1028-4700 m/s section, the start model smoothed over 300 m
    from adseismic.config import FWIConfig, load_fwi_config

    c = load_fwi_config(CONFIGS / "marmousi_fwi.yaml")
    assert isinstance(c, FWIConfig) and c.true_model is not None
    assert c.true_model.shape == c.forward.model.shape == (401, 801) and c.true_model.spacing == (7.5, 7.5)
    assert c.true_model.vmin == pytest.approx(1500.0, abs=0.5) and c.true_model.vmax == pytest.approx(4700.0, abs=0.5)
    assert c.true_model.vmin < c.forward.model.vmin < c.forward.model.vmax < c.true_model.vmax  # smoothed


@pytest.mark.parametrize("name, grid", [("fwi_demo", "per_band"), ("elastic_fwi", "fixed"), ("nn_fwi", "fixed")])
def test_band_grids_default_to_per_band_where_it_applies(name, grid):
    """inversion.grid left out: per_band for acoustic pixel models, fixed for other physics and network models
    (which per_band refuses when asked for)."""
    from adseismic.config import load_fwi_config

    assert load_fwi_config(CONFIGS / f"{name}.yaml").inversion.grid == grid


def test_parse_defaults_and_axis_order():
    c = parse_config(cfg(**{"simulation": None, "output": ...}))
    assert c.simulation == SimulationConfig()
    assert c.output.snapshot_interval == 0.0
    # points are stored in model axis order (z, x)
    np.testing.assert_allclose(c.geometry.sources, [[20, 100], [20, 400]])
    assert c.geometry.receivers.shape == (60, 2)
    np.testing.assert_allclose(c.geometry.receivers[[0, -1]], [[10, 0], [10, 590]])
    assert c.wavelet.kind == "ricker" and c.wavelet.params == {"peak_frequency": 10.0}
    assert c.path is None and c.raw["simulation"] is None


def test_3d_geometry_order_zyx():
    raw = cfg(**{"model.shape": [10, 11, 12],
                 "geometry.sources": {"points": [{"x": 30, "y": 20, "z": 10}]},
                 "geometry.receivers": {"line": {"start": {"x": 0, "y": 0, "z": 0},
                                                 "end": {"x": 110, "y": 100, "z": 0},
                                                 "count": 1}}})
    c = parse_config(raw)
    np.testing.assert_allclose(c.geometry.sources, [[10, 20, 30]])
    np.testing.assert_allclose(c.geometry.receivers, [[0, 0, 0]])  # count 1: the start point


def test_numeric_strings_accepted():
    # PyYAML reads 1e-3 (no dot) as the string '1e-3'
    raw = yaml.safe_load("dt: 1e-3\npml_reflection: 1e-4\naccuracy: 2e-2")
    assert raw["dt"] == "1e-3"
    c = parse_config(cfg(**{f"simulation.{k}": v for k, v in raw.items()},
                         **{"wavelet.peak_frequency": "1e1"}))
    assert c.simulation.dt == 1e-3 and c.simulation.pml_reflection == 1e-4
    assert c.simulation.accuracy == 0.02 and c.wavelet.params["peak_frequency"] == 10.0


def test_load_config_resolves_relative_paths(tmp_path):
    np.save(tmp_path / "w.npy", np.sin(np.linspace(0, np.pi, 50)))
    raw = cfg(**{"wavelet": {"kind": "array", "file": "w.npy", "dt_in": "1e-3"}})
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(raw))
    c = load_config(tmp_path / "run.yaml")
    assert c.wavelet.kind == "array" and c.wavelet.params["dt_in"] == 1e-3
    assert c.wavelet.params["samples"].shape == (50,)


# ------------------------------------------------------------------------------ bad configs

@pytest.mark.parametrize("edits, key, fragment", [
    ({"simulation.oder": 4}, "simulation.oder", "allowed: order, accuracy"),
    ({"simulaton": {}}, "simulaton", "allowed: model, geometry"),
    ({"simulation.order": 3}, "simulation.order", "2, 4, 8"),
    ({"simulation.order": "four"}, "simulation.order", "2, 4, 8"),
    ({"simulation.accuracy": 2}, "simulation.accuracy", "(0, 0.5)"),
    ({"simulation.accuracy": "high"}, "simulation.accuracy", "number"),
    ({"simulation.device": "gpu"}, "simulation.device", "cuda:N"),
    ({"simulation.device": "cuda:x"}, "simulation.device", "cuda:N"),
    ({"simulation.precision": "float16"}, "simulation.precision", "float32"),
    ({"simulation.free_surface": "yes"}, "simulation.free_surface", "true or false"),
    ({"simulation.cfl_safety": 1.5}, "simulation.cfl_safety", "(0, 1]"),
    ({"simulation.dx": -5}, "simulation.dx", "> 0"),
    ({"simulation.dt": 0}, "simulation.dt", "> 0"),
    ({"simulation.duration": [1]}, "simulation.duration", "number"),
    ({"simulation.pml_width": 2}, "simulation.pml_width", ">= 4"),
    ({"simulation.pml_width": 10.5}, "simulation.pml_width", "integer"),
    ({"simulation.pml_reflection": 1.0}, "simulation.pml_reflection", "(0, 1)"),
    ({"simulation.margin": -1}, "simulation.margin", "negative"),
    ({"simulation.domain": "box"}, "simulation.domain", "auto, model"),
    ({"output.snapshot_interval": -0.1}, "output.snapshot_interval", "negative"),
    ({"output.snapshots": 1}, "output.snapshots", "allowed: snapshot_interval"),
    ({"wavelet.kind": "sinc"}, "wavelet.kind", "ricker"),
    ({"wavelet.peak_frequency": ...}, "wavelet.peak_frequency", "missing"),
    ({"wavelet.peak_frequency": 0}, "wavelet.peak_frequency", "> 0"),
    ({"wavelet.file": "w.npy"}, "wavelet.file", "allowed: kind, peak_frequency"),
    ({"geometry.sources": {"points": [{"x": 100}]}}, "geometry.sources.points[0].z", "missing"),
    ({"geometry.sources": {"points": [{"x": 100, "y": 0, "z": 20}]}},
     "geometry.sources.points[0].y", "2D model"),
    ({"geometry.receivers.line.count": 0}, "geometry.receivers.line.count", ">= 1"),
    ({"geometry.receivers.line.count": 2.5}, "geometry.receivers.line.count", "integer"),
    ({"geometry.receivers.line.end": ...}, "geometry.receivers.line.end", "missing"),
    ({"geometry.receivers.line.start.x": "left"}, "geometry.receivers.line.start.x", "number"),
    ({"geometry.sources": {}}, "geometry.sources", "empty"),
    ({"geometry.receivers": {"lines": []}}, "geometry.receivers.lines", "non-empty"),
    ({"geometry.sources": {"points": []}}, "geometry.sources.points", "non-empty"),
    ({"geometry.sources": {"points": [{"x": 9000, "z": 20}]}}, "geometry.sources",
     "outside the model"),
    ({"geometry.receivers": ...}, "geometry.receivers", "missing"),
    ({"geometry.shots": {}}, "geometry.shots", "allowed: sources, receivers"),
    ({"wavelet": ...}, "wavelet", "missing"),
    ({"model.velocitys": [1]}, "model.velocitys", "layered"),
    ({"model.kind": "marmousi"}, "model.kind", "layered"),
])
def test_bad_input_names_the_key(edits, key, fragment):
    msg = error(cfg(**edits))
    assert msg.startswith(key + ":") or msg.startswith(key + "["), msg
    assert fragment in msg, msg


def test_3d_point_in_2d_model_and_2d_point_in_3d_model():
    msg = error(cfg(**{"geometry.receivers": {"points": [{"x": 1, "y": 2, "z": 3}]}}))
    assert msg.startswith("geometry.receivers.points[0].y:") and "x, z" in msg
    raw = cfg(**{"model.shape": [10, 10, 10]})  # 3D model, 2D points
    assert error(raw).startswith("geometry.sources.points[0].y: missing")


def test_array_wavelet_file_problems(tmp_path):
    raw = cfg(**{"wavelet": {"kind": "array", "file": "nope.npy", "dt_in": 0.001}})
    assert error(raw, tmp_path).startswith("wavelet.file:")
    np.save(tmp_path / "w.npy", np.ones((3, 3)))
    raw["wavelet"]["file"] = "w.npy"
    assert "shape" in error(raw, tmp_path)
    raw["wavelet"] = {"kind": "array", "file": "w.npy"}
    assert error(raw, tmp_path).startswith("wavelet.dt_in: missing")


def test_not_a_mapping_and_bad_yaml(tmp_path):
    assert error([1, 2]).startswith("config:")
    assert error(cfg(**{"simulation": [1]})).startswith("simulation:")
    p = tmp_path / "bad.yaml"
    p.write_text("model: [unclosed\n")
    with pytest.raises(ConfigError, match="^config:"):
        load_config(p)
    with pytest.raises(ConfigError, match="^config:.*does not exist"):
        load_config(tmp_path / "missing.yaml")


def test_config_error_is_value_error():
    assert issubclass(ConfigError, ValueError)


def test_spread_forms_concatenate():
    from adseismic.config.forward import _parse_spread

    pts = _parse_spread({"points": [{"x": 5.0, "z": 1.0}], "line": {"start": {"x": 0, "z": 0}, "end": {"x": 10, "z": 0}, "count": 3},
                         "lines": [{"start": {"x": 0, "z": 9}, "end": {"x": 10, "z": 9}, "count": 2}]}, "geometry.receivers", 2)  # fmt: skip
    np.testing.assert_allclose(pts, [[1, 5], [0, 0], [0, 5], [0, 10], [9, 0], [9, 10]])


# ------------------------------------------------------------------------------ no workflow imports

def test_accepted_names_match_the_workflow_registries():
    """The config modules keep their own copies of the workflows' names (so that loading a config
    imports no workflow); they must not drift apart."""
    from adseismic.config.fwi import MISFIT_NAMES, OPTIMIZERS
    from adseismic.config.locate import LOCATE_METHODS, STF_KINDS
    from adseismic.inversion import optimize
    from adseismic.location import locate
    from adseismic.solve import misfits

    assert set(MISFIT_NAMES) == set(misfits.MISFITS)
    assert set(OPTIMIZERS) == set(optimize.METHODS)
    assert set(LOCATE_METHODS) == set(locate.METHODS)
    assert set(STF_KINDS) == set(locate.STFS)


def test_parsing_a_config_imports_no_workflow():
    """Parsing a forward, an inversion and a location config loads the config and data layers only."""
    fwi = {**BASE, "true_model": BASE["model"], "inversion": {"misfit": "l2", "optimizer": "lbfgs"}}
    loc = {"model": BASE["model"], "traces": {"paths": ["event/*.mseed"]}, "preprocess": {"noise_window": [0, 0.1]},
           "source": {"stf": "ricker"}, "search": {"method": "lbfgs"}}
    code = f"""
import sys
import adseismic.config as c
c.parse_config({BASE!r})
c.parse_fwi_config({fwi!r})
c.parse_locate_config({loc!r})
bad = sorted(m for m in sys.modules if m.startswith(("adseismic.inversion", "adseismic.location",
                                                      "adseismic.solve", "adseismic.cli", "adseismic.bench")))
print(",".join(bad))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"parsing a config imported workflow modules: {out.stdout.strip()}"
