"""physics: viscoacoustic from YAML (issue 26 items 2 and 7): `adseismic forward` runs forward_viscoacoustic bit for bit,
the planner's dt comes from the unrelaxed (fastest) speed, and its attenuation report (the amplitude lost over the
longest path) is right for a homogeneous medium."""

import math

import h5py
import numpy as np
import pytest
import yaml

from adseismic.cli import main
from adseismic.config import parse_config
from adseismic.data.models import ViscoacousticModel
from adseismic.kernels.numerics import staggered_cfl_limit
from adseismic.scene import ATTENUATION_LOSS, attenuation_check, plan_scene
from adseismic.solve.viscoacoustic import forward_viscoacoustic
from adseismic.wavelets import make_wavelet

CONFIG = """
physics: viscoacoustic
model:
  vp: {kind: layered, shape: [31, 41], spacing: 10.0, velocities: [2000.0, 2500.0], interfaces: [150.0]}
  q: {kind: layered, values: [.inf, 20.0], interfaces: [150.0]}
  rho: {kind: layered, velocities: [1000.0, 2000.0], interfaces: [150.0]}
  q_band: [3.0, 25.0]
  f_ref: 12.0
  mechanisms: 2
geometry:
  sources: {points: [{x: 200.0, z: 20.0}]}
  receivers:
    line: {start: {x: 50.0, z: 10.0}, end: {x: 350.0, z: 10.0}, count: 7}
    components: [pressure, vx, vz]
wavelet: {kind: ricker, peak_frequency: 10.0}
source: {type: explosive, components: 1.0e+6}
simulation: {order: 4, pml_width: 10, pml_reflection: 0.001, dx: 10.0, dt: 0.001, duration: 0.3, domain: model,
             free_surface: true}
"""


def test_cli_forward_is_forward_viscoacoustic_bitwise(tmp_path):
    (tmp_path / "c.yaml").write_text(CONFIG)
    assert main(["forward", str(tmp_path / "c.yaml"), "-o", str(tmp_path / "out"), "-q"]) == 0
    with h5py.File(tmp_path / "out" / "data.h5") as f:
        cli = {c: f[c][()] for c in ("pressure", "vx", "vz")}
        assert f.attrs["physics"] == "viscoacoustic"
    # the same run from the config's numbers (the grid is the model's: dx and domain pinned, so nothing is resampled)
    z = 10.0 * np.arange(31)[:, None] * np.ones((1, 41))
    vp, q, rho = (np.where(z < 150.0, a, b) for a, b in ((2000.0, 2500.0), (np.inf, 20.0), (1000.0, 2000.0)))
    nt = int(math.ceil(0.3 / 1e-3)) + 1
    amplitudes = 1e6 * make_wavelet("ricker", nt, 1e-3, peak_frequency=10.0)[None, None]
    receivers = np.stack([np.full(7, 10.0), np.linspace(50.0, 350.0, 7)], -1)[None]
    direct = forward_viscoacoustic(vp, q, rho, 10.0, 1e-3, amplitudes, np.array([[[20.0, 200.0]]]), receivers,
                                   q_band=(3.0, 25.0), f_ref=12.0, mechanisms=2, order=4, pml_width=10, pml_reflection=1e-3,
                                   free_surface=True, precision="float32")
    for c in cli:
        assert cli[c].shape == (1, 7, nt) and np.abs(cli[c]).max() > 0
        np.testing.assert_array_equal(cli[c], getattr(direct, c))  # bit for bit


def _homogeneous(q: str, duration="") -> ViscoacousticModel:
    text = (CONFIG.replace("velocities: [2000.0, 2500.0]", "velocities: [2000.0, 2000.0]")
            .replace("values: [.inf, 20.0]", f"values: [{q}, {q}]").replace("  q_band: [3.0, 25.0]\n  f_ref: 12.0\n  mechanisms: 2\n", "")
            .replace("dx: 10.0, dt: 0.001, duration: 0.3, ", duration))
    return parse_config(yaml.safe_load(text))


def test_plan_takes_dt_from_the_unrelaxed_speed():
    config = _homogeneous("5.0")
    plan = plan_scene(config)
    a = plan.attenuation
    # defaults from the Ricker's dominant frequency (its spectrum peaks at peak_frequency: 10 Hz within the sampled
    # spectrum's resolution)
    assert a.f_dominant == pytest.approx(10.0, rel=0.02) and a.mechanisms == 3
    assert a.q_band == pytest.approx((a.f_dominant / 3.0, 2.5 * a.f_dominant)) and a.f_ref == a.f_dominant
    # at Q = 5 the unrelaxed speed is ~15% above vp (docs/viscoacoustic.md); the phase velocity at the band's low end
    # below it
    assert 1.12 < a.v_unrelaxed / 2000.0 < 1.18 and a.v_slowest < 2000.0
    limit = staggered_cfl_limit(4, 2)
    assert plan.courant == pytest.approx(a.v_unrelaxed * plan.dt / plan.dx) and plan.courant <= 0.9 * limit
    assert "unrelaxed (w -> infinity) speed" in plan.reasons["dt"] and "Q band's low end" in plan.reasons["dx"]
    # the planner's usual margin applied to vp would be unstable: the solver refuses that dt
    dt_vp = 0.9 * limit * plan.dx / 2000.0
    amplitudes = make_wavelet("ricker", 50, dt_vp, peak_frequency=10.0)[None, None]
    with pytest.raises(ValueError, match="is unstable .* unrelaxed vp_max"):
        forward_viscoacoustic(np.full((31, 41), 2000.0), np.full((31, 41), 5.0), np.full((31, 41), 1000.0), plan.dx, dt_vp,
                              amplitudes, np.array([[[20.0, 200.0]]]), np.array([[[10.0, 100.0]]]), q_band=a.q_band,
                              f_ref=a.f_ref)
    # lossless: the unrelaxed speed is vp
    assert plan_scene(_homogeneous(".inf")).attenuation.v_unrelaxed == pytest.approx(2000.0, rel=1e-12)


@pytest.mark.parametrize("q, needed", [(50.0, True), (1e5, False)])
def test_attenuation_report(q, needed):
    config = _homogeneous(str(q))
    src, rec = np.array([[20.0, 0.0]]), np.array([[20.0, 400.0], [220.0, 400.0]])
    check = attenuation_check(config.model, src, rec, config.wavelet)
    # straight rays through a homogeneous medium: t* = distance / (vp Q), exactly up to round-off
    distance = np.hypot(*(rec - src).T)
    np.testing.assert_allclose(check.t_star[0], distance / (2000.0 * q), rtol=1e-12)
    expected = 1.0 - np.exp(-math.pi * check.f_dominant * distance.max() / (2000.0 * q))
    assert check.pair == (0, 1) and check.loss == pytest.approx(expected, rel=1e-12) and check.loss_ray == pytest.approx(expected)
    assert check.needed is needed and (check.loss >= ATTENUATION_LOSS) is needed
    text = check.describe()
    assert ("Q matters" in text) is needed and ("lossless acoustic suffices (amplitude error" in text) is not needed


def test_q_resamples_by_its_inverse():
    config = parse_config(yaml.safe_load(CONFIG))
    m = config.model.resample(5.0, (0.0, 0.0), (61, 81))
    # nodes 140 m and 150 m hold Q = inf and 20; 145 m interpolates 1 / Q: 1 / 40
    assert np.isinf(m.q[28]).all() and m.q[29] == pytest.approx(40.0, rel=1e-12) and m.q[30] == pytest.approx(20.0, rel=1e-12)
