"""physics: elastic from YAML (issue 23, forward side): the config (physics, {vp, vs, rho}, source, receiver
components, DAS), the planner's dx and dt, `adseismic forward` against forward_elastic called directly, and the DAS
operator (dot-product test, analytic plane-wave strain rate). The bad combinations are rows of tests/test_bad_inputs.py."""
import math
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from adseismic.cli import main
from adseismic.config import ConfigError, load_config, parse_config
from adseismic.config.fwi import parse_fwi_config
from adseismic.config.schema import SCHEMAS
from adseismic.data.model import Model
from adseismic.data.models import ElasticModel, ModelError, load_physics_model
from adseismic.kernels.numerics import rayleigh_speed, staggered_cfl_limit
from adseismic.scene import build_scene, plan_scene
from adseismic.solve.receivers import DasOperator, Recording

CONFIGS = Path(__file__).resolve().parents[1] / "configs"

SMALL = """
physics: elastic
model:
  vp: {kind: constant, shape: [21, 41], spacing: 10.0, velocity: 2000.0}
  vs: {vp_ratio: 1.8}
  rho: {gardner: true}
geometry:
  sources: {points: [{x: 150, z: 80}, {x: 250, z: 80}]}
  receivers:
    line: {start: {x: 50, z: 20}, end: {x: 350, z: 20}, count: 7}
    components: [vx, pressure]
    das: {gauge_length: 10.0, direction: 30}
wavelet: {kind: ricker, peak_frequency: 4.0}
source: {type: force, components: [1.0e+3, 5.0e+2]}
simulation: {order: 4, pml_width: 8, duration: 0.25, free_surface: true, domain: model}
"""


def small(**changes) -> dict:
    raw = yaml.safe_load(SMALL)
    for key, value in changes.items():
        section, _, name = key.partition("__")
        if name:
            raw[section][name] = value
        else:
            raw[section] = value
    return raw


# ------------------------------------------------------------------------------ the config

def test_demo_config_parses_into_an_elastic_model_source_and_recording():
    raw = yaml.safe_load((CONFIGS / "elastic_forward.yaml").read_text())
    SCHEMAS["forward"].model_validate(raw)  # the whole file fits the documented schema
    c = load_config(CONFIGS / "elastic_forward.yaml")
    assert c.physics == "elastic" and isinstance(c.model, ElasticModel)
    vp, vs, rho = c.model.vp.values, c.model.vs.values, c.model.rho.values
    assert vp.shape == vs.shape == rho.shape == (61, 121)  # vs's layered spec took vp's grid
    assert (vp[0, 0], vs[0, 0], vp[-1, 0], vs[-1, 0]) == (1800.0, 900.0, 3000.0, 1700.0)
    np.testing.assert_allclose(rho, 310.0 * vp**0.25, rtol=1e-15)  # Gardner, kg/m^3
    assert c.geometry.components == ("vx", "vz") and c.geometry.das.gauge_length == 20.0
    assert c.geometry.das.direction == (0.0, 1.0)  # 0 degrees: horizontal
    assert c.source.type == "moment" and c.source.components == (1e6, -1e6, 5e5) and c.source.solver_type == "moment"


@pytest.mark.parametrize("name", ["elastic_forward", "das_forward"])
def test_demo_configs_fit_the_json_schema_and_plan(name, capsys):
    import json

    from adseismic.config.schema import json_schema

    raw = yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())
    jsonschema = pytest.importorskip("jsonschema")
    jsonschema.validate(json.loads(json.dumps(raw, default=str)), json_schema("forward"))
    assert main(["plan", str(CONFIGS / f"{name}.yaml")]) == 0
    assert "physics   elastic" in capsys.readouterr().out


def test_the_schema_names_are_the_solvers_and_the_loaders():
    from adseismic.config import schema
    from adseismic.data import models
    from adseismic.solve import elastic, elastic3d

    assert schema.PHYSICS == models.PHYSICS and schema.COMPONENTS == elastic3d.COMPONENTS  # 2D's and vy
    assert set(schema.COMPONENTS) - set(elastic.COMPONENTS) == {"vy"}
    assert set(schema.SOURCE_TYPES) == set(elastic.SOURCE_TYPES)


