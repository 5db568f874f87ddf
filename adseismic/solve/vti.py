"""2D pseudo-acoustic VTI propagation and its checkpointed gradients (kernels/vti/, docs/vti.md).

Conventions (as adseismic.solve.elastic; z depth, positive down):
- vp (m/s, the vertical P speed), epsilon, delta (Thomsen, dimensionless), rho (kg/m^3): (nz, nx) NumPy or Warp
  arrays on a regular grid of spacing dx (m); node (0, 0) at 0 m. Stable iff epsilon >= delta everywhere (refused
  otherwise); delta > -1/2.
- locations: metres (z, x), shape (n_shots, n_per_shot, 2).
- source_amplitudes (n_shots, n_src, nt): the explosive source's moment M(t) = s(t) at t_k = k dt (N m per metre of
  line, as the elastic solver's "explosive" source), injected into both stresses through its rate; s must start at 0.
- receiver data: vx, vz (m/s) sample n at t = (n - 1/2) dt, pressure -(sH + sV)/2 (Pa) at t = n dt, each
  (n_shots, n_receivers, nt).

The time loop is solve/loop.py's (VTISetup maps the kernels onto it) and the gradient Warp's generated adjoints of
every kernel under wp.Tape in checkpointed segments (solve/sweep.py's taped_sweep).
"""

import functools
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from adseismic.kernels.common import unique_kernel
from adseismic.kernels.numerics import check_order
from adseismic.kernels.vti import DESCRIPTION, PSI, VTI, thomsen_check
from adseismic.solve import common, loop
from adseismic.solve.staggered import COMPONENTS, StaggeredSetup, taped_gradient

MODELS = ("vp", "epsilon", "delta", "rho")
WRT = (*MODELS, "source_amplitudes")


@dataclass
class VTIResult:
    """Output of :func:`forward_vti`: vx, vz (m/s) and pressure (Pa), each (n_shots, n_receivers, nt) in the
    simulation's precision: Warp arrays on the model's device where vp was given as a Warp array, else NumPy arrays;
    dt (s)."""

    vx: np.ndarray | wp.array
    vz: np.ndarray | wp.array
    pressure: np.ndarray | wp.array
    dt: float


@dataclass
class VTIGradient:
    """Misfit and its gradients: vp (per m/s), epsilon, delta (per unit), rho (per kg/m^3) (nz, nx), source_amplitudes
    (n_shots, n_src, nt); None where not requested. synthetic: {"vx", "vz", "pressure"} (n_shots, n_receivers, nt).
    segment_length (steps) and n_segments of the checkpointed sweep, peak_bytes_estimate its planned memory."""

    loss: float
    synthetic: dict
    vp: np.ndarray | None = None
    epsilon: np.ndarray | None = None
    delta: np.ndarray | None = None
    rho: np.ndarray | None = None
    source_amplitudes: np.ndarray | None = None
    segment_length: int = 0
    n_segments: int = 0
    peak_bytes_estimate: int = 0


def check_model_values(vp, epsilon, delta, rho):
    """Raise ValueError at the first bad value of the NumPy models (nz, nx): finite, vp, rho > 0, delta > -1/2 and
    epsilon >= delta (thomsen_check)."""
    for name, a, ok in (("vp", vp, vp > 0), ("rho", rho, rho > 0), ("epsilon", epsilon, True), ("delta", delta, True)):
        bad = ~(np.isfinite(a) & ok)
        if bad.any():
            raise ValueError(f"{name} has {int(bad.sum())} non-finite or out-of-range values (first at index "
                             f"{tuple(int(i) for i in np.argwhere(bad)[0])}: {a[tuple(np.argwhere(bad)[0])]:g}); vp, rho > 0, all finite")
    thomsen_check(epsilon, delta)


def horizontal_speed(vp, epsilon):
    """The horizontal P speed vp sqrt(1 + 2 epsilon) (m/s), the fastest of a pseudo-acoustic VTI medium."""
    return vp * np.sqrt(1.0 + 2.0 * epsilon)


