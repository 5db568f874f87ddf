"""FWI with physics viscoacoustic (vp, q, rho) and vti (vp, epsilon, delta, rho): the whole objective's Taylor test in
float64 in every quantity, the VTI clamp delta <= epsilon, the plan's speed range for the bounds and the default bounds,
and small inversions through the CLI whose anomaly error falls (the refusals: tests/test_bad_inputs.py). On the test
device (ADSEISMIC_TEST_DEVICE, conftest.py)."""

import copy
import json
from types import SimpleNamespace

import numpy as np
import pytest

from adseismic.config.fwi import InversionConfig
from adseismic.inversion.fwi import Simulator, make_objective
from adseismic.inversion.model_space import PHYSICS_PARAMETERS, REFERENCE, ModelSpace
from adseismic.solve.receivers import Recording
from adseismic.wavelets import ricker

from .conftest import DEVICE
from .test_fwi_physics import DT, DX, NT, SHAPE, _run, _smooth_field


def _bump():
    return np.exp(-((np.arange(SHAPE[0])[:, None] - 12) ** 2 + (np.arange(SHAPE[1])[None, :] - 14) ** 2) / 18.0)


def _models(physics):
    """(start, true) {solver parameter: (nz, nx)} on the tiny scene: a vp gradient, rho 2000-2115 kg/m^3 and Q 50 or
    epsilon 0.1, delta 0.05; the truth adds a Gaussian anomaly to every parameter."""
    z = np.arange(SHAPE[0])[:, None] * np.ones(SHAPE)
    start = {"vp": 2000.0 + 10.0 * z, "rho": 2000.0 + 5.0 * z}
    extra, anomaly = (({"q": 50.0}, {"q": -20.0}) if physics == "viscoacoustic" else
                      ({"epsilon": 0.1, "delta": 0.05}, {"epsilon": 0.08, "delta": 0.03}))  # fmt: skip
    start.update({k: np.full(SHAPE, v) for k, v in extra.items()})
    true = {k: v + {"vp": 150.0, "rho": 80.0, **anomaly}[k] * _bump() for k, v in start.items()}
    return start, true


def _objective(physics, names):
    """The whole FWI objective (inversion.fwi.make_objective: the misfit of the pressure over two shot batches,
    normalised, with Tikhonov regularisation) on a tiny scene in float64; viscoacoustic with its Q band pinned."""
    start, true = _models(physics)
    amp = np.broadcast_to(ricker(18.0, NT, DT), (2, 1, NT)).copy()
    src = np.array([[[30.0, 60.0]], [[30.0, 210.0]]])
    rec = np.broadcast_to(np.stack([np.full(12, 20.0), np.linspace(20.0, 250.0, 12)], -1), (2, 12, 2)).copy()
    kw = {"order": 4, "pml_width": 8, "pml_velocity": 3000.0, "pml_frequency": 18.0, "device": DEVICE, "precision": "float64"}
    if physics == "viscoacoustic":
        kw.update(q_band=(6.0, 45.0), f_ref=18.0, mechanisms=3)
    sim = Simulator(physics, kw, Recording(("pressure",)), 12, "moment", np.broadcast_to([1.0, 1.0, 0.0], (2, 1, 3)).copy())
    observed = sim.forward(true, DX, DT, amp, src, rec)
    space = ModelSpace(physics, start, names, bounds={k: (-1e12, 1e12) for k in names})
    f = make_objective(space, sim, SimpleNamespace(dx=DX, dt=DT), amp, src, rec, observed, np.ones((2, 12, NT)), [slice(0, 1), slice(1, 2)],
                       InversionConfig(tikhonov=1e-3), np.ones(SHAPE), np.ones(SHAPE), {})  # fmt: skip
    return space, f


@pytest.mark.parametrize("physics", ["viscoacoustic", "vti"])
def test_whole_objective_taylor(physics):
    # Taylor test of f(x + h d) - f(x) - h g.d = O(h^2) along a smooth direction d in every quantity at once (float64):
    # the remainder must fall ~4x per halving of h (second order), and g.d be the first-order term (remainder << h
    # |g.d|). A wrong chain rule, reference scaling or Q-band drift gives an O(h) remainder, whose ratio is ~2.
    # Measured: ratios 4.0000 (viscoacoustic), 3.9999-4.0000 (vti); remainder / (h g.d) at h = 1e-4 0.0023 and 0.089
    # (VTI's curvature along d is large: the smaller steps keep that ratio well below 0.1).
    # (d's epsilon and delta parts are equal, so that the start's epsilon - delta = 0.05 stays >> h |d|: no clamp.)
    names = PHYSICS_PARAMETERS[physics]
    space, f = _objective(physics, names)
    rng = np.random.default_rng(0)
    x = space.x0()
    parts = {k: _smooth_field(rng) * 0.05 for k in names}
    if physics == "vti":
        parts["delta"] = parts["epsilon"]
    d = np.concatenate([parts[k].ravel() for k in names])
    f0, g0 = f(x)
    slope = float(g0 @ d)
    rem = [abs(f(x + h * d)[0] - f0 - h * slope) for h in (1e-4, 5e-5, 2.5e-5)]
    ratios = [rem[i] / rem[i + 1] for i in range(2)]
    assert abs(slope) > 0
    assert all(3.5 < r < 4.5 for r in ratios), (rem, ratios)
    assert rem[-1] < 0.1 * abs(2.5e-5 * slope)