def test_defaults_acoustic_physics_explosive_source_all_components_and_direction_vectors():
    raw = small(source=None)
    raw["geometry"]["receivers"].pop("components")
    raw["geometry"]["receivers"].pop("das")
    c = parse_config(raw)
    assert c.source.type == "explosive" and c.source.components == (1.0, 1.0, 0.0)
    assert c.geometry.components == ("vx", "vz", "pressure") and c.geometry.das is None
    raw["geometry"]["receivers"]["das"] = {"gauge_length": 5, "direction": [3, 4]}
    c = parse_config(raw)
    assert c.geometry.components == () and c.geometry.das.direction == (0.6, 0.8)  # das alone records only DAS
    acoustic = parse_config(yaml.safe_load((CONFIGS / "example_2d.yaml").read_text()), base_dir=CONFIGS)
    assert acoustic.physics == "acoustic" and acoustic.source is None and acoustic.geometry.components == ()


def test_fwi_config_carries_physics_and_an_elastic_true_model():
    raw = small(true_model={"vp": {"kind": "constant", "shape": [21, 41], "spacing": 10.0, "velocity": 2100.0},
                            "vs": {"vp_ratio": 1.8}, "rho": {"gardner": True}}, inversion={"iterations": 1})
    c = parse_fwi_config(raw)
    assert c.forward.physics == "elastic" and isinstance(c.true_model, ElasticModel)
    assert c.true_model.vs.values[0, 0] == pytest.approx(2100.0 / 1.8)


@pytest.mark.parametrize("change, message", [
    ({"model__vs": {"kind": "constant", "velocity": 1500.0}}, "model.vs: vs = 1500 m/s > vp / sqrt(2) = 1414.21"),
    ({"model__rho": {"kind": "constant"}}, "model.rho.velocity: missing"),
    ({"model__vs": {"vp_ratio": 1.8, "kind": "constant"}}, "model.vs: {'vp_ratio': 1.8, 'kind': 'constant'} mixes"),
    ({"model__rho": {"gardner": False}}, "model.rho: {'gardner': False} is not {gardner: true}"),
    ({"model__mu": 3}, "model.mu: unknown key of an elastic model"),
    ({"source": {"type": "force", "components": [0, 0]}}, "source.components: [0.0, 0.0] are all 0"),
    ({"source": {"type": "explosive", "components": "big"}}, "source.components: 'big' is not a finite number"),
    ({"physics": "viscoelastic"}, "physics: 'viscoelastic' is not one of acoustic, elastic"),
])
def test_bad_elastic_sections_name_the_key_the_value_and_the_fix(change, message):
    with pytest.raises(ConfigError) as e:
        parse_config(small(**change))
    assert str(e.value).startswith(message), str(e.value)


def test_elastic_resampling_keeps_lambda_nonnegative_and_is_exact_on_its_own_grid():
    """vp and vs are resampled with the same weights (on their slownesses): at a sharp interface between a layer at
    the limit vs = vp / sqrt(2) and a low-ratio layer, no resampled node may pass the limit, and the round trip onto
    the model's own grid returns its values."""
    spec = {"vp": {"kind": "layered", "shape": [40, 10], "spacing": 5.0, "velocities": [2000.0, 4000.0],
                   "interfaces": [100.0]},
            "vs": {"kind": "layered", "velocities": [2000.0 / math.sqrt(2), 1000.0], "interfaces": [100.0]},
            "rho": {"kind": "constant", "velocity": 2000.0}}
    m = load_physics_model(spec, "elastic")
    same = m.resample(5.0, (0.0, 0.0), (40, 10))
    for a, b in zip((same.vp, same.vs, same.rho), (m.vp, m.vs, m.rho)):
        np.testing.assert_allclose(a.values, b.values, rtol=1e-14)  # 1 / (1 / v): rounding only
    r = m.resample(3.3, (1.1, 0.0), (55, 12))
    assert (r.vs.values / r.vp.values).max() <= (1 + 1e-12) / math.sqrt(2)  # ElasticModel's own tolerance
    assert (r.vs.values / r.vp.values).min() == pytest.approx(0.25)  # the lower layer's ratio, not below it
    assert r.vp.values.min() == pytest.approx(2000.0) and r.vp.values.max() == pytest.approx(4000.0)
    with pytest.raises(ModelError, match="model.vs: its grid"):
        ElasticModel(m.vp, Model(m.vs.values[:-1], 5.0), m.rho)


