"""Acoustic simulation and its exact gradients: the entry points and the acoustic setup for the shared solver.

Conventions (shared by every public function of adseismic):
- velocity: (nz, nx) or (nz, ny, nx) array in m/s on a regular grid of spacing dx (m), axis order
  (z, [y,] x) with z depth (positive down); node (0, ..., 0) is at coordinate 0 m.
- locations: metres in the same axis order, shape (n_shots, n_per_shot, ndim).
- source_amplitudes: (n_shots, n_sources_per_shot, nt); the source term s(t) of
  (1/v^2) d2u/dt2 - laplacian(u) = s(t) delta(x - x_s), so that in a homogeneous medium
  u = s(t - r/v) / (4 pi r) in 3D (units of s: [u] m^(ndim-2)).
- receiver data: (n_shots, n_receivers_per_shot, nt) samples of u at t = n dt, n = 0..nt-1.

The time loop is solve/loop.py's and the checkpointed gradient solve/sweep.py's, as for every physics; this
module says how the acoustic kernels (kernels/acoustic) map onto them (Setup) and holds the hand-written
adjoint's arrays and segment functions (Levels).
"""

from __future__ import annotations

import copy
import functools
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import warp as wp

from adseismic.accel import graphs
from adseismic.accel.reductions import l2_residual_kernel, value_range, weighted_l2_residual_kernel
from adseismic.kernels.acoustic import DESCRIPTION, Acoustic, State
from adseismic.kernels.common import operator_shape
from adseismic.kernels.numerics import check_order
from adseismic.runs import progress_bar
from adseismic.solve import common, loop, sweep
from adseismic.solve.misfits import misfit as named_misfit
from adseismic.solve.misfits import weighted_l2

WRT = ("velocity", "source_amplitudes", "source_locations")


@dataclass
class ForwardResult:
    """Output of :func:`forward`.

    receiver_amplitudes: (n_shots, n_receivers_per_shot, nt), samples of u at t = n dt, in the simulation's
    precision (float32 or float64); a Warp array on the model's device when the velocity was given as a Warp
    array (as gradient's velocity gradient), else a NumPy array.
    dt: time step (s). snapshots: (n_snapshots, n_shots, *grid shape) or None; snapshot_times (s).
    """

    receiver_amplitudes: np.ndarray | wp.array
    dt: float
    snapshots: np.ndarray | None = None
    snapshot_times: np.ndarray | None = None


def to_zyx(locations: np.ndarray, ndim: int) -> np.ndarray:
    """(S, n, ndim) metres in model axis order -> (S, n, 3) as (z, y, x) with y = 0 in 2D."""
    loc = np.asarray(locations, dtype=float)
    if ndim == 3:
        return loc
    out = np.zeros(loc.shape[:-1] + (3,))
    out[..., 0], out[..., 2] = loc[..., 0], loc[..., 1]
    return out


def check_inputs(shape, value_range, dx, dt, source_amplitudes, source_locations, receiver_locations, order):
    """Shape, value and stability checks shared by forward and gradient; raises ValueError. shape: the
    velocity model's (nz, [ny,] nx); value_range: (min, max, first index of a non-finite or non-positive
    value or None) of its values. Returns (ndim, max velocity in m/s)."""
    ndim = len(shape)
    if ndim not in (2, 3):
        raise ValueError(f"velocity must be 2D (nz, nx) or 3D (nz, ny, nx); got shape {shape}")
    check_order(order)
    vmin, vmax, bad = value_range
    if bad is not None:
        raise ValueError(f"velocity has non-finite or non-positive values (first at index {bad}, min {vmin:.6g} m/s); fix the model")
    common.check_geometry(shape, dx, source_amplitudes, source_locations, receiver_locations, "z, x" if ndim == 2 else "z, y, x")
    common.check_courant(DESCRIPTION, order, ndim, vmax, dx, dt)
    return ndim, vmax