def test_vti_clamps_delta_to_epsilon_with_its_gradient():
    # a delta above epsilon reaches the solver as epsilon (stable: epsilon >= delta), its gradient moved to epsilon
    start, _ = _models("vti")
    space = ModelSpace("vti", start, ("epsilon", "delta"), bounds={"epsilon": (-0.4, 0.5), "delta": (-0.4, 0.5)})
    x = space.x0()
    n = int(np.prod(SHAPE))
    x[n:] = 0.3  # delta 0.3 > epsilon 0.1 everywhere
    pt = space.point(x)
    assert pt.delta_clamped.all() and np.array_equal(pt.physical["delta"], pt.physical["epsilon"])
    ones, zeros = np.ones(SHAPE), np.zeros(SHAPE)
    g = space.cells_gradient(pt, {"vp": zeros, "epsilon": ones, "delta": 2 * ones, "rho": zeros})
    assert np.all(g["delta"] == 0) and np.allclose(g["epsilon"], 3 * REFERENCE["epsilon"])


# --------------------------------------------------------------------------- through the CLI

GRID = {"shape": [21, 31], "spacing": 20.0}
VP = {"kind": "constant", **GRID, "velocity": 2000.0}
GEOMETRY = {"sources": {"points": [{"x": 150, "z": 20}, {"x": 450, "z": 20}]},
            "receivers": {"lines": [{"start": {"x": 0, "z": 10}, "end": {"x": 600, "z": 10}, "count": 16},
                                    {"start": {"x": 0, "z": 390}, "end": {"x": 600, "z": 390}, "count": 16}]}}  # fmt: skip


def _field(background, perturbation, tmp_path, name, radius=80.0):
    """A dimensionless field file (npy on vp's grid): background + a Gaussian anomaly at (200, 300) m, radius m."""
    z, x = np.meshgrid(np.arange(21) * 20.0, np.arange(31) * 20.0, indexing="ij")
    np.save(tmp_path / f"{name}.npy", background + perturbation * np.exp(-((z - 200) ** 2 + (x - 300) ** 2) / radius**2))
    return {"kind": "npy", "path": f"{name}.npy"}


def _config(physics, tmp_path):
    geometry = GEOMETRY
    if physics == "viscoacoustic":  # Q 100, a Q 30 anomaly inside the transmission paths (top to bottom receivers)
        model = {"vp": VP, "q": 100.0, "rho": {"kind": "constant", **GRID, "velocity": 2000.0}}
        true = {**model, "q": _field(100.0, -70.0, tmp_path, "q")}
        inversion = {"parameters": ["q"], "bounds": {"q": [10, 300]}}
    else:  # epsilon 0.05, a +0.15 anomaly of radius 150 m; delta 0; cross-well: horizontal paths, which epsilon sets
        geometry = {"sources": {"points": [{"x": 20, "z": z} for z in (50, 150, 250, 350)]},
                    "receivers": {"line": {"start": {"x": 580, "z": 0}, "end": {"x": 580, "z": 400}, "count": 21}}}
        model = {"vp": VP, "epsilon": 0.05, "delta": 0.0, "rho": {"kind": "constant", **GRID, "velocity": 2000.0}}
        true = {**model, "epsilon": _field(0.05, 0.15, tmp_path, "eps", 150.0)}
        inversion = {"parameters": ["epsilon"], "source_radius": 60.0}
    return {"physics": physics, "model": model, "true_model": true, "geometry": geometry,
            "wavelet": {"kind": "ricker", "peak_frequency": 6.0}, "simulation": {"order": 4, "pml_width": 8, "device": DEVICE},
            "inversion": {"bands": [None], "iterations": 3, **inversion}}