# ------------------------------------------------------------------------------ the planner

@pytest.mark.parametrize("free_surface", [False, True])
def test_planner_takes_dx_from_the_slowest_wave_and_dt_from_vp_max(free_surface):
    """dx: at least the points per wavelength the accuracy target needs for S (1% group error: the staggered scheme
    at order 4 needs ~5.6 points; numerics) or, with a free surface, RAYLEIGH_PPW = 20 points per Rayleigh
    wavelength; nice_floor rounding to 2 digits loses < 10%. dt: 0.9 x the staggered CFL limit at vp_max, rounded
    down likewise."""
    c = parse_config(small(simulation={"order": 4, "pml_width": 8, "free_surface": free_surface, "domain": "model"}))
    p = plan_scene(c)
    vp, vs = 2000.0, 2000.0 / 1.8
    slowest = rayleigh_speed(vp, vs) if free_surface else vs
    ppw = slowest / (p.f_max * p.dx)
    need = 20.0 if free_surface else 5.0
    assert need <= ppw < (need / 0.9 if free_surface else 12.0)
    assert p.physics == "elastic" and p.cfl_limit == pytest.approx(staggered_cfl_limit(4, 2))
    assert 0.9 * 0.9 * p.cfl_limit <= vp * p.dt / p.dx <= 0.9 * p.cfl_limit
    text = p.describe()
    assert text.startswith("physics   elastic") and "for vp_max 2000 m/s" in text
    # without a free surface the P wave needs the finer grid here: at the Courant number 0.54 of vp_max its time
    # dispersion asks 11.9 points per P wavelength, more than S's ~5.6 at its lower Courant number
    assert ("20 points per Rayleigh wavelength" if free_surface else "11.9 points per P wavelength (2000 m/s)") in text
    acoustic = plan_scene(parse_config(yaml.safe_load((CONFIGS / "example_2d.yaml").read_text()), base_dir=CONFIGS))
    assert acoustic.physics == "acoustic" and "pressure wave equation" in acoustic.describe()


def test_planner_honours_pins_and_refuses_an_unstable_elastic_dt():
    p = plan_scene(parse_config(small(simulation={"dt": 6e-3, "pml_width": 8})))  # planned: dx 18 m, dt 4.9 ms
    assert p.dt == 6e-3 and p.dx == 22.0  # dx grown to keep dt stable: nice_ceil(2000 x 6e-3 / (0.9 x 0.6061) = 21.998)
    assert "pinned dt = 0.006 s is stable" in p.describe()
    p = plan_scene(parse_config(small(simulation={"dx": 4.0, "pml_width": 8})))
    assert p.dx == 4.0 and p.dt == pytest.approx(0.001, rel=1e-12)  # nice_floor(0.9 x 0.6061 x 4 / 2000 = 0.00109)
    with pytest.raises(ValueError, match="simulation.dt"):
        plan_scene(parse_config(small(simulation={"dx": 4.0, "dt": 2e-3, "pml_width": 8})))


def test_planner_plans_for_an_inversions_vp_and_vs_ranges():
    """An inversion plans for its bounds (every model it may visit is stable and resolved): dt from the upper vp
    bound, dx from the lower vs bound (here with a free surface: the Rayleigh wave of vp 1500, vs 800 m/s)."""
    c = parse_config(small())
    p = plan_scene(c, velocity_range=(1500.0, 3500.0), vs_range=(800.0, 1200.0), check_memory_of_run=False)
    assert "c_R 742 m/s" in p.describe() and "vp_max 3500 m/s" in p.describe()
    assert 20.0 <= rayleigh_speed(1500.0, 800.0) / (p.f_max * p.dx) < 20.0 / 0.9
    assert 3500.0 * p.dt / p.dx <= 0.9 * staggered_cfl_limit(4, 2) and p.dx < plan_scene(c).dx