def upload_velocity(velocity, dtype, device: str, requires_grad=False):
    """The model (NumPy or Warp array, (nz, [ny,] nx) m/s) as a new (nz, ny, nx) Warp array of dtype on
    device (ny = 1 in 2D), its shape as given, and its (min, max, first bad index or None) for check_inputs;
    a Warp array of that dtype is copied between devices and its range taken there."""
    if isinstance(velocity, wp.array) and velocity.dtype == dtype and velocity.ndim in (2, 3):
        shape3 = velocity.shape if velocity.ndim == 3 else (velocity.shape[0], 1, velocity.shape[1])
        vel = wp.empty(shape3, dtype=dtype, device=device, requires_grad=requires_grad)
        wp.copy(vel, velocity.reshape(shape3))
        shape = velocity.shape
        host = None if vel.device.is_cuda else vel.numpy()
    else:
        host = np.asarray(velocity.numpy() if isinstance(velocity, wp.array) else velocity, dtype=wp.dtype_to_numpy(dtype))
        shape = host.shape
        # reshape, not [:, None], whose zero stride Warp copies slowly
        vel = wp.array(host.reshape(shape[0], 1, -1) if host.ndim == 2 else host, dtype=dtype, device=device, requires_grad=requires_grad)
    if host is None:
        vmin, vmax, nonfinite = value_range(vel)
    else:
        vmin, vmax = float(host.min()), float(host.max())  # NaN propagates: one pass each, not isfinite + min + max
        nonfinite = int(not (math.isfinite(vmin) and math.isfinite(vmax)))
    bad = None
    if nonfinite or vmin <= 0:
        v = vel.numpy().reshape(shape)
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(v) | (v <= 0))[0])
    return vel, tuple(shape), (vmin, vmax, bad)


KEPT_PROPAGATORS = 8  # launch helpers kept per process for later calls on a GPU (each a few small arrays)


@functools.lru_cache(maxsize=KEPT_PROPAGATORS)
def _kept_propagator(shape, dx, dt, n_shots, order, pml, free_surface, device, dtype) -> Acoustic:
    prop = Acoustic(shape, dx, dt, order, n_shots, *pml, free_surface=free_surface, dtype=dtype, device=device)
    prop.kept_operators = {}  # make_operator's, by the locations' values
    return prop


def make_propagator(shape, dx, dt, n_shots, order, pml, free_surface, device, dtype, keep=None) -> Acoustic:
    """The Acoustic launch helper for a grid of `shape` cells on a resolved device; pml: (width, reflection,
    frequency, reference speed) from pml_settings. keep (default: on a GPU) starts from the helper an earlier call
    made for the same arguments, with the operators it made (an FWI's evaluations, a bench's repeats; docs/benchmarks.md):
    a shallow copy whose CPML coefficients are device copies of the kept ones (a kept time loop copies a later call's
    inputs into the arrays it was captured with), its attributes the caller's. A CPU helper is not kept: its threads
    record launches per set of arrays."""
    if keep is None:
        keep = wp.get_device(device).is_cuda
    if not keep:
        return Acoustic(shape, dx, dt, order, n_shots, *pml, free_surface=free_surface, dtype=dtype, device=device)
    prop = _kept_propagator(tuple(shape), float(dx), float(dt), int(n_shots), int(order), tuple(pml), bool(free_surface), str(device),
                            dtype)  # fmt: skip
    mine = copy.copy(prop)
    mine._launches = {}  # a CPU's recorded launches (keep=True on a CPU: tests)
    mine.axes = [prop.k.Axis() for _ in prop.axes]
    for ax, kept in zip(mine.axes, prop.axes):
        ax.a, ax.b, ax.store, ax.pos = wp.clone(kept.a), wp.clone(kept.b), kept.store, kept.pos  # store, pos: fixed by the key
    return mine


