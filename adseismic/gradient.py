"""Exact, memory-bounded gradients: reverse-mode differentiation of the time stepping with wp.Tape.

Differentiating the discrete scheme is the discrete adjoint-state method, so the gradient is exact for
the simulated data (not an approximation of the continuous adjoint). Memory is bounded by
checkpointing: a forward sweep without a tape stores the state (u[n-1], u[n], psi, zeta) every
`segment_length` steps; the backward sweep re-runs each segment, last first, under a fresh tape with
fresh arrays for every time level (a tape keeps references, so reused buffers would silently give
wrong gradients) and back-propagates the data residual plus the adjoint state carried from the later
segment. Peak memory ~ n_segments x checkpoint + segment_length x taped step, minimised near
segment_length ~ sqrt(nt); the cost is one extra forward run. When the memory budget allows every
step to be kept, a single taped run is used (no recomputation).

The model may be a differentiable function of other parameters (see adseismic.parameterization):
the mapping is recorded on every segment's tape, so the chain rule is done by Warp as well.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp
from tqdm.auto import tqdm

from adseismic.misfits import misfit as named_misfit
from adseismic.propagate import run_steps, setup, velocity_3d

WRT = ("velocity", "source_amplitudes", "source_locations")


@dataclass
class GradientResult:
    """Misfit and gradients. velocity: dJ/dv (nz, [ny,] nx) per m/s; source_amplitudes: dJ/ds
    (n_shots, n_src, nt); source_locations: dJ/dx_s (n_shots, n_src, ndim) per metre; parameters:
    dJ/dtheta of a parameterization; illumination: sum over time and shots of u^2 (model shape;
    the pseudo-Hessian diagonal of Shin et al. 2001); synthetic: (n_shots, n_receivers, nt). Entries
    not requested are None."""

    loss: float
    synthetic: np.ndarray
    velocity: np.ndarray | None = None
    source_amplitudes: np.ndarray | None = None
    source_locations: np.ndarray | None = None
    parameters: np.ndarray | None = None
    illumination: np.ndarray | None = None
    segment_length: int = 0
    n_segments: int = 0
    peak_bytes_estimate: int = 0


def plan_segments(prop, nt: int, memory_budget: float | None = None, segment_length: int | None = None):
    """(segment_length, estimated peak bytes) for the checkpointed sweep.

    memory_budget (bytes) caps checkpoints + one taped segment; None picks the memory minimum.
    """
    item = 4 if prop.dtype == wp.float32 else 8
    cells = prop.n_shots * math.prod(prop.padded)
    strips = sum(math.prod(prop.strip_shape(a)) for a in range(3) if prop.strip_width[a])
    per_step = 2 * item * (cells + 2 * strips)  # fresh u, psi, zeta and their adjoints
    per_ckpt = item * (2 * cells + 2 * strips)

    def total(seg):
        n_seg = math.ceil(nt / seg)
        return (n_seg - 1) * per_ckpt + seg * per_step if n_seg > 1 else nt * per_step

    if segment_length is None:
        if memory_budget is not None and total(nt) <= memory_budget:
            segment_length = nt
        else:
            candidates = range(1, nt + 1)
            fits = [s for s in candidates if memory_budget is None or total(s) <= memory_budget]
            if not fits:
                need = min(total(s) for s in candidates)
                raise ValueError(f"memory_budget = {memory_budget / 2**20:.0f} MiB is below the minimum {need / 2**20:.0f} MiB this gradient needs; raise it or use fewer shots per call")
            segment_length = min(fits, key=total) if memory_budget is None else max(fits)
    return int(segment_length), int(total(int(segment_length)))


def gradient(velocity, dx, dt, source_amplitudes, source_locations, receiver_locations, observed=None, *,
             misfit="l2", wrt=("velocity",), parameterization=None, order=4, pml_width=None, pml_reflection=None,
             pml_frequency=None, pml_velocity=None, free_surface=False, device="cpu", precision="float32",
             memory_budget=None, segment_length=None, adjoint="hand", illumination=False,
             progress=False) -> GradientResult:  # fmt: skip
    """Misfit between simulated and observed data and its gradient for a batch of shots.

    Arguments as in propagate.forward; observed (n_shots, n_receivers, nt). misfit: a name in
    misfits.MISFITS, or a callable synthetic -> (J, dJ/dsynthetic). wrt: any of "velocity",
    "source_amplitudes", "source_locations". parameterization: an object with `parameters`
    (numpy array theta) and `velocity(theta: wp.array) -> wp.array` (nz, [ny,] nx) written with Warp
    kernels; velocity is then ignored except for its shape and the gradient is returned for theta.
    memory_budget: bytes for checkpoints plus the taped segment; segment_length pins it instead.
    adjoint: "hand" (the hand-written adjoint of the stencil kernels, faster) or "warp" (Warp's
    generated adjoints of every kernel; the reference the hand-written one is tested against).
    illumination: also return sum_t sum_shots u^2 per cell.
    """
    if adjoint not in ("hand", "warp"):
        raise ValueError(f"adjoint {adjoint!r} is not 'hand' or 'warp'")
    wrt = tuple(wrt)
    unknown = set(wrt) - set(WRT)
    if unknown:
        raise ValueError(f"wrt: {sorted(unknown)} not among {WRT}")
    if parameterization is not None:
        velocity = np.asarray(parameterization.initial_velocity())
    want = set(wrt) - ({"velocity"} if parameterization is not None else set())
    su = setup(velocity, dx, dt, source_amplitudes, source_locations, receiver_locations, order=order, pml_width=pml_width,
               pml_reflection=pml_reflection, pml_frequency=pml_frequency, pml_velocity=pml_velocity,
               free_surface=free_surface, device=device, precision=precision, requires_grad=want)  # fmt: skip
    prop, nt = su.prop, su.nt
    n_rec = su.receivers.shape[1]
    if callable(misfit):
        loss_fn = misfit
    else:
        obs = np.asarray(observed, dtype=float)
        loss_fn = lambda d: named_misfit(misfit, d, obs, dt)  # noqa: E731
    theta = None
    if parameterization is not None:
        theta = wp.array(parameterization.parameters, dtype=prop.dtype, device=prop.device, requires_grad=True)

    def model_on_tape():
        v = su.velocity if theta is None else parameterization.velocity(theta, prop.dtype, prop.device)
        return prop.pad_model(v if v.ndim == 3 else v.reshape(velocity_3d(velocity).shape), requires_grad=True)

    def zeros_data(n):
        return wp.zeros((prop.n_shots, n_rec, n), dtype=prop.dtype, device=prop.device, requires_grad=True)

    def hand(tape):
        return tape if adjoint == "hand" else None

    energy = wp.zeros(prop.padded, dtype=prop.dtype, device=prop.device) if illumination else None

    def accumulate(st, n):
        if energy is not None:
            prop.accumulate_energy(st.u, energy)

    seg, peak = plan_segments(prop, nt, memory_budget, segment_length)
    n_seg = math.ceil(nt / seg)
    if n_seg == 1:
        data = zeros_data(nt)
        tape = wp.Tape()
        with tape:
            run_steps(su, prop.new_state(requires_grad=True), model_on_tape(), data, range(nt),
                      next_state=lambda: prop.new_state(requires_grad=True, with_prev=False), callback=accumulate, tape=hand(tape))  # fmt: skip
        synthetic = data.numpy().astype(float)
        loss, adj = loss_fn(synthetic)
        tape.backward(grads={data: wp.array(adj, dtype=prop.dtype, device=prop.device)})
        del tape  # (not tape.reset(): that zeroes the gradients it holds, ours included)
    else:
        data = wp.zeros((prop.n_shots, n_rec, nt), dtype=prop.dtype, device=prop.device)
        checkpoints = []

        def keep(st, n):
            if n % seg == 0:
                checkpoints.append([wp.clone(a) for a in st.arrays()])
            accumulate(st, n)

        run_steps(su, prop.new_state(), model_on_tape(), data, range(nt), callback=keep)
        synthetic = data.numpy().astype(float)
        loss, adj = loss_fn(synthetic)
        # One segment's level arrays, allocated once and reused (fresh allocations cost page faults),
        # and two start states used in turn so the carried adjoint survives the next zeroing.
        levels = [prop.new_state(requires_grad=True, with_prev=False) for _ in range(seg)]
        starts = [prop.new_state(requires_grad=True) for _ in range(2)]
        carry = None
        for i, k in enumerate(tqdm(reversed(range(n_seg)), total=n_seg, desc="adjoint segments", disable=not progress, leave=False)):
            n0, n1 = k * seg, min((k + 1) * seg, nt)
            st0 = starts[i % 2]
            for dst, src in zip(st0.arrays(), checkpoints[k]):
                wp.copy(dst, src)
                dst.grad.zero_()
            checkpoints[k] = None
            for lvl in levels:
                for a in lvl.arrays():
                    a.grad.zero_()
            data_seg = zeros_data(n1 - n0)
            pool = iter(levels)
            tape = wp.Tape()
            with tape:
                st = run_steps(su, st0, model_on_tape(), data_seg, range(n0, n1), next_state=lambda: next(pool), tape=hand(tape))
            seeds = {data_seg: wp.array(np.ascontiguousarray(adj[:, :, n0:n1]), dtype=prop.dtype, device=prop.device)}
            if carry is not None:
                seeds.update(zip(st.arrays(), carry))
            tape.backward(grads=seeds)
            carry = [a.grad for a in st0.arrays()]
            del tape
    shape = np.shape(velocity)

    def grad_of(arr):
        return arr.grad.numpy().astype(float)

    res = GradientResult(loss=float(loss), synthetic=synthetic, segment_length=seg, n_segments=n_seg, peak_bytes_estimate=peak)
    if "velocity" in wrt:
        if theta is not None:
            res.parameters = grad_of(theta)
        else:
            res.velocity = grad_of(su.velocity).reshape(shape)
    if energy is not None:
        res.illumination = prop.physical(energy.numpy()).astype(float).reshape(shape)
    if "source_amplitudes" in wrt:
        res.source_amplitudes = grad_of(su.amplitudes)
    if "source_locations" in wrt:
        g = grad_of(su.sources)
        res.source_locations = g if su.ndim == 3 else g[..., [0, 2]]
    return res


def born(velocity, dvelocity, dx, dt, source_amplitudes, source_locations, receiver_locations, **kw) -> np.ndarray:
    """Linearised (Born, tangent-linear) data F dv: the exact derivative of the simulated receiver
    data along the model perturbation dvelocity (m/s, same shape as velocity). Returns
    (n_shots, n_receivers, nt). Keyword arguments as in propagate.forward (no snapshots)."""
    su = setup(velocity, dx, dt, source_amplitudes, source_locations, receiver_locations, **kw)
    prop, nt = su.prop, su.nt
    vpad = prop.pad_model(su.velocity)
    dvpad = prop.pad_model(wp.array(velocity_3d(dvelocity), dtype=prop.dtype, device=prop.device))
    shape = (prop.n_shots, su.receivers.shape[1], nt)
    data = wp.zeros(shape, dtype=prop.dtype, device=prop.device)
    ddata = wp.zeros(shape, dtype=prop.dtype, device=prop.device)
    st, dst = prop.new_state(), prop.new_state()
    u_prev = wp.zeros_like(st.u)
    for n in range(nt):
        prop.record(st.u, data, su.receiver_op, n)
        prop.record(dst.u, ddata, su.receiver_op, n)
        if n == nt - 1:
            break
        wp.copy(u_prev, st.u_prev)
        st = prop.step(st, vpad)
        prop.inject(st.u, vpad, su.amplitudes, su.source_op, n)
        dst = prop.step(dst, vpad)
        prop.scatter(dst.u, st.u, st.u_prev, u_prev, vpad, dvpad)
    return ddata.numpy().astype(float)