# ------------------------------------------------------------------------------ adseismic forward

def test_forward_cli_writes_each_component_equal_to_forward_elastic_called_directly(tmp_path):
    """The CLI's data.h5 against forward_elastic called here with the planned grid and model but the geometry, source
    and DAS gauges built by hand: bitwise equal (float32, as simulated)."""
    from adseismic.data.store import read_forward
    from adseismic.solve.elastic import forward_elastic
    from adseismic.wavelets import make_wavelet

    cfg = tmp_path / "c.yaml"
    cfg.write_text(SMALL)
    assert main(["forward", str(cfg), "-o", str(tmp_path / "out"), "--quiet"]) == 0
    out = read_forward(tmp_path / "out" / "data.h5")
    assert list(out.components) == ["vx", "pressure", "das"]
    with h5py.File(tmp_path / "out" / "data.h5") as f:
        assert [f[n].attrs["units"] for n in out.components] == ["m/s", "Pa", "1/s"]
        assert f["receiver_data"].shape == f["vx"].shape == (2, 7, out.time.size)
    assert out.attrs["physics"] == "elastic" and out.attrs["source_type"] == "force" and out.attrs["das_gauge_length"] == 10.0

    config = load_config(cfg)
    scene = build_scene(config)
    plan, m = scene.plan, scene.model
    x = np.linspace(50.0, 350.0, 7)
    half = 5.0 * np.array([math.sin(math.radians(30)), math.cos(math.radians(30))])  # (dz, dx) x L / 2
    points = np.stack([np.full(7, 20.0), x], axis=1)
    rec = np.concatenate([points, points - half, points + half])  # model origin 0: grid metres = world metres
    wavelet = make_wavelet("ricker", plan.nt, plan.dt, peak_frequency=4.0)
    r = forward_elastic(m.vp.values, m.vs.values, m.rho.values, plan.dx, plan.dt, np.tile(wavelet, (2, 1, 1)),
                        np.array([[[80.0, 150.0]], [[80.0, 250.0]]]), np.broadcast_to(rec, (2, 21, 2)),
                        source_type="force", source_components=np.tile([1e3, 5e2], (2, 1, 1)), order=4, pml_width=8,
                        free_surface=True)
    assert np.array_equal(out.components["vx"], r.vx[:, :7]) and np.array_equal(out.components["pressure"], r.pressure[:, :7])
    along = half[0] * r.vz + half[1] * r.vx  # d . v x L / 2
    das = (along[:, 14:] - along[:, 7:14]) / (0.5 * 10.0) / 10.0
    # by hand in float64 against the file's float32 (rounding of the float32 differences: ~1e-6 of the largest value)
    np.testing.assert_allclose(out.components["das"], das, rtol=0, atol=1e-5 * np.abs(das).max())
    direction = config.geometry.das.direction
    np.testing.assert_allclose(direction, half / 5.0, rtol=1e-15)
    assert np.array_equal(out.components["das"], DasOperator(10.0, direction).forward(r.vx[:, 7:], r.vz[:, 7:]))
    assert np.abs(out.components["das"]).max() > 0 and np.abs(out.components["vx"]).max() > 0
    pngs = sorted(p.name for p in (tmp_path / "out").glob("gather_*.png"))
    assert pngs == [f"gather_shot{k}_{n}.png" for k in (0, 1) for n in ("das", "pressure", "vx")]