def make_operator(prop: Acoustic, locations: wp.array, host: np.ndarray, differentiable=False):
    """prop.operator(locations, differentiable), a device copy of the one a kept helper made at the same points in
    an earlier call if it did (host: locations' values, (S, n, 3) metres)."""
    kept = getattr(prop, "kept_operators", None)
    if kept is None or differentiable:
        return prop.operator(locations, differentiable)
    key = (host.shape, host.tobytes())
    op = kept.get(key)
    if op is None:
        op = kept[key] = prop.operator(locations)
        while len(kept) > 2 * KEPT_PROPAGATORS:
            kept.pop(next(iter(kept)), None)
    return tuple(wp.clone(a) for a in op)


def velocity_3d(velocity) -> np.ndarray:
    v = np.asarray(velocity, dtype=float)
    return v[:, None, :] if v.ndim == 2 else v


@dataclass
class Setup:
    """Device-side inputs of one acoustic simulation and the verbs of the shared solver (solve/loop.py).

    amplitudes (S, n_src, nt); sources, receivers (S, n, 3) metres as (z, y, x); velocity (nz, ny, nx) m/s;
    source_op, receiver_op: the operators at those points (Acoustic.operator); velocity_map: the padded model
    from another parameterisation (gradient's), else velocity padded.
    """

    prop: Acoustic
    ndim: int
    nt: int
    velocity: wp.array
    amplitudes: wp.array
    sources: wp.array
    receivers: wp.array
    source_op: object = None
    receiver_op: object = None
    velocity_map: Callable | None = None

    physics = DESCRIPTION
    period = 3  # a captured loop's wavefield buffers: u[n+1] goes to the third
    lookahead = 0

    def model(self, on_tape=False):
        if self.velocity_map is not None:
            return self.velocity_map()
        return self.prop.pad_model(self.velocity, requires_grad=on_tape)

    def fill_model(self, vpad):
        self.prop.pad_model(self.velocity, out=vpad)

    def sources_of(self, amplitudes, fixed=True):
        return amplitudes, self.source_op

    def advance(self, st, vpad, src, data, k, n, out, clock, side=None):
        # the record is part of the step's own launch here, so there is nothing to run beside it (side unused)
        nxt = self.prop.step(st, vpad, out, record=(data[0], self.receiver_op, k, clock))
        self.prop.inject(nxt.u, vpad, src[0], src[1], n, clock)
        return nxt

    def record(self, st, data, k, clock):
        self.prop.record(st.u, data[0], self.receiver_op, k, clock)

    def new_data(self, n, requires_grad=False):
        p = self.prop
        return (wp.zeros((p.n_shots, self.receivers.shape[1], n), dtype=p.dtype, device=p.device, requires_grad=requires_grad),)

    def new_level(self):
        return self.prop.new_state(requires_grad=True, with_prev=False)

    def fields(self, st):
        return [st.u]

    def spare(self, st):
        return wp.zeros_like(st.u)

    def out_state(self, st, spare):
        return State(None, spare, st.psi, st.zeta)

    def freed(self, st):
        return st.u_prev

    def key(self):
        """What a captured time loop bakes in: kernels, grid, scalars, array shapes, operator kinds."""
        p = self.prop
        return ("acoustic", p.k, p.shape, p.padded, p.dx, p.dt, p.n_shots, p.device, self.nt, self.amplitudes.shape, self.receivers.shape,
                operator_shape(self.source_op), operator_shape(self.receiver_op))  # fmt: skip

    def loop_kernels(self):
        k, p = self.prop.k, self.prop
        return [k.step, k.pre_step, p.core_kernel(), *(k.psi[a][0] for a in range(3)), k.record_fixed, k.record,
                k.inject_fixed if isinstance(self.source_op, tuple) else k.inject]  # fmt: skip

    def inputs(self, src=None):
        """The arrays a kept loop or sweep copies from a later setup: CPML coefficients and the operators' arrays."""
        ops = [a for op in (self.source_op, self.receiver_op) for a in (op if isinstance(op, tuple) else (op,))]
        return [a for ax in self.prop.axes for a in (ax.a, ax.b)] + ops


