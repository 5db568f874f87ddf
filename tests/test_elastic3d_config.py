"""physics: elastic with a 3D model from YAML (issue 26 item 4): the config (3-component force, 6-component moment
tensor, explosive source; vx, vy, vz, pressure receivers), the planner's 3D CFL limit, dispersion and memory bound,
`adseismic forward` against forward_elastic3d called directly, and the refusals (wrong source sizes, DAS in 3D, vy in
2D, 3D vti / viscoacoustic, 3D elastic in fwi, image and locate)."""
import logging
import math

import h5py
import numpy as np
import pytest
import yaml

from adseismic.cli import main
from adseismic.config import parse_config
from adseismic.kernels.numerics import staggered_cfl_limit, staggered_dispersion_error
from adseismic.scene import build_scene, forward_memory_bytes, plan_scene, run_forward
from adseismic.solve.elastic3d import forward_elastic3d

# 16 x 14 x 18 cells of 10 m, dx pinned, 120 steps of 2.2 ms (0.9 x the 3D limit 0.4949 x 10 m / 2000 m/s)
SMALL = """
physics: elastic
model:
  vp: {kind: constant, shape: [16, 14, 18], spacing: 10.0, velocity: 2000.0}
  vs: {vp_ratio: 1.8}
  rho: {gardner: true}
geometry:
  sources: {points: [{z: 70, y: 60, x: 80}, {z: 80, y: 70, x: 100}]}
  receivers:
    line: {start: {z: 30, y: 60, x: 20}, end: {z: 30, y: 60, x: 150}, count: 5}
wavelet: {kind: ricker, peak_frequency: 10.0}
source: {type: force, components: [1.0e+3, 5.0e+2, -2.0e+2]}
simulation: {order: 4, pml_width: 6, dx: 10.0, duration: 0.26, domain: model, precision: float64}
"""


def small(text: str = SMALL, **changes) -> dict:
    """SMALL parsed, with section__key = value changes (a value None drops the key)."""
    raw = yaml.safe_load(text)
    for key, value in changes.items():
        section, _, name = key.partition("__")
        target = raw[section] if name else raw
        name = name or section
        if value is None:
            target.pop(name, None)
        else:
            target[name] = value
    return raw


def receivers_grid(n: int = 5) -> np.ndarray:
    """The SMALL spread in grid metres (model origin 0: world metres), (n, 3) (z, y, x)."""
    return np.stack([np.full(n, 30.0), np.full(n, 60.0), np.linspace(20.0, 150.0, n)], axis=1)


# ------------------------------------------------------------------------------ forward through the CLI

def test_forward_cli_writes_vx_vy_vz_pressure_equal_to_forward_elastic3d_called_directly(tmp_path):
    """data.h5 from `adseismic forward` against forward_elastic3d called here with the plan's dx, dt, the scene's
    arrays and the geometry and source built by hand: bitwise equal (same code path, float64)."""
    from adseismic.data.store import read_forward
    from adseismic.wavelets import make_wavelet

    cfg = tmp_path / "c.yaml"
    cfg.write_text(SMALL)
    assert main(["forward", str(cfg), "-o", str(tmp_path / "out"), "--quiet"]) == 0
    out = read_forward(tmp_path / "out" / "data.h5")
    assert list(out.components) == ["vx", "vy", "vz", "pressure"]  # the 3D default: every component
    with h5py.File(tmp_path / "out" / "data.h5") as f:
        assert [f[n].attrs["units"] for n in out.components] == ["m/s", "m/s", "m/s", "Pa"]
        assert f["vy"].shape == (2, 5, 120) and f["vy"].dtype == np.float64
    assert out.attrs["physics"] == "elastic" and out.attrs["source_type"] == "force"
    assert list(out.attrs["source_components"]) == [1e3, 5e2, -2e2]

    scene = build_scene(parse_config(small(), base_dir=tmp_path))
    plan, m = scene.plan, scene.model
    assert (plan.dx, plan.dt, plan.nt, plan.shape) == (10.0, 0.0022, 120, (16, 14, 18))
    wavelet = make_wavelet("ricker", plan.nt, plan.dt, peak_frequency=10.0)
    r = forward_elastic3d(m.vp.values, m.vs.values, m.rho.values, plan.dx, plan.dt, np.tile(wavelet, (2, 1, 1)),
                          np.array([[[70.0, 60.0, 80.0]], [[80.0, 70.0, 100.0]]]), np.broadcast_to(receivers_grid(), (2, 5, 3)),
                          source_type="force", source_components=np.tile([1e3, 5e2, -2e2], (2, 1, 1)), order=4, pml_width=6,
                          precision="float64")  # fmt: skip
    for name in ("vx", "vy", "vz", "pressure"):
        assert np.array_equal(out.components[name], getattr(r, name)), name
        assert np.abs(out.components[name]).max() > 0, name  # the oblique force moves every component
    pngs = {p.name for p in (tmp_path / "out").glob("*.png")}
    assert {f"gather_shot{k}_{n}.png" for k in (0, 1) for n in ("vx", "vy", "vz", "pressure")} <= pngs