@pytest.mark.slow
@pytest.mark.parametrize("name, names", [("elastic_forward", ["vx", "vz", "das"]), ("das_forward", ["das"])])
def test_elastic_demos_run_through_the_cli_within_three_minutes(name, names, tmp_path):
    t0 = time.perf_counter()
    assert main(["forward", str(CONFIGS / f"{name}.yaml"), "-o", str(tmp_path), "--quiet"]) == 0
    seconds = time.perf_counter() - t0
    with h5py.File(tmp_path / "data.h5") as f:
        assert list(f.attrs["components"]) == names and f["das"].attrs["units"] == "1/s"
        data = {n: f[n][()] for n in names}
    for n in names:
        assert np.isfinite(data[n]).all() and np.abs(data[n]).max() > 0, n
    assert {f"gather_shot0_{n}.png" for n in names} | {"model.png", "model_vs.png", "model_rho.png"} <= {p.name for p in tmp_path.iterdir()}
    assert seconds < 180.0, seconds


# ------------------------------------------------------------------------------ the DAS operator

def test_das_operator_and_recording_pass_the_dot_product_test():
    """<F v, e> = <v, F^T e> in float64 to rounding (1e-12 relative: sums of ~1e3 products of O(1) numbers)."""
    rng = np.random.default_rng(0)
    op = DasOperator(12.5, (math.sin(0.3), math.cos(0.3)))
    vx, vz, e = rng.standard_normal((2, 10, 50)), rng.standard_normal((2, 10, 50)), rng.standard_normal((2, 5, 50))
    ax, az = op.adjoint(e)
    lhs, rhs = np.vdot(op.forward(vx, vz), e), np.vdot(vx, ax) + np.vdot(vz, az)
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)
    for rec in (Recording(("vx", "pressure"), op), Recording((), op), Recording(("vz",))):
        m = len(rec.locations(np.zeros((5, 2))))
        recorded = {c: rng.standard_normal((2, m, 50)) for c in ("vx", "vz", "pressure")}
        residual = {n: rng.standard_normal((2, 5, 50)) for n in rec.names}
        fwd, adj = rec.data(recorded, 5), rec.adjoint(residual, 5)
        lhs = sum(np.vdot(fwd[n], residual[n]) for n in rec.names)
        rhs = sum(np.vdot(recorded[c], adj[c]) for c in recorded)
        assert abs(lhs - rhs) <= 1e-12 * abs(lhs), rec


@pytest.mark.parametrize("wave", ["P", "SV"])
def test_das_strain_rate_of_a_plane_wave_matches_the_analytic_one(wave):
    """A plane wave v = m cos(w (t - n.r / c)) (m = n for P, m perpendicular to n for S) has the point strain rate
    along the fibre d:  e_dot = (d.m)(d.n) (w / c) sin(w (t - n.r / c)); the gauge average over L is e_dot x
    sin(X) / X with X = w (d.n) L / (2 c), exactly: the operator must match that to float64 rounding, and the point
    strain rate within the gauge's own error 1 - sin(X) / X <= X^2 / 6 (1.2% here)."""
    c, f, L = 2000.0 if wave == "P" else 1150.0, 20.0, 10.0
    w = 2 * math.pi * f
    n = np.array([math.sin(0.4), math.cos(0.4)])  # propagation (z, x)
    m = n if wave == "P" else np.array([-n[1], n[0]])
    d = np.array([math.sin(math.radians(-20)), math.cos(math.radians(-20))])  # fibre (dz, dx)
    op = DasOperator(L, tuple(d))
    centres = np.stack([np.linspace(0, 50, 6), np.linspace(0, 300, 6)], axis=1)
    t = np.linspace(0, 0.2, 401)
    ends = op.gauge_ends(centres)
    phase = w * (t[None, :] - (ends @ n)[:, None] / c)
    vz, vx = m[0] * np.cos(phase), m[1] * np.cos(phase)
    das = op.forward(vx, vz)
    tau = w * (t[None, :] - (centres @ n)[:, None] / c)
    point = (d @ m) * (d @ n) * (w / c) * np.sin(tau)
    x = w * (d @ n) * L / (2 * c)
    scale = np.abs(point).max()
    np.testing.assert_allclose(das, point * math.sin(x) / x, rtol=0, atol=1e-12 * scale / L)
    assert np.abs(das - point).max() <= x**2 / 6 * scale
    assert np.abs(das - point).max() >= 0.5 * x**2 / 6 * scale  # the gauge's smoothing is there: not a point sensor
