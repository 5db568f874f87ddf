"""Forward acoustic propagation: the small functional API on top of kernels/acoustic.py.

Conventions (shared by every public function of adseismic):
- velocity: (nz, nx) or (nz, ny, nx) array in m/s on a regular grid of spacing dx (m), axis order
  (z, [y,] x) with z depth (positive down); node (0, ..., 0) is at coordinate 0 m.
- locations: metres in the same axis order, shape (n_shots, n_per_shot, ndim).
- source_amplitudes: (n_shots, n_sources_per_shot, nt); the source term s(t) of
  (1/v^2) d2u/dt2 - laplacian(u) = s(t) delta(x - x_s), so that in a homogeneous medium
  u = s(t - r/v) / (4 pi r) in 3D (units of s: [u] m^(ndim-2)).
- receiver data: (n_shots, n_receivers_per_shot, nt) samples of u at t = n dt, n = 0..nt-1.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import warp as wp
from tqdm.auto import tqdm

from adseismic.accel import graphs
from adseismic.accel.reductions import field_stats, reduction_kernels, value_range
from adseismic.kernels.acoustic import DESCRIPTION, Acoustic, State
from adseismic.kernels.common import operator_shape
from adseismic.kernels.numerics import check_order
from adseismic.solve.common import BlowupGuard, check_courant, check_geometry, pml_settings, precision_dtype, resolve_device, source_end

log = logging.getLogger(__name__)


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
    check_geometry(shape, dx, source_amplitudes, source_locations, receiver_locations, "z, x" if ndim == 2 else "z, y, x")
    check_courant(DESCRIPTION, order, ndim, vmax, dx, dt)
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


def make_propagator(shape, dx, dt, n_shots, order, pml, free_surface, device, dtype) -> Acoustic:
    """The Acoustic launch helper for a grid of `shape` cells on a resolved device; pml: (width, reflection,
    frequency, reference speed) from pml_settings."""
    return Acoustic(shape, dx, dt, order, n_shots, *pml, free_surface=free_surface, dtype=dtype, device=device)


def velocity_3d(velocity) -> np.ndarray:
    v = np.asarray(velocity, dtype=float)
    return v[:, None, :] if v.ndim == 2 else v


@dataclass
class Setup:
    """Device-side inputs of one simulation: the launch helper and the Warp arrays it reads.

    amplitudes (S, n_src, nt); sources, receivers (S, n, 3) metres as (z, y, x); velocity (nz, ny, nx) m/s;
    source_op, receiver_op: the operators at those points (Acoustic.operator).
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


def setup(velocity, dx, dt, source_amplitudes, source_locations, receiver_locations, *, order=4, pml_width=None,
          pml_reflection=None, pml_frequency=None, pml_velocity=None, free_surface=False, device="cpu",
          precision="float32", requires_grad=()) -> Setup:  # fmt: skip
    """Validate the inputs and move them to the device; requires_grad names the arrays to differentiate
    ("velocity", "source_amplitudes", "source_locations"). velocity: NumPy or Warp array (nz, [ny,] nx)."""
    amp = np.asarray(source_amplitudes, dtype=float)
    dtype, device = precision_dtype(precision), resolve_device(device)
    vel, shape, vrange = upload_velocity(velocity, dtype, device, requires_grad="velocity" in requires_grad)
    ndim, vmax = check_inputs(shape, vrange, dx, dt, amp, source_locations, receiver_locations, order)
    pml = pml_settings(order, pml_width, pml_reflection, pml_frequency, pml_velocity, amp, dt, vmax)
    prop = make_propagator(shape, dx, dt, amp.shape[0], order, pml, free_surface, device, dtype)

    def put(x, name):
        return wp.array(x, dtype=prop.dtype, device=prop.device, requires_grad=name in requires_grad)

    su = Setup(prop, ndim, amp.shape[2], vel, put(amp, "source_amplitudes"),
               put(to_zyx(source_locations, ndim), "source_locations"), put(to_zyx(receiver_locations, ndim), "receiver_locations"))  # fmt: skip
    su.source_op = prop.operator(su.sources, differentiable="source_locations" in requires_grad)
    su.receiver_op = prop.operator(su.receivers)
    return su