def setup(velocity, dx, dt, source_amplitudes, source_locations, receiver_locations, *, order=4, pml_width=None,
          pml_reflection=None, pml_frequency=None, pml_velocity=None, free_surface=False, device="cpu",
          precision="float32", requires_grad=()) -> Setup:  # fmt: skip
    """Validate the inputs and move them to the device; requires_grad names the arrays to differentiate
    ("velocity", "source_amplitudes", "source_locations"). velocity: NumPy or Warp array (nz, [ny,] nx)."""
    amp = np.asarray(source_amplitudes, dtype=float)
    dtype, device = common.precision_dtype(precision), common.resolve_device(device)
    vel, shape, vrange = upload_velocity(velocity, dtype, device, requires_grad="velocity" in requires_grad)
    ndim, vmax = check_inputs(shape, vrange, dx, dt, amp, source_locations, receiver_locations, order)
    pml = common.pml_settings(order, pml_width, pml_reflection, pml_frequency, pml_velocity, amp, dt, vmax)
    prop = make_propagator(shape, dx, dt, amp.shape[0], order, pml, free_surface, device, dtype)

    def put(x, name):
        return wp.array(x, dtype=prop.dtype, device=prop.device, requires_grad=name in requires_grad)

    src, rec = to_zyx(source_locations, ndim), to_zyx(receiver_locations, ndim)
    su = Setup(prop, ndim, amp.shape[2], vel, put(amp, "source_amplitudes"), put(src, "source_locations"), put(rec, "receiver_locations"))
    su.source_op = make_operator(prop, su.sources, src, differentiable="source_locations" in requires_grad)
    su.receiver_op = make_operator(prop, su.receivers, rec)
    return su


def forward(velocity, dx, dt, source_amplitudes, source_locations, receiver_locations, *, order=4,
            pml_width=None, pml_reflection=None, pml_frequency=None, pml_velocity=None, free_surface=False,
            device="cpu", precision="float32", snapshot_every=0, check_every=25, progress=False) -> ForwardResult:  # fmt: skip
    """Simulate the acoustic wave equation for all shots at once.

    velocity (nz, [ny,] nx) m/s, a NumPy array or a Warp array (e.g. already on the device); dx m; dt s; source_amplitudes (n_shots, n_src, nt);
    source/receiver_locations (n_shots, n, ndim) metres (axis order z, [y,] x).
    order: spatial order 2, 4 or 8. pml_width: cells (default 20) on every absorbing side;
    pml_reflection: target reflection coefficient; pml_frequency: CPML alpha frequency (Hz,
    default the sources' dominant frequency); pml_velocity: CPML reference speed (m/s, default
    max(velocity)). free_surface: pressure-release top boundary at z = 0.
    device: "cpu" or "cuda:N". precision: "float32" or "float64".
    snapshot_every: keep the physical wavefield every that many steps (0: none).
    check_every: steps between blow-up checks. Raises ValueError on bad input or an unstable dt,
    PropagationError if the run blows up.
    On a GPU the time loop is captured as a CUDA graph and kept (with its wavefields) for the next call
    with the same grid, time step, number of steps, shots, sources and receivers, which then only copies
    its inputs in (accel.graphs.release frees it).
    """
    su = setup(velocity, dx, dt, source_amplitudes, source_locations, receiver_locations, order=order, pml_width=pml_width,
               pml_reflection=pml_reflection, pml_frequency=pml_frequency, pml_velocity=pml_velocity,
               free_surface=free_surface, device=device, precision=precision)  # fmt: skip
    prop = su.prop
    guard = common.BlowupGuard(prop, DESCRIPTION, su.fields, common.source_end(source_amplitudes), check_every)
    snaps, snap_t = [], []
    o, ny = prop.origin, (prop.shape[1] if su.ndim == 3 else 1)
    phys = (slice(None), slice(o[0], o[0] + prop.shape[0]), slice(o[1], o[1] + ny), slice(o[2], o[2] + prop.shape[-1]))

    def snapshot(st, n):
        if n % snapshot_every == 0:
            field = st.u.numpy()[phys].copy()  # on the CPU .numpy() is a view of a reused buffer
            snaps.append(field[:, :, 0, :] if su.ndim == 2 else field)
            snap_t.append(n * dt)

    data, kept = loop.run(su, guard, progress, snapshot if snapshot_every else None)
    return ForwardResult(
        receiver_amplitudes=loop.traces(data[0], su.nt, isinstance(velocity, wp.array), kept),
        dt=float(dt),
        snapshots=np.stack(snaps) if snaps else None,
        snapshot_times=np.asarray(snap_t) if snaps else None,
    )


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

    return sweep.choose_segment(nt, step, total, memory_budget, segment_length)


