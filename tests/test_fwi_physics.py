"""FWI for every physics: the model space (x -> m -> physical and its chain rule), the whole elastic objective's
Taylor test in float64 for vp-vs-rho and lambda-mu-rho, the network model, and the configs' refusals."""

from types import SimpleNamespace

import numpy as np
import pytest

from adseismic.config.fwi import InversionConfig
from adseismic.inversion.fwi import Simulator, make_objective
from adseismic.inversion.model_space import REFERENCE, ModelSpace
from adseismic.inversion.parameterization import MLP
from adseismic.solve.receivers import DasOperator, Recording
from adseismic.wavelets import ricker

SHAPE, DX, DT, NT = (24, 28), 10.0, 1.5e-3, 140


def _start():
    z = np.arange(SHAPE[0])[:, None] * np.ones(SHAPE)
    vp = 2000.0 + 10.0 * z
    return {"vp": vp, "vs": vp / 1.8, "rho": 2000.0 + 5.0 * z}


def _smooth_field(rng, shape=SHAPE):
    """A smooth random perturbation (a few sines), amplitude ~1."""
    z, x = np.meshgrid(*(np.linspace(0, 1, n) for n in shape), indexing="ij")
    return sum(rng.normal() * np.sin(np.pi * (k + 1) * z + rng.uniform(0, 6)) * np.cos(np.pi * (j + 1) * x) for k in range(2) for j in range(2))


@pytest.mark.parametrize("parameterization", ["vp-vs-rho", "lambda-mu-rho"])
def test_chain_rule_matches_finite_differences(parameterization):
    # J(physical) = sum(a vp^2 + b vs^3 + c rho vp vs), dJ/dphysical by hand; the model space's dJ/dm against
    # central differences of J(point(x)) in float64. Step 1e-6 in m (O(1) numbers): truncation ~1e-12 relative,
    # rounding ~1e-16 / 1e-6 = 1e-10 relative; target 1e-7.
    rng = np.random.default_rng(1)
    a, b, c = (rng.normal(size=SHAPE) for _ in range(3))
    names = ("vp", "vs", "rho") if parameterization == "vp-vs-rho" else ("lambda", "mu", "rho")
    space = ModelSpace("elastic", _start(), names, parameterization, {k: (0.0, 1e12) for k in names})

    def J(x):
        p = space.point(x).physical
        return float(np.sum(a * p["vp"] ** 2 + b * p["vs"] ** 3 + c * p["rho"] * p["vp"] * p["vs"]))

    x = space.x0()
    p = space.point(x).physical
    g = {"vp": 2 * a * p["vp"] + c * p["rho"] * p["vs"], "vs": 3 * b * p["vs"] ** 2 + c * p["rho"] * p["vp"], "rho": c * p["vp"] * p["vs"]}
    gx = space.x_gradient(x, space.cells_gradient(space.point(x), g))
    for _ in range(3):
        d = rng.normal(size=x.size)
        h = 1e-6
        fd = (J(x + h * d) - J(x - h * d)) / (2 * h)
        assert fd == pytest.approx(float(gx @ d), rel=1e-7)


def test_sigmoid_transform_chain_rule_bounds_and_start():
    # transform sigmoid: q = lo + (hi - lo) sigmoid(x). x0 gives back the start model; every x maps inside the bounds;
    # dJ/dx against central differences (float64, step 1e-6 in x: as above, target 1e-7).
    rng = np.random.default_rng(2)
    a = rng.normal(size=SHAPE)
    start = _start()
    bounds = {"vp": (1400.0, 5000.0)}
    space = ModelSpace("acoustic", {"vp": start["vp"]}, ("vp",), bounds=bounds, transform="sigmoid")
    assert space.x_bounds() is None
    x = space.x0()
    np.testing.assert_allclose(space.point(x).physical["vp"], start["vp"], rtol=1e-12)
    far = space.point(x + 50 * rng.normal(size=x.size)).physical["vp"]
    assert far.min() >= 1400.0 and far.max() <= 5000.0

    def J(x):
        return float(np.sum(a * space.point(x).physical["vp"] ** 2))

    gx = space.x_gradient(x, space.cells_gradient(space.point(x), {"vp": 2 * a * space.point(x).physical["vp"]}))
    for _ in range(3):
        d = rng.normal(size=x.size)
        h = 1e-6
        assert (J(x + h * d) - J(x - h * d)) / (2 * h) == pytest.approx(float(gx @ d), rel=1e-7)


