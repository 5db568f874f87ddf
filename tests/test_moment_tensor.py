"""Moment-tensor source inversion in elastic physics (issue 23, item 2): the tensor algebra and nodal planes against
ObsPy, the elastic locator's adjoint gradient against its forward Jacobian, a small noise-free joint inversion (CI),
and (slow) the acceptance on the synthetic events of adseismic.data_synthetic.moment_tensor and the demo config."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from adseismic.data.model import Model
from adseismic.data.models import ElasticModel
from adseismic.location import moment_tensor as mt
from adseismic.location.locate import _problem, _simulation_kw, locate, source_wavelet


def _angle(a, b):
    """Smallest difference of two angles (degrees)."""
    return abs((a - b + 180.0) % 360.0 - 180.0)


def _normalised(m):
    """In-plane (Mxx, Mzz, Mxz) divided by its Frobenius norm sqrt(Mxx^2 + Mzz^2 + 2 Mxz^2)."""
    m = np.asarray(m, float)
    return m / np.sqrt(m[0] ** 2 + m[1] ** 2 + 2 * m[2] ** 2)


def _planes(m, constraint, azimuth=90.0):
    """Both nodal planes [{strike, dip, rake}, ...] of the in-plane tensor m under `constraint`."""
    return [dict(zip(("strike", "dip", "rake"), p)) for p in mt.nodal_planes(mt.to_ned(mt.tensor_local(m, constraint), azimuth))]


def _planes_close(est, true, tol):
    """Every true nodal plane has an estimated one within tol degrees in strike, dip and rake."""
    return all(any(all(_angle(e[k], t[k]) <= tol for k in ("strike", "dip", "rake")) for e in est) for t in true)


# ----------------------------------------------------------------------------- tensor algebra (no simulation)


@pytest.mark.parametrize("azimuth", [90.0, 30.0, 200.0])
@pytest.mark.parametrize("dip", [20.0, 35.0, 70.0])
@pytest.mark.parametrize("m0", [1.0, -2.5])
def test_in_plane_double_couple_planes_strike_along_the_section_normal(azimuth, dip, m0):
    """A 2D double couple has nodal planes striking along the section's normal (azimuth +- 90), dips d and 90 - d,
    rake +90 (reverse, m0 > 0) or -90 (normal), as ObsPy's mt2plane/aux_plane derive them from the USE tensor."""
    from obspy.imaging.beachball import MomentTensor, aux_plane, mt2plane

    m = mt.in_plane_double_couple(m0, dip)
    ned = mt.to_ned(mt.tensor_local(m, "double_couple"), azimuth)
    planes = [dict(zip(("strike", "dip", "rake"), p)) for p in mt.nodal_planes(ned)]
    use = mt.ned_to_use(ned)
    p1 = mt2plane(MomentTensor([use[k] for k in mt.COMPONENTS_USE], 0))
    p2 = aux_plane(p1.strike, p1.dip, p1.rake)
    obspy_planes = [{"strike": p1.strike, "dip": p1.dip, "rake": p1.rake}, dict(zip(("strike", "dip", "rake"), p2))]
    assert _planes_close(planes, obspy_planes, 1e-6)
    assert sorted(round(p["dip"], 9) for p in planes) == sorted([round(dip, 9), round(90 - dip, 9)])
    for p in planes:
        assert min(_angle(p["strike"], azimuth + 90), _angle(p["strike"], azimuth - 90)) < 1e-9
        assert _angle(p["rake"], 90.0 if m0 > 0 else -90.0) < 1e-9
    m0_back, dip_back = mt.double_couple_dip(m)
    assert math.isclose(abs(m0_back), abs(m0)) and min(abs(dip_back - dip), abs(dip_back - (90 - dip))) < 1e-9
    assert math.isclose(mt.scalar_moment(mt.tensor_local(m, "double_couple")), abs(m0))