@pytest.mark.parametrize("source, solver_type, components", [
    ({"type": "moment", "components": [1e6, -5e5, -5e5, 2e5, 0.0, 1e5]}, "moment", [1e6, -5e5, -5e5, 2e5, 0.0, 1e5]),
    ({"type": "explosive", "components": 3e5}, "moment", [3e5, 3e5, 3e5, 0.0, 0.0, 0.0]),
])  # fmt: skip
def test_moment_and_explosive_sources_reach_forward_elastic3d_as_six_components(source, solver_type, components, tmp_path):
    """The YAML moment tensor (m_zz, m_yy, m_xx, m_yz, m_xz, m_xy) and explosive M0 reach the solver unchanged (the
    explosive as (M0, M0, M0, 0, 0, 0)), with a free surface and the recorded components chosen (vy, pressure)."""
    raw = small(source=source, simulation__free_surface=True)
    raw["geometry"]["receivers"]["components"] = ["vy", "pressure"]
    config = parse_config(raw, base_dir=tmp_path)
    assert config.source.components == tuple(components) and config.geometry.components == ("vy", "pressure")
    scene = build_scene(config)
    assert scene.source_type == solver_type and scene.source_components.shape == (2, 1, 6)
    result = run_forward(scene)
    p, m = scene.plan, scene.model
    r = forward_elastic3d(m.vp.values, m.vs.values, m.rho.values, p.dx, p.dt, scene.source_amplitudes, scene.source_locations,
                          scene.receiver_locations, source_type="moment", source_components=np.tile(components, (2, 1, 1)),
                          order=4, pml_width=6, free_surface=True, precision="float64")  # fmt: skip
    assert np.array_equal(result.vy, r.vy) and np.array_equal(result.pressure, r.pressure)
    assert np.abs(r.pressure).max() > 0 and np.abs(r.vy).max() > 0


# ------------------------------------------------------------------------------ the plan

