"""physics: vti from YAML (issue 26 items 3 and 7): the model section's Thomsen fields, the planner (dx from the
slowest qP speed, dt from the horizontal one, the travel-time error of dropping the anisotropy) and `adseismic forward`
against forward_vti called directly. Refusals: tests/test_bad_inputs.py; the solver itself: tests/test_vti.py."""

import math

import numpy as np
import pytest
import yaml

from adseismic.cli import main
from adseismic.config.forward import load_config, parse_config
from adseismic.data.models import VTIModel, load_physics_model
from adseismic.kernels.numerics import staggered_cfl_limit
from adseismic.scene import build_scene, plan_scene, qp_group_speed_ratio, qp_min_speed_ratio, vti_ray_times

SMALL = """
physics: vti
model:
  vp: {kind: layered, shape: [31, 41], spacing: 10.0, velocities: [2000.0, 2400.0], interfaces: [150.0]}
  epsilon: {kind: layered, values: [0.0, 0.25], interfaces: [150.0]}
  delta: {kind: layered, values: [0.0, 0.1], interfaces: [150.0]}
geometry:
  sources: {points: [{x: 150.0, z: 30.0}, {x: 250.0, z: 30.0}]}
  receivers:
    line: {start: {x: 50.0, z: 20.0}, end: {x: 350.0, z: 20.0}, count: 7}
    components: [vx, pressure]
wavelet: {kind: ricker, peak_frequency: 12.0}
source: {type: explosive, components: 1.0e+3}
simulation: {order: 4, pml_width: 8, dx: 10.0, domain: model, duration: 0.3, free_surface: true}
"""


def test_model_section_loads_thomsen_fields_on_vps_grid(tmp_path):
    """A number, layers (a node on an interface belongs to the layer below, as for velocities) and an .npy file on vp's
    grid; rho defaults to water; resampling keeps the values at coinciding nodes (to rounding) and epsilon >= delta."""
    np.save(tmp_path / "delta.npy", np.linspace(-0.1, 0.05, 31 * 41).reshape(31, 41))
    spec = yaml.safe_load(SMALL)["model"]
    m = load_physics_model({**spec, "delta": {"kind": "npy", "path": "delta.npy"}}, "vti", base_dir=tmp_path)
    assert isinstance(m, VTIModel) and m.physics == "vti" and m.shape == (31, 41)
    assert np.array_equal(m.epsilon[:, 0], np.where(np.arange(31) * 10.0 >= 150.0, 0.25, 0.0))
    assert np.array_equal(m.delta, np.load(tmp_path / "delta.npy")) and np.all(m.rho.values == 1000.0)
    assert m.vmax == pytest.approx(2400.0 * math.sqrt(1.5), rel=1e-15)  # the fastest: horizontal, in the lower layer
    same = m.resample(10.0, (0.0, 0.0), (31, 41))
    np.testing.assert_allclose(same.epsilon, m.epsilon, rtol=0, atol=1e-15)  # 1 / (1 + 2 t) and back: rounding
    fine = m.resample(5.0, (0.0, 0.0), (61, 81))
    assert np.all(fine.epsilon >= fine.delta) and fine.epsilon[29, 0] == pytest.approx(0.125)  # halfway at 145 m
    assert load_physics_model({**spec, "epsilon": 0.2, "delta": -0.1}, "vti").epsilon.max() == 0.2


def test_qp_speeds_against_thomsen():
    """The group speed ratio at 0 and 90 degrees is 1 and sqrt(1 + 2 epsilon) (whatever delta); the slowest
    phase speed is vp where delta >= 0, and docs/vti.md's 0.986 vp (0.1, -0.1) and 0.942 vp (0, -0.2) where delta < 0
    (1-degree sampling: within 1e-3)."""
    r = qp_group_speed_ratio(0.25, 0.1, np.array([0.0, np.pi / 2]))
    np.testing.assert_allclose(r, [1.0, math.sqrt(1.5)], rtol=1e-8)  # the end's one-sided dV/dtheta: 3e-9 off at 90 deg
    np.testing.assert_allclose(qp_min_speed_ratio(np.array([0.3, 0.1, 0.0]), np.array([0.0, -0.1, -0.2])), [1.0, 0.986, 0.942],
                               atol=1e-3)