def test_constraints_fill_the_unseen_components():
    """deviatoric: Myy = -(Mxx + Mzz) (trace 0); none: Myy reported unresolved; double couple: trace-free in-plane basis."""
    m = np.array([0.7, -0.3, 0.5])
    assert np.trace(mt.tensor_local(m, "deviatoric")) == pytest.approx(0.0, abs=1e-15)
    d = mt.describe(m, np.eye(3) * 1e-4, "none", 90.0)
    assert d["local_xyz"]["Myy"] is None and d["unresolved"] == ["Myy", "Mxy", "Myz"]
    d = mt.describe(m, np.eye(3) * 1e-4, "deviatoric", 90.0)
    assert d["local_xyz"]["Myy"] == pytest.approx(-0.4) and d["local_xyz_error_1sigma"]["Myy"] == pytest.approx(np.sqrt(2e-4))
    assert d["unresolved"] == ["Mxy", "Myz"]
    a = np.array([0.3, -1.2])
    assert np.sum((a @ mt.BASIS["double_couple"])[:2]) == 0.0  # Mxx + Mzz = 0


def test_rows_adjoint_is_exact():
    """The elastic problem's trace selection (with pressure averaged onto the velocity sample times) and its
    adjoint pass the dot test: <R x, y> = <x, R^T y>."""
    from adseismic.location.locate import _ElasticProblem

    prob = _ElasticProblem.__new__(_ElasticProblem)
    prob.components = ["vz", "vx", "pressure", "vz"]
    rng = np.random.default_rng(0)
    x = {c: rng.standard_normal((1, 4, 30)) for c in ("vx", "vz", "pressure")}
    y = rng.standard_normal((4, 30))
    lhs = float(np.sum(prob._rows(x)[0] * y))
    adj = prob._rows_adjoint(y)
    rhs = sum(float(np.sum(x[c] * adj[c])) for c in x)
    assert lhs == pytest.approx(rhs, rel=1e-13)


# ----------------------------------------------------------------------------- small elastic scenes


def _scene(dx=25.0, shape=(21, 33)):
    def m(v):
        return Model(np.full(shape, v), dx)

    model = ElasticModel(m(3000.0), m(1730.0), m(2500.0))
    sta = np.array([[12.5, x] for x in np.linspace(75.0, (shape[1] - 1) * dx - 75.0, 6)])
    return model, np.concatenate([sta, sta]), ["vz"] * 6 + ["vx"] * 6


def _observe(model, rec, comps, pos, m, T, f, nt, dt, order=4, factor=1):
    """Noise-free traces (n_traces, nt) at t = k dt of a moment tensor m at pos, simulated on a grid `factor` times
    finer at dt / factor, velocities moved from (k - 1/2) dt to k dt."""
    from adseismic.solve.elastic import forward_elastic

    h, dtf, ntf = model.spacing[0] / factor, dt / factor, nt * factor + 1
    shape = [(n - 1) * factor + 1 for n in model.shape]
    mats = [np.full(shape, float(getattr(model, k).values[0, 0])) for k in ("vp", "vs", "rho")]
    s, _ = source_wavelet(ntf, dtf, T, f, 1.0)
    r = forward_elastic(*mats, h, dtf, s[None, None], np.asarray(pos, float)[None, None], rec[None], source_type="moment",
                        source_components=np.asarray(m, float)[None, None], order=order, precision="float64", pml_frequency=f)  # fmt: skip
    tf, t = (np.arange(ntf) - 0.5) * dtf, np.arange(nt) * dt
    return np.stack([np.interp(t, tf, getattr(r, c)[0, i]) for i, c in enumerate(comps)])