def test_vs_clamp_keeps_lambda_nonnegative_with_its_exact_gradient():
    # vp-vs-rho boxes cannot say vs <= vp / sqrt(2): a vs pushed above it is clamped there, its gradient moved to vp
    start = _start()
    space = ModelSpace("elastic", start, ("vp", "vs"), "vp-vs-rho", {"vp": (1000.0, 4000.0), "vs": (500.0, 3000.0)})
    x = space.x0()
    n = int(np.prod(SHAPE))
    x[n:] = 2.5  # vs = 2500 m/s > vp / sqrt(2) everywhere
    pt = space.point(x)
    assert np.all(pt.physical["vs"] <= pt.physical["vp"] / np.sqrt(2)) and pt.vs_clamped.all()
    g = space.cells_gradient(pt, {"vp": np.zeros(SHAPE), "vs": np.ones(SHAPE), "rho": np.zeros(SHAPE)})
    assert np.all(g["vs"] == 0) and np.allclose(g["vp"], REFERENCE["vp"] * (1 - 1e-9) / np.sqrt(2))


def test_network_pullback_matches_finite_differences():
    # The MLP's chain rule is Warp's tape of the same kernel; central differences in float64 (step 1e-6 on O(1)
    # weights; relative truncation ~1e-11): target 1e-6.
    net = MLP(SHAPE, v0=2000.0, scale=300.0, hidden=6, seed=3)
    space = ModelSpace("acoustic", {"vp": np.full(SHAPE, 2000.0)}, ("vp",), bounds={"vp": (100.0, 1e5)}, network=net)
    rng = np.random.default_rng(2)
    w = rng.normal(size=SHAPE)

    def J(x):
        return float(np.sum(w * space.point(x).physical["vp"] ** 2))

    x = space.x0()
    gx = space.x_gradient(x, space.cells_gradient(space.point(x), {"vp": 2 * w * space.point(x).physical["vp"]}))
    for _ in range(3):
        d = rng.normal(size=x.size)
        fd = (J(x + 1e-6 * d) - J(x - 1e-6 * d)) / 2e-6
        assert fd == pytest.approx(float(gx @ d), rel=1e-6)


def _elastic_objective(parameterization, names, bounds, recording=None):
    """The whole FWI objective (inversion.fwi.make_objective: misfit of weighted data over two shot batches, vx and
    vz, normalised, with Tikhonov regularisation) on a tiny elastic scene in float64."""
    start = _start()
    true = {k: v.copy() for k, v in start.items()}
    bump = np.exp(-((np.arange(SHAPE[0])[:, None] - 12) ** 2 + (np.arange(SHAPE[1])[None, :] - 14) ** 2) / 18.0)
    true["vp"] += 150 * bump
    true["vs"] += 100 * bump
    true["rho"] += 80 * bump
    wavelet = ricker(18.0, NT, DT)
    n_shots = 2
    amp = np.broadcast_to(wavelet, (n_shots, 1, NT)).copy()
    src = np.array([[[30.0, 60.0]], [[30.0, 210.0]]])
    rec = np.broadcast_to(np.stack([np.full(12, 20.0), np.linspace(20.0, 250.0, 12)], -1), (n_shots, 12, 2)).copy()
    kw = {"order": 4, "pml_width": 8, "pml_velocity": 3000.0, "pml_frequency": 18.0, "device": "cpu", "precision": "float64"}
    recording = recording or Recording(("vx", "vz"))
    rec = np.broadcast_to(recording.locations(rec[0]), (n_shots, *recording.locations(rec[0]).shape)).copy()
    sim = Simulator("elastic", kw, recording, 12, "moment", np.broadcast_to([1.0, 1.0, 0.0], (n_shots, 1, 3)).copy())
    observed = sim.forward(true, DX, DT, amp, src, rec)
    space = ModelSpace("elastic", start, names, parameterization, bounds)
    inv = InversionConfig(tikhonov=1e-3)
    weights = np.ones((n_shots, 12, NT))
    plan = SimpleNamespace(dx=DX, dt=DT)
    batches = [slice(0, 1), slice(1, 2)]
    f = make_objective(space, sim, plan, amp, src, rec, observed, weights, batches, inv, np.ones(SHAPE), np.ones(SHAPE), {})
    return space, f


