"""3D isotropic elastic propagation (kernels/elastic3d/) and its exact, checkpointed gradients.

Conventions (as adseismic.solve.acoustic in 3D and adseismic.solve.elastic; z depth, positive down):
- vp, vs (m/s), rho (kg/m^3): (nz, ny, nx) arrays on a regular grid of spacing dx (m), node (0, 0, 0) at 0 m;
  vs = 0 is a fluid; 0 <= vs <= vp / sqrt(2) (lambda >= 0).
- locations: metres (z, y, x), shape (n_shots, n, 3).
- source_amplitudes (n_shots, n_src, nt): the source time function s(t) at t_k = k dt, and source_components its
  direction or mechanism per source:
    "force":     (n_shots, n_src, 3) = (fz, fy, fx); point force F(t) = s(t) (fz, fy, fx), N (default: vertical);
    "moment":    (n_shots, n_src, 6) = (Mzz, Myy, Mxx, Myz, Mxz, Mxy); moment tensor M_ij(t) = m_ij s(t), N m
                 (equivalent body force -div(M delta)); s must start at 0;
    "explosive": the isotropic moment tensor (1, 1, 1, 0, 0, 0) s(t), N m.
- receiver data: vx, vy, vz (m/s) sample n at t = (n - 1/2) dt, pressure -(sxx + syy + szz)/3 (Pa) at t = n dt,
  each (n_shots, n_receivers, nt).

The time loop is solve/loop.py's and the gradient solve/sweep.py's taped sweep (Warp's generated adjoints of the
kernels, checkpointed segments); this module maps the kernels onto them (Elastic3DSetup).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from adseismic.kernels.elastic import shear_ratio
from adseismic.kernels.elastic3d import DESCRIPTION, FIELDS, PSI, Elastic3D
from adseismic.kernels.numerics import check_order
from adseismic.solve import common, loop
from adseismic.solve.elastic import check_model_values
from adseismic.solve.staggered import StaggeredSetup, taped_gradient

MODELS = ("vp", "vs", "rho")
WRT = (*MODELS, "source_amplitudes")
COMPONENTS = ("vx", "vy", "vz", "pressure")
SOURCE_TYPES = {"force": 3, "moment": 6, "explosive": 6}
RATIO_MARGIN = 8.0 * float(np.finfo(np.float32).eps)  # vs / vp's rounding in float32 and the models' on upload


def _clear(ranges, exact):
    """vp, vs, rho finite, vp, rho > 0, vs >= 0 (> 0 where the upload rounded: a tiny negative vs may round to -0)
    and vs / vp (in dtype, shear_ratio) below 1 / sqrt(2) by RATIO_MARGIN."""
    (vp_lo, _, vp_bad), (vs_lo, _, vs_bad), (rho_lo, _, rho_bad), (_, ratio_hi, _) = ranges
    positive = vp_lo > 0 and rho_lo > 0 and (vs_lo >= 0 if exact else vs_lo > 0)
    return not (vp_bad or vs_bad or rho_bad) and positive and ratio_hi <= (1.0 - RATIO_MARGIN) / math.sqrt(2.0)


# check_model_values' checks of (vp, vs, rho), the CFL speed vp; on a GPU the ratio vs / vp (shear_ratio)
MODEL_CHECKS = common.ModelChecks(
    check_model_values,
    lambda vp, vs, rho: vp,
    _clear,
    lambda arrays: [common.elementwise(shear_ratio(arrays[0].dtype), arrays[:2], dtype=arrays[0].dtype)],
)


@dataclass
class Elastic3DResult:
    """Output of :func:`forward_elastic3d`: vx, vy, vz (m/s) and pressure (Pa), each (n_shots, n_receivers, nt) in the
    simulation's precision: Warp arrays on the model's device where vp was given as a Warp array, else NumPy arrays;
    dt (s)."""

    vx: np.ndarray | wp.array
    vy: np.ndarray | wp.array
    vz: np.ndarray | wp.array
    pressure: np.ndarray | wp.array
    dt: float


@dataclass
class Elastic3DGradient:
    """Misfit and its gradients: vp, vs (per m/s), rho (per kg/m^3) (nz, ny, nx), source_amplitudes (n_shots, n_src,
    nt); None where not requested. synthetic: {"vx", "vy", "vz", "pressure"} data (n_shots, n_receivers, nt);
    segment_length (steps) and n_segments of the checkpointed sweep, peak_bytes_estimate its planned memory."""

    loss: float
    synthetic: dict
    vp: np.ndarray | None = None
    vs: np.ndarray | None = None
    rho: np.ndarray | None = None
    source_amplitudes: np.ndarray | None = None
    segment_length: int = 0
    n_segments: int = 0
    peak_bytes_estimate: int = 0


def source_components_of(source_type: str, source_components, shape) -> np.ndarray:
    """The sources' components (n_shots, n_src, 3 | 6) for source_type (module docstring); shape: (n_shots, n_src)."""
    if source_type not in SOURCE_TYPES:
        raise ValueError(f"source_type {source_type!r} is not one of {sorted(SOURCE_TYPES)}")
    nc = SOURCE_TYPES[source_type]
    if source_type == "explosive":
        return np.ascontiguousarray(np.broadcast_to(np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]), (*shape, 6)))
    if source_components is None:
        if source_type == "moment":
            raise ValueError("source_type 'moment' needs source_components (n_shots, n_src, 6) = (Mzz, Myy, Mxx, Myz, Mxz, Mxy)")
        return np.ascontiguousarray(np.broadcast_to(np.array([1.0, 0.0, 0.0]), (*shape, 3)))  # vertical force
    comp = np.asarray(source_components, dtype=float)
    if comp.shape != (*shape, nc):
        raise ValueError(f"source_components must be (n_shots, n_src, {nc}) for source_type {source_type!r}; got {comp.shape}")
    return np.ascontiguousarray(comp)


