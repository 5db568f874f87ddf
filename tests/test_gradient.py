"""Acoustic gradients: Taylor tests (every parameter kind x every misfit but "l2"), the adjoint dot-product
test in float32, checkpointed vs. all-steps equality in float32 (and that this check catches the reused-buffer
bug), the memory budget, the parameterisation hook, and the hand-written adjoints against Warp's for orders 2 and 8
and the free surface. float64 unless stated; the CPML reference speed and frequency are pinned so that the PML
does not move when the model is perturbed (the gradient treats it as fixed). The float64 dot-product, "l2" Taylor
(2D and 3D) and checkpoint / hand vs Warp tests of order 4 without a free surface are test_adjoint.py's, one
module over every physics."""

import functools

import numpy as np
import pytest
import warp as wp
from scipy.ndimage import gaussian_filter

from adseismic.inversion.parameterization import MLP, LogVelocity, Slowness, SmoothBasis
from adseismic.solve import acoustic as G
from adseismic.solve.acoustic import forward, setup
from adseismic.solve.loop import run_levels
from adseismic.solve.misfits import MISFITS
from adseismic.wavelets import ricker

from .conftest import DEVICE, slow

DX, DT, NT = 10.0, 1e-3, 250
KW = dict(precision="float64", pml_velocity=2600.0, pml_frequency=15.0, pml_width=8, device=DEVICE)
gradient = functools.partial(G.gradient, **KW)
STEPS = np.array([1e-1, 1e-2, 1e-3, 1e-4])  # three decades


@functools.lru_cache(maxsize=None)
def problem():
    rng = np.random.default_rng(0)
    v = gaussian_filter(2000 + 400 * rng.random((30, 40)), 2)
    v_true = v.copy()
    v_true[12:18, 15:25] += 120.0
    s = ricker(15.0, NT, DT)[None, None]
    src = np.array([[[55.3, 101.7]]])
    rec = np.array([[[20.0, x] for x in np.linspace(10.0, 380.0, 8)]])
    obs = forward(v_true, DX, DT, ricker(15.0, NT, DT, delay=0.104)[None, None], src, rec, **KW).receiver_amplitudes
    return v, s, src, rec, obs


def loss(v, s, src, rec, obs, misfit):
    return gradient(v, DX, DT, s, src, rec, obs, misfit=misfit, wrt=(), segment_length=NT).loss


def taylor_slopes(j0, directional, evaluate):
    r1 = np.array([abs(evaluate(h) - j0) for h in STEPS])
    r2 = np.array([abs(evaluate(h) - j0 - h * directional) for h in STEPS])
    fit = lambda r: np.polyfit(np.log(STEPS), np.log(r), 1)[0]  # noqa: E731
    return fit(r1), fit(r2)


def perturbation(kind, shape, rng, grad=None):
    """A smooth random direction of a size that suits the parameter; with `grad`, half of it along the
    gradient, so the first-order term dominates the first-order remainder over all the steps."""
    if kind == "velocity":
        d, size = gaussian_filter(rng.standard_normal(shape), 2), 40.0  # m/s
    elif kind == "source_amplitudes":
        d, size = gaussian_filter(rng.standard_normal(shape), (0, 0, 3)), 0.05
    else:
        d, size = np.array([[[3.0, -2.0]]]), 3.0  # m
    d = d / np.abs(d).max()
    if grad is not None:
        d = d + grad / np.abs(grad).max()
    return size * d / np.abs(d).max()


@pytest.mark.parametrize("misfit", [m for m in MISFITS if m != "l2"])  # "l2": test_adjoint.test_taylor
@pytest.mark.parametrize("kind", G.WRT)
def test_taylor(kind, misfit):
    v, s, src, rec, obs = problem()
    base = {"velocity": v, "source_amplitudes": s, "source_locations": src}
    g = gradient(v, DX, DT, s, src, rec, obs, misfit=misfit, wrt=(kind,))
    dm = perturbation(kind, base[kind].shape, np.random.default_rng(1), getattr(g, kind))

    def evaluate(h):
        args = dict(base)
        args[kind] = base[kind] + h * dm
        return loss(args["velocity"], args["source_amplitudes"], args["source_locations"], rec, obs, misfit)

    s1, s2 = taylor_slopes(g.loss, float(np.sum(getattr(g, kind) * dm)), evaluate)
    assert abs(s1 - 1.0) <= 0.1
    assert abs(s2 - 2.0) <= 0.1


@pytest.mark.parametrize("precision, tol", [("float32", 1e-4)])  # float64 (1e-10): test_adjoint.test_adjoint_dot_product
def test_adjoint_dot_product(precision, tol):
    # <F dv, d> = <dv, F^T d>: F is the Born operator (tangent-linear model, propagated explicitly),
    # F^T the reverse sweep seeded with d. Measured mismatch: 8e-16 (float64).
    v, s, src, rec, obs = problem()
    rng = np.random.default_rng(2)
    dv = perturbation("velocity", v.shape, rng)
    d = rng.standard_normal(obs.shape)
    kw = dict(KW, precision=precision)
    f_dv = G.born(v, dv, DX, DT, s, src, rec, **kw)
    ft_d = G.gradient(v, DX, DT, s, src, rec, misfit=lambda syn: (float(np.sum(syn * d)), d), **kw).velocity
    a, b = np.sum(f_dv * d), np.sum(dv * ft_d)
    assert abs(a - b) / abs(a) <= tol