@pytest.mark.parametrize("parameterization,names,das", [("vp-vs-rho", ("vp", "vs", "rho"), False),
                                                        ("lambda-mu-rho", ("lambda", "mu", "rho"), False),
                                                        ("vp-vs-rho", ("vp", "vs"), True)])
def test_whole_elastic_objective_taylor(parameterization, names, das):
    # Taylor test of f(x + h d) - f(x) - h g.d = O(h^2) along a smooth direction d in every quantity at once, in
    # float64: the remainder must fall ~4x per halving of h (second order; measured 4.0000-4.0002 for both), and g.d must be the
    # first-order term (remainder << h |g.d|). A wrong chain rule, scaling or normalisation gives an O(h) remainder,
    # whose ratio is ~2.
    # das: vz at the points and DAS strain rate along x over a 20 m gauge (solve.receivers.Recording and its adjoint)
    recording = Recording(("vz",), DasOperator(20.0, (0.0, 1.0))) if das else None
    space, f = _elastic_objective(parameterization, names, {k: (0.0, 1e12) for k in names}, recording)
    rng = np.random.default_rng(0)
    x = space.x0()
    d = np.concatenate([_smooth_field(rng).ravel() * 0.05 for _ in names])
    f0, g0 = f(x)
    slope = float(g0 @ d)
    rem = []
    for h in (4e-4, 2e-4, 1e-4):
        rem.append(abs(f(x + h * d)[0] - f0 - h * slope))
    assert abs(slope) > 0
    ratios = [rem[i] / rem[i + 1] for i in range(2)]
    assert all(3.5 < r < 4.5 for r in ratios), (rem, ratios)
    assert rem[-1] < 0.1 * abs(1e-4 * slope)


# --------------------------------------------------------------------------- through the CLI

ELASTIC = {
    "physics": "elastic",
    "model": {"vp": {"kind": "constant", "shape": [21, 31], "spacing": 20.0, "velocity": 2000.0}, "vs": {"vp_ratio": 1.8},
              "rho": {"kind": "constant", "shape": [21, 31], "spacing": 20.0, "velocity": 2000.0}},
    "true_model": {"vp": {"kind": "gaussian_anomaly", "shape": [21, 31], "spacing": 20.0, "background": 2000.0, "perturbation": 200.0,
                          "center": [200.0, 300.0], "radius": 60.0},
                   "vs": {"kind": "gaussian_anomaly", "shape": [21, 31], "spacing": 20.0, "background": 2000.0 / 1.8,
                          "perturbation": -80.0, "center": [200.0, 300.0], "radius": 60.0},
                   "rho": {"kind": "constant", "shape": [21, 31], "spacing": 20.0, "velocity": 2000.0}},
    "geometry": {"sources": {"points": [{"x": 150, "z": 20}, {"x": 450, "z": 20}]},
                 "receivers": {"lines": [{"start": {"x": 0, "z": 10}, "end": {"x": 600, "z": 10}, "count": 16},
                                         {"start": {"x": 0, "z": 390}, "end": {"x": 600, "z": 390}, "count": 16}],
                               "components": ["vx", "vz"]}},
    "source": {"type": "explosive"},
    "wavelet": {"kind": "ricker", "peak_frequency": 5.0},
    "simulation": {"order": 4, "pml_width": 8, "accuracy": 0.03},
    "inversion": {"bands": [None], "iterations": 2, "parameters": ["vs"], "bounds": {"vs": [900, 1300]}},
}  # fmt: skip


def _run(tmp_path, cfg, name="c.yaml", extra=()):
    import yaml

    from adseismic.cli import main

    path = tmp_path / name
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "run"
    assert main(["fwi", str(path), "-o", str(out), "-q", *extra]) == 0
    return out