def run_steps(su: Setup, st, vpad, data, steps: range, next_state=None, callback=None):
    """Record u[n] into data[:, :, n - steps.start] and advance one step, for n in steps; returns the
    state at steps.stop (or at nt - 1). next_state: callable returning the arrays of the next level
    (each level needs its own under wp.Tape); None updates the state in place. callback(state, n)
    runs at each level n before it is recorded and stepped from."""
    prop = su.prop
    for n in steps:
        if callback is not None:
            callback(st, n)
        record = (data, su.receiver_op, n - steps.start, None)
        if n == su.nt - 1:
            prop.record(st.u, *record)
            break
        st = prop.step(st, vpad, next_state() if next_state is not None else None, record=record)
        prop.inject(st.u, vpad, su.amplitudes, su.source_op, n)
    return st


ROLES = 3  # the GPU time loop's wavefield buffers: u[n+1] goes to the third (a GPU writes an array faster than it updates one in place)


def capture(su: Setup, st, vpad, data, every: int) -> graphs.Loop:
    """The untaped time loop of run_steps (record, the guard's check every `every` levels, step, inject)
    captured as a CUDA graph (graphs.capture), u[n+1] written into a third buffer (kept.spare) instead of
    over u[n-1]; data must have K * graphs samples (graphs.graph_plan with period ROLES)."""
    prop = su.prop
    K, n_graphs = graphs.graph_plan(prop.cuda, su.nt, every, ROLES)
    if data.shape[2] < K * n_graphs:
        raise ValueError(f"data has {data.shape[2]} samples; the graph replays record {K * n_graphs}")
    amplitudes = wp.array(graphs.padded_samples(su.amplitudes.numpy(), K * n_graphs, prop.dtype), dtype=prop.dtype, device=prop.device)
    spare = wp.zeros_like(st.u)
    state = [st, spare]

    def step(k, clock, stats):
        st, spare = state
        if stats is not None:
            field_stats([st.u], stats)
        nxt = prop.step(st, vpad, out=State(None, spare, st.psi, st.zeta), record=(data, su.receiver_op, k, clock))
        prop.inject(nxt.u, vpad, amplitudes, su.source_op, k, clock)
        state[:] = [nxt, st.u_prev]

    kernels = [reduction_kernels(prop.dtype)[0], prop.k.step, prop.k.pre_step, prop.core_kernel(), *(prop.k.psi[a][0] for a in range(3))]
    kernels += [prop.k.record_fixed, prop.k.record]
    kernels += [prop.k.inject_fixed if isinstance(su.source_op, tuple) else prop.k.inject]
    kept = SimpleNamespace(su=su, st=st, spare=spare, vpad=vpad, data=data, amplitudes=amplitudes)
    return graphs.capture(_graph_key(su, every), prop.device, prop.dtype, K, n_graphs, every, step, kernels, kept, su.nt)


def run_graphs(su: Setup, st, vpad, data, guard: BlowupGuard, progress=None):
    """The untaped time loop of run_steps on a CUDA device: capture, then replay (nothing kept)."""
    graphs.replay(capture(su, st, vpad, data, guard.every), su.nt, guard, progress)


def _graph_key(su: Setup, every: int) -> tuple:
    """What a captured time loop bakes in: kernels, grid, scalars, array shapes, operator kinds."""
    p = su.prop
    return ("acoustic", p.k, p.shape, p.padded, p.dx, p.dt, p.n_shots, p.device, su.nt, su.amplitudes.shape, su.receivers.shape,
            operator_shape(su.source_op), operator_shape(su.receiver_op), every)  # fmt: skip


