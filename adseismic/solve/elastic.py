"""2D isotropic elastic propagation and its exact, memory-bounded gradients (kernels/elastic/).

Conventions (as adseismic.solve.acoustic; z depth, positive down):
- vp, vs (m/s), rho (kg/m^3): (nz, nx) NumPy or Warp arrays (a Warp array of the run's precision, e.g. already
  on the GPU, is copied there without visiting the host) on a regular grid of spacing dx (m); node (0, 0) at 0 m.
  vs = 0 is a fluid; 0 <= vs <= vp / sqrt(2) (lambda >= 0).
- locations: metres (z, x), shape (n_shots, n_per_shot, 2).
- source_amplitudes (n_shots, n_src, nt): the source time function s(t) at t_k = k dt, and
  source_components its direction/mechanism per source:
    "force":     (n_shots, n_src, 2) = (f_z, f_x); line force F(t) = s(t) (f_z, f_x), N per metre of line;
    "moment":    (n_shots, n_src, 3) = (Mxx, Mzz, Mxz); moment tensor M_ij(t) = m_ij s(t), N m per metre
                 (equivalent body force -div(M delta)); s must start at 0;
    "explosive": the moment tensor (1, 1, 0) s(t) (isotropic).
- receiver data: vx, vz (m/s) sample n at t = (n - 1/2) dt, pressure -(sxx + szz)/2 (Pa) at t = n dt
  (leapfrog staggering in time, see kernels/elastic/propagator.py), each (n_shots, n_receivers, nt).

The time loop is solve/loop.py's and the checkpointed gradient solve/sweep.py's, as for every physics; this module
says how the elastic kernels map onto them (ElasticSetup) and holds the hand-written adjoint's arrays and segment
functions (Levels). Gradients (gradient_elastic) are the discrete adjoint: by default the hand-written adjoint kernels
in an explicit time loop (CUDA graphs on a GPU, kept for the next call with the same geometry) with Warp
differentiating only the materials (vp, vs, rho -> MATERIALS) on a small tape; adjoint="warp" differentiates every
kernel under wp.Tape (the reference).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from adseismic.accel import graphs
from adseismic.accel.reductions import value_ranges
from adseismic.kernels.elastic import DESCRIPTION, MATERIALS, PSI, Elastic, shear_ratio
from adseismic.kernels.numerics import check_order
from adseismic.runs import progress_bar
from adseismic.solve import common, loop, sweep
from adseismic.solve.misfits import misfit as named_misfit
from adseismic.solve.staggered import COMPONENTS, StaggeredSetup, l2_on_device, observed_on_device

SOURCE_TYPES = {"force": 2, "moment": 3, "explosive": 3}
WRT = ("vp", "vs", "rho", "source_amplitudes", "source_components", "source_locations")


@dataclass
class ElasticResult:
    """Output of :func:`forward_elastic`: vx, vz (m/s) and pressure (Pa), each (n_shots, n_receivers, nt) in the
    simulation's precision: Warp arrays on the model's device where vp was given as a Warp array (copies of E2000's
    three 2 MB records to fresh host memory, widened to float64, were a good part of a 69 ms call), else NumPy
    arrays; dt (s)."""

    vx: np.ndarray | wp.array
    vz: np.ndarray | wp.array
    pressure: np.ndarray | wp.array
    dt: float


@dataclass
class ElasticGradient:
    """Misfit and its gradients: vp, vs (per m/s) and rho (per kg/m^3) (nz, nx), each a Warp array on the model's
    device where that model was given as a Warp array, else a NumPy array; source_amplitudes (n_shots, n_src, nt);
    source_components (n_shots, n_src, 2 or 3); source_locations (n_shots, n_src, 2) per metre; None where not
    requested; in the simulation's precision. synthetic: {"vx", "vz", "pressure"} data (n_shots, n_receivers, nt) in the
    simulation's precision, Warp arrays on the device where vp was given as a Warp array, else NumPy. segment_length
    (steps) and n_segments of the checkpointed sweep, peak_bytes_estimate its planned memory (plan_segments)."""

    loss: float
    synthetic: dict
    vp: np.ndarray | None = None
    vs: np.ndarray | None = None
    rho: np.ndarray | None = None
    source_amplitudes: np.ndarray | None = None
    source_components: np.ndarray | None = None
    source_locations: np.ndarray | None = None
    segment_length: int = 0
    n_segments: int = 0
    peak_bytes_estimate: int = 0


def check_model_values(vp, vs, rho, tolerance=1e-12):
    """Raise ValueError at the first bad value of the NumPy models (nz, nx): each finite, vp, rho > 0,
    0 <= vs <= vp / sqrt(2) (1 + tolerance) (lambda >= 0)."""
    for name, a, ok in (("vp", vp, vp > 0), ("rho", rho, rho > 0), ("vs", vs, vs >= 0)):
        bad = ~np.isfinite(a) | ~ok
        if bad.any():
            raise ValueError(f"{name} has {int(bad.sum())} non-finite or out-of-range values (first at index {tuple(int(i) for i in np.argwhere(bad)[0])}); vp, rho > 0 and vs >= 0")
    neg = (vs / vp).astype(float) > (1.0 + tolerance) / math.sqrt(2.0)  # as the device check forms it
    if neg.any():
        i = tuple(int(k) for k in np.argwhere(neg)[0])
        raise ValueError(f"vs > vp / sqrt(2) at index {i} (vp {vp[i]:g}, vs {vs[i]:g} m/s) gives a negative Lame lambda; use vs <= {vp[i] / math.sqrt(2):g} m/s")


def upload_models(vp, vs, rho, dtype, device: str, requires_grad=()):
    """vp, vs (m/s), rho (kg/m^3): NumPy or Warp arrays (nz, nx), as new Warp arrays of dtype on device, checked
    (check_model_values). A Warp array of dtype is copied device to device, so a model already on the GPU never
    visits the host: on a GPU the checks run there (Warp reductions, in dtype, vs / vp with a tolerance of 4 dtype
    epsilons) and the host only locates a bad value; on the CPU they run in float64. requires_grad: the names
    (of "vp", "vs", "rho") to differentiate. Returns ((vp, vs, rho), max(vp))."""
    given = {"vp": vp, "vs": vs, "rho": rho}
    common.model_shape(given)
    arrays, host, _ = common.upload_models(given, dtype, device, requires_grad)
    if not wp.get_device(device).is_cuda:
        host = [a.numpy().astype(float) if h is None else h for a, h in zip(arrays, host)]
        check_model_values(*host)
        return arrays, float(host[0].max())
    ratio = wp.empty(arrays[0].size, dtype=dtype, device=device)
    wp.launch(shear_ratio(dtype), dim=ratio.size, inputs=[arrays[0].flatten(), arrays[1].flatten(), ratio], device=device)
    (vp_min, vp_max, vp_bad), (vs_min, _, vs_bad), (rho_min, _, rho_bad), (_, ratio_max, _) = value_ranges([*arrays, ratio])
    tolerance = max(1e-12, 4.0 * float(np.finfo(wp.dtype_to_numpy(dtype)).eps))
    ok = not (vp_bad or vs_bad or rho_bad) and vp_min > 0 and rho_min > 0 and vs_min >= 0
    if not (ok and ratio_max <= (1.0 + tolerance) / math.sqrt(2.0)):
        check_model_values(*(a.numpy() for a in arrays), tolerance)
        raise ValueError("vp, vs, rho fail the value checks (non-finite, vp or rho <= 0, vs < 0, or vs > vp / sqrt(2))")
    return tuple(arrays), vp_max


def check_elastic_inputs(shape, vmax, dx, dt, source_amplitudes, source_locations, receiver_locations, order, source_type,
                         source_components):  # fmt: skip
    """Shape and stability checks of everything but the model values (upload_models); shape: the models' (nz, nx),
    vmax: max(vp) (m/s). Returns the components (n_shots, n_src, 2|3). Raises ValueError."""
    check_order(order)
    if source_type not in SOURCE_TYPES:
        raise ValueError(f"source_type {source_type!r} is not one of {sorted(SOURCE_TYPES)}")
    amp = np.asarray(source_amplitudes)
    common.check_geometry(shape, dx, amp, source_locations, receiver_locations, "z, x")
    nc = SOURCE_TYPES[source_type]
    if source_type == "explosive":
        comp = np.broadcast_to(np.array([1.0, 1.0, 0.0]), (*amp.shape[:2], 3))
    elif source_components is None:
        if source_type == "moment":
            raise ValueError("source_type 'moment' needs source_components (n_shots, n_src, 3) = (Mxx, Mzz, Mxz)")
        comp = np.broadcast_to(np.array([1.0, 0.0]), (*amp.shape[:2], 2))  # vertical force
    else:
        comp = np.asarray(source_components, dtype=float)
        if comp.shape != (*amp.shape[:2], nc):
            raise ValueError(f"source_components must be (n_shots, n_src, {nc}) for source_type {source_type!r}; got {comp.shape}")
    common.check_courant(DESCRIPTION, order, 2, vmax, dx, dt)
    return np.ascontiguousarray(comp)


@dataclass
class ElasticSetup(StaggeredSetup):
    """Device-side inputs of one elastic simulation (see :func:`setup_elastic`) and the verbs of the shared solver
    (solve/loop.py). models: physical (vp, vs, rho) wp.array2d; source_op: the sources' fixed operator (None where
    their locations are differentiated); receiver_op: the receivers' (Elastic.operator)."""

    prop: Elastic
    nt: int
    kind: str  # "force" or "moment"
    models: tuple
    amplitudes: wp.array
    components: wp.array
    sources: wp.array
    receivers: wp.array
    receiver_op: tuple
    source_op: tuple | None = None

    physics = DESCRIPTION

    def model(self, on_tape=False, out=None):
        """The padded model's MATERIALS (kernels/elastic), into out (an earlier call's) if given; differentiable under a
        tape."""
        return self.prop.materials(*(self.prop.pad_model(m, on_tape) for m in self.models), requires_grad=on_tape, out=out)

    def sources_of(self, amplitudes, fixed=True):
        """The step's sources: samples `amplitudes`, through the fixed operator (no Kaiser-sinc weights evaluated each
        step) where fixed and the locations are not differentiated."""
        where = self.source_op if fixed and self.source_op is not None else self.sources
        return (self.kind, amplitudes, self.components, where)

    def fields(self, st):
        return (st.vx, st.vz)

    def key(self):
        p = self.prop
        return ("elastic", p.k, p.layout, p.shape, p.padded, p.dx, p.dt, p.n_shots, p.device, self.nt, self.amplitudes.shape,
                self.receivers.shape, self.kind)  # fmt: skip

    def loop_kernels(self):
        k = self.prop.k
        return [k.velocity, k.stress, *self.prop.update_kernels(), k.record, k.inject_force_op if self.kind == "force" else k.inject_moment_op]

    def inputs(self, src):
        """The arrays a kept loop or sweep copies from a later setup: CPML coefficients, the receivers' operator, the
        sources' components and locations and the fixed operator in src (sources_of)."""
        out = [getattr(ax, f) for ax in self.prop.axes for f in ("a", "b", "ah", "bh")]
        out += [*self.receiver_op, self.components, self.sources]
        return out + (list(src[3]) if isinstance(src[3], tuple) else [])