@functools.lru_cache(maxsize=None)
def horizontal_speed_kernel(dtype):
    """Kernel h[i] = horizontal_speed(vp[i], epsilon[i]) in float64 on flat arrays (vp, epsilon of dtype). (This
    module has no `from __future__ import annotations`: Warp evaluates the kernel's annotations, dtype's too.)"""

    @unique_kernel(enable_backward=False)
    def speed(vp: wp.array(dtype=dtype), epsilon: wp.array(dtype=dtype), h: wp.array(dtype=wp.float64)):
        i = wp.tid()
        h[i] = wp.float64(vp[i]) * wp.sqrt(wp.float64(1.0) + wp.float64(2.0) * wp.float64(epsilon[i]))

    return speed


@functools.lru_cache(maxsize=None)
def anellipticity_kernel(dtype):
    """Kernel d[i] = epsilon[i] - delta[i] in float64 on flat arrays of dtype (thomsen_check's epsilon >= delta)."""

    @unique_kernel(enable_backward=False)
    def difference(epsilon: wp.array(dtype=dtype), delta: wp.array(dtype=dtype), d: wp.array(dtype=wp.float64)):
        i = wp.tid()
        d[i] = wp.float64(epsilon[i]) - wp.float64(delta[i])

    return difference


def _clear(ranges, exact):
    """Finite models, vp, rho > 0, delta > -1/2 and epsilon >= delta (> where the upload rounded: rounding keeps
    order but may make two values equal); ranges of (vp, epsilon, delta, rho, horizontal speed, epsilon - delta)."""
    (vp_lo, _, vp_bad), (_, _, eps_bad), (delta_lo, _, delta_bad), (rho_lo, _, rho_bad), (_, _, h_bad), (d_lo, _, _) = ranges
    finite = not (vp_bad or eps_bad or delta_bad or rho_bad or h_bad)
    return finite and vp_lo > 0 and rho_lo > 0 and delta_lo > -0.5 and (d_lo >= 0 if exact else d_lo > 0)


# check_model_values' checks of (vp, epsilon, delta, rho) and the CFL speed horizontal_speed
MODEL_CHECKS = common.ModelChecks(
    check_model_values,
    lambda vp, epsilon, delta, rho: horizontal_speed(vp, epsilon),
    _clear,
    lambda arrays: [common.elementwise(horizontal_speed_kernel(arrays[0].dtype), arrays[:2]),
                    common.elementwise(anellipticity_kernel(arrays[0].dtype), arrays[1:3])],  # fmt: skip
    speed_range=4,
)


@dataclass
class VTISetup(StaggeredSetup):
    """Device-side inputs of one VTI simulation (see :func:`setup_vti`) and the verbs of the shared solver
    (solve/loop.py). models: physical (vp, epsilon, delta, rho) wp.array2d; source_op, receiver_op: fixed operators
    (VTI.operator)."""

    prop: VTI
    nt: int
    models: tuple
    amplitudes: wp.array
    receivers: wp.array
    receiver_op: tuple
    source_op: tuple

    physics = DESCRIPTION

    def model(self, on_tape=False, out=None):
        """The padded MATERIALS (kernels/vti), into out (an earlier call's) if given; differentiable under a tape."""
        return self.prop.materials(*self.models, requires_grad=on_tape, out=out)

    def fields(self, st):
        return (st.vx, st.vz)

    def loop_kernels(self):
        k = self.prop.k
        return [k.velocity, k.stress, k.inject, k.record]


def setup_vti(vp, epsilon, delta, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, *, order=4,
              pml_width=None, pml_reflection=None, pml_frequency=None, pml_velocity=None, free_surface=False, device="cpu",
              precision="float32", requires_grad=()) -> VTISetup:  # fmt: skip
    """Validate the inputs (model values, geometry, the CFL limit with the horizontal P speed) and move them to the
    device; requires_grad names the arrays (WRT) to differentiate."""
    check_order(order)
    given = dict(zip(MODELS, (vp, epsilon, delta, rho)))
    shape = common.model_shape(given)
    dtype = common.precision_dtype(precision)
    device = common.resolve_device(device)
    models, vmax = common.checked_models(given, MODEL_CHECKS, dtype, device, requires_grad)
    amp = np.asarray(source_amplitudes, dtype=float)
    common.check_geometry(shape, dx, amp, source_locations, receiver_locations, "z, x")
    common.check_courant(DESCRIPTION, order, 2, vmax, dx, dt)
    pml = common.pml_settings(order, pml_width, pml_reflection, pml_frequency, pml_velocity, amp, dt, vmax)
    prop = VTI(shape, dx, dt, order, amp.shape[0], *pml, free_surface=free_surface, dtype=dtype, device=device)

    def put(x, grad=False):
        return wp.array(np.ascontiguousarray(x, dtype=float), dtype=dtype, device=device, requires_grad=grad)

    receivers = put(receiver_locations)
    return VTISetup(prop, amp.shape[2], models,
                    put(amp, "source_amplitudes" in requires_grad), receivers, prop.operator(receivers),
                    prop.operator(put(source_locations)))