def gradient(velocity, dx, dt, source_amplitudes, source_locations, receiver_locations, observed=None, *,
             misfit="l2", wrt=("velocity",), parameterization=None, order=4, pml_width=None, pml_reflection=None,
             pml_frequency=None, pml_velocity=None, free_surface=False, device="cpu", precision="float32",
             memory_budget=None, segment_length=None, adjoint="hand", illumination=False, weights=None,
             progress=False) -> GradientResult:  # fmt: skip
    """Misfit between simulated and observed data and its gradient for a batch of shots.

    Arguments as in forward; observed (n_shots, n_receivers, nt). misfit: a name in
    misfits.MISFITS, or a callable synthetic -> (J, dJ/dsynthetic). weights (n_shots, n_receivers, nt), 0 to 1
    (mutes, windows): the named misfit of the weighted data w d against w o, its adjoint times w ("l2":
    misfits.weighted_l2). observed (and weights) given as float64 Warp arrays on the run's device, kept there by the
    caller across calls: with "l2" and adjoint="hand" the residual and the loss are formed on the device (no copy of
    the data either way) and the synthetic is returned as a Warp array there. wrt: any of "velocity",
    "source_amplitudes", "source_locations". parameterization: an object with `parameters`
    (numpy array theta) and `velocity(theta: wp.array) -> wp.array` (nz, [ny,] nx) written with Warp
    kernels; velocity is then ignored except for its shape and the gradient is returned for theta.
    memory_budget: bytes for checkpoints plus one segment's levels; segment_length pins the checkpoint
    spacing instead (at most nt, rounded up to a multiple of 6 for adjoint="hand").
    adjoint: "hand" (the hand-written adjoint time loop; on a GPU captured as CUDA graphs and kept, with
    its arrays, for the next call with the same grid, steps, shots and geometry: accel.graphs.release() frees it)
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
    device_l2 = None
    if not callable(misfit) and misfit == "l2" and adjoint == "hand" and isinstance(observed, wp.array):
        device_l2 = _device_arrays(su, observed, weights)
        loss_fn = None
    else:
        loss_fn = _host_misfit(misfit, observed, weights, dt)
    theta = None
    if parameterization is not None:
        theta = wp.array(parameterization.parameters, dtype=prop.dtype, device=prop.device, requires_grad=True)

    def model_on_tape():
        v = su.velocity if theta is None else parameterization.velocity(theta, prop.dtype, prop.device)
        return prop.pad_model(v if v.ndim == 3 else v.reshape(su.velocity.shape), requires_grad=True)

    seg, peak = plan_segments(prop, nt, memory_budget, segment_length, adjoint)
    n_seg = math.ceil(nt / seg)
    energy = wp.zeros(prop.padded, dtype=prop.dtype, device=prop.device) if illumination else None
    bar = progress_bar(total=2 * n_seg, desc="gradient segments", unit="segments", enabled=progress)
    if adjoint == "hand":
        model_tape = wp.Tape()
        with model_tape:
            vpad = model_on_tape()
        synthetic, loss, amplitudes_grad = _hand_sweep(su, vpad, seg, n_seg, loss_fn, energy, bar, device_l2)
        model_tape.backward(grads={vpad: vpad.grad})
        del model_tape  # (not tape.reset(): that zeroes the gradients it holds, ours included)
    else:
        su.velocity_map = model_on_tape

        def on_level(st, n):
            if energy is not None:
                prop.accumulate_energy(st.u, energy, 0, prop.clock, nt)

        data, loss = sweep.taped_sweep(su, seg, n_seg, lambda d: _host_loss(loss_fn, d[0]), bar, on_level)
        synthetic = data[0].astype(float)
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


def _host_loss(loss_fn, synthetic):
    """(J, (dJ/dsynthetic,)) of the misfit on the host, the synthetic in float64."""
    loss, adj = loss_fn(synthetic.astype(float))
    return loss, (adj,)


def _host_misfit(misfit, observed, weights, dt):
    """The misfit as a host function synthetic (float64) -> (J, dJ/dsynthetic)."""
    if callable(misfit):
        return misfit
    obs = common.host_array(observed)
    if weights is None:
        return lambda d: named_misfit(misfit, d, obs, dt)
    w = common.host_array(weights)
    if misfit == "l2":
        return lambda d: weighted_l2(d, obs, w, dt)

    def weighted(d):
        j, adj = named_misfit(misfit, w * d, w * obs, dt)
        return j, adj * w

    return weighted


def _device_arrays(su, observed: wp.array, weights) -> tuple:
    """(observed, weights or None) as float64 Warp arrays (n_shots, n_receivers, nt) on the run's device."""
    shape, device = (su.prop.n_shots, su.receivers.shape[1], su.nt), su.prop.device
    pairs = ((observed, "observed"), (weights, "weights"))
    return tuple(None if a is None else common.float64_on_device(a, device, name, shape) for a, name in pairs)