def setup_elastic(vp, vs, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, *, source_type="force",
                  source_components=None, order=4, pml_width=None, pml_reflection=None, pml_frequency=None,
                  pml_velocity=None, free_surface=False, device="cpu", precision="float32", requires_grad=()) -> ElasticSetup:  # fmt: skip
    """Validate the inputs and move them to the device (vp, vs, rho: NumPy or Warp arrays, see upload_models);
    requires_grad names the arrays (WRT) to differentiate."""
    amp = np.asarray(source_amplitudes, dtype=float)
    dtype = common.precision_dtype(precision)
    device = common.resolve_device(device)
    models, vmax = upload_models(vp, vs, rho, dtype, device, requires_grad)
    comp = check_elastic_inputs(models[0].shape, vmax, dx, dt, amp, source_locations, receiver_locations, order, source_type, source_components)
    pml = common.pml_settings(order, pml_width, pml_reflection, pml_frequency, pml_velocity, amp, dt, vmax)
    prop = Elastic(models[0].shape, dx, dt, order, amp.shape[0], *pml, free_surface=free_surface, dtype=dtype, device=device)

    def put(x, name):
        return wp.array(np.ascontiguousarray(x, dtype=float), dtype=dtype, device=prop.device, requires_grad=name in requires_grad)

    kind = "force" if source_type == "force" else "moment"
    receivers, sources = put(receiver_locations, "receiver_locations"), put(source_locations, "source_locations")
    return ElasticSetup(prop, amp.shape[2], kind, models, put(amp, "source_amplitudes"), put(comp, "source_components"), sources, receivers,
                        prop.operator(receivers), None if sources.requires_grad else prop.operator(sources))  # fmt: skip