def test_adjoint_gradient_matches_the_jacobian():
    """The L-BFGS path's misfit gradient (adjoint state, exact) equals J^T W r from the Gauss-Newton path's Jacobian
    (central differences in position, exact in T, f and the tensor): two independent derivations. Tolerance 1e-4
    relative: the position columns are central differences with h = 0.05 dx (error O(h^2) ~ 1e-5 here)."""
    model, rec, comps = _scene()
    nt, dt, f = 150, 0.004, 6.0
    obs = _observe(model, rec, comps, (260.0, 410.0), (0.6, -0.4, 0.5), 0.2, f, nt, dt)
    prob = _problem(model, rec, comps, "none", nt, dt, _simulation_kw(model.vp, f, 4, None, False, "cpu", "float64"))
    p = np.array([270.0, 400.0, 0.205, 5.5, 0.5, -0.3, 0.6])
    sigma = np.full(len(rec), 0.05)
    w2 = 1.0 / sigma[:, None] ** 2
    loss, grad = prob.loss_gradient(p, obs, w2)
    r = prob.simulate(p) - obs
    assert loss == pytest.approx(0.5 * float(np.sum(w2 * r * r)), rel=1e-9)
    jt_r = np.einsum("ptn,tn->p", prob.jacobian(p), w2 * r)
    np.testing.assert_allclose(grad, jt_r, rtol=1e-4, atol=1e-4 * np.abs(jt_r).max())


@pytest.mark.parametrize("method", ["gauss-newton", pytest.param("lbfgs", marks=pytest.mark.slow)])
def test_joint_inversion_noise_free_small(method):
    """CI-sized joint inversion (position, origin time, peak frequency, in-plane tensor) from a start one cell off:
    data simulated at order 8 on the same coarse grid (the acceptance test below uses a finer grid). Position within
    0.1 cell, origin time within 1 ms, normalised components within 1% (order 4 vs 8 on 8 points per S wavelength)."""
    model, rec, comps = _scene()
    nt, dt, f, T = 150, 0.004, 6.0, 0.2
    pos, m = np.array([260.0, 410.0]), np.array([0.6, -0.4, 0.5])
    obs = _observe(model, rec, comps, pos, m, T, f, nt, dt, order=8)
    res = locate(model, rec, obs, dt, components=comps, constraint="none", noise_std=np.full(len(rec), 0.01 * np.abs(obs).max()),
                 start={"position": pos + [20.0, -15.0], "origin_time": T + 0.008}, peak_frequency=5.5, method=method,
                 max_iterations=30)  # fmt: skip
    assert np.linalg.norm(res.position - pos) < 0.1 * 25.0, res.position
    assert abs(res.origin_time - T) < 1e-3
    np.testing.assert_allclose(_normalised(res.moment_tensor), _normalised(m), atol=0.01)
    assert res.moment_tensor_covariance.shape == (3, 3) and np.all(np.diag(res.moment_tensor_covariance) > 0)


@pytest.mark.slow
def test_free_source_time_function_elastic():
    """stf: free with a moment tensor (the tensor held at the Ricker fit's): the recovered STF is the Ricker
    (correlation > 0.99), the origin time (its peak) within a quarter sample, the position within 0.1 cell. A moment
    source injects -(s[k+1] - s[k]), so the impulse response comes from a spike at sample 1 (a spike at 0 gave an STF
    uncorrelated with the truth and a 30 ms origin-time error)."""
    model, rec, comps = _scene()
    nt, dt, f, T = 150, 0.004, 6.0, 0.2
    pos, m = np.array([260.0, 410.0]), np.array([0.6, -0.4, 0.5])
    obs = _observe(model, rec, comps, pos, m, T, f, nt, dt, order=8)
    res = locate(model, rec, obs, dt, components=comps, constraint="none", noise_std=np.full(len(rec), 0.01 * np.abs(obs).max()),
                 start={"position": pos + [20.0, -15.0], "origin_time": T + 0.008}, peak_frequency=5.5, method="gauss-newton",
                 max_iterations=30, stf="free")  # fmt: skip
    r, _ = source_wavelet(nt, dt, T - dt / 2, f, 1.0)  # the solver's input: advanced by the half-sample time_offset
    assert res.stf_kind == "free" and np.corrcoef(res.stf, r)[0, 1] > 0.99
    assert abs(res.origin_time - T) < dt / 4
    assert np.linalg.norm(res.position - pos) < 0.1 * 25.0


# ----------------------------------------------------------------------------- acceptance (slow)