def test_checkpointed_equals_all_steps_float32():
    v, s, src, rec, obs = problem()
    kw = dict(KW, precision="float32")
    wrt = G.WRT
    every = G.gradient(v, DX, DT, s, src, rec, obs, wrt=wrt, segment_length=NT, **kw)
    repeats = [G.gradient(v, DX, DT, s, src, rec, obs, wrt=wrt, segment_length=NT, **kw) for _ in range(1 if DEVICE == "cpu" else 3)]
    ckpt = G.gradient(v, DX, DT, s, src, rec, obs, wrt=wrt, **kw)
    assert ckpt.n_segments > 4
    for k in wrt:
        # relative L2 <= 1e-6, or within twice the run-to-run spread of the all-steps gradient itself:
        # CUDA's float32 atomics add in a varying order (the source-position gradient sums ~16,000
        # terms into two numbers; measured 0.6-2e-6 between runs, so the spread is the largest of three
        # repeats: one pair alone can understate it); on the CPU repeated runs are equal.
        a, b = getattr(every, k), getattr(ckpt, k)
        spread = max(np.linalg.norm(a - getattr(r, k)) for r in repeats) / np.linalg.norm(a)
        assert np.linalg.norm(a - b) <= max(1e-6, 2.0 * spread) * np.linalg.norm(a)


def test_model_on_the_device_keeps_its_gradient_there():
    # a Warp array model gets its velocity gradient as a Warp array on its device (no copy to the host),
    # equal to the NumPy path's (to the rounding of float64 atomics, whose order varies on a GPU)
    v, s, src, rec, obs = problem()
    host = gradient(v, DX, DT, s, src, rec, obs)
    dev = gradient(wp.array(v, dtype=wp.float64, device=DEVICE), DX, DT, s, src, rec, obs)
    assert isinstance(dev.velocity, wp.array) and dev.velocity.device == wp.get_device(DEVICE) and dev.velocity.shape == v.shape
    assert np.abs(dev.velocity.numpy() - host.velocity).max() <= 1e-12 * np.abs(host.velocity).max()
    assert abs(dev.loss - host.loss) <= 1e-12 * host.loss


def test_equality_check_catches_reused_buffers():
    # The same comparison must fail for a tape run over a ring of reused wavefield buffers
    # (in-place stepping): the tape keeps references, so the model gradient is silently wrong.
    v, s, src, rec, obs = problem()
    good = gradient(v, DX, DT, s, src, rec, obs, segment_length=NT).velocity
    su = setup(v, DX, DT, s, src, rec, requires_grad=("velocity",), **KW)
    data = wp.zeros(obs.shape, dtype=su.prop.dtype, device=su.prop.device, requires_grad=True)
    tape = wp.Tape()
    with tape:
        run_levels(su, su.prop.new_state(requires_grad=True), su.prop.pad_model(su.velocity, requires_grad=True), (data,), range(NT))
    tape.backward(grads={data: wp.array((data.numpy() - obs) * DT, dtype=su.prop.dtype, device=su.prop.device)})
    ring = su.velocity.grad.numpy().reshape(v.shape)
    assert np.abs(ring - good).max() > 1e-2 * np.abs(good).max()