def forward_vti(vp, epsilon, delta, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, *, order=4,
                pml_width=None, pml_reflection=None, pml_frequency=None, pml_velocity=None, free_surface=False, device="cpu",
                precision="float32", check_every=25, progress=False) -> VTIResult:  # fmt: skip
    """Simulate 2D pseudo-acoustic VTI for all shots at once (conventions: module docstring).

    vp (m/s), epsilon, delta, rho (kg/m^3): (nz, nx) arrays; dx m; dt s; source_amplitudes (n_shots, n_src, nt) the
    explosive sources' moment; source/receiver_locations (n_shots, n, 2) metres (z, x). Returns vx, vz (m/s) and
    pressure (Pa), each (n_shots, n_receivers, nt). order 2, 4 or 8; pml_width cells (default 20); pml_reflection
    target; pml_frequency CPML alpha frequency (Hz, default the sources' dominant frequency); pml_velocity CPML reference
    speed (m/s, default max(vp sqrt(1 + 2 epsilon))); free_surface: pressure-release top at z = 0. Raises ValueError on
    bad input (epsilon < delta, an unstable dt), PropagationError if the run blows up."""
    su = setup_vti(vp, epsilon, delta, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, order=order,
                   pml_width=pml_width, pml_reflection=pml_reflection, pml_frequency=pml_frequency, pml_velocity=pml_velocity,
                   free_surface=free_surface, device=device, precision=precision)  # fmt: skip
    guard = common.BlowupGuard(su.prop, DESCRIPTION, su.fields, common.source_end(source_amplitudes, lag=2, rate=True), check_every, "v")
    data, kept = loop.run(su, guard, progress)
    return VTIResult(*(loop.traces(d, su.nt, isinstance(vp, wp.array), kept) for d in data), dt=float(dt))


def gradient_vti(vp, epsilon, delta, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, observed=None, *,
                 misfit="l2", components=("pressure",), wrt=MODELS, order=4, pml_width=None, pml_reflection=None,
                 pml_frequency=None, pml_velocity=None, free_surface=False, device="cpu", precision="float32",
                 memory_budget=None, segment_length=None, progress=False) -> VTIGradient:  # fmt: skip
    """Misfit between simulated and observed data and its exact gradient (the discrete adjoint, Warp's generated adjoints
    of every kernel under wp.Tape, checkpointed).

    observed: {"vx", "vz", "pressure"} arrays (n_shots, n_receivers, nt) for the names in `components`; misfit: a name in
    misfits.MISFITS (summed over components) or a callable synthetic dict -> (J, {name: dJ/d synthetic}). wrt: any of
    WRT. Memory: memory_budget bytes (None: the minimum, ~sqrt(nt) steps per segment) or segment_length steps. Other
    arguments as in forward_vti; the PML settings are fixed (pin pml_velocity and pml_frequency when the model changes
    between calls)."""
    unknown = set(wrt) - set(WRT)
    if unknown:
        raise ValueError(f"wrt: {sorted(unknown)} not among {WRT}")
    su = setup_vti(vp, epsilon, delta, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, order=order,
                   pml_width=pml_width, pml_reflection=pml_reflection, pml_frequency=pml_frequency, pml_velocity=pml_velocity,
                   free_surface=free_surface, device=device, precision=precision, requires_grad=set(wrt))  # fmt: skip
    state = (4 if su.prop.dtype == wp.float32 else 8) * (4 + len(PSI)) * su.prop.n_shots * math.prod(su.prop.padded)  # 4 fields, 4 psi
    return taped_gradient(su, state, misfit, components, observed, wrt, dict(zip(MODELS, su.models), source_amplitudes=su.amplitudes),
                          VTIGradient, memory_budget, segment_length, progress)  # fmt: skip