def _hand_sweep(su, vpad, seg: int, n_seg: int, loss_fn, energy, bar, device_l2=None):
    """The hand-written adjoint time loop (Levels in a sweep.Sweep). vpad: the padded model (requires_grad; its .grad
    gets dJ/dvpad). loss_fn: the misfit on the host, or device_l2 = (observed, weights or None) on the device for the
    (weighted) "l2" misfit. Returns (synthetic, loss, the padded source amplitudes, whose .grad is dJ/ds)."""
    prop, nt = su.prop, su.nt
    illumination = energy is not None
    key = ("gradient", *su.key()[1:], seg, n_seg, su.amplitudes.requires_grad, illumination)
    sw = sweep.kept_sweep(key, lambda: sweep.Sweep(key, Levels(su, seg, n_seg, illumination), seg, n_seg), prop.cuda)
    lv = sw.levels
    lv.refill(su, vpad)
    sw.forward_sweep(bar)
    if device_l2 is None:
        synthetic = lv.data.numpy()[:, :, :nt].astype(float)
        loss, adj = loss_fn(synthetic)
        lv.residual.assign(common.padded_samples(np.asarray(adj), seg * n_seg, prop.dtype))
    else:  # samples from nt on stay zero (zeros since allocation, and the host path writes zeros there)
        synthetic = loop.traces(lv.data, nt, True, True)
        total = wp.zeros(1, dtype=wp.float64, device=prop.device)
        obs, w = device_l2
        kernel, inputs = (l2_residual_kernel, [lv.data, obs]) if w is None else (weighted_l2_residual_kernel, [lv.data, obs, w])
        wp.launch(kernel(lv.data.dtype), dim=lv.data.shape[:2], inputs=[*inputs, nt, prop.dt, lv.residual, total], device=prop.device)
    sw.backward_sweep(bar)
    lv.collect(su, vpad, energy)
    if device_l2 is not None:  # read after the backward sweep is queued: the one wait of the call
        loss = 0.5 * float(total.numpy()[0]) * prop.dt
    return synthetic, loss, lv.amplitudes.grad