def forward_elastic(vp, vs, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, *, source_type="force",
                    source_components=None, order=4, pml_width=None, pml_reflection=None, pml_frequency=None,
                    pml_velocity=None, free_surface=False, device="cpu", precision="float32", check_every=25,
                    progress=False) -> ElasticResult:  # fmt: skip
    """Simulate the 2D elastic wave equation for all shots at once (conventions: module docstring).

    vp, vs (m/s), rho (kg/m^3): (nz, nx) NumPy or Warp arrays; dx m; dt s; source_amplitudes (n_shots, n_src, nt);
    source/receiver_locations (n_shots, n, 2) metres (z, x); source_type "force", "moment" or "explosive" with
    source_components (n_shots, n_src, 2 or 3). Returns vx, vz (m/s) and pressure (Pa), each (n_shots, n_receivers, nt).
    order 2, 4 or 8; pml_width cells (default 20); pml_reflection target; pml_frequency CPML alpha
    frequency (Hz, default the sources' dominant frequency); pml_velocity CPML reference speed (m/s, default
    max(vp)); free_surface: stress-free top boundary at z = 0. Raises ValueError on bad input or an
    unstable dt, PropagationError if the run blows up.
    """
    su = setup_elastic(vp, vs, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, source_type=source_type,
                       source_components=source_components, order=order, pml_width=pml_width, pml_reflection=pml_reflection,
                       pml_frequency=pml_frequency, pml_velocity=pml_velocity, free_surface=free_surface, device=device,
                       precision=precision)  # fmt: skip
    guard = common.BlowupGuard(su.prop, DESCRIPTION, su.fields, common.source_end(source_amplitudes, lag=2, rate=True), check_every, "v")
    data, kept = loop.run(su, guard, progress)
    return ElasticResult(*(loop.traces(d, su.nt, isinstance(vp, wp.array), kept) for d in data), dt=float(dt))


