"""2D visco-acoustic propagation (constant Q over a band, kernels/viscoacoustic/) and its exact, checkpointed gradients.

Conventions (as adseismic.solve.elastic; z depth, positive down):
- vp (m/s): the phase velocity at f_ref (Hz); q: the quality factor (dimensionless, > 0; inf: lossless); rho
  (kg/m^3): (nz, nx) arrays on a regular grid of spacing dx (m), node (0, 0) at 0 m.
- q_band (f_min, f_max) Hz: the band over which Q is flat (L = `mechanisms` standard linear solids, relaxation.py);
  default (f_dom / 3, 2.5 f_dom) and f_ref f_dom, f_dom the sources' dominant frequency.
- locations: metres (z, x), shape (n_shots, n, 2).
- source_amplitudes (n_shots, n_src, nt): S(t_k), the explosive source's isotropic moment in N m per metre of line
  (as the elastic solver's explosive source: dp/dt gains dS/dt delta(x - x_s), so p in Pa is what physics
  acoustic_vd gives for the same S when Q -> infinity).
- receiver data: pressure p (Pa) sample n at t = n dt; vx, vz (m/s) at t = (n - 1/2) dt; each (n_shots, n_rec, nt).

The time loop is solve/loop.py's and the gradient solve/sweep.py's taped sweep (Warp's generated adjoints of the
kernels, checkpointed segments); this module maps the kernels onto them (ViscoacousticSetup).
"""

import functools
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from adseismic.kernels.common import unique_kernel
from adseismic.kernels.numerics import check_order
from adseismic.kernels.viscoacoustic import DESCRIPTION, PSI, Viscoacoustic, fit_mechanisms
from adseismic.solve import common, loop
from adseismic.solve.staggered import COMPONENTS, StaggeredSetup, taped_gradient

MODELS = ("vp", "q", "rho")
WRT = (*MODELS, "source_amplitudes")
DEFAULT_MECHANISMS = 3


@dataclass
class ViscoacousticResult:
    """Output of :func:`forward_viscoacoustic`: pressure (Pa), vx, vz (m/s), each (n_shots, n_receivers, nt) in the
    simulation's precision: Warp arrays on the model's device where vp was given as a Warp array, else NumPy arrays;
    dt (s); vmax_unrelaxed (m/s), the fastest (w -> infinity) speed that set the CFL check."""

    pressure: np.ndarray | wp.array
    vx: np.ndarray | wp.array
    vz: np.ndarray | wp.array
    dt: float
    vmax_unrelaxed: float


@dataclass
class ViscoacousticGradient:
    """Misfit and its gradients: vp (per m/s), q (per unit Q), rho (per kg/m^3) (nz, nx), source_amplitudes (n_shots,
    n_src, nt); None where not requested. synthetic: {"vx", "vz", "pressure"} data (n_shots, n_receivers, nt);
    segment_length (steps) and n_segments of the checkpointed sweep, peak_bytes_estimate its planned memory."""

    loss: float
    synthetic: dict
    vp: np.ndarray | None = None
    q: np.ndarray | None = None
    rho: np.ndarray | None = None
    source_amplitudes: np.ndarray | None = None
    segment_length: int = 0
    n_segments: int = 0
    peak_bytes_estimate: int = 0


def check_model_values(vp, q, rho):
    """Raise ValueError at the first bad value of the NumPy models (nz, nx): vp, rho finite and > 0, q > 0 (inf
    allowed: no loss there; NaN refused)."""
    for name, a, ok in (("vp", vp, np.isfinite(vp) & (vp > 0)), ("rho", rho, np.isfinite(rho) & (rho > 0)), ("q", q, q > 0)):
        bad = ~ok
        if bad.any():
            i = tuple(int(k) for k in np.argwhere(bad)[0])
            raise ValueError(f"{name} has {int(bad.sum())} non-finite or non-positive values (first {a[i]!r} at index {i}); "
                             f"vp, rho must be finite and > 0, q > 0 (q = inf: lossless)")  # fmt: skip


