"""Variable-density acoustic propagation in 2D and 3D (kernels/acoustic_vd/) and its exact, checkpointed gradients.

Conventions (as adseismic.solve.viscoacoustic and adseismic.solve.elastic3d; z depth, positive down):
- vp (m/s), rho (kg/m^3): (nz, nx) or (nz, ny, nx) arrays on a regular grid of spacing dx (m), node 0 at 0 m.
- locations: metres (z, x) or (z, y, x), shape (n_shots, n, ndim).
- source_amplitudes (n_shots, n_src, nt): S(t_k), the explosive source's isotropic moment, N m per metre of line in
  2D and N m in 3D (dp/dt gains dS/dt delta(x - x_s): the convention of forward_viscoacoustic and of forward_elastic /
  forward_elastic3d's explosive source, so p in Pa is theirs for the same S).
- receiver data: pressure p (Pa) sample n at t = n dt; vx, [vy,] vz (m/s) at t = (n - 1/2) dt; each (n_shots, n_rec,
  nt).

The time loop is solve/loop.py's and the gradient solve/sweep.py's taped sweep (Warp's generated adjoints of the
kernels, checkpointed segments); this module maps the kernels onto them (AcousticVDSetup).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from adseismic.kernels.acoustic_vd import DESCRIPTION, PSI, VELOCITIES, AcousticVD
from adseismic.kernels.numerics import check_order
from adseismic.solve import common, loop
from adseismic.solve.elastic import check_model_values
from adseismic.solve.staggered import StaggeredSetup, taped_gradient

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
    nt); None where not requested. synthetic: {"vx", ["vy",] "vz", "pressure"} data (n_shots, n_receivers, nt);
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
                         segment_length=None, progress=False) -> AcousticVDGradient:  # fmt: skip
    """Misfit between simulated and observed data and its exact gradient (the discrete adjoint: Warp's generated
    adjoints of the kernels through checkpointed segments, sweep.taped_sweep).

    observed: {component: (n_shots, n_receivers, nt)} for the names in `components` (vx, [vy,] vz, pressure);
    misfit: a name in misfits.MISFITS (summed over components) or a callable synthetic dict -> (J, {name: dJ/d
    synthetic}); wrt: any of WRT. memory_budget (bytes) / segment_length: staggered.taped_gradient. Other arguments
    as forward_acoustic_vd's; the PML is fixed (pin pml_velocity and pml_frequency when the model changes between
    calls)."""
    unknown = set(wrt) - set(WRT)
    if unknown:
        raise ValueError(f"wrt: {sorted(unknown)} not among {WRT}")
    su = setup_acoustic_vd(vp, rho, dx, dt, source_amplitudes, source_locations, receiver_locations, order=order, pml_width=pml_width,
                           pml_reflection=pml_reflection, pml_frequency=pml_frequency, pml_velocity=pml_velocity,
                           free_surface=free_surface, device=device, precision=precision, requires_grad=set(wrt))  # fmt: skip
    p = su.prop
    size = 4 if p.dtype == wp.float32 else 8
    state = size * ((1 + p.ndim) * p.n_shots * math.prod(p.padded) + sum(math.prod(p.psi_shape(k)) for k in PSI[p.ndim]))
    arrays = {**dict(zip(MODELS, su.models)), "source_amplitudes": su.amplitudes}
    return taped_gradient(su, state, misfit, components, observed, wrt, arrays, AcousticVDGradient, memory_budget, segment_length, progress)