def test_elastic_fwi_cli_inverts_only_the_chosen_parameter(tmp_path):
    # vs alone: vp and rho leave model.h5 exactly as they started; every output names its parameter and unit
    import json

    import h5py

    from adseismic.inversion.fwi import read_history

    out = _run(tmp_path, ELASTIC)
    with h5py.File(out / "model.h5", "r") as f:
        assert list(f.attrs["inverted"]) == ["vs"] and f["vs"].attrs["units"] == "m/s" and f["rho"].attrs["units"] == "kg/m^3"
        assert np.array_equal(f["vp"][...], f["start_vp"][...]) and np.array_equal(f["rho"][...], f["start_rho"][...])
        assert np.abs(f["vs"][...] - f["start_vs"][...]).max() > 1.0  # m/s: vs moved
        assert f["vs"][...].min() >= 900 - 1e-9 and f["vs"][...].max() <= 1300 + 1e-9  # inside its bounds
    for png in ("model_vs.png", "gradient_vs.png", "residual.png", "misfit.png"):
        assert (out / png).exists(), png
    assert not (out / "model_vp.png").exists()
    rows = read_history(out / "history.h5")
    assert {"model_vp", "model_vs", "model_rho", "gradient_vs"} <= set(rows[-1]) and "gradient_vp" not in rows[-1]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["bands"][0]["misfit"] < 1.0  # the misfit, relative to its start, went down
    assert summary["errors"]["vs_final_anomaly"] < summary["errors"]["vs_start_anomaly"]
    # --resume replays the journal and the stored observed components (observed.h5: vx, vz) to the same model
    with h5py.File(out / "model.h5", "r") as f:
        first = f["vs"][...]
    _run(tmp_path, ELASTIC, extra=("--resume",))
    with h5py.File(out / "model.h5", "r") as f:
        assert np.array_equal(f["vs"][...], first)


def test_nn_model_fwi_cli_moves_the_network(tmp_path):
    # model: {kind: nn}: the start model is the constant v0 (output layer at 0); after two L-BFGS iterations over the
    # weights the velocity varies and the anomaly's error fell; history keeps the weights' gradient and the per-cell one
    import json

    import h5py

    from adseismic.inversion.fwi import read_history

    cfg = {"model": {"kind": "nn", "shape": [21, 31], "spacing": 20.0, "v0": 2000.0, "scale": 300.0, "hidden": 6, "seed": 1},
           "true_model": {"kind": "gaussian_anomaly", "shape": [21, 31], "spacing": 20.0, "background": 2000.0, "perturbation": 200.0,
                          "center": [200.0, 300.0], "radius": 80.0},
           "geometry": {"sources": {"points": [{"x": 150, "z": 20}, {"x": 450, "z": 20}]},
                        "receivers": {"lines": [{"start": {"x": 0, "z": 10}, "end": {"x": 600, "z": 10}, "count": 16},
                                                {"start": {"x": 0, "z": 390}, "end": {"x": 600, "z": 390}, "count": 16}]}},
           "wavelet": {"kind": "ricker", "peak_frequency": 6.0}, "simulation": {"order": 4, "pml_width": 8},
           "inversion": {"bands": [None], "iterations": 2, "bounds": [1600, 2500]}}  # fmt: skip
    out = _run(tmp_path, cfg)
    with h5py.File(out / "model.h5", "r") as f:
        assert np.all(f["start_model"][...] == 2000.0) and np.ptp(f["model"][...]) > 1.0
    rows = read_history(out / "history.h5")
    assert rows[-1]["gradient"].shape == (6 * 3 + 6 + 36 + 6 + 6 + 1,) and rows[-1]["gradient_vp"].shape == rows[-1]["model"].shape
    errors = json.loads((out / "summary.json").read_text())["errors"]
    assert errors["final_anomaly"] < errors["start_anomaly"]