def unrelaxed_coefficients(mechanisms, f_ref: float) -> np.ndarray:
    """(SERIES_TERMS, 3) float64: the coefficients of 1/q's powers in Re and Im of sum_l y_l c_l and in sum_l y_l,
    c_l = i w tau_l / (1 + i w tau_l) at w = 2 pi f_ref (Hz) (y_l = sum_k series[k, l] q^-(k+1): the mechanisms
    folded into the coefficients, one Horner pass a term where y (cells x L) took several)."""
    wt = 2.0 * math.pi * f_ref * mechanisms.tau
    c = (1j * wt) / (1.0 + 1j * wt)
    return mechanisms.series @ np.stack([c.real, c.imag, np.ones_like(wt)], axis=1)


def unrelaxed_velocity(vp, q, mechanisms, f_ref: float) -> np.ndarray:
    """sqrt(M_U / rho) (m/s): the speed at w -> infinity of a medium of phase velocity vp (m/s) at f_ref (Hz) and
    quality factor q (arrays of one shape), the fastest the scheme carries (its CFL speed)."""
    iq = 1.0 / np.asarray(q, dtype=float)
    coef = unrelaxed_coefficients(mechanisms, f_ref)
    re, im, ysum = (np.zeros_like(iq) for _ in range(3))
    for k in reversed(range(coef.shape[0])):
        re, im, ysum = (re + coef[k, 0]) * iq, (im + coef[k, 1]) * iq, (ysum + coef[k, 2]) * iq
    m_ref = (1.0 + re) + 1j * im
    return np.asarray(vp, dtype=float) * np.real(m_ref**-0.5) * np.sqrt(1.0 + ysum)


@functools.lru_cache(maxsize=None)
def unrelaxed_velocity_kernel(dtype):
    """Kernel u[i] = unrelaxed_velocity(vp[i], q[i]) in float64 on flat arrays (vp, q of dtype; coef:
    unrelaxed_coefficients), NaN where q is not > 0 (q = inf: lossless, u = vp); Re(m^-1/2) = |m|^-1/2 cos(arg(m) / 2).
    (This module has no `from __future__ import annotations`: Warp evaluates the kernel's annotations, dtype's too.)"""

    @unique_kernel(enable_backward=False)
    def unrelaxed(vp: wp.array(dtype=dtype), q: wp.array(dtype=dtype), u: wp.array(dtype=wp.float64), coef: wp.array2d(dtype=wp.float64)):
        i = wp.tid()
        qi = wp.float64(q[i])
        iq = wp.float64(1.0) / qi
        re = wp.float64(0.0)
        im = wp.float64(0.0)
        ysum = wp.float64(0.0)
        for j in range(coef.shape[0]):
            k = coef.shape[0] - 1 - j
            re = (re + coef[k, 0]) * iq
            im = (im + coef[k, 1]) * iq
            ysum = (ysum + coef[k, 2]) * iq
        mr = wp.float64(1.0) + re
        scale = wp.pow(mr * mr + im * im, wp.float64(-0.25)) * wp.cos(wp.float64(0.5) * wp.atan2(im, mr))
        u[i] = wp.float64(vp[i]) * scale * wp.sqrt(wp.float64(1.0) + ysum)
        if not (qi > wp.float64(0.0)):
            u[i] = wp.float64(wp.nan)

    return unrelaxed


def model_checks(mechanisms, f_ref: float) -> common.ModelChecks:
    """The checks of (vp, q, rho) (check_model_values) and their CFL speed, unrelaxed_velocity at f_ref (Hz); on a
    GPU the unrelaxed velocity u (unrelaxed_velocity_kernel, NaN where q is not > 0) clears q: clear where vp, rho are
    finite and > 0 and u is finite and > 0 (q = inf: u = vp, lossless, clear)."""

    def derive(arrays):
        coef = wp.array(unrelaxed_coefficients(mechanisms, f_ref), dtype=wp.float64, device=arrays[0].device)
        return [common.elementwise(unrelaxed_velocity_kernel(arrays[0].dtype), arrays[:2], coef)]

    def clear(ranges, exact):
        (vp_lo, _, vp_bad), _, (rho_lo, _, rho_bad), (u_lo, _, u_bad) = ranges
        return not (vp_bad or rho_bad or u_bad) and vp_lo > 0 and rho_lo > 0 and u_lo > 0

    return common.ModelChecks(check_model_values, lambda vp, q, rho: unrelaxed_velocity(vp, q, mechanisms, f_ref), clear, derive, 3)