def _locate_event(event, noise=0.0, seed=1, method="gauss-newton"):
    """Locate EVENTS[event] of the synthetic module on the demo's 20 m grid (its data: 10 m, order 8)."""
    from adseismic.data_synthetic import moment_tensor as syn
    from adseismic.location.locate import back_projection, phase_models

    ev = syn.EVENTS[event]
    dt = 0.0025  # s: the solver's step (Courant 0.4 at 20 m for vp 3200 m/s, order 4)
    vz, vx = syn.simulate(event, dt=dt, noise=noise, seed=seed, noise_free=noise == 0)
    obs = np.concatenate([vz, vx])
    sta = syn.stations()
    rec, comps = np.concatenate([sta, sta]), ["vz"] * len(sta) + ["vx"] * len(sta)
    model = syn.model(syn.MODEL["spacing"])
    peak = np.abs(obs).max(axis=1)
    sigma = noise * peak if noise > 0 else np.full(len(obs), 0.01 * peak.max())
    bounds = [(60.0, 660.0), (100.0, 1100.0)]
    start = back_projection(phase_models(model), rec, obs, dt, bounds, 20.0)[0]
    res = locate(model, rec, obs, dt, components=comps, constraint=ev["constraint"], noise_std=sigma, bounds=bounds,
                 start={"position": start["position"], "origin_time": start["origin_time"]}, peak_frequency=ev["peak_frequency"],
                 method=method, max_iterations=25, order=4, pml_width=20)  # fmt: skip
    m_true = syn.dc_tensor() if ev["moment_tensor"] is None else np.asarray(ev["moment_tensor"])
    return res, ev, m_true


@pytest.mark.slow
@pytest.mark.parametrize("event", ["dc", "general"])
def test_acceptance_noise_free(event):
    """Issue 23's acceptance on the synthetic events (data on a grid twice as fine, no inverse crime): position within
    0.5 cell (10 m), normalised moment-tensor components within 5%, strike/dip/rake of both nodal planes within 5 deg."""
    res, ev, m_true = _locate_event(event)
    assert np.linalg.norm(res.position - ev["position"]) <= 0.5 * 20.0, res.position
    np.testing.assert_allclose(_normalised(res.moment_tensor), _normalised(m_true), atol=0.05)
    est, true = _planes(res.moment_tensor, ev["constraint"]), _planes(m_true, ev["constraint"])
    assert _planes_close(est, true, 5.0), (est, true)