@dataclass
class Elastic3DSetup(StaggeredSetup):
    """Device-side inputs of one 3D elastic simulation (see :func:`setup_elastic3d`) and the verbs of the shared
    solver (solve/loop.py). models: physical (vp, vs, rho) wp.array3d; kind: "force" or "moment"; source_op,
    receiver_op: the sources' and receivers' fixed operators (Elastic3D.operator)."""

    prop: Elastic3D
    nt: int
    kind: str
    models: tuple
    amplitudes: wp.array
    components: wp.array
    receivers: wp.array
    source_op: tuple
    receiver_op: tuple

    physics = DESCRIPTION
    data_components = COMPONENTS  # in new_data's order

    def sources_of(self, amplitudes, fixed=True):
        return (self.kind, amplitudes, self.components, self.source_op)

    def fields(self, st):
        return (st.vx, st.vy, st.vz)

    def key(self):
        return (*super().key(), self.kind)

    def loop_kernels(self):
        k = self.prop.k
        return [k.velocity, k.stress, k.record, k.inject_force if self.kind == "force" else k.inject_moment]

    def inputs(self, src):
        """StaggeredSetup.inputs and the sources' components."""
        return [self.components, *super().inputs(src)]


def setup_elastic3d(vp, vs, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, *, source_type="force",
                    source_components=None, order=4, pml_width=None, pml_reflection=None, pml_frequency=None, pml_velocity=None,
                    free_surface=False, device="cpu", precision="float32", requires_grad=()) -> Elastic3DSetup:  # fmt: skip
    """Validate the inputs (ValueError naming the argument) and move them to the device; requires_grad names the
    arrays (WRT) to differentiate."""
    check_order(order)
    dtype = common.precision_dtype(precision)
    device = common.resolve_device(device)
    given = dict(zip(MODELS, (vp, vs, rho)))
    shape = common.model_shape(given, (3,))
    models, vmax = common.checked_models(given, MODEL_CHECKS, dtype, device, requires_grad)
    amp = np.asarray(source_amplitudes, dtype=float)
    common.check_geometry(shape, dx, amp, source_locations, receiver_locations, "z, y, x")
    comp = source_components_of(source_type, source_components, amp.shape[:2])
    common.check_courant(DESCRIPTION, order, 3, vmax, dx, dt)
    pml = common.pml_settings(order, pml_width, pml_reflection, pml_frequency, pml_velocity, amp, dt, vmax)
    prop = Elastic3D(shape, dx, dt, order, amp.shape[0], *pml, free_surface=free_surface, dtype=dtype, device=device)

    def put(x, name):
        return wp.array(np.ascontiguousarray(x, dtype=float), dtype=dtype, device=prop.device, requires_grad=name in requires_grad)

    receivers = put(receiver_locations, "")
    return Elastic3DSetup(prop, amp.shape[2], "force" if source_type == "force" else "moment",
                          models, put(amp, "source_amplitudes"), put(comp, ""), receivers,
                          prop.operator(put(source_locations, "")), prop.operator(receivers))  # fmt: skip