def plan_segments(prop, nt: int, memory_budget: float | None = None, segment_length: int | None = None, adjoint: str = "hand"):
    """(segment_length, estimated peak bytes) of the checkpointed sweep.

    memory_budget (bytes) caps the checkpoints (States) plus one segment's levels (and, for adjoint="hand", the
    sweep's fixed arrays); None picks the memory minimum (~sqrt(nt) steps); segment_length (at most nt) pins the
    length instead. The hand-written sweep keeps a State per level (its last segment runs past nt into zero sources
    and residuals); Warp's tape keeps each level's adjoint too.
    """
    item = 4 if prop.dtype == wp.float32 else 8
    fields, model = prop.n_shots * math.prod(prop.padded), math.prod(prop.padded)
    state = item * (5 * fields + sum(math.prod(prop.psi_shape(k)) for k in PSI))
    hand = adjoint == "hand"
    # hand: the adjoint State, four scratch fields, MATERIALS and their adjoints (sweep and model tape), padded models
    fixed = state + item * (4 * fields + 33 * model) if hand else 0

    def total(seg):
        n_seg = math.ceil(nt / seg)
        if hand:  # no checkpoint of the first and the last segments' starts
            return fixed + max(n_seg - 2, 0) * state + (seg + 1) * state
        return (n_seg - 1) * state + (seg + 2) * 2 * state  # taped levels and two starts, with adjoints

    return sweep.choose_segment(nt, 1, total, memory_budget, segment_length)