def test_planner_takes_dx_from_the_slowest_qp_and_dt_from_the_horizontal_speed():
    """dt: 0.9 x the staggered CFL limit at vh_max = 2400 sqrt(1.5) m/s, rounded down to 2 digits (so within 0.9 x
    0.9 .. 0.9 of the limit); dx (planned, not pinned): vp_min 2000 m/s resolved. The plan names both."""
    raw = yaml.safe_load(SMALL)
    raw["simulation"].pop("dx")
    p = plan_scene(parse_config(raw))
    vh = 2400.0 * math.sqrt(1.5)
    assert p.physics == "vti" and 0.81 * staggered_cfl_limit(4, 2) <= vh * p.dt / p.dx <= 0.9 * staggered_cfl_limit(4, 2)
    assert p.courant == pytest.approx(vh * p.dt / p.dx)
    text = p.describe()
    assert "horizontal speed max vp sqrt(1 + 2 epsilon) = 2939 m/s" in text and "qP at 2000 m/s (vp_min 2000 m/s" in text
    # delta < 0 lowers the slowest qP speed below vp_min: 0.942 x 2000 m/s for (0, -0.2) (test above)
    raw["model"]["epsilon"], raw["model"]["delta"] = 0.0, -0.2
    assert "qP at 1884 m/s (vp_min 2000 m/s" in plan_scene(parse_config(raw)).describe()


def test_anisotropy_line_and_the_direct_ray_times():
    """Straight rays in a homogeneous medium: vertical at vp, horizontal at vp sqrt(1 + 2 epsilon) (the group speeds).
    The plan's error is the bound t_iso |1 - vp / V_g| at the geometry's angles, largest for source 0 -> receiver 6
    (200.25 m, 87 degrees from the vertical): 18.3 ms for epsilon 0.25 (below a quarter of 1/12 Hz = 20.8 ms: isotropic
    suffices), 25.3 ms for epsilon 0.4 (vti needed), 0 for epsilon = delta = 0."""
    raw = yaml.safe_load(SMALL)
    raw["model"]["vp"] = {"kind": "constant", "shape": [31, 41], "spacing": 10.0, "velocity": 2000.0}
    raw["model"]["epsilon"], raw["model"]["delta"] = 0.25, 0.1
    c = parse_config(raw)
    t_vti, t_iso, angle = vti_ray_times(c.model, np.array([[0.0, 0.0], [0.0, 0.0]]), np.array([[300.0, 0.0], [0.0, 400.0]]))
    np.testing.assert_allclose(t_vti[0], [300.0 / 2000.0, 400.0 / (2000.0 * math.sqrt(1.5))], rtol=1e-8)  # as above: 4e-9
    np.testing.assert_allclose(t_iso[0], [0.15, 0.2], rtol=1e-12)
    length, theta = math.hypot(200.0, 10.0), round(math.atan2(200.0, 10.0), 3)  # the plan rounds the angles to 1e-3 rad
    needed = "physics vti needed: dropping the anisotropy (isotropic vp) moves qP arrivals by up to"
    for eps, verdict in ((0.25, "isotropic acoustic suffices (travel-time error"), (0.4, needed)):
        raw["model"]["epsilon"] = eps
        error = length / 2000.0 * (1.0 - 1.0 / qp_group_speed_ratio(eps, 0.1, theta))
        text = plan_scene(parse_config(raw)).describe()
        assert f"{verdict} {1e3 * error:.3g} ms" in text and "1/12 Hz = 20.8 ms" in text, text
    raw["model"]["epsilon"] = raw["model"]["delta"] = 0.0
    assert "anisotropy isotropic acoustic suffices (travel-time error 0 ms < " in plan_scene(parse_config(raw)).describe()


def test_forward_cli_equals_forward_vti_called_directly(tmp_path):
    """The CLI's data.h5 against forward_vti called here with the planned grid and model but the geometry and the
    source (M0 x the Ricker wavelet) built by hand: bitwise equal (float32, as simulated); free surface on."""
    from adseismic.data.store import read_forward
    from adseismic.solve.vti import forward_vti
    from adseismic.wavelets import make_wavelet

    cfg = tmp_path / "c.yaml"
    cfg.write_text(SMALL)
    assert main(["forward", str(cfg), "-o", str(tmp_path / "out"), "--quiet"]) == 0
    out = read_forward(tmp_path / "out" / "data.h5")
    assert list(out.components) == ["vx", "pressure"] and out.attrs["physics"] == "vti"
    assert sorted(p.name for p in (tmp_path / "out").glob("model_*.png")) == ["model_delta.png", "model_epsilon.png", "model_rho.png"]
    scene = build_scene(load_config(cfg))
    plan, m = scene.plan, scene.model.materials()
    assert plan.dx == 10.0 and plan.free_surface and plan.origin == (0.0, 0.0)
    rec = np.stack([np.full(7, 20.0), np.linspace(50.0, 350.0, 7)], 1)
    amp = 1e3 * np.tile(make_wavelet("ricker", plan.nt, plan.dt, peak_frequency=12.0), (2, 1, 1))
    r = forward_vti(m["vp"], m["epsilon"], m["delta"], m["rho"], plan.dx, plan.dt, amp, np.array([[[30.0, 150.0]], [[30.0, 250.0]]]),
                    np.broadcast_to(rec, (2, 7, 2)), order=4, pml_width=8, free_surface=True)
    assert np.array_equal(out.components["vx"], r.vx) and np.array_equal(out.components["pressure"], r.pressure)
    assert np.abs(r.pressure).max() > 0 and np.abs(r.vx).max() > 0