@pytest.mark.slow
def test_demo_config_end_to_end(tmp_path, capsys):
    """adseismic locate configs/locate_mt_demo.yaml: exit 0; QuakeML with the origin and a FocalMechanism whose nodal
    planes are the event's (reverse fault dipping 35 degrees, strike along the section normal) within 5 degrees;
    the beachball, the two-component trace fit and summary.json with the unresolved components marked."""
    from adseismic.cli import main
    from adseismic.data_synthetic import moment_tensor as syn
    from adseismic.location.quakeml import read_quakeml_focal_mechanism, read_quakeml_origin

    out = tmp_path / "out"
    assert main(["locate", "configs/locate_mt_demo.yaml", "-o", str(out), "-q", "--misfit-map", "5"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["truth_position_error_m"] <= 10.0
    assert s["moment_tensor"]["unresolved"] == ["Mxy", "Myz"] and s["moment_tensor"]["local_xyz"]["Mxy"] is None
    fm = read_quakeml_focal_mechanism(out / "event.xml")
    true = _planes(syn.dc_tensor(), "double_couple")
    assert _planes_close(fm["nodal_planes"], true, 5.0), (fm["nodal_planes"], true)
    assert "unresolved components (carried as 0): Mxy, Myz" in fm["comment"]
    assert read_quakeml_origin(out / "event.xml")["depth"] == pytest.approx(syn.EVENTS["dc"]["position"][0], abs=10.0)
    for name in ("beachball.png", "traces.png", "location.png", "location.h5"):
        assert (out / name).stat().st_size > 1000


# ----------------------------------------------------------------------------- QuakeML and config (no simulation)


def test_quakeml_focal_mechanism_round_trip(tmp_path):
    """write_quakeml with a focal mechanism: the Tensor (USE), its errors, the scalar moment, both nodal planes and the
    comment naming the unresolved components read back as written (QuakeML keeps ~7 significant digits)."""
    from adseismic.data.geometry import Reference
    from adseismic.location.quakeml import read_quakeml_focal_mechanism, write_quakeml

    m = mt.in_plane_double_couple(2.0e12, 35.0)
    d = mt.describe(m, np.diag([1e20, 1e20, 4e20]), "double_couple", 90.0)
    write_quakeml(tmp_path / "e.xml", position=np.array([450.0, 560.0]), origin_time="2026-11-22T08:15:00.5",
                  covariance=np.diag([4.0, 1.0, 1e-6]), reference=Reference(46.0, 7.0, 0.0, 90.0), ndim=2, focal_mechanism=d)  # fmt: skip
    fm = read_quakeml_focal_mechanism(tmp_path / "e.xml")
    for k, v in d["use"].items():
        assert fm["use"][k] == pytest.approx(v, rel=1e-6, abs=1e-6 * 2e12)
    assert fm["use_error_1sigma"]["m_rp"] == pytest.approx(2e10, rel=1e-6)
    assert fm["scalar_moment"] == pytest.approx(2.0e12, rel=1e-6)
    assert _planes_close(fm["nodal_planes"], d["nodal_planes"], 1e-4)
    assert "unresolved components (carried as 0): Mxy, Myz" in fm["comment"]


def test_locate_config_physics_and_mechanism():
    """The demo config parses to physics elastic with an ElasticModel and the double-couple constraint; an acoustic
    config keeps its pressure source and no constraint."""
    from adseismic.config import load_locate_config

    c = load_locate_config("configs/locate_mt_demo.yaml")
    assert c.physics == "elastic" and isinstance(c.model, ElasticModel)
    assert (c.source["type"], c.source["constraint"]) == ("moment", "double_couple")
    a = load_locate_config("configs/locate_demo.yaml")
    assert a.physics == "acoustic" and (a.source["type"], a.source["constraint"]) == ("pressure", None)


def test_trace_components_need_z_and_x():
    """Channel codes map to components (Z up = -vz, X = vx); a station without X is refused by name."""
    from adseismic.location.run import trace_components

    comps, signs = trace_components(["AD.M00..HHZ", "AD.M00..HHX"])
    assert comps == ["vz", "vx"] and signs.tolist() == [-1.0, 1.0]
    with pytest.raises(ValueError, match=r"station AD.M01. lacks its X component"):
        trace_components(["AD.M00..HHZ", "AD.M00..HHX", "AD.M01..HHZ"])
    with pytest.raises(ValueError, match=r"orientation code 'N'"):
        trace_components(["AD.M00..HHZ", "AD.M00..HHN"])


def test_config_constraints_match_the_locator():
    """The schema's copy of the constraint names (a config imports no workflow) equals the locator's."""
    from adseismic.config import schema

    assert schema.MT_CONSTRAINTS == mt.CONSTRAINTS == tuple(mt.BASIS)


def test_trace_fit_figure_has_one_column_per_component(tmp_path):
    """plot_station_traces with components draws one panel per component (vz, vx): a 2 x 5 inch wide PNG at 100 dpi;
    the beachball PNG of a tensor is written through ObsPy."""
    import matplotlib.image

    from adseismic.plotting import plot_station_traces

    rng = np.random.default_rng(0)
    obs = rng.standard_normal((6, 50))
    names = [f"AD.M{i:02d}..HH{c}" for c in "ZX" for i in range(3)]
    plot_station_traces(tmp_path / "t.png", obs, obs, 0.01, names, components=["vz"] * 3 + ["vx"] * 3)
    assert matplotlib.image.imread(tmp_path / "t.png").shape[1] == 1000
    mt.plot_beachball(tmp_path / "b.png", mt.to_ned(mt.tensor_local(mt.in_plane_double_couple(1.0, 35.0), "double_couple"), 90.0))
    assert (tmp_path / "b.png").stat().st_size > 5000