def gradient_elastic(vp, vs, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, observed=None, *,
                     misfit="l2", components=COMPONENTS, wrt=("vp", "vs", "rho"), source_type="force", source_components=None,
                     order=4, pml_width=None, pml_reflection=None, pml_frequency=None, pml_velocity=None,
                     free_surface=False, device="cpu", precision="float32", memory_budget=None, segment_length=None,
                     adjoint="hand", progress=False) -> ElasticGradient:  # fmt: skip
    """Misfit between simulated and observed data and its exact gradient (the discrete adjoint).

    observed: {"vx": ..., "vz": ..., "pressure": ...} arrays (n_shots, n_receivers, nt) for the names in
    `components`; misfit: a name in misfits.MISFITS (summed over components) or a callable
    synthetic dict -> (J, {name: dJ/d synthetic}). wrt: any of WRT. Memory is bounded by checkpointing
    (plan_segments): memory_budget bytes, None for the minimum (~sqrt(nt) steps per segment); segment_length
    pins the checkpoint spacing instead. adjoint: "hand" (Levels:
    the hand-written adjoints of the stencil kernels in an explicit time loop; on a GPU captured as CUDA graphs
    and kept, with its arrays, for the next call with the same grid, steps, shots and geometry: accel.graphs.release()
    frees it) or "warp" (Warp's generated adjoints of every kernel under wp.Tape, the reference the hand-written
    ones are tested against). The materials' chain rule to vp, vs, rho is Warp's in both. Other arguments as in
    forward_elastic. PML settings are treated as fixed (pin pml_velocity and pml_frequency when the model changes
    between calls).
    """
    unknown = set(wrt) - set(WRT)
    if unknown:
        raise ValueError(f"wrt: {sorted(unknown)} not among {WRT}")
    if adjoint not in ("hand", "warp"):
        raise ValueError(f"adjoint {adjoint!r} is not 'hand' or 'warp'")
    su = setup_elastic(vp, vs, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, source_type=source_type,
                       source_components=source_components, order=order, pml_width=pml_width, pml_reflection=pml_reflection,
                       pml_frequency=pml_frequency, pml_velocity=pml_velocity, free_surface=free_surface, device=device,
                       precision=precision, requires_grad=set(wrt))  # fmt: skip
    observed_l2 = None
    if callable(misfit):
        loss_fn = misfit
    elif misfit == "l2":  # residual and loss formed on the device (staggered.l2_on_device)
        loss_fn = None
        observed_l2 = {c: observed_on_device(su, observed, c) for c in components}
    else:

        def loss_fn(syn):
            total, adj = 0.0, {}
            for c in components:
                j, adj[c] = named_misfit(misfit, syn[c], np.asarray(observed[c], dtype=float), dt)
                total += j
            return total, adj

    seg, peak = plan_segments(su.prop, su.nt, memory_budget, segment_length, adjoint)
    n_seg = math.ceil(su.nt / seg)
    bar = progress_bar(total=2 * n_seg, desc="gradient segments", unit="segments", enabled=progress)
    if adjoint == "hand":
        loss, synthetic, grads = _hand_sweep(su, seg, n_seg, loss_fn, bar, observed_l2, on_device=isinstance(vp, wp.array))
    else:
        loss, synthetic, grads = _taped_sweep(su, seg, n_seg, loss_fn, bar, observed_l2)
    bar.close()
    res = ElasticGradient(loss=float(loss), synthetic=synthetic, segment_length=seg, n_segments=n_seg, peak_bytes_estimate=peak)
    models = dict(zip(("vp", "vs", "rho"), (vp, vs, rho)))
    for name in wrt:  # a model given as a Warp array keeps its gradient on its device (E2000: 3 x 16 MB not copied)
        setattr(res, name, grads[name] if isinstance(models.get(name), wp.array) else _on_host(name, grads[name], su.nt))
    return res


def _gradients(su: ElasticSetup, sources) -> dict:
    """{name in WRT: gradient as a Warp array}: vp, vs, rho from the models' .grad, the sources' from `sources` (the
    adjoints of the amplitudes (nt or more samples), the components and the locations); names without one are left out."""
    arrays = {**dict(zip(("vp", "vs", "rho"), (m.grad for m in su.models))), **dict(zip(WRT[3:], sources))}
    return {k: a for k, a in arrays.items() if a is not None}


def _on_host(name: str, a: wp.array, nt: int) -> np.ndarray:
    """A gradient copied to the host, in the simulation's precision (source amplitudes cut to nt samples)."""
    out = np.array(a.numpy())
    return out[:, :, :nt] if name == "source_amplitudes" else out