class Levels:
    """The acoustic hand-written adjoint's arrays and segment functions (what sweep.Sweep drives).

    The forward segment runs `seg` steps from levels[0] (its start state) into levels[1..seg] (u[n], psi[n],
    zeta[n] of every level); the adjoint segment steps back through them: the adjoint of u at level j in
    lam[j % 3], the sum g of the model gradient alternating between two buffers (a GPU writes an array faster than
    it updates one in place), the adjoints of psi and zeta alternating likewise; seg is a multiple of 6, so every
    segment starts with the same roles. Time indices are j + clock[0].
    """

    def __init__(self, su, seg: int, n_seg: int, illumination: bool):
        prop = su.prop
        self.su, self.seg, self.device = su, seg, prop.device
        levels = seg * n_seg
        self.levels = [prop.new_state()] + [prop.new_state(with_prev=False) for _ in range(seg)]
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
        self.side = graphs.SideStream(prop.device)

    def start(self):
        return self.levels[0].arrays()

    def end(self):
        """The state at the segment's end (u_prev, u, psi, zeta)."""
        return [self.levels[self.seg - 1].u, *self.levels[self.seg].arrays()]

    def kernels(self):
        """Every kernel the segments launch (loaded before a capture, which cannot compile)."""
        prop, k = self.su.prop, self.su.prop.k
        out = [k.step, k.pre_step, prop.core_kernel(), *(k.psi[a][0] for a in range(3)), k.record, k.record_fixed, k.inject, k.inject_fixed]
        return out + [k.adjoint_step, k.pre_adjoint, k.post_adjoint, prop.adjoint_kernel(), *k.psi_adjoint, k.energy]

    def forward_segment(self):
        su, prop, lv = self.su, self.su.prop, self.levels
        st = lv[0]
        for j in range(self.seg):
            st = prop.step(st, self.vpad, out=lv[j + 1], record=(self.data, su.receiver_op, j, self.clock))
            prop.inject(st.u, self.vpad, self.amplitudes, su.source_op, j, self.clock)

    def adjoint_segment(self):
        su, prop, lv = self.su, self.su.prop, self.levels
        for j in reversed(range(self.seg)):
            lam, adj, out = (self.lam[(j + d) % 3] for d in (1, 2, 0))
            psi = (self.adj_psi[(j + 1) % 2], self.adj_psi[j % 2])
            zeta = (self.adj_zeta[(j + 1) % 2], self.adj_zeta[j % 2])
            with self.side():  # beside the step's launches, which neither write lam nor read what it adds into
                prop.inject_adjoint(lam, self.vpad, self.amplitudes, su.source_op, j, self.clock)
            prop.adjoint_step(lv[j], lv[j + 1], self.vpad, self.w, lam, adj, self.g[(j + 1) % 2], psi, zeta,
                              residual=(self.residual, su.receiver_op, j, self.clock), out=(out, self.g[j % 2]))  # fmt: skip
            self.side.join()  # before lam's array is written again, two steps on
            if self.energy is not None:
                prop.accumulate_energy(lv[j].u, self.energy, j, self.clock, su.nt)

    def finish(self):
        pass

    def refill(self, su, vpad):
        """Copy su's inputs (model, CPML coefficients, operators, source samples) into these arrays and zero the
        state, data and adjoints."""
        mine = self.su
        prop = mine.prop
        for a, b in zip(mine.inputs(), su.inputs()):
            if a.ptr != b.ptr:  # the same arrays where su is the setup these levels were made from
                wp.copy(a, b)
        wp.copy(self.amplitudes[:, :, : su.amplitudes.shape[2]], su.amplitudes)  # the padding past nt stays zero
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


def born(velocity, dvelocity, dx, dt, source_amplitudes, source_locations, receiver_locations, **kw) -> np.ndarray:
    """Linearised (Born, tangent-linear) data F dv: the exact derivative of the simulated receiver
    data along the model perturbation dvelocity (m/s, same shape as velocity). Returns
    (n_shots, n_receivers, nt). Keyword arguments as in forward (no snapshots)."""
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