@pytest.mark.slow
def test_elastic_demo_lowers_the_model_error(tmp_path):
    # configs/elastic_fwi.yaml through the CLI: the anomaly's relative model error (root mean square over vp and vs)
    # must fall by at least 2x (measured 0.040 -> 0.012, 3.4x; vp 0.044 -> 0.015, vs 0.037 -> 0.007)
    import json
    from pathlib import Path

    from adseismic.cli import main

    demo = Path(__file__).parents[1] / "configs" / "elastic_fwi.yaml"
    assert main(["fwi", str(demo), "-o", str(tmp_path / "run"), "-q"]) == 0
    e = json.loads((tmp_path / "run" / "summary.json").read_text())["errors"]
    assert e["final_anomaly"] < 0.5 * e["start_anomaly"], e
    assert e["vs_final_anomaly"] < 0.5 * e["vs_start_anomaly"] and e["vp_final_anomaly"] < e["vp_start_anomaly"], e


def test_bounds_forms_and_defaults():
    # acoustic [v_min, v_max] and {vp: [...]} mean the same; elastic defaults are the start range +-25% per quantity
    import copy

    from adseismic.config import parse_fwi_config
    from adseismic.inversion.fwi import inversion_bounds

    from .test_fwi import TINY

    a = copy.deepcopy(TINY)
    b = copy.deepcopy(TINY)
    b["inversion"]["bounds"] = {"vp": [1700, 2400]}
    assert inversion_bounds(parse_fwi_config(a)) == inversion_bounds(parse_fwi_config(b)) == {"vp": (1700.0, 2400.0)}
    e = copy.deepcopy(ELASTIC)
    e["inversion"] = {"parameterization": "lambda-mu-rho", "parameters": ["mu", "rho"], "bounds": {"rho": [1500, 2600]}}
    mu = 2000.0 * (2000.0 / 1.8) ** 2  # Pa
    got = inversion_bounds(parse_fwi_config(e))
    assert got["rho"] == (1500.0, 2600.0) and got["mu"] == pytest.approx((0.75 * mu, 1.25 * mu), rel=1e-12)


@pytest.mark.slow
def test_nn_demo_lowers_the_model_error(tmp_path):
    # configs/nn_fwi.yaml through the CLI: the network's anomaly error must fall by at least 30% (measured 0.044 ->
    # 0.024, 45%; docs/nn_fwi.md compares it with pixel FWI)
    import json
    from pathlib import Path

    from adseismic.cli import main

    demo = Path(__file__).parents[1] / "configs" / "nn_fwi.yaml"
    assert main(["fwi", str(demo), "-o", str(tmp_path / "run"), "-q"]) == 0
    e = json.loads((tmp_path / "run" / "summary.json").read_text())["errors"]
    assert e["final_anomaly"] < 0.7 * e["start_anomaly"], e


def test_elastic_fwi_cli_with_das_and_a_free_surface(tmp_path):
    # DAS strain rate along x (20 m gauges) and vz at buried receivers, free surface on: observed.h5 holds each
    # channel with its unit and one L-BFGS iteration lowers the misfit
    import copy
    import json

    import h5py

    cfg = copy.deepcopy(ELASTIC)
    cfg["geometry"]["receivers"] = {"line": {"start": {"x": 40, "z": 40}, "end": {"x": 560, "z": 40}, "count": 14},
                                    "components": ["vz"], "das": {"gauge_length": 20.0, "direction": [0, 1]}}
    cfg["simulation"].update(free_surface=True, dx=20.0)  # (pinned: the Rayleigh wave's 20 points per wavelength is a 4 m grid)
    cfg["inversion"] = {"bands": [None], "iterations": 1, "parameters": ["vp", "vs"]}
    out = _run(tmp_path, cfg)
    with h5py.File(out / "observed.h5", "r") as f:
        assert sorted(f) == ["das", "vz"] and f["das"].attrs["units"] == "1/s" and f["das"].shape[:2] == (2, 14)
    assert json.loads((out / "summary.json").read_text())["bands"][0]["misfit"] < 1.0


def test_config_and_model_space_agree_on_the_parameterisations():
    # the config names them without importing the workflow (tests/test_config.py); the two tables must not drift
    from adseismic.config import schema
    from adseismic.inversion.model_space import PARAMETERIZATIONS, REFERENCE, UNITS

    assert schema.PARAMETERIZATION_QUANTITIES == PARAMETERIZATIONS
    assert set(schema.INVERTED_QUANTITIES) == set(REFERENCE) == set(UNITS) and schema._BOUND_UNITS == UNITS