def _taped_sweep(su: ElasticSetup, seg: int, n_seg: int, loss_fn, bar, observed_l2=None):
    """Warp's generated adjoints (sweep.taped_sweep). The misfit: loss_fn on the host, or with observed_l2 the "l2"
    misfit formed as the hand-written sweep forms it (so that the two give the same loss). Returns (loss, synthetic,
    gradients)."""
    prop = su.prop

    def loss(synthetic):
        if observed_l2 is None:
            J, adj = loss_fn(dict(zip(COMPONENTS, synthetic)))
        else:
            syn = [wp.array(s, dtype=prop.dtype, device=prop.device) for s in synthetic]
            res = [wp.zeros_like(a) for a in syn]
            J = 0.5 * float(l2_on_device(syn, res, observed_l2, su.nt, prop.dt, COMPONENTS).numpy()[0]) * prop.dt
            adj = {c: r.numpy() for c, r in zip(COMPONENTS, res) if c in observed_l2}
        return J, tuple(adj.get(c) for c in COMPONENTS)

    synthetic, J = sweep.taped_sweep(su, seg, n_seg, loss, bar)
    return J, dict(zip(COMPONENTS, synthetic)), _gradients(su, [a.grad for a in (su.amplitudes, su.components, su.sources)])


def _hand_sweep(su: ElasticSetup, seg: int, n_seg: int, loss_fn, bar, observed_l2=None, on_device=False):
    """The hand-written adjoint (Levels in a sweep.Sweep, the kept one on a GPU), with MATERIALS differentiated by Warp
    on a small tape around them (its backward maps the sweep's adjoints of MATERIALS to vp, vs, rho). The misfit:
    loss_fn on the host, or with observed_l2 ({component: observed float64 device array}) the "l2" misfit on the
    device, the same residual as misfits._l2's (the data stay there; E2000's host misfit alone took 4 ms of a 180 ms
    call under a profiler). Returns (loss, synthetic as Warp arrays where on_device, else NumPy, gradients)."""
    prop = su.prop
    model_tape = wp.Tape()
    with model_tape:
        mat = su.model(on_tape=True)
    key = ("elastic_gradient", *su.key()[1:], prop.adjoint_layout, seg, n_seg, su.sources.requires_grad)
    sw = sweep.kept_sweep(key, lambda: sweep.Sweep(key, Levels(su, seg, n_seg), seg, n_seg), prop.cuda)
    lv = sw.levels
    lv.refill(su, mat)
    sw.forward_sweep(bar)
    # copied before the backward sweep records into the data again (a CPU array's numpy() is a view)
    synthetic = {c: loop.traces(d, su.nt, True, True) if on_device else np.array(d.numpy()[:, :, : su.nt]) for c, d in zip(COMPONENTS, lv.data)}
    if observed_l2 is None:
        loss, adj = loss_fn({c: d if isinstance(d, np.ndarray) else d.numpy() for c, d in synthetic.items()})
        for c, r in zip(COMPONENTS, lv.residual):
            if c in adj:
                r.assign(common.padded_samples(np.asarray(adj[c], dtype=float), seg * n_seg, prop.dtype))
    else:
        total = l2_on_device(lv.data, lv.residual, observed_l2, su.nt, prop.dt, COMPONENTS)
    sw.backward_sweep(bar)
    model_tape.backward(grads=dict(zip(mat[: len(lv.adj_mat)], lv.adj_mat)))
    del model_tape  # (not tape.reset(): that zeroes the gradients it holds, ours included)
    if observed_l2 is not None:  # read after the backward sweep is queued
        loss = 0.5 * float(total.numpy()[0]) * prop.dt
    return loss, synthetic, _gradients(su, lv.adj_sources)