def test_memory_budget_sets_segments():
    v, s, src, rec, obs = problem()
    roomy = gradient(v, DX, DT, s, src, rec, obs, memory_budget=2**30)
    assert roomy.n_segments == 1  # every step fits: no recomputation
    tight = gradient(v, DX, DT, s, src, rec, obs, memory_budget=roomy.peak_bytes_estimate // 4)
    assert tight.n_segments > 1 and tight.peak_bytes_estimate <= roomy.peak_bytes_estimate // 4
    np.testing.assert_allclose(tight.velocity, roomy.velocity, rtol=0, atol=1e-12 * np.abs(roomy.velocity).max())
    with pytest.raises(ValueError, match="memory_budget"):
        gradient(v, DX, DT, s, src, rec, obs, memory_budget=1000)


@pytest.mark.parametrize("make", [Slowness, LogVelocity])
def test_parameterization_chain_rule(make):
    v, s, src, rec, obs = problem()
    g = gradient(v, DX, DT, s, src, rec, obs)
    p = make(v)
    gp = gradient(v, DX, DT, s, src, rec, obs, parameterization=p).parameters.reshape(v.shape)
    dv_dtheta = -(v**2) if make is Slowness else v
    np.testing.assert_allclose(gp, g.velocity * dv_dtheta, rtol=0, atol=1e-12 * np.abs(gp).max())


@pytest.mark.parametrize("make", [lambda shape: SmoothBasis(shape, (4, 5), 2100.0), lambda shape: MLP(shape, 2100.0, 100.0)])
def test_parameterization_taylor(make):
    v, s, src, rec, obs = problem()
    p = make(v.shape)
    g = gradient(v, DX, DT, s, src, rec, obs, parameterization=p)
    theta0 = p.parameters.copy()
    d = np.random.default_rng(4).standard_normal(theta0.shape) * (10.0 if isinstance(p, SmoothBasis) else 0.1)

    def evaluate(h):
        p.parameters = theta0 + h * d
        return gradient(v, DX, DT, s, src, rec, obs, parameterization=p, wrt=(), segment_length=NT).loss

    s1, s2 = taylor_slopes(g.loss, float(np.sum(g.parameters * d)), evaluate)
    assert abs(s1 - 1) <= 0.1 and abs(s2 - 2) <= 0.1


# order 4 without a free surface (2D and 3D): test_adjoint.test_checkpointed_equals_all_steps_and_warp
@pytest.mark.parametrize("order, shape, free_surface", [(2, (30, 40), False), slow(8, (30, 40), False)] +
                         [(o, s, True) for o, s in ((2, (30, 40)), (4, (30, 40)), (8, (30, 40)))] + [slow(4, (12, 14, 16), True)])  # fmt: skip
def test_hand_adjoint_matches_warp_generated(order, shape, free_surface):
    # The hand-written adjoints of the stencil kernels replace Warp's generated ones for speed; they
    # must give the same gradients (measured: <= 1e-14 relative in float64).
    rng = np.random.default_rng(5)
    v = gaussian_filter(2000 + 400 * rng.random(shape), 2)
    nt = 150
    s = ricker(15.0, nt, DT)[None, None]
    mid = [61.2] * (len(shape) - 2)
    src = np.array([[[55.3, *mid, 101.7]]])
    rec = np.array([[[20.0, *mid, x] for x in np.linspace(10.0, 150.0, 5)]])
    obs = rng.standard_normal((1, 5, nt)) * 1e-8
    kw = dict(order=order, free_surface=free_surface, wrt=G.WRT, pml_width=6)
    ref = gradient(v, DX, DT, s, src, rec, obs, adjoint="warp", **kw)
    ours = gradient(v, DX, DT, s, src, rec, obs, adjoint="hand", **kw)
    for k in G.WRT:
        a, b = getattr(ref, k), getattr(ours, k)
        assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max()


@pytest.mark.skipif(DEVICE != "cpu", reason="the CPU's threaded steps")
def test_cpu_threads_do_not_change_the_gradient(monkeypatch):
    # A CPU step is split among threads (forward: row blocks; adjoint: the tiles shared, the frame in one thread,
    # each writing only its own cells): bitwise the single-thread result.
    from adseismic.kernels.acoustic import propagator

    v, s, src, rec, obs = problem()
    runs = []
    for threads in (1, 3):
        monkeypatch.setattr(propagator, "CPU_THREADS", threads)
        monkeypatch.setattr(propagator.os, "cpu_count", lambda: 3)
        runs.append(gradient(v, DX, DT, s, src, rec, obs, free_surface=True, wrt=G.WRT))
    for k in ("loss", *G.WRT):
        assert np.array_equal(getattr(runs[0], k), getattr(runs[1], k)), k


@pytest.mark.parametrize("weighted", [False, True])
def test_l2_formed_on_the_device_equals_the_host_misfit(weighted):
    """observed (and weights) given as device arrays: the "l2" residual and loss are formed by a kernel where the data
    are; the same float64 operations as misfits.weighted_l2 / _l2 on the host, so the residual, hence the gradient,
    is bitwise the host's on the CPU; the loss is a sum in another order (float64: 1e-13 relative). On a GPU the
    receivers' adjoint adds overlapping operator points with float64 atomics in a varying order: measured on an H200,
    45 of 1200 values differ, each by at most 7e-16 of itself (2.9e-12 and half the values while the CPML strips'
    adjoints were scattered with atomics too), so 1e-14 of the largest value."""
    v, s, src, rec, obs = problem()
    rng = np.random.default_rng(5)
    w = rng.random(obs.shape) * (rng.random(obs.shape[:2]) > 0.3)[..., None] if weighted else None
    host = gradient(v, DX, DT, s, src, rec, obs, weights=w)
    dev = DEVICE if DEVICE != "cpu" else "cpu"
    obs_d = wp.array(obs, dtype=wp.float64, device=dev)
    w_d = None if w is None else wp.array(w, dtype=wp.float64, device=dev)
    on_device = gradient(v, DX, DT, s, src, rec, obs_d, weights=w_d)
    assert isinstance(on_device.synthetic, wp.array)
    np.testing.assert_array_equal(on_device.synthetic.numpy(), host.synthetic)
    atol = 0.0 if DEVICE == "cpu" else 1e-14 * np.abs(host.velocity).max()
    np.testing.assert_allclose(on_device.velocity, host.velocity, rtol=0, atol=atol)
    assert on_device.loss == pytest.approx(host.loss, rel=1e-13)
    if weighted:  # the weights are applied: the unweighted misfit differs
        assert abs(gradient(v, DX, DT, s, src, rec, obs).loss - host.loss) > 0.05 * host.loss
