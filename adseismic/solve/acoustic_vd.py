"""Variable-density acoustic propagation in 2D and 3D (kernels/acoustic_vd/) and its exact, checkpointed gradients.

Conventions (as adseismic.solve.viscoacoustic and adseismic.solve.elastic3d; z depth, positive down):
- vp (m/s), rho (kg/m^3): (nz, nx) or (nz, ny, nx) arrays on a regular grid of spacing dx (m), node 0 at 0 m.
- locations: metres (z, x) or (z, y, x), shape (n_shots, n, ndim).
- source_amplitudes (n_shots, n_src, nt): S(t_k), the explosive source's isotropic moment, N m per metre of line in
  2D and N m in 3D (dp/dt gains dS/dt delta(x - x_s): the convention of forward_viscoacoustic and of forward_elastic /
  forward_elastic3d's explosive source, so p in Pa is theirs for the same S).
- receiver data: pressure p (Pa) sample n at t = n dt; vx, [vy,] vz (m/s) at t = (n - 1/2) dt; each (n_shots, n_rec,
  nt).

The time loop is solve/loop.py's; the gradient, in checkpointed segments, solve/sweep.py's Sweep of the hand-written
adjoint step (2D: Levels, AcousticVD.adjoint_step) or its taped sweep (Warp's generated adjoints of the kernels; 3D,
and the 2D reference); this module maps the kernels onto them (AcousticVDSetup).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from adseismic.kernels.acoustic_vd import DESCRIPTION, MATERIALS, PSI, VELOCITIES, AcousticVD, Materials, State
from adseismic.accel import graphs
from adseismic.kernels.numerics import check_order
from adseismic.runs import progress_bar
from adseismic.solve import common, loop, sweep
from adseismic.solve.elastic import check_model_values
from adseismic.solve.staggered import StaggeredSetup, l2_on_device, misfit_function, observed_on_device, taped_gradient

MODELS = ("vp", "rho")
WRT = (*MODELS, "source_amplitudes")
# vp, rho finite and > 0 (elastic's check with vs = 0); CFL speed vp; on a GPU clear where their ranges show it
MODEL_CHECKS = common.ModelChecks(
    lambda vp, rho: check_model_values(vp, np.zeros_like(vp), rho),
    lambda vp, rho: vp,
    lambda ranges, exact: all(bad == 0 and lo > 0 for lo, _, bad in ranges),
)


@dataclass
class AcousticVDResult:
    """Output of :func:`forward_acoustic_vd`: pressure (Pa), vx, vz, vy (m/s; vy None in 2D), each (n_shots,
    n_receivers, nt) in the simulation's precision: Warp arrays on the model's device where vp was given as a Warp
    array (as forward_elastic's), else NumPy arrays; dt (s)."""

    pressure: np.ndarray | wp.array
    vx: np.ndarray | wp.array
    vz: np.ndarray | wp.array
    vy: np.ndarray | wp.array | None
    dt: float


@dataclass
class AcousticVDGradient:
    """Misfit and its gradients: vp (per m/s), rho (per kg/m^3) (nz, [ny,] nx), source_amplitudes (n_shots, n_src,
    nt); None where not requested; the 2D hand-written adjoint leaves vp's and rho's as Warp arrays on the device
    where they were given as Warp arrays (forward_elastic's gradient's convention), and the synthetic data there too.
    synthetic: {"vx", ["vy",] "vz", "pressure"} data (n_shots, n_receivers, nt);
    segment_length (steps) and n_segments of the checkpointed sweep, peak_bytes_estimate its planned memory."""

    loss: float
    synthetic: dict
    vp: np.ndarray | None = None
    rho: np.ndarray | None = None
    source_amplitudes: np.ndarray | None = None
    segment_length: int = 0
    n_segments: int = 0
    peak_bytes_estimate: int = 0


@dataclass
class AcousticVDSetup(StaggeredSetup):
    """Device-side inputs of one variable-density acoustic simulation (see :func:`setup_acoustic_vd`) and the verbs of
    the shared solver (solve/loop.py). models: physical (vp, rho) wp.arrays; source_op, receiver_op: the sources' and
    receivers' fixed operators (AcousticVD.source_operator: with the tiled step's plan of the sources' terms;
    AcousticVD.operator); data_components: the velocities then "pressure"."""

    prop: AcousticVD
    nt: int
    models: tuple
    amplitudes: wp.array
    receivers: wp.array
    source_op: tuple
    receiver_op: tuple
    data_components: tuple

    physics = DESCRIPTION

    def fields(self, st):
        return (st.p,)

    def loop_kernels(self):
        k = self.prop.k
        return [k.velocity, k.pressure, k.inject, k.record]

    # A captured loop of the 2D tiled step steps in place and records in the step's own launches (AcousticVD.step's
    # record=), not round two states with the record beside the step: a VD1000 step with its source 16.2 against 20.2 us
    # on an H200 (docs/benchmarks.md, "acoustic_vd's captured loop in place").
    @property
    def period(self):
        return 1 if self.prop.tiles is not None else 2

    def spare(self, st):
        return None if self.prop.tiles is not None else super().spare(st)

    def out_state(self, st, spare):
        return None if self.prop.tiles is not None else spare

    def freed(self, st):
        return None if self.prop.tiles is not None else st

    def advance(self, st, mat, src, data, k, n, out, clock, side=None):
        if side is not None and self.prop.tiles is not None:  # in a captured loop
            return self.prop.step(st, mat, src, n, out, clock, record=(data, self.receiver_op, k))
        return super().advance(st, mat, src, data, k, n, out, clock, side)


def setup_acoustic_vd(vp, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, *, order=4, pml_width=None,
                      pml_reflection=None, pml_frequency=None, pml_velocity=None, free_surface=False, device="cpu",
                      precision="float32", requires_grad=()) -> AcousticVDSetup:  # fmt: skip
    """Validate the inputs (ValueError naming the argument) and move them to the device; requires_grad names the
    arrays (WRT) to differentiate."""
    check_order(order)
    dtype = common.precision_dtype(precision)
    device = common.resolve_device(device)
    given = dict(zip(MODELS, (vp, rho)))
    shape = common.model_shape(given, DESCRIPTION.ndims)
    models, vmax = common.checked_models(given, MODEL_CHECKS, dtype, device, requires_grad)
    ndim = len(shape)
    amp = np.asarray(source_amplitudes, dtype=float)
    common.check_geometry(shape, dx, amp, source_locations, receiver_locations, "z, x" if ndim == 2 else "z, y, x")
    common.check_courant(DESCRIPTION, order, ndim, vmax, dx, dt)
    pml = common.pml_settings(order, pml_width, pml_reflection, pml_frequency, pml_velocity, amp, dt, vmax)
    prop = AcousticVD(shape, dx, dt, order, amp.shape[0], *pml, free_surface=free_surface, dtype=dtype, device=device)

    def put(x, name):
        return wp.array(np.ascontiguousarray(x, dtype=float), dtype=dtype, device=prop.device, requires_grad=name in requires_grad)

    receivers = put(receiver_locations, "")
    sources = prop.source_operator(put(source_locations, ""))
    return AcousticVDSetup(prop, amp.shape[2], models, put(amp, "source_amplitudes"), receivers, sources, prop.operator(receivers),
                           (*VELOCITIES[ndim], "pressure"))  # fmt: skip


def forward_acoustic_vd(vp, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, *, order=4, pml_width=None,
                        pml_reflection=None, pml_frequency=None, pml_velocity=None, free_surface=False, device="cpu",
                        precision="float32", check_every=25, progress=False) -> AcousticVDResult:  # fmt: skip
    """Simulate the variable-density acoustic wave equation (2D or 3D, from vp's shape) for all shots at once
    (conventions: module docstring).

    vp (m/s), rho (kg/m^3): (nz, nx) or (nz, ny, nx); dx m; dt s; source_amplitudes (n_shots, n_src, nt) N m/m (2D)
    or N m (3D); source/receiver_locations (n_shots, n, ndim) metres (z, [y,] x); order 2, 4 or 8; PML settings as
    forward_elastic's; free_surface: p = 0 at z = 0. Returns pressure (Pa), vx, vz and in 3D vy (m/s), each
    (n_shots, n_receivers, nt), on the device where vp is a Warp array (AcousticVDResult). Raises ValueError on bad
    input or a dt above the CFL limit, PropagationError if the run blows up."""
    su = setup_acoustic_vd(vp, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, order=order, pml_width=pml_width,
                           pml_reflection=pml_reflection, pml_frequency=pml_frequency, pml_velocity=pml_velocity,
                           free_surface=free_surface, device=device, precision=precision)  # fmt: skip
    guard = common.BlowupGuard(su.prop, DESCRIPTION, su.fields, common.source_end(source_amplitudes, lag=2, rate=True), check_every, "p")
    data, kept = loop.run(su, guard, progress)
    out = {c: loop.traces(d, su.nt, isinstance(vp, wp.array), kept) for c, d in zip(su.data_components, data)}
    return AcousticVDResult(pressure=out["pressure"], vx=out["vx"], vz=out["vz"], vy=out.get("vy"), dt=float(dt))


def gradient_acoustic_vd(vp, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, observed=None, *, misfit="l2",
                         components=("pressure",), wrt=MODELS, order=4, pml_width=None, pml_reflection=None, pml_frequency=None,
                         pml_velocity=None, free_surface=False, device="cpu", precision="float32", memory_budget=None,
                         segment_length=None, adjoint=None, progress=False) -> AcousticVDGradient:  # fmt: skip
    """Misfit between simulated and observed data and its exact gradient (the discrete adjoint, through checkpointed
    segments).

    observed: {component: (n_shots, n_receivers, nt)} for the names in `components` (vx, [vy,] vz, pressure);
    misfit: a name in misfits.MISFITS (summed over components) or a callable synthetic dict -> (J, {name: dJ/d
    synthetic}); wrt: any of WRT. memory_budget (bytes; None: the minimum, ~sqrt(nt) steps a segment) or
    segment_length (steps; rounded up to even with the hand-written adjoint) sets the segments. adjoint: "hand" (2D:
    the hand-written adjoint step in sweep.Sweep, on a GPU captured as CUDA graphs and kept with its arrays for the
    next call with the same grid, steps, shots and geometry), "warp" (Warp's generated adjoints under wp.Tape,
    sweep.taped_sweep: the reference, and 3D's), None: "hand" in 2D, else "warp". The materials' chain rule to vp
    and rho is Warp's in both. Other arguments as forward_acoustic_vd's; the PML is fixed (pin pml_velocity and
    pml_frequency when the model changes between calls)."""
    unknown = set(wrt) - set(WRT)
    if unknown:
        raise ValueError(f"wrt: {sorted(unknown)} not among {WRT}")
    if adjoint not in (None, "hand", "warp"):
        raise ValueError(f"adjoint {adjoint!r} is not 'hand', 'warp' or None")
    if adjoint == "hand" and np.ndim(vp) != 2:
        raise ValueError("adjoint='hand' is 2D only (vp of shape (nz, nx)); use adjoint='warp' or None in 3D")
    su = setup_acoustic_vd(vp, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, order=order, pml_width=pml_width,
                           pml_reflection=pml_reflection, pml_frequency=pml_frequency, pml_velocity=pml_velocity,
                           free_surface=free_surface, device=device, precision=precision, requires_grad=set(wrt))  # fmt: skip
    p = su.prop
    size = 4 if p.dtype == wp.float32 else 8
    state = size * ((1 + p.ndim) * p.n_shots * math.prod(p.padded) + sum(math.prod(p.psi_shape(k)) for k in PSI[p.ndim]))
    arrays = {**dict(zip(MODELS, su.models)), "source_amplitudes": su.amplitudes}
    if p.ndim == 3 or adjoint == "warp":
        return taped_gradient(su, state, misfit, components, observed, wrt, arrays, AcousticVDGradient, memory_budget, segment_length,
                              progress)  # fmt: skip
    loss = misfit_function(su, misfit, components, observed)
    observed_l2 = None if callable(misfit) or misfit != "l2" else {c: observed_on_device(su, observed, c) for c in components}

    def total(seg):  # the checkpoints, a segment's levels, the adjoint (fields and two sets of lambda_psi)
        return (max(math.ceil(su.nt / seg) - 2, 0) + seg + 3) * state

    seg, peak = sweep.choose_segment(su.nt, 2, total, memory_budget, segment_length)
    n_seg = math.ceil(su.nt / seg)
    bar = progress_bar(total=2 * n_seg, desc="gradient segments", unit="segments", enabled=progress)
    parts = 3 if callable(misfit) else int("pressure" in components) | 2 * bool({"vx", "vz"} & set(components))
    synthetic, J, g_amp = _hand_sweep(su, seg, n_seg, loss, bar, observed_l2, isinstance(vp, wp.array), parts)
    bar.close()
    res = AcousticVDGradient(loss=float(J), synthetic=dict(zip(su.data_components, synthetic)), segment_length=seg, n_segments=n_seg,
                             peak_bytes_estimate=peak)  # fmt: skip
    models = dict(zip(MODELS, (vp, rho)))
    for name in wrt:  # a model given as a Warp array keeps its gradient on its device (VD1000: 2 x 4 MB not copied)
        if name == "source_amplitudes":
            res.source_amplitudes = np.array(g_amp.numpy()[..., : su.nt])
        else:
            g = arrays[name].grad
            setattr(res, name, g if isinstance(models[name], wp.array) else np.array(g.numpy()))
    return res


def _hand_sweep(su: AcousticVDSetup, seg: int, n_seg: int, loss, bar, observed_l2=None, on_device=False, parts=3):
    """The hand-written adjoint (Levels in a sweep.Sweep, the kept one on a GPU), MATERIALS' chain rule to vp and rho
    Warp's on a small tape around them. The misfit: loss (misfit_function's) on the host, or with observed_l2
    ({component: observed float64 device array}) the "l2" misfit on the device (staggered.l2_on_device: no copy of the
    data, the loss read once the backward sweep is queued); parts: the residuals it may give, p's (1), the velocities'
    (2). Returns (synthetic, Warp arrays where on_device, else NumPy; J; dJ/d amplitudes (S, n_src, >= nt))."""
    prop = su.prop
    model_tape = wp.Tape()
    with model_tape:
        mat = su.model(on_tape=True)
    key = ("acoustic_vd_gradient", *su.key()[1:], seg, n_seg, parts)
    sw = sweep.kept_sweep(key, lambda: sweep.Sweep(key, Levels(su, seg, n_seg, parts), seg, n_seg), prop.cuda)
    lv = sw.levels
    lv.refill(su, mat)
    sw.forward_sweep(bar)
    # copies: the re-runs record into the data again
    synthetic = tuple(loop.traces(d, su.nt, True, True) if on_device else np.array(d.numpy()[:, :, : su.nt]) for d in lv.data)
    if observed_l2 is None:
        J, adjoints = loss(tuple(s.numpy() if on_device else s for s in synthetic))
        for r, a in zip(lv.residual, adjoints):
            if a is not None:
                r.assign(common.padded_samples(a, r.shape[2], prop.dtype))
    else:
        total = l2_on_device(lv.data, lv.residual, observed_l2, su.nt, prop.dt, su.data_components)
    sw.backward_sweep(bar)
    model_tape.backward(grads=dict(zip(mat, lv.adj_mat)))
    del model_tape  # (not tape.reset(): that zeroes the gradients it holds, ours included)
    if observed_l2 is not None:
        J = 0.5 * float(total.numpy()[0]) * prop.dt
    return synthetic, J, lv.g_amp


class Levels:
    """The 2D hand-written adjoint's arrays and segment functions (what sweep.Sweep drives).

    The forward segment steps `seg` levels from levels[0] out of place into levels[1..seg] (the tiled step,
    recording the data in its launches; in_place_segment the same steps in place on levels[0], rerun_segment without
    recording); the adjoint segment steps back through them (AcousticVD.adjoint_step): the adjoint fields in place,
    the adjoints of the CPML memory variables alternating between the two States of `adj` (seg is even, so every
    segment starts with the same roles), the materials' sums in `sums` and the amplitudes' adjoint in g_amp over all
    steps; finish turns the sums (a shot each) into adj_mat, dJ/d MATERIALS. The levels are packed
    (AcousticVD.new_state): start() and end() are one array each. Time indices are j + clock[0]. data and residual:
    (vx, vz, pressure) arrays (S, n_rec, n_seg * seg)."""

    def __init__(self, su: AcousticVDSetup, seg: int, n_seg: int, parts=3):
        prop = su.prop
        self.su, self.seg, self.device, self.parts = su, seg, prop.device, parts
        levels = seg * n_seg

        def zeros(shape):
            return wp.zeros(shape, dtype=prop.dtype, device=prop.device)

        self.levels = [prop.new_state(packed=True) for _ in range(seg + 1)]
        self.mat = Materials([zeros(prop.padded) for _ in MATERIALS[2]])
        self.amplitudes = zeros((*su.amplitudes.shape[:2], levels + su.lookahead))
        self.g_amp = zeros(self.amplitudes.shape)
        self.sources = su.sources_of(self.amplitudes)
        self.data = su.new_data(levels)
        self.residual = su.new_data(levels)
        a = prop.new_state()
        self.adj = (a, State(a.v, a.p, {k: zeros(x.shape) for k, x in a.psi.items()}))
        self.sums = Materials([zeros((prop.n_shots, *prop.padded)) for _ in range(3)])  # the image's (gbx, gbz, gk) a shot
        self.adj_mat = [zeros(prop.padded) for _ in range(3)]
        self.clock = wp.zeros(1, dtype=wp.int32, device=prop.device)
        self.side = graphs.SideStream(prop.device)

    def start(self):
        return [self.levels[0].packed]

    def end(self):
        return [self.levels[self.seg].packed]

    def kernels(self):
        """Every kernel the segments launch (loaded before a capture, which cannot compile)."""
        k = self.su.prop.k
        V = self.su.prop.tiles[0]
        return [*k.tiled[V], *k.adjoint_tiled[V], k.source_adjoint, k.record_adjoint]

    def forward_segment(self, record=True):
        su, lv = self.su, self.levels
        for j in range(self.seg):
            su.prop.step(lv[j], self.mat, self.sources, j, out=lv[j + 1], clock=self.clock,
                         record=(self.data, su.receiver_op, j) if record else None)  # fmt: skip

    def rerun_segment(self):
        self.forward_segment(record=False)

    def in_place_segment(self):
        su, st = self.su, self.levels[0]
        for j in range(self.seg):
            su.prop.step(st, self.mat, self.sources, j, clock=self.clock, record=(self.data, su.receiver_op, j))

    def adjoint_segment(self):
        su, lv = self.su, self.levels
        for j in reversed(range(self.seg)):
            su.prop.adjoint_step(lv[j], lv[j + 1], self.mat, self.adj if j % 2 == 0 else self.adj[::-1], self.sums, self.sources,
                                 self.g_amp, (*self.residual, su.receiver_op), j, self.clock, self.side, self.parts)  # fmt: skip

    def finish(self):
        prop = self.su.prop
        wp.launch(prop.k.material_adjoints, dim=prop.interior[1:], inputs=[*self.sums, *self.mat, *self.adj_mat], device=prop.device)

    def refill(self, su: AcousticVDSetup, mat):
        """Copy su's inputs (CPML coefficients, MATERIALS mat, operators, source samples) into these arrays and zero the
        start State, data, residuals and adjoints."""
        for a, b in [*zip(self.su.inputs(self.sources), su.inputs(su.sources_of(su.amplitudes))), *zip(self.mat, mat)]:
            if a.ptr != b.ptr:  # (self.su is su on a sweep's first call)
                wp.copy(a, b)
        wp.copy(self.amplitudes[:, :, : su.nt], su.amplitudes)  # the padding past nt stays zero
        for a in (*self.start(), *self.data, *self.residual, *self.adj[0].arrays(), *self.adj[1].psi.values(), *self.sums,
                  *self.adj_mat, self.g_amp):  # fmt: skip
            a.zero_()