def test_plan_uses_the_3d_cfl_limit_and_dispersion():
    """dx pinned at 10 m: dt = 0.9 x staggered_cfl_limit(4, 3) x dx / vp_max rounded down (2.2 ms), below the 2D plan's
    of the same speeds (2.7 ms, 0.9 x the 2D limit 0.6061); unpinned: the expected error is the 3D dispersion's."""
    plan3 = plan_scene(parse_config(small()))
    limit3 = staggered_cfl_limit(4, 3)
    assert plan3.cfl_limit == limit3 and plan3.ndim == 3
    assert 0.8 * limit3 < plan3.courant <= 0.9 * limit3  # 0.9 x the limit, dt rounded down to 2 digits
    assert plan3.courant == pytest.approx(2000.0 * 0.0022 / 10.0, rel=1e-12) and plan3.dt == 0.0022
    two_d = {"model": {"vp": {"kind": "constant", "shape": [16, 18], "spacing": 10.0, "velocity": 2000.0},
                       "vs": {"vp_ratio": 1.8}, "rho": {"gardner": True}},
             "geometry": {"sources": {"points": [{"z": 70, "x": 80}]},
                          "receivers": {"line": {"start": {"z": 30, "x": 20}, "end": {"z": 30, "x": 150}, "count": 5}}},
             "source": {"type": "force", "components": [1.0, 0.0]}}
    plan2 = plan_scene(parse_config(small(**two_d)))
    assert plan2.cfl_limit == staggered_cfl_limit(4, 2) and plan2.dt == 0.0027 and plan3.dt < plan2.dt

    free = plan_scene(parse_config(small(simulation={"order": 4, "pml_width": 6, "duration": 0.26, "domain": "model"})))
    vs = 2000.0 / 1.8
    err = max(staggered_dispersion_error(4, 3, v / (free.f_max * free.dx), v * free.dt / free.dx)["group"][0] for v in (vs, 2000.0))
    assert free.expected_error == pytest.approx(err, rel=1e-12) and free.expected_error <= 0.01
    assert free.courant <= 0.9 * limit3


def test_plan_memory_is_the_elastic3d_bound_and_covers_the_solver_arrays():
    """Plan.memory_bytes is forward_memory_bytes(..., "elastic3d") and at least the solver's state (9 fields and the
    CPML strips of every shot), materials and traces as setup_elastic3d allocates them."""
    from adseismic.kernels.elastic3d.propagator import FIELDS, MATERIALS, PSI
    from adseismic.solve.elastic3d import setup_elastic3d

    scene = build_scene(parse_config(small()))
    p = scene.plan
    assert p.memory_bytes == forward_memory_bytes(p.padded_cells, 2, 5, p.nt, 8, "elastic3d")
    m = scene.model.materials()
    su = setup_elastic3d(m["vp"], m["vs"], m["rho"], p.dx, p.dt, scene.source_amplitudes, scene.source_locations,
                         scene.receiver_locations, source_components=scene.source_components, order=4, pml_width=6,
                         precision="float64")  # fmt: skip
    prop = su.prop
    state = len(FIELDS) * prop.n_shots * math.prod(prop.padded) + sum(math.prod(prop.psi_shape(k)) for k in PSI)
    arrays = state + (3 + len(MATERIALS)) * math.prod(prop.padded) + 4 * 2 * 5 * p.nt
    assert p.padded_cells >= math.prod(prop.padded)
    assert p.memory_bytes >= 8 * arrays, (p.memory_bytes, 8 * arrays)


# ------------------------------------------------------------------------------ refusals

VD3 = SMALL.replace("  vs: {vp_ratio: 1.8}\n", "").replace("physics: elastic", "physics: acoustic_vd").replace(
    "source: {type: force, components: [1.0e+3, 5.0e+2, -2.0e+2]}", "")
TWO_D = (SMALL.replace("shape: [16, 14, 18]", "shape: [16, 18]")
         .replace("{z: 70, y: 60, x: 80}, {z: 80, y: 70, x: 100}", "{z: 70, x: 80}")
         .replace("{z: 30, y: 60, x: 20}", "{z: 30, x: 20}").replace("{z: 30, y: 60, x: 150}", "{z: 30, x: 150}")
         .replace("[1.0e+3, 5.0e+2, -2.0e+2]", "[1.0, 0.0]"))
FWD = ["forward", "{d}/c.yaml", "-o", "{out}"]
FWI_TAIL = ("true_model:\n  vp: {kind: constant, shape: [16, 14, 18], spacing: 10.0, velocity: 2100.0}\n  vs: {vp_ratio: 1.8}\n"
            "  rho: {gardner: true}\ninversion: {bands: [null], iterations: 1}\n")