@pytest.mark.parametrize("physics,name", [("viscoacoustic", "q"), ("vti", "epsilon")])
def test_small_inversion_moves_the_anomaly_toward_the_truth(tmp_path, physics, name):
    # 3 L-BFGS iterations of q (vp, rho known) or epsilon (vp, delta, rho known) from the background: the misfit falls
    # and the anomaly's error too (numbers in docs/fwi_physics.md); only the inverted quantity moves
    import h5py

    out = _run(tmp_path, _config(physics, tmp_path))
    summary = json.loads((out / "summary.json").read_text())
    e = summary["errors"]
    # measured (CPU, float32): q misfit 0.27 of its start, anomaly error 0.279 -> 0.154; epsilon misfit 0.0069, error
    # 0.568 -> 0.312 (both 0.55x); asked: below 0.5 and 0.7x
    assert summary["bands"][0]["misfit"] < 0.5, summary  # relative to the start's misfit
    assert e[f"{name}_final_anomaly"] < 0.7 * e[f"{name}_start_anomaly"], e
    with h5py.File(out / "model.h5", "r") as f:
        params = PHYSICS_PARAMETERS[physics]
        assert list(f.attrs["inverted"]) == [name] and sorted(f) == sorted(params + tuple(f"start_{k}" for k in params))
        for k in PHYSICS_PARAMETERS[physics]:
            assert (k == name) == (not np.array_equal(f[k][...], f[f"start_{k}"][...])), k
        first = f[name][...]
    assert (out / f"model_{name}.png").exists() and (out / f"gradient_{name}.png").exists()
    _run(tmp_path, _config(physics, tmp_path), extra=("--resume",))  # replays the journal and observed.h5 to the same model
    with h5py.File(out / "model.h5", "r") as f:
        assert np.array_equal(f[name][...], first)


@pytest.mark.parametrize("physics", ["viscoacoustic", "vti"])
def test_plan_is_made_for_the_bounds(tmp_path, physics):
    # the plan's dt holds the fastest speed any model inside the bounds has (vti: vp_max sqrt(1 + 2 epsilon_max) at the
    # epsilon bound 0.5; viscoacoustic: the unrelaxed speed at the lowest Q bound 10, above vp), not the start model's
    from adseismic.config import parse_fwi_config
    from adseismic.inversion.fwi import _simulator, inversion_bounds, prepare_fwi

    cfg = _config(physics, tmp_path)
    name = "q" if physics == "viscoacoustic" else "epsilon"
    cfg["inversion"]["bounds"] = {"vp": [1800, 2200], name: [10, 300] if name == "q" else [0.0, 0.5]}
    cfg["inversion"]["parameters"] = ["vp", name]
    fwi = parse_fwi_config(cfg, base_dir=tmp_path)
    prep = prepare_fwi(fwi)
    vmin, vmax = prep.bounds
    if physics == "vti":
        assert vmax == pytest.approx(2200 * np.sqrt(2.0), rel=1e-12) and vmin == pytest.approx(1800.0, rel=1e-12)
    else:
        assert vmax > 2200 * 1.05 and vmin < 1800  # Q 10: ~10% dispersion between the band's ends
        # every band's simulations pin the plan's relaxation mechanisms (the full wavelet's f_dom 6 Hz: 2-15 Hz)
        a, kw = prep.plan.attenuation, _simulator(fwi, prep, fwi.inversion, prep.bounds).kw
        assert (kw["q_band"], kw["f_ref"], kw["mechanisms"]) == (a.q_band, a.f_ref, 3) and a.q_band == pytest.approx((2.0, 15.0), rel=0.05)
    assert vmax * prep.plan.dt / prep.plan.dx <= prep.plan.cfl_limit
    del cfg["inversion"]["bounds"]  # defaults: vp +-25%, q [5, 1000] around Q 100, epsilon 0.05 -0.1 / +0.2
    got = inversion_bounds(parse_fwi_config(cfg, base_dir=tmp_path))
    assert got["vp"] == (1500.0, 2500.0)
    assert got[name] == ((5.0, 1000.0) if name == "q" else pytest.approx((-0.05, 0.25), abs=1e-12))


def test_a_band_outside_the_q_band_is_warned_about(tmp_path):
    # Q is flat over q_band only (the full wavelet's f_dom 6 Hz: 2-15 Hz): a band below it fits another attenuation
    from adseismic.config import parse_fwi_config
    from adseismic.inversion.fwi import prepare_fwi

    cfg = _config("viscoacoustic", tmp_path)
    cfg["inversion"]["bands"] = [1.5, 4.0, None]
    warned = [w for w in prepare_fwi(parse_fwi_config(cfg, base_dir=tmp_path)).plan.warnings if "q_band" in w]
    assert len(warned) == 1 and warned[0].startswith("inversion.bands[0]: ") and "lies outside model.q_band" in warned[0], warned


def test_config_and_model_space_agree_on_the_physics_quantities():
    # the config names them without importing the workflow; the two tables must not drift
    from adseismic.config import schema
    from adseismic.inversion.model_space import OWN_QUANTITIES

    assert set(schema.OWN_QUANTITIES) == set(OWN_QUANTITIES)
    assert all(schema.OWN_QUANTITIES[p] == PHYSICS_PARAMETERS[p] for p in OWN_QUANTITIES)