@dataclass
class ViscoacousticSetup(StaggeredSetup):
    """Device-side inputs of one visco-acoustic simulation (see :func:`setup_viscoacoustic`) and the verbs of the
    shared solver (solve/loop.py). models: physical (vp, q, rho) wp.array2d; source_op, receiver_op: the sources' and
    receivers' fixed operators (Viscoacoustic.operator)."""

    prop: Viscoacoustic
    nt: int
    models: tuple
    amplitudes: wp.array
    receivers: wp.array
    source_op: tuple
    receiver_op: tuple
    vmax_unrelaxed: float

    physics = DESCRIPTION

    def fields(self, st):
        return (st.p,)

    def loop_kernels(self):
        k = self.prop.k
        return [k.velocity, k.pressure, k.inject, k.record]

    def inputs(self, src):
        """StaggeredSetup.inputs and the mechanisms' constants."""
        return [self.prop.c1, self.prop.c2, *super().inputs(src)]


def setup_viscoacoustic(vp, q, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, *, q_band=None, f_ref=None,
                        mechanisms=DEFAULT_MECHANISMS, order=4, pml_width=None, pml_reflection=None, pml_frequency=None,
                        pml_velocity=None, free_surface=False, device="cpu", precision="float32",
                        requires_grad=()) -> ViscoacousticSetup:  # fmt: skip
    """Validate the inputs (ValueError naming the argument) and move them to the device; requires_grad names the
    arrays (WRT) to differentiate."""
    check_order(order)
    dtype = common.precision_dtype(precision)
    device = common.resolve_device(device)
    given = dict(zip(MODELS, (vp, q, rho)))
    shape = common.model_shape(given)
    amp = np.asarray(source_amplitudes, dtype=float)
    common.check_geometry(shape, dx, amp, source_locations, receiver_locations, "z, x")
    f_dom = common.dominant_frequency(amp, dt)
    band = (f_dom / 3.0, 2.5 * f_dom) if q_band is None else tuple(float(f) for f in np.atleast_1d(q_band))
    if len(band) != 2:
        raise ValueError(f"q_band {q_band!r} must be [f_min, f_max] Hz")
    mech = fit_mechanisms(*band, mechanisms)
    f_ref = f_dom if f_ref is None else float(f_ref)
    if not f_ref > 0:
        raise ValueError(f"f_ref = {f_ref} Hz must be > 0 (the frequency at which vp is the phase velocity)")
    models, vmax = common.checked_models(given, model_checks(mech, f_ref), dtype, device, requires_grad)
    common.check_courant(DESCRIPTION, order, 2, vmax, dx, dt)
    pml = common.pml_settings(order, pml_width, pml_reflection, pml_frequency, pml_velocity, amp, dt, vmax)
    prop = Viscoacoustic(shape, dx, dt, order, amp.shape[0], mech, f_ref, *pml, free_surface=free_surface, dtype=dtype,
                         device=device)  # fmt: skip

    def put(x, name):
        return wp.array(np.ascontiguousarray(x, dtype=float), dtype=dtype, device=prop.device, requires_grad=name in requires_grad)

    receivers = put(receiver_locations, "")
    return ViscoacousticSetup(prop, amp.shape[2], models, put(amp, "source_amplitudes"),
                              receivers, prop.operator(put(source_locations, "")), prop.operator(receivers), vmax)  # fmt: skip