LOCATE = ("physics: elastic\nmodel:\n  vp: {kind: constant, shape: [16, 14, 18], spacing: 10.0, velocity: 2000.0}\n"
          "  vs: {vp_ratio: 1.8}\n  rho: {gardner: true}\ntraces: {paths: [ev.mseed]}\n")

REFUSALS = [  # name, config text, command, fragments of the message
    ("3D force of 2 components", SMALL.replace("[1.0e+3, 5.0e+2, -2.0e+2]", "[1.0, 0.0]"), FWD,
     ["source.components: [1.0, 0.0] is not [f_z, f_y, f_x] in N", "3D model needs its 3 components"]),
    ("3D moment tensor of 3 components", SMALL.replace("type: force, components: [1.0e+3, 5.0e+2, -2.0e+2]",
                                                       "type: moment, components: [1.0, 1.0, 0.0]"), FWD,
     ["source.components: [1.0, 1.0, 0.0] is not [m_zz, m_yy, m_xx, m_yz, m_xz, m_xy] in N m", "needs its 6 components"]),
    ("DAS in 3D", SMALL.replace("count: 5}", "count: 5}\n    das: {gauge_length: 10.0}"), FWD,
     ["geometry.receivers.das: {'gauge_length': 10.0} with a 3D model", "2D only", "drop das"]),
    ("vy in 2D", TWO_D.replace("count: 5}", "count: 5}\n    components: [vx, vy]"), FWD,
     ["geometry.receivers.components: ['vx', 'vy'] names vy with a 2D model", "drop vy"]),
    ("3D vti", VD3.replace("physics: acoustic_vd", "physics: vti").replace("  rho:", "  epsilon: 0.1\n  delta: 0.05\n  rho:"), FWD,
     ["model.vp: a 3D model (shape [16, 14, 18]) with physics vti", "give a 2D model"]),
    ("3D viscoacoustic", VD3.replace("physics: acoustic_vd", "physics: viscoacoustic").replace("  rho:", "  q: 30.0\n  rho:"), FWD,
     ["model.vp: a 3D model (shape [16, 14, 18]) with physics viscoacoustic", "give a 2D model"]),
    ("3D elastic fwi", SMALL + FWI_TAIL, ["fwi", "{d}/c.yaml", "-o", "{out}"],
     ["model.vp: a 3D model (shape [16, 14, 18]) with physics elastic", "forward modelling only", "adseismic fwi"]),
    ("3D elastic image", SMALL + FWI_TAIL.replace("inversion: {bands: [null], iterations: 1}\n", "image: {method: rtm}\n"),
     ["image", "{d}/c.yaml", "-o", "{out}"], ["model.vp: a 3D model (shape [16, 14, 18]) with physics elastic", "image"]),
    ("3D elastic parallel", SMALL + "parallel: {workers: 2}\n", FWD,
     ["parallel: given with a 3D elastic model", "drop the parallel section"]),
    ("3D elastic locate", LOCATE, ["locate", "{d}/c.yaml", "-o", "{out}"],
     ["model.vp: a 3D model (shape [16, 14, 18]) with physics elastic", "locate", "give a 2D model"]),
]


@pytest.mark.parametrize("name, text, argv, fragments", REFUSALS, ids=[r[0] for r in REFUSALS])
def test_refusals_exit_2_naming_the_key_value_and_fix(name, text, argv, fragments, tmp_path, capsys, caplog):
    d = tmp_path / "in"
    d.mkdir()
    (d / "c.yaml").write_text(text)
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO, logger="adseismic"):
        status = main([a.format(d=d, out=out) for a in argv])
    captured = capsys.readouterr()
    message = captured.out + captured.err + caplog.text
    assert status == 2 and "Traceback" not in message, message
    for fragment in fragments:
        assert fragment in message, f"{fragment!r} not in:\n{message}"
    assert not out.exists() or not any(out.iterdir())