class Levels:
    """The elastic hand-written adjoint's arrays and segment functions (what sweep.Sweep drives).

    The forward segment runs `seg` steps from levels[0] (its start State) out of place into levels[1..seg]; the
    adjoint segment steps back through them, taking the adjoint State `adj` from level j + 1's to level j's in place
    (Elastic.adjoint_step) and on to the previous segment. The adjoints of MATERIALS (adj_mat) and of the sources'
    amplitudes, components and locations (adj_sources) accumulate over all steps. Time indices are j + clock[0].
    data and residual: (vx, vz, pressure) arrays (S, n_rec, n_seg * seg).
    """

    def __init__(self, su: ElasticSetup, seg: int, n_seg: int):
        prop = su.prop
        self.su, self.seg, self.device = su, seg, prop.device
        levels = seg * n_seg

        def zeros(shape):
            return wp.zeros(shape, dtype=prop.dtype, device=prop.device)

        self.levels = [prop.new_state() for _ in range(seg + 1)]
        self.mat = tuple(zeros(prop.padded) for _ in MATERIALS)
        self.adj_mat = tuple(zeros(prop.padded) for _ in MATERIALS[:-1])  # b is the lean core's alone (not differentiated)
        self.amplitudes = zeros((*su.amplitudes.shape[:2], levels + su.lookahead))
        # the sources' fixed operator unless their locations are differentiated (the generated adjoint of the injection
        # at its locations evaluates the operator and its derivative every step: E2000 23 us a step)
        self.sources = su.sources_of(self.amplitudes, fixed=True)
        self.adj_sources = tuple(zeros(a.shape) for a in (self.amplitudes, su.components, su.sources))
        self.data = su.new_data(levels)
        self.residual = su.new_data(levels)
        self.adj = prop.new_state()
        self.scratch = [zeros((prop.n_shots, *prop.padded)) for _ in range(4)]  # their halo stays zero
        self.clock = wp.zeros(1, dtype=wp.int32, device=prop.device)
        self.side = graphs.SideStream(prop.device)
        # a GPU runs a force's adjoint beside the velocity half step's (Elastic.adjoint_step), its buoyancies' adjoints
        # kept apart until the backward sweep ends
        self.source_buoyancy = tuple(zeros(prop.padded) for _ in range(2)) if prop.cuda and su.kind == "force" else ()
        self.beside = (self.side, self.source_buoyancy) if self.source_buoyancy else None

    def start(self):
        return self.levels[0].arrays()

    def end(self):
        return self.levels[self.seg].arrays()

    def kernels(self):
        """Every kernel the segments launch (loaded before a capture, which cannot compile)."""
        su = self.su
        prop, k = su.prop, su.prop.k
        updates = prop.update_kernels() if prop.has_core else (k.velocity, k.stress)
        inject = {"force": (k.inject_force, k.inject_force_op), "moment": (k.inject_moment, k.inject_moment_op)}[su.kind]
        return (*updates, k.record, k.record_adjoint, inject[not su.sources.requires_grad], *prop.adjoint_kernels())

    def forward_segment(self):
        su, lv = self.su, self.levels
        for j in range(self.seg):
            with self.side():  # beside the step, which writes level j + 1 only (E2000: 5 us a step)
                su.prop.record(lv[j], self.data, su.receiver_op, j, self.clock)
            su.prop.step(lv[j], self.mat, self.sources, j, out=lv[j + 1], clock=self.clock)
        self.side.join()

    def adjoint_segment(self):
        su, lv = self.su, self.levels
        for j in reversed(range(self.seg)):
            su.prop.adjoint_step(lv[j], lv[j + 1], self.mat, self.adj, self.adj_mat, self.sources, self.adj_sources, self.scratch, j,
                                 self.clock, self.beside)  # fmt: skip
            su.prop.record_adjoint(self.adj, self.residual, su.receiver_op, j, self.clock)

    def finish(self):
        for g, b in zip(self.adj_mat, self.source_buoyancy):
            wp.launch(self.su.prop.k.add_into, dim=g.shape, inputs=[g, b], device=g.device)

    def refill(self, su: ElasticSetup, mat):
        """Copy su's inputs (CPML coefficients, MATERIALS mat, operators, source samples) into these arrays and zero the
        start State, data, residuals and adjoints."""
        for a, b in [*zip(self.su.inputs(self.sources), su.inputs(su.sources_of(self.amplitudes, fixed=True))), *zip(self.mat, mat)]:
            if a.ptr != b.ptr:  # (self.su is su on a sweep's first call)
                wp.copy(a, b)
        self.amplitudes.assign(common.padded_samples(su.amplitudes.numpy(), self.amplitudes.shape[2], su.prop.dtype))
        for a in (*self.levels[0].arrays(), *self.data, *self.residual, *self.adj.arrays(), *self.adj_mat,
                  *self.adj_sources, *self.source_buoyancy):  # fmt: skip
            a.zero_()