def forward_elastic3d(vp, vs, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, *, source_type="force",
                      source_components=None, order=4, pml_width=None, pml_reflection=None, pml_frequency=None, pml_velocity=None,
                      free_surface=False, device="cpu", precision="float32", check_every=25,
                      progress=False) -> Elastic3DResult:  # fmt: skip
    """Simulate the 3D isotropic elastic wave equation for all shots at once (conventions: module docstring).

    vp, vs (m/s), rho (kg/m^3): (nz, ny, nx); dx m; dt s; source_amplitudes (n_shots, n_src, nt); source_type "force"
    (N), "moment" or "explosive" (N m) with source_components (module docstring); source/receiver_locations (n_shots,
    n, 3) metres (z, y, x); order 2, 4 or 8; PML settings as forward_elastic's; free_surface: traction-free z = 0.
    Returns vx, vy, vz (m/s) and pressure (Pa), each (n_shots, n_receivers, nt). Raises ValueError on bad input or a dt
    above the CFL limit, PropagationError if the run blows up."""
    su = setup_elastic3d(vp, vs, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, source_type=source_type,
                         source_components=source_components, order=order, pml_width=pml_width, pml_reflection=pml_reflection,
                         pml_frequency=pml_frequency, pml_velocity=pml_velocity, free_surface=free_surface, device=device,
                         precision=precision)  # fmt: skip
    end = common.source_end(source_amplitudes, lag=2, rate=source_type != "force")
    guard = common.BlowupGuard(su.prop, DESCRIPTION, su.fields, end, check_every, "v")
    data, kept = loop.run(su, guard, progress)
    vx, vy, vz, p = (loop.traces(d, su.nt, isinstance(vp, wp.array), kept) for d in data)
    return Elastic3DResult(vx=vx, vy=vy, vz=vz, pressure=p, dt=float(dt))


def gradient_elastic3d(vp, vs, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, observed=None, *, misfit="l2",
                       components=("vz",), wrt=MODELS, source_type="force", source_components=None, order=4, pml_width=None,
                       pml_reflection=None, pml_frequency=None, pml_velocity=None, free_surface=False, device="cpu",
                       precision="float32", memory_budget=None, segment_length=None, progress=False) -> Elastic3DGradient:  # fmt: skip
    """Misfit between simulated and observed data and its exact gradient (the discrete adjoint: Warp's generated
    adjoints of the kernels through checkpointed segments, sweep.taped_sweep).

    observed: {component: (n_shots, n_receivers, nt)} for the names in `components` (of COMPONENTS); misfit: a name
    in misfits.MISFITS (summed over components) or a callable synthetic dict -> (J, {name: dJ/d synthetic}); wrt: any
    of WRT. memory_budget (bytes) / segment_length: staggered.taped_gradient. Other arguments as forward_elastic3d's;
    the PML is fixed (pin pml_velocity and pml_frequency when the model changes between calls)."""
    unknown = set(wrt) - set(WRT)
    if unknown:
        raise ValueError(f"wrt: {sorted(unknown)} not among {WRT}")
    su = setup_elastic3d(vp, vs, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, source_type=source_type,
                         source_components=source_components, order=order, pml_width=pml_width, pml_reflection=pml_reflection,
                         pml_frequency=pml_frequency, pml_velocity=pml_velocity, free_surface=free_surface, device=device,
                         precision=precision, requires_grad=set(wrt))  # fmt: skip
    p = su.prop
    size = 4 if p.dtype == wp.float32 else 8
    state = size * (len(FIELDS) * p.n_shots * math.prod(p.padded) + sum(math.prod(p.psi_shape(k)) for k in PSI))
    arrays = {**dict(zip(MODELS, su.models)), "source_amplitudes": su.amplitudes}
    return taped_gradient(su, state, misfit, components, observed, wrt, arrays, Elastic3DGradient, memory_budget, segment_length, progress)
