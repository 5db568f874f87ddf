"""Adjoint tests of every physics, written once (as Devito runs one adjoint test over all its seismic examples).

For each physics (CASES: acoustic 2D and 3D, elastic 2D with a point force, elastic 2D with a free surface and a
moment-tensor source, vti 2D with a free surface, viscoacoustic 2D, acoustic_vd 2D with a free surface and 3D,
elastic 3D with a point force and with a free surface and a moment-tensor source), in float64 on the test device:

- test_adjoint_dot_product: <J dm, dd> = <dm, J^T dd>, J the derivative of the receiver data along a perturbation
  (acoustic: the Born modelling for the velocity; data linear in the source wavelet and components: the forward
  run; elastic vp, vs, rho: central finite differences of the forward run), J^T dd the gradient of <d(m), dd>;
- test_taylor: |L(m + h dm) - L(m)| falls as h and |L(m + h dm) - L(m) - h <g, dm>| as h^2 over h = 1e-1..1e-4,
  L = 1/2 ||d(m) - d_obs||^2 (the "l2" misfit), for every parameter of the gradient, g through the checkpointed
  sweep, L(m + h dm) from the forward run (on the CPU bit for bit the sweep's loss);
- test_checkpointed_equals_all_steps_and_warp: the checkpointed gradient (several segments) equals the gradient with
  every step kept (one segment) and Warp's generated adjoints (adjoint="warp") to float64 rounding;
- test_named_misfit_loss_is_the_host_misfit_of_the_synthetics: for every name in misfits.MISFITS the gradient's loss
  is misfits.misfit's value of the synthetics it returns (the elastic "l2" is formed on the device).

A physics is an adapter (Case): its model and source parameters at the point m, geometry and misfits, and a few
callables; the tests read nothing else. The CPML reference speed and frequency are pinned so that the PML does not
move when the model is perturbed (the gradient treats it as fixed). Other gradient tests (other misfits,
parameterisations, float32, orders 2 and 8, the GPU's kernels) stay in test_gradient.py and test_elastic.py.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

import adseismic.solve.acoustic as A
import adseismic.solve.acoustic_vd as AVD
import adseismic.solve.elastic as E
import adseismic.solve.elastic3d as E3
import adseismic.solve.viscoacoustic as Q
import adseismic.solve.vti as V
from adseismic.accel import graphs
from adseismic.solve import sweep
from adseismic.solve.misfits import MISFITS
from adseismic.solve.misfits import misfit as named_misfit
from adseismic.wavelets import ricker

from .conftest import DEVICE
from .problems import P_SCALE, elastic_problem

DX, DT = 10.0, 1e-3
STEPS = np.array([1e-1, 1e-2, 1e-3, 1e-4])  # three decades


@dataclass
class Case:
    """One physics for the adjoint tests.

    params: parameter name -> array at the model point m (models and source parameters), the keyword arguments of
    the callables' `changes`; kinds: the parameters the gradients are taken for (wrt), each perturbed by the Taylor
    test; dot_kinds: those the dot-product test perturbs; nt: time steps.
    gradient(misfit, wrt, segment_length=None, adjoint="hand", **changes) -> result with .loss, .n_segments and an
    attribute per kind (misfit: l2 below, or what projection returns);
    l2: the misfit 1/2 ||d(m) - d_obs||^2 as gradient takes it; loss(**changes): its value from the forward run;
    random_data(rng) -> dd, data of the receivers' shape; projection(dd): the misfit <d(m), dd> (its gradient is
    J^T dd); inner(a, b): <a, b> of two data;
    tangent(kind, rng) -> (dm, J dm, relative tolerance of the dot-product test, with its justification there);
    direction(kind, rng) -> a random direction (unscaled) of the kind's shape; sizes: kind -> the Taylor test's
    perturbation size (the parameter's units); host_misfit(name, synthetic) -> misfits.misfit(name)'s value of the
    synthetic data against the observed data that gradient passes with a named misfit (elastic: summed over vx, vz,
    pressure, in their units).
    """

    params: dict
    kinds: tuple
    dot_kinds: tuple
    nt: int
    gradient: Callable
    l2: object
    loss: Callable
    random_data: Callable
    projection: Callable
    inner: Callable
    tangent: Callable
    direction: Callable
    sizes: dict
    host_misfit: Callable


# --- acoustic -------------------------------------------------------------------------------------------------

ACOUSTIC_KW = dict(precision="float64", pml_velocity=2600.0, pml_frequency=15.0, device=DEVICE)


def acoustic_case(ndim: int) -> Case:
    rng = np.random.default_rng(0)
    if ndim == 2:  # test_gradient.problem()
        nt, pml = 250, 8
        v = gaussian_filter(2000 + 400 * rng.random((30, 40)), 2)
        v_true = v.copy()
        v_true[12:18, 15:25] += 120.0
        s = ricker(15.0, nt, DT)[None, None]
        src = np.array([[[55.3, 101.7]]])
        rec = np.array([[[20.0, x] for x in np.linspace(10.0, 380.0, 8)]])
        s_true = ricker(15.0, nt, DT, delay=0.104)[None, None]
        location_direction = np.array([[[3.0, -2.0]]])
    else:  # a two-layer cube, source and receivers off the grid's planes (test_gradient's former 3D Taylor test)
        nt, pml = 120, 6
        v = np.full((14, 14, 14), 2000.0)
        v[7:] = 2300.0
        v_true = v * 1.02
        s = s_true = ricker(20.0, nt, DT)[None, None]
        src = np.array([[[40.0, 61.0, 62.5]]])
        rec = np.array([[[20.0, 20.0, 110.0], [30.0, 110.0, 30.0], [100.0, 70.0, 70.0]]])
        location_direction = np.array([[[2.0, -1.0, 1.5]]])
    kw = dict(ACOUSTIC_KW, pml_width=pml)
    obs = A.forward(v_true, DX, DT, s_true, src, rec, **kw).receiver_amplitudes
    params = dict(velocity=v, source_amplitudes=s, source_locations=src)

    def args(changes):
        a = dict(params, **changes)
        return a["velocity"], DX, DT, a["source_amplitudes"], a["source_locations"], rec

    def gradient(misfit, wrt, segment_length=None, adjoint="hand", **changes):
        return A.gradient(*args(changes), obs, misfit=misfit, wrt=wrt, segment_length=segment_length, adjoint=adjoint, **kw)

    def tangent(kind, rng):
        if kind == "velocity":
            # The Born operator (tangent-linear model, propagated explicitly) is J, the reverse sweep seeded with
            # dd is J^T. Measured mismatch: 5e-15 (2D), 2e-14 (3D).
            dv = direction(kind, rng)
            dv *= 40.0 / np.abs(dv).max()
            return dv, A.born(v, dv, DX, DT, s, src, rec, **kw), 1e-10
        # the data are linear in the source wavelet: the forward run is J, exact to rounding (target 1e-10, as the
        # elastic source's; measured 6e-15 (2D), 3e-15 (3D))
        ds = rng.standard_normal(s.shape)
        return ds, A.forward(*args({kind: ds}), **kw).receiver_amplitudes, 1e-10

    def direction(kind, rng):
        if kind == "velocity":
            return gaussian_filter(rng.standard_normal(v.shape), 2)
        if kind == "source_amplitudes":
            return gaussian_filter(rng.standard_normal(s.shape), (0, 0, 3))
        return location_direction.copy()

    def loss(**changes):  # misfit "l2": 1/2 sum (d - o)^2 dt
        r = (A.forward(*args(changes), **kw).receiver_amplitudes - obs).ravel()
        return 0.5 * float(r @ r) * DT

    return Case(params=params, kinds=A.WRT, dot_kinds=("velocity", "source_amplitudes"), nt=nt, gradient=gradient,
                l2="l2", loss=loss,
                random_data=lambda rng: rng.standard_normal(obs.shape),
                projection=lambda dd: lambda syn: (float(np.sum(syn * dd)), dd),
                inner=lambda a, b: float(np.sum(a * b)), tangent=tangent, direction=direction,
                sizes=dict(velocity=40.0, source_amplitudes=0.05, source_locations=3.0),
                host_misfit=lambda name, syn: named_misfit(name, syn, obs, DT)[0])  # fmt: skip


# --- elastic --------------------------------------------------------------------------------------------------



def elastic_case(free_surface: bool, source_type: str) -> Case:
    params, rec, o, kw = elastic_problem(free_surface, source_type)
    obs = {"vx": o.vx, "vz": o.vz, "pressure": o.pressure * P_SCALE}
    named_obs = {"vx": o.vx, "vz": o.vz, "pressure": o.pressure}  # for the named misfits: the components in their units

    def args(changes):
        a = dict(params, **changes)
        return (a["vp"], a["vs"], a["rho"], DX, DT, a["source_amplitudes"], a["source_locations"], rec), a["source_components"]

    def gradient(misfit, wrt, segment_length=None, adjoint="hand", **changes):
        a, components = args(changes)
        return E.gradient_elastic(*a, named_obs, misfit=misfit, wrt=wrt, source_components=components, segment_length=segment_length,
                                  adjoint=adjoint, **kw)  # fmt: skip

    def data(**changes):
        a, components = args(changes)
        r = E.forward_elastic(*a, source_components=components, **kw)
        return {"vx": r.vx, "vz": r.vz, "pressure": r.pressure}

    def l2(syn):
        total, adj = 0.0, {}
        for c in E.COMPONENTS:
            scale = P_SCALE if c == "pressure" else 1.0
            r = syn[c] * scale - obs[c]
            total += 0.5 * float(np.sum(r * r))
            adj[c] = r * scale
        return total, adj

    def inner(a, b):
        return float(sum(np.sum(a[c] * b[c]) for c in E.COMPONENTS))

    def tangent(kind, rng):
        # The data are linear in the source wavelet and in the source components, so the forward run is the
        # exact linear operator J: <J ds, d> = <ds, J^T d> to rounding (target 1e-10 in float64). For vp, vs,
        # rho the adjoint is checked against central finite differences of the forward run along a smooth dm of
        # 1e-4 relative size: the mismatch is the O(h^2) truncation (measured to fall as h^2 from 5e-5 at 1e-2
        # to 1e-10 at 1e-5; at 1e-4: 7e-10 .. 1.5e-7). Target 1e-6; the exact (linear) checks measure
        # 1e-16 .. 1e-14.
        if kind in ("source_amplitudes", "source_components"):
            ds = rng.standard_normal(params[kind].shape)
            return ds, data(**{kind: ds}), 1e-10
        dm = gaussian_filter(rng.standard_normal(params[kind].shape), 2)
        dm *= 1e-4 * params[kind].mean() / np.abs(dm).max()
        plus, minus = data(**{kind: params[kind] + dm}), data(**{kind: params[kind] - dm})
        return dm, {c: (plus[c] - minus[c]) / 2.0 for c in E.COMPONENTS}, 1e-6

    def direction(kind, rng):
        d = rng.standard_normal(params[kind].shape)
        return gaussian_filter(d, 2) if kind in ("vp", "vs", "rho") else d

    return Case(params=params, kinds=E.WRT, nt=params["source_amplitudes"].shape[2], gradient=gradient, l2=l2, loss=lambda **changes: l2(data(**changes))[0],
                dot_kinds=("source_amplitudes", "source_components", "vp", "vs", "rho"),
                random_data=lambda rng: {c: rng.standard_normal(obs[c].shape) for c in E.COMPONENTS},
                projection=lambda dd: lambda syn: (inner(syn, dd), dd), inner=inner, tangent=tangent, direction=direction,
                sizes={"vp": 50.0, "vs": 50.0, "rho": 50.0, "source_amplitudes": 0.05, "source_components": 0.05,
                       "source_locations": 3.0},
                host_misfit=lambda name, syn: sum(named_misfit(name, syn[c], named_obs[c], DT)[0] for c in E.COMPONENTS))  # fmt: skip


# --- staggered physics on Warp's taped adjoints: vti, viscoacoustic ----------------------------------------------


def taped_case(physics: str, free_surface: bool, ndim: int = 2) -> Case:
    """vti (vp, epsilon, delta, rho), viscoacoustic (vp, q, rho) or acoustic_vd (vp, rho): a smooth 24 x 30 model (3D,
    acoustic_vd: 12^3 with a 4-cell PML), one source, six (3D: four) pressure receivers, float64; observed data from a
    model 3% off in vp and rho (and 30% in q). Their gradients are Warp's generated adjoints, so adjoint="warp" is the
    one gradient there is (the checkpoint test still compares segments), but for acoustic_vd's 2D hand-written one."""
    rng = np.random.default_rng(0)
    shape, nt = ((24, 30), 200) if ndim == 2 else ((12, 12, 12), 100)
    smooth = gaussian_filter(rng.random(shape), 2)
    z = np.arange(shape[0]).reshape(-1, *(1,) * (ndim - 1)) * np.ones(shape)
    base = {"vp": 2000.0 + 10.0 * z + 200.0 * smooth, "rho": 1500.0 + 20.0 * z}
    if physics == "vti":
        models, extra = V.MODELS, {}
        base.update(epsilon=0.2 + 0.002 * z + 0.05 * smooth, delta=0.05 + 0.001 * z)
        true = dict(base, vp=base["vp"] * 1.03, rho=base["rho"] * 0.97)
        sizes = {"vp": 50.0, "epsilon": 0.02, "delta": 0.02, "rho": 50.0}  # epsilon - delta >= 0.1 stays >= 0 (stability)
        forward, gradient_fn = V.forward_vti, V.gradient_vti
    elif physics == "acoustic_vd":
        models, extra = AVD.MODELS, {}
        true = dict(base, vp=base["vp"] * 1.03, rho=base["rho"] * 0.97)
        sizes = {"vp": 50.0, "rho": 50.0}
        forward, gradient_fn = AVD.forward_acoustic_vd, AVD.gradient_acoustic_vd
    else:
        models, extra = Q.MODELS, {"q_band": (3.0, 25.0), "f_ref": 10.0}
        base.update(q=40.0 - 20.0 * smooth)
        true = dict(base, vp=base["vp"] * 1.03, rho=base["rho"] * 0.97, q=base["q"] * 1.3)
        sizes = {"vp": 50.0, "q": 5.0, "rho": 50.0}
        forward, gradient_fn = Q.forward_viscoacoustic, Q.gradient_viscoacoustic
    f0 = 15.0 if ndim == 2 else 20.0
    params = dict(base, source_amplitudes=ricker(f0, nt, DT)[None, None])
    if ndim == 2:
        src = np.array([[[75.3, 141.7]]])
        rec = np.array([[[5.0 if free_surface else 30.0, x] for x in np.linspace(20.0, 270.0, 6)]])
    else:
        src = np.array([[[43.3 if not free_surface else 12.3, 51.7, 48.1]]])
        rec = np.array([[[5.0 if free_surface else 80.0, 20.0 + 25.0 * k, 90.0 - 20.0 * k] for k in range(4)]])
    kw = dict(precision="float64", pml_velocity=3000.0, pml_frequency=f0, pml_width=6 if ndim == 2 else 4, free_surface=free_surface,
              device=DEVICE, **extra)  # fmt: skip

    def args(changes):
        a = dict(params, **changes)
        return (*(a[m] for m in models), DX, DT, a["source_amplitudes"], src, rec)

    obs = forward(*args(true), **kw).pressure

    def data(**changes):
        return forward(*args(changes), **kw).pressure

    def gradient(misfit, wrt, segment_length=None, adjoint="hand", **changes):
        choice = {"adjoint": adjoint} if physics == "acoustic_vd" and ndim == 2 else {}
        return gradient_fn(*args(changes), {"pressure": obs}, misfit=misfit, wrt=wrt, segment_length=segment_length, **choice, **kw)

    def l2(syn):
        r = syn["pressure"] - obs
        return 0.5 * float(np.sum(r * r)), {"pressure": r}

    def tangent(kind, rng):
        # as the elastic case's: the data are linear in the source wavelet (the forward run is J: target 1e-10), and
        # the models' adjoint against central differences along a smooth dm of 1e-4 relative size (the O(h^2)
        # truncation; measured in test_vti / test_viscoacoustic 1e-10 .. 6e-8: target 1e-6)
        if kind == "source_amplitudes":
            ds = rng.standard_normal(params[kind].shape)
            return ds, data(source_amplitudes=ds), 1e-10
        dm = gaussian_filter(rng.standard_normal(shape), 2)
        dm *= 1e-4 * params[kind].mean() / np.abs(dm).max()
        return dm, (data(**{kind: params[kind] + dm}) - data(**{kind: params[kind] - dm})) / 2.0, 1e-6

    def direction(kind, rng):
        d = rng.standard_normal(params[kind].shape)
        return d if kind == "source_amplitudes" else gaussian_filter(d, 2)

    kinds = (*models, "source_amplitudes")
    return Case(params=params, kinds=kinds, dot_kinds=kinds, nt=nt, gradient=gradient, l2=l2, loss=lambda **changes: l2({"pressure": data(**changes)})[0],
                random_data=lambda rng: rng.standard_normal(obs.shape),
                projection=lambda dd: lambda syn: (float(np.sum(syn["pressure"] * dd)), {"pressure": dd}),
                inner=lambda a, b: float(np.sum(a * b)), tangent=tangent, direction=direction,
                sizes=dict(sizes, source_amplitudes=0.05),
                host_misfit=lambda name, syn: named_misfit(name, syn["pressure"], obs, DT)[0])  # fmt: skip


def elastic3d_case(free_surface: bool, source_type: str) -> Case:
    """elastic3d (vp, vs, rho, source_amplitudes): a smooth 12^3 model with a 4-cell PML (order 4: 24^3 padded), one
    force or moment-tensor source, four receivers recording vx, vy, vz and pressure, float64; observed data from a
    model 3% off in vp, vs and rho. Its gradient is Warp's generated adjoints (taped_gradient), as vti's."""
    rng = np.random.default_rng(0)
    shape, nt = (12, 12, 12), 100
    smooth = gaussian_filter(rng.random(shape), 2)
    z = np.arange(shape[0])[:, None, None] * np.ones(shape)
    base = {"vp": 2000.0 + 10.0 * z + 200.0 * smooth, "vs": 1000.0 + 5.0 * z + 100.0 * smooth, "rho": 1800.0 + 20.0 * z}
    true = dict(base, vp=base["vp"] * 1.03, vs=base["vs"] * 0.97, rho=base["rho"] * 0.97)
    params = dict(base, source_amplitudes=ricker(20.0, nt, DT)[None, None])
    src = np.array([[[43.3 if not free_surface else 12.3, 51.7, 48.1]]])
    rec = np.array([[[5.0 if free_surface else 80.0, 20.0 + 25.0 * k, 90.0 - 20.0 * k] for k in range(4)]])
    comp = np.array([[[0.3, -0.5, 0.8] if source_type == "force" else [1.0, -0.5, 0.7, 0.4, -0.3, 0.2]]])
    kw = dict(precision="float64", pml_velocity=2600.0, pml_frequency=20.0, pml_width=4, free_surface=free_surface, device=DEVICE,
              source_type=source_type, source_components=comp)  # fmt: skip
    scale = {"vx": 1.0, "vy": 1.0, "vz": 1.0, "pressure": 1.0 / (2000.0 * 2000.0)}  # pressure / (rho vp): velocity units

    def args(changes):
        a = dict(params, **changes)
        return (*(a[m] for m in E3.MODELS), DX, DT, a["source_amplitudes"], src, rec)

    def data(**changes):
        r = E3.forward_elastic3d(*args(changes), **kw)
        return {c: getattr(r, c) for c in E3.COMPONENTS}

    obs = data(**true)

    def gradient(misfit, wrt, segment_length=None, adjoint="hand", **changes):
        return E3.gradient_elastic3d(*args(changes), obs, misfit=misfit, components=E3.COMPONENTS, wrt=wrt, segment_length=segment_length,
                                     **kw)  # fmt: skip

    def inner(a, b):
        return float(sum(np.sum(a[c] * b[c] * scale[c] ** 2) for c in E3.COMPONENTS))

    def l2(syn):
        res = {c: syn[c] - obs[c] for c in E3.COMPONENTS}
        return 0.5 * inner(res, res), {c: res[c] * scale[c] ** 2 for c in E3.COMPONENTS}

    def tangent(kind, rng):
        # as the 2D staggered cases' (taped_case): the source wavelet exactly (target 1e-10), the models against
        # central differences along a smooth dm of 1e-4 relative size (the O(h^2) truncation: target 1e-6)
        if kind == "source_amplitudes":
            ds = rng.standard_normal(params[kind].shape)
            return ds, data(source_amplitudes=ds), 1e-10
        dm = gaussian_filter(rng.standard_normal(shape), 2)
        dm *= 1e-4 * params[kind].mean() / np.abs(dm).max()
        plus, minus = data(**{kind: params[kind] + dm}), data(**{kind: params[kind] - dm})
        return dm, {c: (plus[c] - minus[c]) / 2.0 for c in E3.COMPONENTS}, 1e-6

    def direction(kind, rng):
        d = rng.standard_normal(params[kind].shape)
        return d if kind == "source_amplitudes" else gaussian_filter(d, 2)

    return Case(params=params, kinds=E3.WRT, dot_kinds=E3.WRT, nt=nt, gradient=gradient, l2=l2,
                loss=lambda **changes: l2(data(**changes))[0],
                random_data=lambda rng: {c: rng.standard_normal(obs[c].shape) / scale[c] for c in E3.COMPONENTS},
                projection=lambda dd: lambda syn: (inner(syn, dd), {c: dd[c] * scale[c] ** 2 for c in E3.COMPONENTS}), inner=inner,
                tangent=tangent, direction=direction, sizes={"vp": 50.0, "vs": 25.0, "rho": 50.0, "source_amplitudes": 0.05},
                host_misfit=lambda name, syn: sum(named_misfit(name, syn[c], obs[c], DT)[0] for c in E3.COMPONENTS))  # fmt: skip


CASES = {
    "acoustic-2d": functools.partial(acoustic_case, 2),
    "acoustic-3d": functools.partial(acoustic_case, 3),
    "elastic-2d-force": functools.partial(elastic_case, False, "force"),
    "elastic-2d-free-surface-moment": functools.partial(elastic_case, True, "moment"),
    "vti-2d-free-surface": functools.partial(taped_case, "vti", True),
    "viscoacoustic-2d": functools.partial(taped_case, "viscoacoustic", False),
    "acoustic_vd-2d-free-surface": functools.partial(taped_case, "acoustic_vd", True),
    "acoustic_vd-3d": functools.partial(taped_case, "acoustic_vd", False, 3),
    "elastic3d-force": functools.partial(elastic3d_case, False, "force"),
    "elastic3d-free-surface-moment": functools.partial(elastic3d_case, True, "moment"),
}


@functools.lru_cache(maxsize=None)
def case(physics: str) -> Case:
    return CASES[physics]()


@functools.lru_cache(maxsize=None)
def checkpointed_gradient(physics: str):
    """The l2 misfit's gradient for every kind through the checkpointed sweep (the memory minimum's segments), shared
    by the Taylor test and the checkpoint test."""
    c = case(physics)
    return c.gradient(c.l2, c.kinds)


# --- the tests ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("physics", CASES)
def test_adjoint_dot_product(physics):
    # <J dm, dd> = <dm, J^T dd>: J^T dd is the gradient of the misfit <d(m), dd> (the reverse sweep seeded with
    # dd). Tolerances and their justification: Case.tangent.
    c = case(physics)
    rng = np.random.default_rng(2)
    dd = c.random_data(rng)
    adj = c.gradient(c.projection(dd), c.kinds)
    for kind in c.dot_kinds:
        dm, j_dm, tol = c.tangent(kind, rng)
        lhs, rhs = c.inner(j_dm, dd), float(np.sum(dm * getattr(adj, kind)))
        assert abs(lhs - rhs) <= tol * abs(lhs), kind


@pytest.mark.parametrize("physics", CASES)
def test_taylor(physics):
    # First-order remainder slope 1 and second-order slope 2 (within 0.1) over h = 1e-1..1e-4 for every
    # parameter, through the checkpointed sweep (10-17 segments). The direction is a smooth random one of a size that
    # suits the parameter plus half along the gradient, so the first-order term dominates the first-order remainder
    # over all the steps. Measured: 0.994-1.056 / 1.999-2.001 (acoustic; 1.056: the 3D source position),
    # 1.002-1.038 / 1.999-2.001 (elastic).
    c = case(physics)
    g = checkpointed_gradient(physics)
    assert g.n_segments > 4
    rng = np.random.default_rng(1)
    fit = lambda r: np.polyfit(np.log(STEPS), np.log(r), 1)[0]  # noqa: E731
    for kind in c.kinds:
        grad = getattr(g, kind)
        d = c.direction(kind, rng)
        d = d / np.abs(d).max() + grad / np.abs(grad).max()
        d = c.sizes[kind] * d / np.abs(d).max()
        j = np.array([c.loss(**{kind: c.params[kind] + h * d}) for h in STEPS])
        r1, r2 = np.abs(j - g.loss), np.abs(j - g.loss - STEPS * np.sum(grad * d))
        assert abs(fit(r1) - 1.0) <= 0.1, kind
        assert abs(fit(r2) - 2.0) <= 0.1, kind


@pytest.mark.parametrize("physics", CASES)
def test_checkpointed_equals_all_steps_and_warp(physics):
    # The checkpointed sweep (several segments: recomputation from checkpoints, the adjoint state carried across
    # segments) against every step kept in one segment, and the hand-written adjoints (which replace Warp's
    # generated ones for speed) against Warp's generated adjoints under wp.Tape: the same loss and gradients for
    # every parameter (float64: equal to rounding; measured <= 1e-15 relative (checkpoints; bit for bit on the CPU)
    # and <= 1e-14 (hand vs Warp: 6e-15 at most)).
    # Also segments that divide nt (the taped sweep then runs its last segment as the others, in two passes).
    c = case(physics)
    ckpt = checkpointed_gradient(physics)
    every = c.gradient(c.l2, c.kinds, segment_length=c.nt)
    even = c.gradient(c.l2, c.kinds, segment_length=c.nt // 5)
    warp = c.gradient(c.l2, c.kinds, adjoint="warp")
    assert every.n_segments == 1 and ckpt.n_segments > 4 and warp.n_segments > 4 and even.n_segments >= 5
    for other in (ckpt, warp, even):
        assert abs(other.loss - every.loss) <= 1e-12 * every.loss
    for k in c.kinds:
        a, b, w, e = getattr(every, k), getattr(ckpt, k), getattr(warp, k), getattr(even, k)
        assert np.abs(a).max() > 0, k
        assert np.linalg.norm(a - b) <= 1e-12 * np.linalg.norm(a), k
        assert np.linalg.norm(a - e) <= 1e-12 * np.linalg.norm(a), k
        assert np.abs(w - b).max() <= 1e-12 * np.abs(w).max(), k


def test_taped_sweep_passes_the_lookahead_samples(monkeypatch):
    # A taped sweep whose segments divide nt runs its last segment as the others, stepping from level nt - 1 too: a step
    # reads source sample n + 1 (lookahead), so the samples it is given must reach nt, zero past the data. Reading past
    # su.amplitudes instead (uninitialised memory) made a moment source's adjoints NaN in about half the runs.
    c = case("elastic-2d-free-surface-moment")
    lengths = []
    plain = E.ElasticSetup.sources_of

    def sources_of(self, amplitudes, fixed=True):
        lengths.append(amplitudes.shape[2] - self.nt - self.lookahead)
        return plain(self, amplitudes, fixed)

    monkeypatch.setattr(E.ElasticSetup, "sources_of", sources_of)
    g = c.gradient(c.l2, ("source_components",), segment_length=c.nt // 5, adjoint="warp")
    assert g.n_segments == 5 and lengths and min(lengths) >= 0
    assert np.all(np.isfinite(g.source_components))


@pytest.mark.parametrize("misfit", MISFITS)
@pytest.mark.parametrize("physics", CASES)
def test_named_misfit_loss_is_the_host_misfit_of_the_synthetics(physics, misfit):
    # Every misfit the gradients offer by name: the loss a gradient returns is misfits.misfit's value of the synthetics
    # it returns (elastic: summed over vx, vz and pressure; its "l2" formed on the device by l2_residual_kernel, the
    # others on the host). Measured: 0 .. 2e-16 relative. (The elastic velocities' "l2" is 1e-12 of the pressure's
    # here: test_elastic.test_named_misfit_loss_is_the_host_misfit_per_component checks each component alone.) The
    # values themselves: test_misfits.py.
    c = case(physics)
    g = c.gradient(misfit, c.kinds[:1])
    expected = c.host_misfit(misfit, g.synthetic)
    assert expected > 0 and abs(g.loss - expected) <= 1e-13 * expected


@pytest.mark.parametrize("physics", ["viscoacoustic-2d", "elastic3d-force"])
def test_a_kept_taped_sweep_serves_the_next_call_as_a_new_one(physics, monkeypatch):
    # A GPU keeps a taped sweep (its graphs and arrays) for the next call with the same key; that call's model, wavelet
    # and misfit are loaded into the kept arrays and its gradients handed back. Kept here on the CPU too: the gradients
    # equal a new sweep's (bit for bit on a CPU: the same launches on the same values), one sweep serving the first two.
    c = case(physics)
    calls = [(c.kinds, {}), (c.kinds, {"vp": c.params["vp"] * 1.01, "source_amplitudes": c.params["source_amplitudes"] * 2.0}),
             (c.kinds[:1], {}), (c.kinds, {})]  # the third without the wavelet's adjoint: a sweep of its own
    monkeypatch.setattr(sweep, "_keeps", lambda prop: False)
    new = [c.gradient(c.l2, wrt, segment_length=40, **ch) for wrt, ch in calls]
    made = []
    init = sweep._TapedSegments.__init__
    graphs.release()
    monkeypatch.setattr(sweep, "_keeps", lambda prop: True)
    monkeypatch.setattr(sweep._TapedSegments, "__init__", lambda self, *a: made.append(init(self, *a)))
    try:
        kept = [c.gradient(c.l2, wrt, segment_length=40, **ch) for wrt, ch in calls]
    finally:
        graphs.release()
    assert len(made) == 3
    tol = 0.0 if DEVICE == "cpu" else 1e-12  # a GPU's atomic adds sum in no fixed order (as test_checkpointed_equals_...)
    for a, b, (wrt, _) in zip(new, kept, calls):
        assert abs(a.loss - b.loss) <= tol * a.loss
        for k in wrt:
            x, y = getattr(a, k), getattr(b, k)
            assert np.abs(x).max() > 0 and np.abs(x - y).max() <= tol * np.abs(x).max(), k
    assert not np.array_equal(new[0].vp, new[1].vp)