def forward_viscoacoustic(vp, q, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, *, q_band=None, f_ref=None,
                          mechanisms=DEFAULT_MECHANISMS, order=4, pml_width=None, pml_reflection=None, pml_frequency=None,
                          pml_velocity=None, free_surface=False, device="cpu", precision="float32", check_every=25,
                          progress=False) -> ViscoacousticResult:  # fmt: skip
    """Simulate the 2D visco-acoustic wave equation for all shots at once (conventions: module docstring).

    vp (m/s at f_ref), q, rho (kg/m^3): (nz, nx); dx m; dt s; source_amplitudes (n_shots, n_src, nt) N m/m;
    source/receiver_locations (n_shots, n, 2) metres (z, x); q_band (f_min, f_max) Hz and f_ref Hz (defaults: module
    docstring); mechanisms: number of standard linear solids; order 2, 4 or 8; PML settings as forward_elastic's
    (the CPML reference speed defaults to the unrelaxed maximum); free_surface: p = 0 at z = 0. Returns pressure (Pa),
    vx, vz (m/s), each (n_shots, n_receivers, nt). Raises ValueError on bad input or a dt above the CFL limit of the
    unrelaxed speed, PropagationError if the run blows up."""
    su = setup_viscoacoustic(vp, q, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, q_band=q_band, f_ref=f_ref,
                             mechanisms=mechanisms, order=order, pml_width=pml_width, pml_reflection=pml_reflection,
                             pml_frequency=pml_frequency, pml_velocity=pml_velocity, free_surface=free_surface, device=device,
                             precision=precision)  # fmt: skip
    guard = common.BlowupGuard(su.prop, DESCRIPTION, su.fields, common.source_end(source_amplitudes, lag=2, rate=True), check_every, "p")
    data, kept = loop.run(su, guard, progress)
    vx, vz, p = (loop.traces(d, su.nt, isinstance(vp, wp.array), kept) for d in data)
    return ViscoacousticResult(pressure=p, vx=vx, vz=vz, dt=float(dt), vmax_unrelaxed=su.vmax_unrelaxed)


def gradient_viscoacoustic(vp, q, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, observed=None, *,
                           misfit="l2", components=("pressure",), wrt=MODELS, q_band=None, f_ref=None,
                           mechanisms=DEFAULT_MECHANISMS, order=4, pml_width=None, pml_reflection=None, pml_frequency=None,
                           pml_velocity=None, free_surface=False, device="cpu", precision="float32", memory_budget=None,
                           segment_length=None, progress=False) -> ViscoacousticGradient:  # fmt: skip
    """Misfit between simulated and observed data and its exact gradient (the discrete adjoint: Warp's generated
    adjoints of the kernels through checkpointed segments, sweep.taped_sweep).

    observed: {component: (n_shots, n_receivers, nt)} for the names in `components` (of COMPONENTS); misfit: a name
    in misfits.MISFITS (summed over components) or a callable synthetic dict -> (J, {name: dJ/d synthetic}); wrt: any
    of WRT. memory_budget (bytes) / segment_length: staggered.taped_gradient. Other arguments as forward_viscoacoustic's; the
    PML settings and the mechanisms (q_band, f_ref) are fixed (pin pml_velocity, pml_frequency, q_band and f_ref when
    the model changes between calls). A model with q = inf has gradient 0 in q there."""
    unknown = set(wrt) - set(WRT)
    if unknown:
        raise ValueError(f"wrt: {sorted(unknown)} not among {WRT}")
    su = setup_viscoacoustic(vp, q, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, q_band=q_band, f_ref=f_ref,
                             mechanisms=mechanisms, order=order, pml_width=pml_width, pml_reflection=pml_reflection,
                             pml_frequency=pml_frequency, pml_velocity=pml_velocity, free_surface=free_surface, device=device,
                             precision=precision, requires_grad=set(wrt))  # fmt: skip
    p = su.prop
    state = (4 if p.dtype == wp.float32 else 8) * ((3 + p.mechanisms.count) * p.n_shots * math.prod(p.padded) +
                                                   sum(math.prod(p.psi_shape(k)) for k in PSI))  # fmt: skip
    return taped_gradient(su, state, misfit, components, observed, wrt, {**dict(zip(MODELS, su.models)), "source_amplitudes": su.amplitudes},
                          ViscoacousticGradient, memory_budget, segment_length, progress)  # fmt: skip
