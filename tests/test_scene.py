"""Scene planner: the coarsest grid and time step that meet the accuracy target, record length,
domain, refusals and warnings; and a planned homogeneous scene against the analytic solution."""

import numpy as np
import pytest

from adseismic.analytic import acoustic_2d
from adseismic.config import parse_config
from adseismic.kernels.numerics import cfl_limit, dispersion_error
from adseismic.scene import build_scene, plan_scene, run_forward
from adseismic.wavelets import duration, ricker

from .conftest import DEVICE

C = 2000.0


def config(order=4, accuracy=0.01, receivers=((500.0, 1100.0), (100.0, 900.0)), **sim):
    raw = {
        "model": {"kind": "constant", "shape": [201, 301], "spacing": 5.0, "velocity": C},
        "geometry": {"sources": {"points": [{"x": 300.0, "z": 500.0}]},
                     "receivers": {"points": [{"x": x, "z": z} for z, x in receivers]}},
        "wavelet": {"kind": "ricker", "peak_frequency": 15.0},
        "simulation": {"order": order, "accuracy": accuracy, "precision": "float64", "device": DEVICE, **sim},
    }  # fmt: skip
    return parse_config(raw)


def group_error(plan, dx, dt):
    return dispersion_error(plan.order, 2, C / (plan.f_max * dx), C * dt / dx)["group"][0]


@pytest.mark.parametrize("order", [2, 4, 8])
def test_grid_is_the_coarsest_that_meets_the_target(order):
    p = plan_scene(config(order=order))
    assert p.expected_error <= 0.01
    # 15% coarser at the same Courant number would miss the target (the planner searches the
    # Courant number too: at order 8 the time error dominates near the CFL limit)
    assert group_error(p, 1.15 * p.dx, 1.15 * p.dt) > 0.01
    assert p.f_max == pytest.approx(2.21 * 15.0, rel=0.01)  # Ricker -20 dB edge
    assert p.courant <= 0.9 * cfl_limit(order, 2) + 1e-9


def test_higher_order_needs_fewer_cells():
    cells = [np.prod(plan_scene(config(order=o)).shape) for o in (2, 4, 8)]
    assert cells[0] > 4 * cells[1] > 4 * cells[2] / 2  # measured 139k, 18k, 11k


def test_record_length_and_domain():
    p = plan_scene(config())
    t_direct = 800.0 / C
    wavelet_length = duration(ricker(15.0, 2000, 1e-4), 1e-4)  # 0.165 s above 1e-3 of the peak
    assert p.nt * p.dt == pytest.approx(t_direct + wavelet_length, abs=2 * p.dt)
    margin = C * (p.nt - 1) * p.dt / 2
    assert p.origin[1] == pytest.approx(max(300.0 - margin, 0.0), abs=1e-6)
    pinned = plan_scene(config(margin=50.0, duration=0.6))
    assert pinned.origin == pytest.approx((50.0, 250.0))
    assert pinned.shape[1] == pytest.approx(900.0 / pinned.dx + 1, abs=1)
    assert pinned.nt * pinned.dt == pytest.approx(0.6, abs=2 * pinned.dt)


def test_pinned_unstable_dt_is_refused_with_the_limit():
    with pytest.raises(ValueError, match=r"simulation\.dt.*exceeds the exact limit 0\.6124.*use dt <= "):
        plan_scene(config(dx=10.0, dt=0.0035))


def test_pinned_coarse_grid_warns_with_expected_error():
    p = plan_scene(config(dx=20.0))
    assert any("under-resolved" in w and "%" in w for w in p.warnings)
    assert p.expected_error > 0.01


def test_short_pinned_record_warns():
    p = plan_scene(config(duration=0.2))
    assert any("shorter than the longest direct arrival" in w for w in p.warnings)


@pytest.mark.parametrize("order", [4, 8])
def test_planned_scene_matches_analytic_solution(order):
    # accuracy 0.3% group-velocity error at f_max -> measured trace errors 1.05-1.5% after ~13
    # wavelengths of travel (the dispersion error accumulates with distance).
    sc = build_scene(config(order=order, accuracy=0.003))
    r = run_forward(sc)
    for i, (z, x) in enumerate(((500.0, 1100.0), (100.0, 900.0))):
        a = acoustic_2d(sc.wavelet, sc.plan.dt, np.hypot(z - 500.0, x - 300.0), C)
        assert np.linalg.norm(r.receiver_amplitudes[0, i] - a) / np.linalg.norm(a) < 0.016


def test_a_second_plan_of_the_same_model_and_geometry_traces_no_ray(monkeypatch):
    # the longest direct arrival is kept per model object and geometry (an FWI plans each band's grid for them)
    import dataclasses

    from adseismic import scene as sc

    calls = []
    rays = sc.straight_ray_times
    monkeypatch.setattr(sc, "straight_ray_times", lambda *a, **k: calls.append(1) or rays(*a, **k))
    c = config()
    first = plan_scene(c)
    plan_scene(c, f_max=20.0)  # another band's plan
    assert len(calls) == 1
    near = dataclasses.replace(c, geometry=config(receivers=((500.0, 700.0),)).geometry)  # the same model, another geometry
    assert plan_scene(near).nt < first.nt and len(calls) == 2
