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

from adseismic.accel import graphs
from adseismic.kernels.common import operator_shape
from adseismic.inversion.misfits import misfit as named_misfit
from adseismic.solve.acoustic import run_steps, setup, velocity_3d

WRT = ("velocity", "source_amplitudes", "source_locations")


@dataclass
class GradientResult:
    """Misfit and gradients. velocity: dJ/dv (nz, [ny,] nx) per m/s (a Warp array on the model's device
    when the model was given as a Warp array, else a NumPy array); source_amplitudes: dJ/ds
    (n_shots, n_src, nt); source_locations: dJ/dx_s (n_shots, n_src, ndim) per metre; parameters:
    dJ/dtheta of a parameterization; illumination: sum over time and shots of u^2 (model shape;
    the pseudo-Hessian diagonal of Shin et al. 2001); synthetic: (n_shots, n_receivers, nt). Entries
    not requested are None; the gradients are in the simulation's precision (float32 or float64)."""

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


def plan_segments(prop, nt: int, memory_budget: float | None = None, segment_length: int | None = None, adjoint: str = "hand"):
    """(segment_length, estimated peak bytes) for the checkpointed sweep.

    memory_budget (bytes) caps checkpoints + one segment's levels; None picks the memory minimum. The
    hand-written sweep keeps, per level of a segment, u and the CPML strips (psi, zeta); Warp's tape keeps
    their adjoints too. Its segments are a multiple of 6 steps long (the adjoint's buffers rotate in threes
    and twos), and the last one runs past nt into zero sources and residuals.
    """
    item = 4 if prop.dtype == wp.float32 else 8
    cells = prop.n_shots * math.prod(prop.padded)
    strips = sum(math.prod(prop.strip_shape(a)) for a in range(3) if prop.strip_width[a])
    hand = adjoint == "hand"
    per_level = item * (cells + 2 * strips) * (1 if hand else 2)
    per_ckpt = item * (2 * cells + 2 * strips)
    fixed = item * (5 * cells + 4 * strips + 3 * math.prod(prop.padded)) if hand else 0  # adjoint ring, g pair, strips' adjoints, vpad, w
    step = 6 if hand else 1

    def total(seg):
        n_seg = math.ceil(nt / seg)
        kept = max(n_seg - 2, 0) if hand else n_seg - 1  # the Sweep keeps no checkpoint of the first and last starts
        return fixed + kept * per_ckpt + (seg + 1) * per_level

    return choose_segment(nt, step, total, memory_budget, segment_length)