def _kept_loop(su: Setup, every: int) -> graphs.Loop:
    """forward's time loop for su: the kept one refilled with su's inputs when the key matches, else a new
    capture (which replaces it)."""
    loop = graphs.kept(_graph_key(su, every))
    if loop is None:
        prop = su.prop
        K, n_graphs = graphs.graph_plan(prop.cuda, su.nt, every, ROLES)
        data = wp.zeros((prop.n_shots, su.receivers.shape[1], K * n_graphs), dtype=prop.dtype, device=prop.device)
        return graphs.keep(capture(su, prop.new_state(), prop.pad_model(su.velocity), data, every))
    mine = loop.kept
    prop = mine.su.prop

    def inputs(s):  # CPML coefficients (they depend on the model's maximum speed) and the operators' arrays
        ops = [a for op in (s.source_op, s.receiver_op) for a in (op if isinstance(op, tuple) else (op,))]
        return [a for ax in s.prop.axes for a in (ax.a, ax.b)] + ops

    for a, b in zip(inputs(mine.su), inputs(su)):
        wp.copy(a, b)
    mine.amplitudes.assign(graphs.padded_samples(su.amplitudes.numpy(), loop.K * loop.graphs, prop.dtype))
    prop.pad_model(su.velocity, out=mine.vpad)
    for a in (*mine.st.arrays(), mine.spare, mine.data, loop.clock):
        a.zero_()
    return loop


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
    its inputs in (graphs.release frees it).
    """
    su = setup(velocity, dx, dt, source_amplitudes, source_locations, receiver_locations, order=order, pml_width=pml_width,
               pml_reflection=pml_reflection, pml_frequency=pml_frequency, pml_velocity=pml_velocity,
               free_surface=free_surface, device=device, precision=precision)  # fmt: skip
    prop = su.prop
    guard = BlowupGuard(prop, DESCRIPTION, lambda st: [st.u], source_end(source_amplitudes), check_every)
    use_graphs = graphs.graph_plan(prop.cuda, su.nt, guard.every, ROLES)[1] > 0 and not snapshot_every
    snaps, snap_t = [], []
    o, ny = prop.origin, (prop.shape[1] if su.ndim == 3 else 1)
    phys = (slice(None), slice(o[0], o[0] + prop.shape[0]), slice(o[1], o[1] + ny), slice(o[2], o[2] + prop.shape[-1]))
    bar = tqdm(total=su.nt, desc="time steps", unit="step", disable=not progress, leave=False)

    def callback(st, n):
        guard(st, n)
        if snapshot_every and n % snapshot_every == 0:
            field = st.u.numpy()[phys].copy()  # on the CPU .numpy() is a view of a reused buffer
            snaps.append(field[:, :, 0, :] if su.ndim == 2 else field)
            snap_t.append(n * dt)
        bar.update()

    if use_graphs:
        loop = _kept_loop(su, guard.every)
        graphs.replay(loop, su.nt, guard, bar)
        data = loop.kept.data
    else:
        data = wp.zeros((prop.n_shots, su.receivers.shape[1], su.nt), dtype=prop.dtype, device=prop.device)
        run_steps(su, prop.new_state(), prop.pad_model(su.velocity), data, range(su.nt), callback=callback)
    bar.close()
    if isinstance(velocity, wp.array):  # stays on the device (S600x16's 20 MB to fresh host memory: ~12 ms of ~75)
        traces = data
        if use_graphs:  # the kept loop's buffer (K * graphs samples), overwritten by the next call
            traces = wp.empty((*data.shape[:2], su.nt), dtype=data.dtype, device=data.device)
            wp.copy(traces, data[:, :, : su.nt])
    else:
        traces = data.numpy()[:, :, : su.nt]  # no float64 copy: it cost 6.7 ms of a 72 ms S600x16 call
    return ForwardResult(
        receiver_amplitudes=traces,
        dt=float(dt),
        snapshots=np.stack(snaps) if snaps else None,
        snapshot_times=np.asarray(snap_t) if snaps else None,
    )