def choose_segment(nt: int, step: int, total, memory_budget: float | None, segment_length: int | None):
    """(segment length, total(it)) of a checkpointed sweep of nt steps whose segments are a multiple of `step`
    long and whose peak bytes are total(segment length): segment_length (clipped to 1..nt, rounded up) if
    given, else every step in one segment if that fits memory_budget, else the memory minimum (budget None)
    or the longest segment that fits; raises ValueError when none fits."""

    def length(seg):
        return -(-seg // step) * step

    if segment_length is not None:
        seg = length(min(max(int(segment_length), 1), nt))
    elif memory_budget is not None and total(length(nt)) <= memory_budget:
        seg = length(nt)
    else:
        candidates = range(step, length(nt) + 1, step)
        fits = [s for s in candidates if memory_budget is None or total(s) <= memory_budget]
        if not fits:
            need = min(total(s) for s in candidates)
            raise ValueError(f"memory_budget = {memory_budget / 2**20:.1f} MiB is below the minimum {need / 2**20:.1f} MiB this gradient needs; raise it or use fewer shots per call")
        seg = min(fits, key=total) if memory_budget is None else max(fits)
    return int(seg), int(total(seg))


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
    memory_budget: bytes for checkpoints plus one segment's levels; segment_length pins the checkpoint
    spacing instead (at most nt, rounded up to a multiple of 6 for adjoint="hand").
    adjoint: "hand" (the hand-written adjoint time loop; on a GPU captured as CUDA graphs and kept, with
    its arrays, for the next call with the same grid, steps, shots and geometry: graphs.release() frees it)
    or "warp" (Warp's generated adjoints of every kernel under wp.Tape; the reference the hand-written one
    is tested against).
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
        return prop.pad_model(v if v.ndim == 3 else v.reshape(su.velocity.shape), requires_grad=True)

    seg, peak = plan_segments(prop, nt, memory_budget, segment_length, adjoint)
    n_seg = math.ceil(nt / seg)
    energy = wp.zeros(prop.padded, dtype=prop.dtype, device=prop.device) if illumination else None
    bar = tqdm(total=2 * n_seg, desc="gradient segments", disable=not progress, leave=False)
    if adjoint == "hand":
        model_tape = wp.Tape()
        with model_tape:
            vpad = model_on_tape()
        synthetic, loss, amplitudes_grad = _hand_sweep(su, vpad, seg, n_seg, loss_fn, energy, bar)
        model_tape.backward(grads={vpad: vpad.grad})
        del model_tape  # (not tape.reset(): that zeroes the gradients it holds, ours included)
    else:
        synthetic, loss = _taped_sweep(su, model_on_tape, seg, n_seg, loss_fn, energy, bar)
        amplitudes_grad = su.amplitudes.grad
    bar.close()

    def grad_of(arr):  # in the simulation's precision (a float64 copy of an S4000 gradient costs as much as 60 time steps)
        return arr.grad.numpy()

    res = GradientResult(loss=float(loss), synthetic=synthetic, segment_length=seg, n_segments=n_seg, peak_bytes_estimate=peak)
    if "velocity" in wrt:
        if theta is not None:
            res.parameters = grad_of(theta)
        elif isinstance(velocity, wp.array):  # stays on the device (the S4000 gradient's copy to the host took 37 ms of 187)
            res.velocity = su.velocity.grad.reshape(prop.shape)
        else:
            res.velocity = grad_of(su.velocity).reshape(prop.shape)
    if energy is not None:
        res.illumination = prop.physical(energy.numpy()).astype(float).reshape(prop.shape)
    if "source_amplitudes" in wrt:
        res.source_amplitudes = amplitudes_grad.numpy()[:, :, :nt]
    if "source_locations" in wrt:
        g = grad_of(su.sources)
        res.source_locations = g if su.ndim == 3 else g[..., [0, 2]]
    return res


def _taped_sweep(su, model_on_tape, seg: int, n_seg: int, loss_fn, energy, bar):
    """Warp's generated adjoints: a checkpointed forward sweep, then each segment, last first, re-run under
    a fresh tape with fresh arrays for every time level and back-propagated. Returns (synthetic, loss)."""
    prop, nt = su.prop, su.nt
    n_rec = su.receivers.shape[1]

    def zeros_data(n):
        return wp.zeros((prop.n_shots, n_rec, n), dtype=prop.dtype, device=prop.device, requires_grad=True)

    def new_level():
        return prop.new_state(requires_grad=True, with_prev=False)

    data = wp.zeros((prop.n_shots, n_rec, nt), dtype=prop.dtype, device=prop.device)
    checkpoints = []

    def keep(st, n):
        if n % seg == 0:
            checkpoints.append([wp.clone(a) for a in st.arrays()])
        if energy is not None:
            prop.accumulate_energy(st.u, energy, 0, prop.clock, nt)

    run_steps(su, prop.new_state(), model_on_tape(), data, range(nt), callback=keep)
    bar.update(n_seg)
    synthetic = data.numpy().astype(float)
    loss, adj = loss_fn(synthetic)
    starts = [prop.new_state(requires_grad=True) for _ in range(2)]  # used in turn: the carried adjoint survives
    carry = None
    for i, k in enumerate(reversed(range(n_seg))):
        n0, n1 = k * seg, min((k + 1) * seg, nt)
        st0 = starts[i % 2]
        for dst, src in zip(st0.arrays(), checkpoints[k]):
            wp.copy(dst, src)
            dst.grad.zero_()
        checkpoints[k] = None
        data_seg = zeros_data(n1 - n0)
        tape = wp.Tape()
        with tape:
            st = run_steps(su, st0, model_on_tape(), data_seg, range(n0, n1), next_state=new_level)
        seeds = {data_seg: wp.array(np.ascontiguousarray(adj[:, :, n0:n1]), dtype=prop.dtype, device=prop.device)}
        if carry is not None:
            seeds.update(zip(st.arrays(), carry))
        tape.backward(grads=seeds)
        carry = [a.grad for a in st0.arrays()]
        del tape
        bar.update()
    return synthetic, loss


def _hand_sweep(su, vpad, seg: int, n_seg: int, loss_fn, energy, bar):
    """The hand-written adjoint time loop (Sweep). vpad: the padded model (requires_grad; its .grad gets
    dJ/dvpad). Returns (synthetic, loss, the padded source amplitudes, whose .grad is dJ/ds)."""
    prop, nt = su.prop, su.nt
    sw = _kept_sweep(su, seg, n_seg, energy is not None)
    sw.refill(su, vpad)
    sw.forward_sweep(bar)
    synthetic = sw.data.numpy()[:, :, :nt].astype(float)
    loss, adj = loss_fn(synthetic)
    sw.residual.assign(graphs.padded_samples(np.asarray(adj), seg * n_seg, prop.dtype))
    sw.backward_sweep(bar)
    sw.collect(su, vpad, energy)
    return synthetic, loss, sw.amplitudes.grad


class Sweep:
    """The hand-written adjoint time loop of one geometry, with every array it reads.

    The forward sweep runs the segments of `seg` steps, each from levels[0] (its start state) into
    levels[1..seg] (u[n], psi[n], zeta[n] of every level), and keeps each segment's start as a
    checkpoint. The backward sweep runs the segments last first: the forward steps again from the
    checkpoint (but for the last segment, still in `levels`), then the adjoint steps back through them:
    the adjoint of u at level j in lam[j % 3], the sum g of the model gradient alternating between two
    buffers (a GPU writes an array faster than it updates one in place), the adjoints of psi and zeta
    alternating likewise; seg is a multiple of 6, so every segment starts with the same roles. Time
    indices are k + clock[0] (the segment's first level), so one captured graph per direction serves every
    segment; nt is padded to n_seg * seg with zero source samples and residuals.
    """

    def __init__(self, key, su, seg: int, n_seg: int, illumination: bool):
        prop = su.prop
        self.key, self.su, self.seg, self.n_seg = key, su, seg, n_seg
        levels = seg * n_seg
        self.levels = [prop.new_state()] + [prop.new_state(with_prev=False) for _ in range(seg)]
        self.checkpoints = [[wp.empty_like(a) for a in self.levels[0].arrays()] for _ in range(n_seg - 2)]
        self.amplitudes = wp.zeros((*su.amplitudes.shape[:2], levels), dtype=prop.dtype, device=prop.device, requires_grad=su.amplitudes.requires_grad)
        self.vpad = wp.zeros(prop.padded, dtype=prop.dtype, device=prop.device, requires_grad=True)
        self.w = wp.zeros_like(self.vpad)
        shape = (prop.n_shots, su.receivers.shape[1], levels)
        self.data = wp.zeros(shape, dtype=prop.dtype, device=prop.device)
        self.residual = wp.zeros(shape, dtype=prop.dtype, device=prop.device)
        self.lam = [wp.zeros_like(self.levels[0].u) for _ in range(3)]
        self.g = [wp.zeros_like(self.levels[0].u) for _ in range(2)]
        self.adj_psi = [prop.new_state(with_prev=False).psi for _ in range(2)]
        self.adj_zeta = [prop.new_state(with_prev=False).zeta for _ in range(2)]
        self.energy = wp.zeros(prop.padded, dtype=prop.dtype, device=prop.device) if illumination else None
        self.clock = wp.zeros(1, dtype=wp.int32, device=prop.device)
        self.segments = graphs.Segments(prop.device, self.clock, kernels_of(prop), (self._forward_segment, self._adjoint_segment))

    def _forward_segment(self):
        su, prop, lv = self.su, self.su.prop, self.levels
        st = lv[0]
        for j in range(self.seg):
            st = prop.step(st, self.vpad, out=lv[j + 1], record=(self.data, su.receiver_op, j, self.clock))
            prop.inject(st.u, self.vpad, self.amplitudes, su.source_op, j, self.clock)

    def _adjoint_segment(self):
        su, prop, lv = self.su, self.su.prop, self.levels
        for j in reversed(range(self.seg)):
            lam, adj, out = (self.lam[(j + d) % 3] for d in (1, 2, 0))
            psi = (self.adj_psi[(j + 1) % 2], self.adj_psi[j % 2])
            zeta = (self.adj_zeta[(j + 1) % 2], self.adj_zeta[j % 2])
            prop.inject_adjoint(lam, self.vpad, self.amplitudes, su.source_op, j, self.clock)
            prop.adjoint_step(lv[j], lv[j + 1], self.vpad, self.w, lam, adj, self.g[(j + 1) % 2], psi, zeta,
                              residual=(self.residual, su.receiver_op, j, self.clock), out=(out, self.g[j % 2]))  # fmt: skip
            if self.energy is not None:
                prop.accumulate_energy(lv[j].u, self.energy, j, self.clock, su.nt)

    def _start(self, k: int):
        """levels[0] <- the state at level k * seg (zero for k = 0, else checkpoint k - 1)."""
        for i, a in enumerate(self.levels[0].arrays()):
            if k == 0:
                a.zero_()
            else:
                wp.copy(a, self.checkpoints[k - 1][i])

    def forward_sweep(self, bar):
        last = self.levels[self.seg]
        end = [self.levels[self.seg - 1].u, *last.arrays()]  # the state at the segment's end (u_prev, u, psi, zeta)
        for k in range(self.n_seg):
            if k > 0:
                for dst, src in zip(self.levels[0].arrays(), end):
                    wp.copy(dst, src)
                if k < self.n_seg - 1:
                    for dst, src in zip(self.checkpoints[k - 1], end):
                        wp.copy(dst, src)
            self.segments.run(0, k * self.seg)
            bar.update()

    def backward_sweep(self, bar):
        for k in reversed(range(self.n_seg)):
            if k < self.n_seg - 1:
                self._start(k)
                self.segments.run(0, k * self.seg)
            self.segments.run(1, k * self.seg)
            bar.update()

    def refill(self, su, vpad):
        """Copy su's inputs (model, CPML coefficients, operators, source samples) into the kept arrays and
        zero the state, data and adjoints."""
        mine = self.su
        prop = mine.prop
        for a, b in zip(_inputs(mine), _inputs(su)):
            wp.copy(a, b)
        self.amplitudes.assign(graphs.padded_samples(su.amplitudes.numpy(), self.seg * self.n_seg, prop.dtype))
        wp.copy(self.vpad, vpad)
        wp.launch(prop.k.squared, dim=prop.padded, inputs=[self.vpad, prop.dt2, self.w], device=prop.device)
        zero = [self.data, *self.g, *self.lam, *(a for r in (self.adj_psi, self.adj_zeta) for p in r for a in p), self.vpad.grad]
        zero += [a.grad for a in (self.amplitudes, mine.sources) if a.requires_grad]
        zero += [self.energy] if self.energy is not None else []
        for a in zero:
            a.zero_()

    def collect(self, su, vpad, energy):
        """Move the results to su's arrays: dJ/dvpad into vpad.grad, dJ/d(locations), the illumination."""
        prop = su.prop
        wp.launch(prop.k.model_gradient, dim=prop.padded, inputs=[self.vpad, self.g[0], prop.dt2, self.vpad.grad], device=prop.device)
        wp.copy(vpad.grad, self.vpad.grad)
        if su.sources.requires_grad and su.sources is not self.su.sources:
            wp.copy(su.sources.grad, self.su.sources.grad)
        if energy is not None:
            wp.copy(energy, self.energy)


def _inputs(su):
    """The arrays a Sweep copies from a setup: CPML coefficients and the operators' arrays."""
    ops = [a for op in (su.source_op, su.receiver_op) for a in (op if isinstance(op, tuple) else (op,))]
    return [a for ax in su.prop.axes for a in (ax.a, ax.b)] + ops


def kernels_of(prop):
    """Every kernel a Sweep launches (loaded before a capture, which cannot compile)."""
    k = prop.k
    out = [k.step, k.pre_step, prop.core_kernel(), *(k.psi[a][0] for a in range(3)), k.record, k.record_fixed, k.inject, k.inject_fixed]
    out += [k.adjoint_step, k.post_adjoint, prop.adjoint_kernel(), *k.psi_adjoint, k.energy]
    return out


def _sweep_key(su, seg: int, n_seg: int, illumination: bool) -> tuple:
    p = su.prop
    return ("gradient", p.k, p.shape, p.padded, p.dx, p.dt, p.n_shots, p.device, seg, n_seg, su.amplitudes.shape, su.receivers.shape,
            operator_shape(su.source_op), operator_shape(su.receiver_op), su.amplitudes.requires_grad, illumination)  # fmt: skip


def _kept_sweep(su, seg: int, n_seg: int, illumination: bool) -> Sweep:
    """The kept Sweep for this geometry (CUDA), else a new one (kept on CUDA)."""
    key = _sweep_key(su, seg, n_seg, illumination)
    sw = graphs.kept(key)
    if sw is None:
        sw = Sweep(key, su, seg, n_seg, illumination)
        if su.prop.cuda:
            graphs.keep(sw)
    return sw


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
