"""Scene planning: model no more than a scene needs.

From the velocity range, the wavelet's frequency content, the spatial order and an accuracy target,
the planner chooses (each value can be pinned in the config's `simulation` section):

- dx: the coarsest spacing whose worst-direction group-velocity error at f_max (the wavelet's -20 dB
  upper band edge) stays within `accuracy`, for the slowest wave (fewest points per wavelength) and the
  fastest (largest Courant number, where time dispersion grows), using the scheme's exact dispersion
  relation (adseismic.numerics);
- dt: cfl_safety x the exact CFL limit; a smaller dt is chosen when that makes the whole run cheaper
  (at order 8 time dispersion near the CFL limit would otherwise force a finer grid);
- record length: the longest straight-ray source-receiver travel time plus the wavelet's duration;
- domain: the source/receiver box plus an aperture margin of v_max T / 2 (nothing farther can send
  energy back to a receiver within the record), cut to the model, plus the PML;
and resamples the model onto that grid.

With ``physics: elastic`` (config.model an ElasticModel, 2D or 3D) dx and dt come from :func:`plan_elastic_grid`: dx from
the slowest wave (S, or with a free surface the Rayleigh wave) and dt from the staggered scheme's CFL limit at vp_max
(of the model's dimension; a 3D model runs adseismic.solve.elastic3d);
the record length from the S-wave straight-ray times (Rayleigh with a free surface). ``physics: acoustic_vd`` (an
ElasticModel with vs None: a fluid, 2D or 3D) runs adseismic.solve.acoustic_vd on the same staggered scheme: dx from
vp_min, dt from the staggered CFL at vp_max, the record from P-wave times; its plan also reports what dropping the
density would cost (:func:`density_reflection_check`).
``physics: vti`` (a VTIModel, the pseudo-acoustic VTI solver of docs/vti.md) plans on the same staggered scheme: dx from
the slowest qP speed (vp_min, vertical, lower where delta < 0), dt from the CFL limit at the fastest, the horizontal
vp sqrt(1 + 2 epsilon); the record from the qP group velocities along straight rays, and the plan reports the
travel-time error of dropping the anisotropy (:func:`anisotropy_check`). ``physics: viscoacoustic`` (a
ViscoacousticModel, docs/viscoacoustic.md) too: dx from the slowest P phase velocity (vp_min at the low end of the Q band),
dt from the CFL limit at the fastest, the unrelaxed (w -> infinity) speed, ~15% above vp at Q = 5; the record from vp;
the plan resolves the Q band, f_ref and mechanisms the run uses and reports the amplitude lost to attenuation over the
longest path (:func:`attenuation_check`).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import map_coordinates

from adseismic.data.model import Model
from adseismic.data.models import ElasticModel, ViscoacousticModel, VTIModel
from adseismic.kernels.acoustic import DESCRIPTION as ACOUSTIC
from adseismic.kernels.elastic import DESCRIPTION as ELASTIC
from adseismic.kernels.elastic3d import DESCRIPTION as ELASTIC3D
from adseismic.kernels.viscoacoustic import DESCRIPTION as VISCOACOUSTIC
from adseismic.kernels.vti import DESCRIPTION as VTI
from adseismic.kernels.numerics import (
    cfl_limit,
    dispersion_error,
    ppw_for_error,
    rayleigh_speed,
    staggered_cfl_limit,
    staggered_dispersion_error,
)
from adseismic.solve.acoustic import forward
from adseismic.solve.common import DEFAULT_PML_REFLECTION, DEFAULT_PML_WIDTH, check_courant, dominant_frequency
from adseismic.wavelets import duration, make_wavelet, spectral_fmax

# Padded-grid cell updates per second used for the time estimate (forward): the rates measured in
# docs/benchmarks.md (2-core CPU VM: 30 M/s on one core; H200: 35 G/s on large grids), rounded down.
EST_RATE = {"cpu": 5.0e7, "cuda": 3.0e10}
ELASTIC_STEP_COST = 4.0  # an elastic cell update (5 fields, staggered) costs ~3-4 acoustic ones (2-core CPU, float32:
# configs/elastic_forward.yaml 7.2e6 padded cell updates/s beside configs/example_2d.yaml's 2.3e7/s, docs/elastic.md)
ELASTIC3D_STEP_COST = 12.0  # a 3D elastic cell update (9 fields, 3D stencils) costs ~3 2D elastic ones (2-core CPU,
# float32, order 4, warm: 4.9e6 padded cell updates/s on 56^3 cells beside 1.5e7/s for 2D elastic on 400^2)
ACOUSTIC_VD_STEP_COST = {2: 3.0, 3: 6.5}  # an acoustic_vd cell update (3 / 4 fields, kernels/acoustic_vd) in acoustic
# ones at EST_RATE (2-core CPU, float32, order 4, warm: 1.6-1.8e7 padded cell updates/s in 2D on 100^2..400^2,
# 7.6e6/s in 3D on 60^3; docs/acoustic_vd.md, benchmarks/acoustic_vd_cost.py)
ELASTIC_CPU_STEP_SECONDS = 2e-3  # and a CPU time step of it ~2 ms more (its ~15 launches; 84 x 84 cells: 2.6 ms a step)
SAFETY_STEPS = tuple(np.linspace(1.0, 0.1, 37))  # fractions of cfl_safety searched for the cheapest (dx, dt)


@dataclass
class Plan:
    """The planner's decisions. Lengths in m, times in s, frequencies in Hz; axis order (z,[y,]x)."""

    ndim: int
    order: int
    dx: float
    dt: float
    nt: int
    shape: tuple
    origin: tuple
    pml_width: int
    pml_reflection: float
    free_surface: bool
    device: str
    precision: str
    f_max: float
    expected_error: float
    courant: float
    cfl_limit: float
    padded_cells: int
    memory_bytes: int
    seconds_per_shot: float
    n_shots: int = 1
    reasons: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    physics: str = "acoustic"  # acoustic, elastic or acoustic_vd
    attenuation: AttenuationCheck | None = None  # physics viscoacoustic: the Q band, f_ref and mechanisms the run uses

    def describe(self) -> str:
        grid = " x ".join(str(n) for n in self.shape)
        axes = "z, y, x" if self.ndim == 3 else "z, x"
        what = {"elastic": f" ({self.ndim}D velocity-stress, staggered grid; dx for the wave that needs the finest grid, dt from vp_max)",
                "acoustic_vd": f" ({self.ndim}D variable-density acoustic: pressure-velocity, staggered grid; dx from vp_min, dt "
                               "from vp_max)",
                "vti": " (2D pseudo-acoustic VTI: velocity-stress, staggered grid; dx from the slowest qP speed, dt from the "
                       "horizontal vp sqrt(1 + 2 epsilon))",
                "viscoacoustic": " (2D visco-acoustic, constant Q: velocity-pressure with memory variables, staggered grid; "
                                 "dx from the slowest P phase velocity, dt from the unrelaxed speed)"}.get(self.physics, " (pressure wave equation)")
        lines = [
            f"physics   {self.physics}{what}",
            f"grid      {grid} cells ({axes}), dx = {self.dx:g} m, origin {tuple(round(o, 3) for o in self.origin)} m",
            f"          why: {self.reasons['dx']}",
            f"dt        {self.dt:.6g} s (Courant {self.courant:.3f}, limit {self.cfl_limit:.3f} for order {self.order} in {self.ndim}D)",
            f"          why: {self.reasons['dt']}",
            f"nt        {self.nt} steps = {self.nt * self.dt:.4g} s record",
            f"          why: {self.reasons['nt']}",
            f"domain    {self.reasons['domain']}",
            f"PML       {self.pml_width} cells, target reflection {self.pml_reflection:g}{', free surface on top' if self.free_surface else ''}",
            f"accuracy  expected group-velocity error {100 * self.expected_error:.2f}% at f_max = {self.f_max:.3g} Hz",
            f"cost      {self.padded_cells:,} padded cells x {self.nt} steps x {self.n_shots} shot(s); "
            f"~{self.memory_bytes / 2**20:.0f} MiB, ~{self.seconds_per_shot:.3g} s per shot on {self.device} ({self.precision}, estimate)",
        ]
        if self.reasons.get("memory"):
            lines.append(f"memory    {self.reasons['memory']}")
        if self.reasons.get("density"):
            lines.append(f"density   {self.reasons['density']}")
        if self.reasons.get("anisotropy"):
            lines.append(f"anisotropy {self.reasons['anisotropy']}")
        if self.attenuation is not None:
            lines.append(f"attenuation {self.attenuation.describe()}")
        lines += [f"WARNING   {w}" for w in self.warnings]
        return "\n".join(lines)


@dataclass
class Scene:
    """A planned simulation: locations in metres relative to grid node 0 (axis order z,[y,]x).

    source_locations (n_shots, 1, ndim); receiver_locations (n_shots, n_receivers, ndim);
    source_amplitudes (n_shots, 1, nt); wavelet (nt,). Physics elastic: model an ElasticModel; source_type
    "force" or "moment" with source_components (n_shots, 1, 2 or 3) (adseismic.solve.elastic); recording says
    what the receivers record, and receiver_locations are its recording.locations (the points, then the DAS
    gauges' ends).
    """

    plan: Plan
    model: Model | ElasticModel
    source_locations: np.ndarray
    receiver_locations: np.ndarray
    source_amplitudes: np.ndarray
    wavelet: np.ndarray
    source_type: str | None = None
    source_components: np.ndarray | None = None
    recording: object = None  # adseismic.solve.receivers.Recording (physics elastic)


def _nice_floor(x: float, digits: int = 2) -> float:
    """Round down to `digits` significant digits (keeps plans readable and reproducible)."""
    e = math.floor(math.log10(x)) - digits + 1
    return float(f"{math.floor(x / 10**e + 1e-9)}e{e}")


def _nice_ceil(x: float, digits: int = 2) -> float:
    """Round up to `digits` significant digits."""
    e = math.floor(math.log10(x)) - digits + 1
    return float(f"{math.ceil(x / 10**e - 1e-9)}e{e}")


MIN_VELOCITY = 10.0  # m/s: below this a P velocity is a unit error (km/s typed as m/s), not a material
MAX_VELOCITY = 15000.0  # m/s: above this (faster than any rock) a warning asks whether the units are right
ABSURD_CELLS = 1e13  # grid cells (all shots) that no machine holds (4e13 bytes at float32 for one field)
ABSURD_CELL_STEPS = 1e20  # cell updates that no machine runs (~100 years at 3e10 per second)
ABSURD_VELOCITY = 1e5  # m/s: above this a velocity is refused (a unit error: mm/s? cm/s?)
LONG_RUN_SECONDS = 86400.0  # a forward run estimated above a day gets a warning with the estimate


def check_velocity_units(vmin: float, vmax: float, key: str = "model") -> list:
    """Refuse velocities below MIN_VELOCITY m/s (ValueError naming `key`: km/s typed as m/s); warnings (list of str)
    for velocities above MAX_VELOCITY m/s."""
    if vmin < MIN_VELOCITY:
        raise ValueError(f"{key}: velocities {vmin:.4g}..{vmax:.4g} m/s go below {MIN_VELOCITY:g} m/s, slower than any "
                         f"seismic P wave; km/s? multiply by 1000 (for a model file set model.units: km/s)")
    if vmax > ABSURD_VELOCITY:
        raise ValueError(f"{key}: velocities up to {vmax:.4g} m/s, more than {ABSURD_VELOCITY:g} m/s (no seismic wave is "
                         f"faster than ~14 km/s); check the units: velocities are in m/s")
    if vmax > MAX_VELOCITY:
        return [f"{key}: velocities up to {vmax:.4g} m/s are faster than any rock ({MAX_VELOCITY:g} m/s); check the "
                f"units (m/s expected)"]
    return []


def forward_memory_bytes(padded: int, n_shots: int, n_receivers: int, nt: int, itemsize: int,
                         physics: str = "acoustic", ndim: int = 2) -> int:
    """Estimated peak bytes of a forward run of every shot at once: acoustic, per shot u_prev, u and the CPML strips
    (~3 padded grids), one padded model, and the receiver data on the device and on the host; elastic, per shot two
    states of 5 fields and their CPML memory (bounded by 16 padded grids), 6 padded material grids, three
    components' data; elastic3d (3D elastic), per shot two states of 9 fields and their CPML memory (bounded by 54
    padded grids), 11 padded material grids, four components' data; acoustic_vd (2D or 3D), per shot two states of
    ndim + 1 fields and their CPML memory (bounded by 2 (2 ndim + 1) + 1 padded grids), ndim + 3 padded model and
    material grids, ndim + 1 components' data."""
    if physics == "elastic":
        return int(itemsize * (16 * padded * n_shots + 6 * padded) + 6 * itemsize * n_shots * n_receivers * nt)
    if physics == "elastic3d":  # an upper bound: two states of 9 fields, their CPML memory (6 strips of 3 components
        # each) counted as whole padded grids, 3 + 8 padded material grids, four components' data on device and host
        return int(itemsize * (54 * padded * n_shots + 11 * padded) + 8 * itemsize * n_shots * n_receivers * nt)
    if physics == "acoustic_vd":
        fields = (4 * ndim + 3) * padded * n_shots + (ndim + 3) * padded
        return int(itemsize * fields + 2 * (ndim + 1) * itemsize * n_shots * n_receivers * nt)
    return int(itemsize * (3 * padded * n_shots + padded) + 2 * itemsize * n_shots * n_receivers * nt)


class _GridSize:
    """The sizes of kernels.acoustic.Acoustic's padded grid and CPML strips, without building its kernels or arrays
    (what solve.acoustic.plan_segments reads)."""

    def __init__(self, plan, n_shots: int):
        import warp as wp

        R, nb, ndim = plan.order // 2, plan.pml_width, plan.ndim
        shape3 = (plan.shape[0], plan.shape[1] if ndim == 3 else 1, plan.shape[-1])
        lo = [0 if plan.free_surface else nb, nb if ndim == 3 else 0, nb]
        hi = [nb, nb if ndim == 3 else 0, nb]
        halo = [R, R if ndim == 3 else 0, R]
        self.n_shots = int(n_shots)
        self.dtype = wp.float32 if plan.precision == "float32" else wp.float64
        self.padded = tuple(shape3[a] + lo[a] + hi[a] + 2 * halo[a] for a in range(3))
        self.strip_width = [((3 * halo[a] + lo[a]) if lo[a] else 0) + ((3 * halo[a] + hi[a]) if hi[a] else 0) for a in range(3)]

    def strip_shape(self, axis: int):
        shape = [self.n_shots, *self.padded]
        shape[axis + 1] = self.strip_width[axis]
        return tuple(shape)


def gradient_memory_bytes(plan, n_shots: int, memory_budget: float | None = None) -> int:
    """Estimated peak bytes of one checkpointed gradient of `n_shots` shots at once on the planned grid: the
    checkpoint plan solve.acoustic.plan_segments would choose within `memory_budget` (bytes; None: the memory
    minimum). ValueError when the budget is below that gradient's minimum."""
    from adseismic.solve.acoustic import plan_segments

    _, peak = plan_segments(_GridSize(plan, n_shots), plan.nt, memory_budget)
    return int(peak)


def check_memory(need: int, sim, what: str, advice: str) -> str:
    """Refuse (ValueError) an estimated `need` bytes above simulation.memory_budget_gb or, without a budget, above
    the device's free memory, unless simulation.force; returns a one-line account of the comparison."""
    from adseismic.data.memory import available_bytes

    budget = getattr(sim, "memory_budget_gb", None)
    if budget is not None:
        limit, key, where = budget * 1e9, "simulation.memory_budget_gb", f"the budget simulation.memory_budget_gb = {budget:g} GB"
    else:
        free = available_bytes(str(sim.device))
        if free is None:
            return f"estimated {need / 2**30:.3g} GiB ({what}); free memory of {sim.device} unknown, not checked"
        limit, key, where = free, "simulation", f"the {free / 2**30:.3g} GiB free on {sim.device} now"
    line = f"estimated {need / 2**30:.3g} GiB ({what}) of {where}"
    if need > limit:
        if getattr(sim, "force", False):
            return line + " -- above it, running anyway (simulation.force)"
        raise ValueError(f"{key}: the run needs an estimated {need / 2**30:.3g} GiB ({what}), more than {where}; "
                         f"{advice}, or set simulation.force: true (adseismic --force) to run anyway")
    return line


def _sampled_wavelet(kind: str, params: dict):
    """(samples, dt in s) of a configured wavelet, sampled finely."""
    if "peak_frequency" in params:
        dt0 = 1.0 / (50.0 * float(params["peak_frequency"]))
        nt0 = int(round((float(params.get("delay") or 0.0) + 10.0 / float(params["peak_frequency"])) / dt0))
    else:
        dt0 = float(params.get("dt_in", 1e-3))
        nt0 = len(params["samples"])
    return make_wavelet(kind, nt0, dt0, **params), dt0


def wavelet_dominant_frequency(kind: str, params: dict) -> float:
    """The peak of a configured wavelet's amplitude spectrum (Hz), sampled finely."""
    w, dt0 = _sampled_wavelet(kind, params)
    return dominant_frequency(w[None], dt0)


def wavelet_band(kind: str, params: dict):
    """(f_max at -20 dB in Hz, duration in s) of a configured wavelet, sampled finely."""
    w, dt0 = _sampled_wavelet(kind, params)
    return spectral_fmax(w, dt0, -20.0), duration(w, dt0)


RAY_SAMPLES = 512  # points along each straight ray of the planner's longest direct arrival (straight_ray_times)


def straight_ray_times(model: Model, sources: np.ndarray, receivers: np.ndarray, slowness=None,
                       max_samples: int | None = None) -> np.ndarray:
    """Travel times (s) along straight rays through the model's slowness, (n_sources, n_receivers); ``slowness``: another
    integrand on the model's grid (e.g. 1 / (v Q), which gives the attenuation time t* in s). Each source's rays are
    sampled every half cell, or at ``max_samples`` points where that is fewer (the planner's bound on the record length,
    RAY_SAMPLES, needs no finer: on the Marmousi-II race's start model, 7.5 m cells, 8 km rays, 512 points change the
    longest time by 2e-8 of it and take 0.36 s where half-cell sampling takes 1.28 s)."""
    slow = 1.0 / model.values if slowness is None else slowness
    h = min(model.spacing)
    org, spc = np.array(model.origin), np.array(model.spacing)
    out = np.zeros((len(sources), len(receivers)))
    for i, s in enumerate(sources):
        seg = receivers - s
        length = np.linalg.norm(seg, axis=1)
        n = max(int(np.ceil(length.max() / (0.5 * h))), 1) + 1
        n = n if max_samples is None else min(n, max_samples)
        frac = np.linspace(0.0, 1.0, n)
        pts = s[None, None, :] + frac[None, :, None] * seg[:, None, :]  # (n_rec, n, ndim)
        idx = ((pts - org) / spc).reshape(-1, model.ndim).T
        vals = map_coordinates(slow, idx, order=1, mode="nearest").reshape(len(receivers), n)
        out[i] = np.trapezoid(vals, frac, axis=1) * length
    return out


_ARRIVALS = weakref.WeakKeyDictionary()  # model -> {geometry: _longest_direct_arrival's result}


def _longest_direct_arrival(model, src, rec, free_surface: bool):
    """(time in s, the wave's name for the plan, the VTI ray times or None) of the slowest direct wave over every
    source-receiver pair: qP (group velocity) for VTI, P for a fluid or visco-acoustic model, S (Rayleigh along a
    free surface) for an elastic one, else the acoustic wave; straight rays (RAY_SAMPLES points). Kept per model
    object (models are immutable) and geometry: an FWI plans each band's grid for the same model and geometry, and
    the rays do not depend on the grid (0.3-0.6 s a plan for the Marmousi-II race)."""
    key = (src.shape, src.tobytes(), rec.shape, rec.tobytes(), free_surface)
    try:
        kept = _ARRIVALS.setdefault(model, {})
    except TypeError:  # a model that cannot be weakly referenced: computed every time
        kept = {}
    if key not in kept:
        kept[key] = _direct_arrival(model, src, rec, free_surface)
    return kept[key]


def _direct_arrival(model, src, rec, free_surface: bool):
    """_longest_direct_arrival, computed."""
    if isinstance(model, VTIModel):
        rays = vti_ray_times(model, src, rec)
        return float(rays[0].max()), "qP-wave (group velocity) ", rays
    if isinstance(model, ViscoacousticModel) or (isinstance(model, ElasticModel) and model.vs is None):
        return float(straight_ray_times(model.vp, src, rec, max_samples=RAY_SAMPLES).max()), "P-wave ", None
    if isinstance(model, ElasticModel):  # the slowest direct wave arrives last: S, or the Rayleigh wave along a free surface
        i = np.unravel_index(int(np.argmin(model.vs.values)), model.shape)
        slowdown = rayleigh_speed(model.vp.values[i], model.vs.values[i]) / model.vs.values[i] if free_surface else 1.0
        t = float(straight_ray_times(model.vs, src, rec, max_samples=RAY_SAMPLES).max()) / slowdown
        return t, "Rayleigh-wave " if free_surface else "S-wave ", None
    return float(straight_ray_times(model, src, rec, max_samples=RAY_SAMPLES).max()), "", None


def _staggered_reasons(grid, model, vmin, vmax, box, attenuation, dx_planned: bool) -> tuple[str, str]:
    """The plan's reasons for dx and dt of a staggered physics (plan_elastic_grid's), with what sets them in
    acoustic_vd (P at vp_min), vti (qP, the horizontal speed) and viscoacoustic (the phase velocity at the Q band's
    low end, the unrelaxed speed); box: vp over the planned domain (m/s); dx_planned: dx not pinned."""
    why_dx, why_dt = grid.reasons["dx"], grid.reasons["dt"]
    if isinstance(model, ElasticModel) and model.vs is None and dx_planned:
        why_dx += f"; acoustic_vd: the slowest wave is P at vp_min {vmin:.0f} m/s (vs = 0: no S wave)"
    if isinstance(model, VTIModel):
        if dx_planned:
            why_dx += (f"; vti: the slowest wave is qP at {vmin:.0f} m/s (vp_min {float(box.min()):.0f} m/s, vertical; "
                       f"lower where delta < 0)")
        why_dt = why_dt.replace(f"for vp_max {vmax:.0f} m/s", f"for the horizontal speed max vp sqrt(1 + 2 epsilon) = "
                                                               f"{vmax:.0f} m/s")
    if attenuation is not None:
        a = attenuation
        if dx_planned:
            why_dx += (f"; viscoacoustic: the slowest wave is P at {vmin:.0f} m/s, the phase velocity at the Q band's low "
                       f"end {a.q_band[0]:.3g} Hz (vp_min {float(box.min()):.0f} m/s at f_ref {a.f_ref:.3g} Hz)")
        why_dt = why_dt.replace(f"for vp_max {vmax:.0f} m/s", f"for the unrelaxed (w -> infinity) speed {vmax:.0f} m/s "
                                f"({100 * (vmax / float(box.max()) - 1):.1f}% above vp_max {float(box.max()):.0f} m/s at f_ref, "
                                f"Q down to {a.q_min:.3g})")
    return why_dx, why_dt


def _forward_cost(kind: str, ndim: int, padded: int, nt: int, n_shots: int, n_receivers: int, sim) -> tuple[float, float]:
    """(peak bytes of a forward run of every shot, estimated seconds a shot) of a scheme kind ("acoustic", "elastic"
    (every other 2D staggered physics; vti: an upper bound, 4 fields and 4 memory variables where the elastic step has 5
    and 8, docs/vti.md), "elastic3d" or "acoustic_vd" (its own kernels, 2D or 3D)) on padded cells x nt steps in ndim
    dimensions, in sim's precision and on its device."""
    itemsize = 4 if sim.precision == "float32" else 8
    memory = forward_memory_bytes(padded, n_shots, n_receivers, nt, itemsize, kind, ndim)
    device_kind = "cuda" if str(sim.device).startswith("cuda") else "cpu"
    step_cost = {"acoustic": 1.0, "elastic": ELASTIC_STEP_COST, "elastic3d": ELASTIC3D_STEP_COST,
                 "acoustic_vd": ACOUSTIC_VD_STEP_COST[ndim]}[kind]
    seconds = padded * nt / EST_RATE[device_kind] * step_cost
    if kind in ("elastic", "elastic3d") and device_kind == "cpu":
        seconds += nt * ELASTIC_CPU_STEP_SECONDS
    return memory, seconds


def _group_error(order, ndim, vmin, vmax, f_max, dx, dt) -> float:
    """Worst group-velocity error at f_max over the slowest and the fastest wave."""
    return max(dispersion_error(order, ndim, v / (f_max * dx), v * dt / dx)["group"][0] for v in (vmin, vmax))


def _choose_dx_dt(order, ndim, vmin, vmax, f_max, accuracy, safety, pins, extent_cells_fn, t_record):
    """(dx, dt, reason_dx, reason_dt) minimising cells x steps subject to the accuracy target."""
    limit = cfl_limit(order, ndim)
    if pins.get("dt") is not None and pins.get("dx") is not None:
        return pins["dx"], pins["dt"], "pinned by the config", "pinned by the config"
    if pins.get("dt") is not None:
        # dt pinned, dx free: the planner's own dx if the pinned dt is stable with it (Courant <= cfl_safety x the
        # limit), else the smallest such dx; the plan then warns if it misses the accuracy target
        dt = float(pins["dt"])
        free_dx, free_dt, why, _ = _choose_dx_dt(order, ndim, vmin, vmax, f_max, accuracy, safety, {}, extent_cells_fn, t_record)
        dx_stable = vmax * dt / (safety * limit)
        if free_dx >= dx_stable:  # dispersion depends on dt too: a finer dx (still stable) where the pinned dt needs it
            dx = free_dx
            while _group_error(order, ndim, vmin, vmax, f_max, dx, dt) > accuracy and _nice_floor(0.98 * dx) >= dx_stable:
                dx = _nice_floor(0.98 * dx)
            if dx != free_dx:
                why = (f"{vmin / (f_max * dx):.1f} points per minimum wavelength (v_min {vmin:.0f} m/s at f_max {f_max:.3g} Hz) "
                       f"meet the {100 * accuracy:g}% group-velocity target at order {order} with the pinned dt")
            return dx, dt, why, "pinned by the config"
        dx = _nice_ceil(dx_stable)
        return dx, dt, (f"the smallest dx for which the pinned dt = {dt:g} s is stable ({safety:g} x the CFL limit at v_max "
                        f"{vmax:.0f} m/s); the accuracy target needs dx <= {free_dx:g} m, which needs dt <= {free_dt:g} s"), \
            "pinned by the config"
    best = None
    for s in SAFETY_STEPS:
        c_max = safety * s * limit
        c_min = c_max * vmin / vmax
        try:
            ppw_slow = ppw_for_error(order, ndim, c_min, accuracy)
            ppw_fast = ppw_for_error(order, ndim, c_max, accuracy)
        except ValueError:
            continue
        dx = pins["dx"] if pins.get("dx") is not None else _nice_floor(min(vmin / (f_max * ppw_slow), vmax / (f_max * ppw_fast)))
        dt = pins["dt"] if pins.get("dt") is not None else _nice_floor(c_max * dx / vmax)
        # rounding moves the Courant number, and the error is not monotonic in it: re-check
        while pins.get("dx") is None and _group_error(order, ndim, vmin, vmax, f_max, dx, dt) > accuracy:
            dx = _nice_floor(0.98 * dx)
            dt = pins["dt"] if pins.get("dt") is not None else _nice_floor(c_max * dx / vmax)
        cost = extent_cells_fn(dx) * t_record / dt
        if best is None or cost < best[0]:
            why = (f"{vmin / (f_max * dx):.1f} points per minimum wavelength (v_min {vmin:.0f} m/s at f_max {f_max:.3g} Hz) "
                   f"meet the {100 * accuracy:g}% group-velocity target at order {order}")  # fmt: skip
            why_dt = f"{safety * s:.2f} x the CFL limit (the cheapest dt/dx pair that meets the accuracy target)"
            best = (cost, dx, dt, why if pins.get("dx") is None else "pinned by the config", why_dt if pins.get("dt") is None else "pinned by the config")
    if best is None:
        raise ValueError(f"simulation.accuracy: {accuracy:g} cannot be reached at order {order}; raise the target (e.g. 0.01) or use order 4 or 8")
    return best[1:]


def plan_scene(config, velocity_range=None, f_max=None, force=None, check_memory_of_run=True, vs_range=None) -> Plan:
    """Plan the simulation grid, time step, record and domain for a ForwardConfig (see config.py).

    velocity_range: (v_min, v_max) m/s to plan for instead of the model's own range (an inversion
    plans for its velocity bounds, so that every model it may visit is stable and resolved; physics vti and
    viscoacoustic: the slowest and the fastest wave speed, the qP or P phase speeds that the model's own range gives).
    f_max: highest frequency (Hz) the simulation must resolve, when below the wavelet's -20 dB edge
    (an inversion whose highest band is low-passed).

    Refuses (ValueError naming the key): velocities below 10 m/s (km/s typed as m/s); a forward run whose
    estimated memory (Plan.memory_bytes: every shot at once) exceeds simulation.memory_budget_gb or, without a
    budget, the device's free memory (adseismic.data.memory.available_bytes) -- unless ``force`` (default:
    config.simulation.force; the CLI's --force sets it) is true. check_memory_of_run=False skips that comparison
    (callers that run something else than this forward run, e.g. an inversion, check their own estimate).

    Physics elastic (config.model an ElasticModel): velocity_range is vp's, vs_range (vs_min, vs_max) m/s the shear
    speeds to plan for (default the model's); dx and dt by :func:`plan_elastic_grid` (dx, dt pins honoured).
    """
    model, geo, sim = config.model, config.geometry, config.simulation
    if force is not None and bool(force) != bool(getattr(sim, "force", False)):
        import dataclasses

        sim = dataclasses.replace(sim, force=bool(force))
    ndim, order = model.ndim, int(sim.order)
    src, rec = np.asarray(geo.sources, float), np.asarray(geo.receivers, float)
    for name, pts in (("geometry.sources", src), ("geometry.receivers", rec)):
        inside = model.contains(pts)
        if not inside.all():
            i = int(np.argmin(inside))
            raise ValueError(f"{name}[{i}] = {pts[i].tolist()} m lies outside the model {[list(e) for e in model.extent]} m; move it inside or extend the model")
    warnings = check_velocity_units(model.vmin, model.vmax, "model")
    if velocity_range is not None:
        check_velocity_units(*map(float, velocity_range), "inversion.bounds")
    f_wavelet, w_len = wavelet_band(config.wavelet.kind, config.wavelet.params)
    f_max = f_wavelet if f_max is None else min(float(f_max), f_wavelet)

    elastic = isinstance(model, ElasticModel)  # elastic or acoustic_vd: the elastic solver
    fluid = elastic and model.vs is None  # acoustic_vd: P waves only
    vti = isinstance(model, VTIModel)  # the pseudo-acoustic VTI solver: qP waves, staggered like the elastic one
    visco = isinstance(model, ViscoacousticModel)  # the visco-acoustic solver: P waves, staggered like the elastic one
    t_direct, wave, rays = _longest_direct_arrival(model, src, rec, bool(sim.free_surface))
    if sim.duration is not None:
        t_record = float(sim.duration)
        why_nt = "pinned by the config"
        if t_record < t_direct:
            warnings.append(f"record length {t_record:g} s is shorter than the longest direct arrival ({t_direct:.3g} s)")
    else:
        t_record = t_direct + w_len
        why_nt = f"longest straight-ray {wave}source-receiver time {t_direct:.3g} s + wavelet duration {w_len:.3g} s"

    pts = np.vstack([src, rec])
    lo_m = np.array([e[0] for e in model.extent])
    hi_m = np.array([e[1] for e in model.extent])
    if sim.domain == "model":
        lo, hi = lo_m, hi_m
        why_domain = "the whole model (domain: model)"
    else:
        margin = float(sim.margin) if sim.margin is not None else model.vmax * t_record / 2.0
        lo = np.maximum(pts.min(0) - margin, lo_m)
        hi = np.minimum(pts.max(0) + margin, hi_m)
        why_domain = (f"sources/receivers box + {margin:.0f} m margin ({'pinned' if sim.margin is not None else 'v_max T / 2: nothing farther returns energy within the record'}), "
                      "cut to the model")  # fmt: skip
    org, spc = np.array(model.origin), np.array(model.spacing)
    i0 = np.floor((lo - org) / spc + 1e-9).astype(int)
    i1 = np.ceil((hi - org) / spc - 1e-9).astype(int) + 1
    box = model.values[tuple(slice(a, b) for a, b in zip(i0, i1))]
    vmin, vmax = (float(box.min()), float(box.max())) if velocity_range is None else map(float, velocity_range)
    if vti and velocity_range is None:  # the slowest qP speed (min over angles of the phase = group speed), the horizontal one
        sl = tuple(slice(a, b) for a, b in zip(i0, i1))
        vmin = float((box * qp_min_speed_ratio(model.epsilon[sl], model.delta[sl])).min())
        vmax = float(model.horizontal_speed()[sl].max())
    if visco:  # the slowest P phase velocity (at the Q band's low end) and the fastest, the unrelaxed speed
        attenuation = attenuation_check(model, src, rec, config.wavelet, (i0, i1))
        vmin, vmax = (attenuation.v_slowest, attenuation.v_unrelaxed) if velocity_range is None else (vmin, vmax)
        if not attenuation.q_band[0] <= attenuation.f_dominant <= attenuation.q_band[1]:
            warnings.append(f"model.q_band: {list(attenuation.q_band)} Hz misses the wavelet's dominant frequency "
                            f"{attenuation.f_dominant:.3g} Hz; Q is flat (its target) only inside the band: widen it or leave it "
                            f"out (f_dom / 3 .. 2.5 f_dom)")

    pml = DEFAULT_PML_WIDTH if sim.pml_width is None else int(sim.pml_width)

    def cells(dx):
        n = np.ceil((hi - lo) / dx - 1e-9) + 1 + 2 * pml
        return float(np.prod(n))

    pins = {"dx": sim.dx, "dt": sim.dt}
    if elastic or vti or visco:
        vs_box = 0.0 if vti or visco else model.materials()["vs"][tuple(slice(a, b) for a, b in zip(i0, i1))]
        vs_min = float(np.min(vs_box)) if vs_range is None else float(vs_range[0])
        grid = plan_elastic_grid((vmin, vmax), vs_min, f_max, order, float(sim.accuracy), float(sim.cfl_safety),
                                 bool(sim.free_surface), dx=sim.dx, dt=sim.dt, ndim=ndim)
        dx, dt = grid.dx, grid.dt
        why_dx, why_dt = _staggered_reasons(grid, model, vmin, vmax, box, attenuation if visco else None, pins["dx"] is None)
    else:
        dx, dt, why_dx, why_dt = _choose_dx_dt(order, ndim, vmin, vmax, f_max, float(sim.accuracy), float(sim.cfl_safety), pins, cells, t_record)
    try:
        check_courant(VTI if vti else VISCOACOUSTIC if visco else (ELASTIC3D if ndim == 3 else ELASTIC) if elastic else ACOUSTIC,
                      order, ndim, vmax, dx, dt)
    except ValueError as e:
        raise ValueError(f"simulation.{e}") from None
    n_cells, n_steps = cells(dx), t_record / dt + 1  # floats: inf for absurd grids, where ints would overflow later
    if not (n_cells * n_steps * len(src) <= ABSURD_CELL_STEPS and n_cells * len(src) <= ABSURD_CELLS):
        raise ValueError(f"simulation: the plan has {n_cells:.3g} cells x {n_steps:.3g} steps x {len(src)} shot(s) (dx = {dx:g} m, "
                         f"dt = {dt:g} s, a {t_record:.4g} s record over {' x '.join(f'{e:.4g}' for e in hi - lo)} m), beyond any "
                         f"machine even with simulation.force; check the units of dx, dt, duration, the model's spacing and "
                         f"velocities (m, s, m/s) and the wavelet's frequency (Hz)")
    staggered = elastic or vti or visco  # the staggered scheme's limit, dispersion and cost
    limit = grid.cfl_limit if staggered else cfl_limit(order, ndim)
    courant = vmax * dt / dx
    err = grid.expected_error if staggered else _group_error(order, ndim, vmin, vmax, f_max, dx, dt)
    v_slow = vs_min if elastic else vmin
    if err > float(sim.accuracy):
        warnings.append(
            f"under-resolved: expected group-velocity error {100 * err:.2f}% at f_max {f_max:.3g} Hz exceeds the target "
            f"{100 * sim.accuracy:g}% ({v_slow / (f_max * dx):.1f} points per minimum wavelength at dx = {dx:g} m); "
            f"over the longest path ({t_direct:.3g} s) that is ~{err * t_direct * 1e3:.1f} ms of travel-time error"
        )
    if courant < 0.2 * limit:
        warnings.append(f"dt is {courant / limit:.2f} of the CFL limit: the run takes {limit / courant:.1f}x more steps than needed for stability")

    shape = tuple(int(n) for n in np.ceil((hi - lo) / dx - 1e-9) + 1)  # covers every source and receiver
    nt = int(math.ceil(t_record / dt)) + 1
    refl = DEFAULT_PML_REFLECTION[order] if sim.pml_reflection is None else float(sim.pml_reflection)
    padded = math.prod(int(n) + 2 * pml + order for n in shape)  # Python ints: no int64 overflow for absurd grids
    kind = "acoustic_vd" if fluid else "elastic3d" if elastic and ndim == 3 else "elastic" if staggered else "acoustic"
    memory, seconds = _forward_cost(kind, ndim, padded, nt, len(src), len(rec), sim)
    if seconds * len(src) > LONG_RUN_SECONDS:
        warnings.append(f"long run: an estimated {seconds * len(src) / 3600:.3g} h on {sim.device} for {len(src)} shot(s) "
                        f"({padded:,} padded cells x {nt:,} steps each); check the velocities, the wavelet's frequency and "
                        f"simulation.accuracy")
    if check_memory_of_run:
        grid = " x ".join(str(n) for n in shape)
        memory_line = check_memory(memory, sim, f"forward run: {len(src)} shot(s) on a {grid} grid, {nt:,} steps",
                                   "lower the wavelet's frequency, relax simulation.accuracy, use fewer shots or a smaller domain")
        reasons_memory = memory_line
    else:
        reasons_memory = None
    return Plan(
        ndim=ndim, order=order, dx=float(dx), dt=float(dt), nt=nt, shape=shape, origin=tuple(float(x) for x in lo),
        pml_width=pml, pml_reflection=refl, free_surface=bool(sim.free_surface), device=str(sim.device),
        precision=str(sim.precision), f_max=float(f_max), expected_error=float(err), courant=float(courant),
        cfl_limit=float(limit), padded_cells=padded, memory_bytes=int(memory),
        seconds_per_shot=seconds, n_shots=len(src), physics=model.physics if staggered else "acoustic",
        reasons={"dx": why_dx, "dt": why_dt, "nt": why_nt, "domain": why_domain,
                 **({"memory": reasons_memory} if reasons_memory else {}),
                 **({"density": density_reflection_check(model, (i0, i1)).describe()} if fluid else {}),
                 **({"anisotropy": anisotropy_check(model, rays, wavelet_dominant_frequency(config.wavelet.kind, config.wavelet.params),
                                                    (i0, i1)).describe()}
                    if vti else {})}, warnings=warnings, attenuation=attenuation if visco else None,
    )  # fmt: skip


def build_scene(config, plan: Plan | None = None, model: Model | None = None) -> Scene:
    """Plan (unless given) and materialise the scene: resampled model (config.model, or `model`),
    locations, source wavelets."""
    plan = plan or plan_scene(config)
    model = (model or config.model).resample(plan.dx, plan.origin, plan.shape)
    origin = np.array(plan.origin)
    src = np.asarray(config.geometry.sources, float) - origin
    rec = np.asarray(config.geometry.receivers, float) - origin
    n_shots = len(src)
    wavelet = make_wavelet(config.wavelet.kind, plan.nt, plan.dt, **config.wavelet.params)
    elastic = {}
    if isinstance(model, (ElasticModel, VTIModel, ViscoacousticModel)):
        from adseismic.solve.receivers import DasOperator, Recording

        das = config.geometry.das  # a config built in Python may leave out what parse_config fills in: its defaults
        solid = ("vx", "vy", "vz", "pressure") if model.ndim == 3 else ("vx", "vz", "pressure")
        default = solid if getattr(model, "vs", None) is not None else ("pressure",)
        components = tuple(config.geometry.components) or (() if das else default)
        recording = Recording(components, das and DasOperator(das.gauge_length, das.direction))
        rec = recording.locations(rec)
        source = config.source
        explosive = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0] if model.ndim == 3 else [1.0, 1.0, 0.0])
        kind, comp = ("moment", explosive) if source is None else (source.solver_type, np.asarray(source.components, float))
        elastic = {"source_type": kind, "recording": recording,
                   "source_components": np.broadcast_to(comp, (n_shots, 1, comp.size)).copy()}
    return Scene(
        plan=plan,
        model=model,
        source_locations=src[:, None, :],
        receiver_locations=np.broadcast_to(rec, (n_shots, *rec.shape)).copy(),
        source_amplitudes=np.broadcast_to(wavelet, (n_shots, 1, plan.nt)).copy(),
        wavelet=wavelet,
        **elastic,
    )


def run_forward(scene: Scene, snapshot_every: int = 0, progress: bool = False):
    """Run the planned forward simulation for every shot of the scene at once: a ForwardResult (acoustic) or, for an
    ElasticModel, adseismic.solve.elastic's ElasticResult (3D: adseismic.solve.elastic3d's Elastic3DResult; vs None, i.e.
    acoustic_vd: adseismic.solve.acoustic_vd's AcousticVDResult, the explosive source's moment M0 x the wavelet), for a
    VTIModel adseismic.solve.vti's VTIResult, for a ViscoacousticModel adseismic.solve.viscoacoustic's ViscoacousticResult
    (with the plan's q_band, f_ref, mechanisms) (VTI and visco-acoustic: the explosive source's moment M0 x the wavelet),
    at scene.receiver_locations (no snapshots)."""
    p = scene.plan
    if isinstance(scene.model, ViscoacousticModel):
        from adseismic.solve.viscoacoustic import forward_viscoacoustic

        m, a = scene.model.materials(), p.attenuation
        return forward_viscoacoustic(
            m["vp"], m["q"], m["rho"], p.dx, p.dt, scene.source_amplitudes * scene.source_components[:, :, :1],
            scene.source_locations, scene.receiver_locations, q_band=a.q_band, f_ref=a.f_ref, mechanisms=a.mechanisms,
            order=p.order, pml_width=p.pml_width, pml_reflection=p.pml_reflection, free_surface=p.free_surface,
            device=p.device, precision=p.precision, progress=progress,
        )  # fmt: skip
    if isinstance(scene.model, VTIModel):
        from adseismic.solve.vti import forward_vti

        m = scene.model.materials()
        return forward_vti(
            m["vp"], m["epsilon"], m["delta"], m["rho"], p.dx, p.dt, scene.source_amplitudes * scene.source_components[:, :, :1],
            scene.source_locations, scene.receiver_locations, order=p.order, pml_width=p.pml_width,
            pml_reflection=p.pml_reflection, free_surface=p.free_surface, device=p.device, precision=p.precision, progress=progress,
        )  # fmt: skip
    if isinstance(scene.model, ElasticModel) and scene.model.vs is None:  # acoustic_vd: its own kernels, 2D or 3D
        from adseismic.solve.acoustic_vd import forward_acoustic_vd

        m = scene.model.materials()
        return forward_acoustic_vd(
            m["vp"], m["rho"], p.dx, p.dt, scene.source_amplitudes * scene.source_components[:, :, :1], scene.source_locations,
            scene.receiver_locations, order=p.order, pml_width=p.pml_width, pml_reflection=p.pml_reflection,
            free_surface=p.free_surface, device=p.device, precision=p.precision, progress=progress,
        )  # fmt: skip
    if isinstance(scene.model, ElasticModel):
        from adseismic.solve.elastic import forward_elastic
        from adseismic.solve.elastic3d import forward_elastic3d

        m = scene.model.materials()
        return (forward_elastic3d if scene.model.ndim == 3 else forward_elastic)(
            m["vp"], m["vs"], m["rho"], p.dx, p.dt, scene.source_amplitudes, scene.source_locations,
            scene.receiver_locations, source_type=scene.source_type, source_components=scene.source_components,
            order=p.order, pml_width=p.pml_width, pml_reflection=p.pml_reflection, free_surface=p.free_surface,
            device=p.device, precision=p.precision, progress=progress,
        )  # fmt: skip
    return forward(
        scene.model.values, p.dx, p.dt, scene.source_amplitudes, scene.source_locations, scene.receiver_locations,
        order=p.order, pml_width=p.pml_width, pml_reflection=p.pml_reflection, free_surface=p.free_surface,
        device=p.device, precision=p.precision, snapshot_every=snapshot_every, progress=progress,
    )  # fmt: skip


# --- Elastic (velocity-stress, staggered grid) --------------------------------------------------------

RAYLEIGH_PPW = 20.0  # points per Rayleigh wavelength at f_max with a free surface (Lamb's problem, order 4:
# 21 points give <= 2.7% trace error, 10 points 9%; docs/accuracy.md; reference.md asks 15-30)


@dataclass
class ElasticGridPlan:
    """dx (m) and dt (s) for the 2D or 3D elastic scheme, with the wave that set them and the reasons."""

    dx: float
    dt: float
    courant: float
    cfl_limit: float
    slowest: str
    expected_error: float
    reasons: dict = field(default_factory=dict)


def plan_elastic_grid(vp_range, vs_min: float, f_max: float, order: int = 4, accuracy: float = 0.01,
                      cfl_safety: float = 0.9, free_surface: bool = False, dx: float | None = None,
                      dt: float | None = None, ndim: int = 2) -> ElasticGridPlan:  # fmt: skip
    """Coarsest dx and its dt for the staggered elastic scheme in ``ndim`` (2 or 3) dimensions (kernels/elastic/,
    kernels/elastic3d/: the CFL limit and the worst-direction dispersion of that dimension).

    vp_range (vp_min, vp_max) m/s; vs_min m/s (0 for a fluid somewhere: the slowest wave is then vp_min);
    f_max Hz. The slowest wave is S (or P in a fluid), or with a free surface the Rayleigh wave, which
    also needs RAYLEIGH_PPW points per wavelength (its error is set by the free-surface stencils, not by
    the interior dispersion). dt = cfl_safety x the staggered CFL limit for vp_max; dx meets the
    worst-direction group-velocity `accuracy` at f_max (numerics.staggered_dispersion_error) for the
    slowest and the fastest wave. dx (m) and dt (s), when given, are pins: a pinned dt alone gets the planned dx or
    the smallest dx for which it is stable (cfl_safety x the limit), whichever is larger; a pinned dx alone its dt.
    """
    pin_dx, pin_dt = dx, dt
    vp_min, vp_max = (float(v) for v in vp_range)
    limit = staggered_cfl_limit(order, ndim)
    c_max = cfl_safety * limit
    if vs_min > 0:
        slow, name = float(vs_min), "S"
    else:
        slow, name = vp_min, "P (fluid)"
    need = []
    for v, label in ((slow, name), (vp_max, "P")):
        ppw = _staggered_ppw(order, c_max * v / vp_max, accuracy, ndim)
        need.append((v / (f_max * ppw), f"{ppw:.1f} points per {label} wavelength ({v:.0f} m/s) for a {100 * accuracy:g}% group-velocity error"))
    if free_surface and vs_min > 0:
        c_r = rayleigh_speed(vp_min, vs_min)
        need.append((c_r / (f_max * RAYLEIGH_PPW), f"{RAYLEIGH_PPW:g} points per Rayleigh wavelength (c_R {c_r:.0f} m/s) at the free surface"))
        name = "Rayleigh"
    dx, why = min(need, key=lambda t: t[0])
    dx = _nice_floor(dx)

    def error(dx, dt):
        return max(staggered_dispersion_error(order, ndim, v / (f_max * dx), v * dt / dx)["group"][0] for v in (slow, vp_max))

    why_dt = f"{cfl_safety:g} x the staggered CFL limit {limit:.4f} (order {order}, {ndim}D) for vp_max {vp_max:.0f} m/s"
    if pin_dx is not None or pin_dt is not None:
        if pin_dx is not None:
            dx, why = float(pin_dx), "pinned by the config"
        elif vp_max * pin_dt / dx > c_max:
            dx = _nice_ceil(vp_max * pin_dt / c_max)
            why = f"the smallest dx for which the pinned dt = {pin_dt:g} s is stable ({why_dt}); {why} would need a smaller dt"
        dt, why_dt = (float(pin_dt), "pinned by the config") if pin_dt is not None else (_nice_floor(c_max * dx / vp_max), why_dt)
    else:
        dt = _nice_floor(c_max * dx / vp_max)
        while error(dx, dt) > accuracy:  # rounding moves the Courant number, and the error is not monotonic in it
            dx = _nice_floor(0.98 * dx)
            dt = _nice_floor(c_max * dx / vp_max)
    courant, err = vp_max * dt / dx, error(dx, dt)
    return ElasticGridPlan(dx=dx, dt=dt, courant=courant, cfl_limit=limit, slowest=name, expected_error=float(err),
                           reasons={"dx": why, "dt": why_dt})  # fmt: skip


def _staggered_ppw(order: int, courant: float, target: float, ndim: int = 2) -> float:
    """Fewest points per wavelength with a staggered group-velocity error <= target in ndim dimensions (bisection)."""
    lo, hi = 2.0, 400.0
    if staggered_dispersion_error(order, ndim, hi, courant)["group"][0] > target:
        raise ValueError(f"a group-velocity error of {target:g} is unreachable at order {order} with Courant number {courant:.3f}")
    for _ in range(60):
        mid = math.sqrt(lo * hi)
        if staggered_dispersion_error(order, ndim, mid, courant)["group"][0] <= target:
            hi = mid
        else:
            lo = mid
    return hi


# --- Which physics a scene needs: density (issue 26, item 7) -------------------------------------------

DENSITY_R_THRESHOLD = 0.01  # absolute error in a normal-incidence reflection coefficient below which dropping the
# density is harmless: the reflected amplitude then moves by < 1% of the incident one, the tolerance of the
# reflection check of tests/test_acoustic_vd.py (issue 26 item 1)


@dataclass
class DensityCheck:
    """The largest error made in a normal-incidence reflection coefficient by dropping the density: ``error`` =
    |R - R0| with R = (Z2 - Z1) / (Z2 + Z1) (Z = rho vp, the model's) and R0 = (v2 - v1) / (v2 + v1) (constant
    density), between vertically adjacent nodes; at ``position`` (z, x) m, the interface's upper node."""

    error: float
    r_density: float
    r_constant: float
    position: tuple

    @property
    def needed(self) -> bool:
        return self.error >= DENSITY_R_THRESHOLD

    def describe(self) -> str:
        where = (f"R = {self.r_density:+.4f} with density, {self.r_constant:+.4f} without, at z = {self.position[0]:g} m, "
                 f"x = {self.position[1]:g} m")
        if self.needed:
            return (f"physics: acoustic drops density contrasts worth up to {self.error:.3g} in reflection coefficient "
                    f"(>= {DENSITY_R_THRESHOLD:g}; {where}); acoustic_vd models them")
        return (f"constant density suffices (error {self.error:.3g} < {DENSITY_R_THRESHOLD:g} in reflection coefficient; "
                f"{where}): physics: acoustic gives the same reflections within 1% of the incident amplitude, faster")


def density_reflection_check(model: ElasticModel, box=None) -> DensityCheck:
    """:class:`DensityCheck` of ``model`` (vp m/s, rho kg/m^3 on its grid, axis order (z, x)), over the index box
    ``box`` = (i0, i1) (per axis, end exclusive; None: the whole model). Node to node along z on the model's own grid,
    so a sharp interface gives its exact coefficients; a gradual transition spreads its contrast over several nodes
    (and reflects less than the same step would)."""
    sl = tuple(slice(None) for _ in range(model.ndim)) if box is None else tuple(slice(a, b) for a, b in zip(*box))
    vp, rho = model.vp.values[sl], model.rho.values[sl]
    if vp.shape[0] < 2:
        return DensityCheck(0.0, 0.0, 0.0, (float(model.origin[0]), float(model.origin[-1])))
    z = rho * vp
    r = (z[1:] - z[:-1]) / (z[1:] + z[:-1])
    r0 = (vp[1:] - vp[:-1]) / (vp[1:] + vp[:-1])
    err = np.abs(r - r0)
    i = np.unravel_index(int(np.argmax(err)), err.shape)
    first = [0 if s.start is None else s.start for s in sl]
    pos = tuple(float(o + (k + f) * h) for o, k, f, h in zip(model.origin, i, first, model.spacing))
    return DensityCheck(float(err[i]), float(r[i]), float(r0[i]), (pos[0], pos[-1]))


# --- Which physics a scene needs: anisotropy (issue 26, item 7) ---------------------------------------------------

ANISOTROPY_PERIODS = 0.25  # travel-time error, in dominant periods, below which dropping the anisotropy is harmless:
# a quarter period shifts a trace by 90 degrees of phase at the dominant frequency, half way to the half-period shift
# where a waveform misfit cycle-skips (locks onto the wrong cycle); below it isotropic data still fit the same arrivals


def qp_group_speed_ratio(epsilon: float, delta: float, angles) -> np.ndarray:
    """The qP group speed over vp at group angles (radians from the vertical, 0..pi/2) of a homogeneous pseudo-acoustic
    VTI medium (C55 = 0; docs/vti.md): the exact phase speed of the Christoffel equation,
    V^2 / vp^2 = (a + b)/2 + sqrt(((a - b)/2)^2 + (1 + 2 delta) sin^2 cos^2) with a = (1 + 2 epsilon) sin^2, b = cos^2 of
    the phase angle, and V_g = sqrt(V^2 + V'^2) at the group angle theta + atan(V'/V), interpolated from 4001 phase angles
    (tests/test_vti.py measures the solver's travel times against it within 0.05%)."""
    th = np.linspace(0.0, np.pi / 2, 4001)
    s2, c2 = np.sin(th) ** 2, np.cos(th) ** 2
    a = (1.0 + 2.0 * epsilon) * s2
    v = np.sqrt(0.5 * (a + c2) + np.sqrt(0.25 * (a - c2) ** 2 + (1.0 + 2.0 * delta) * s2 * c2))
    dv = np.gradient(v, th)
    return np.interp(angles, th + np.arctan2(dv, v), np.hypot(v, dv))


def qp_min_speed_ratio(epsilon: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """min over angles of the qP phase speed over vp (= the group speed's minimum) per node, the arrays' shape: 1 where
    epsilon, delta >= 0 (the vertical is slowest), lower where delta < 0; from 91 phase angles (every 1 degree)."""
    th = np.linspace(0.0, np.pi / 2, 91)[:, None]
    s2, c2 = np.sin(th) ** 2, np.cos(th) ** 2
    e, d = np.ravel(epsilon)[None], np.ravel(delta)[None]
    a = (1.0 + 2.0 * e) * s2
    v = np.sqrt(0.5 * (a + c2) + np.sqrt(0.25 * (a - c2) ** 2 + (1.0 + 2.0 * d) * s2 * c2))
    return v.min(0).reshape(np.shape(epsilon))


@dataclass
class AnisotropyCheck:
    """The largest travel-time error (s) made by dropping the anisotropy (isotropic vp, the vertical speed) at the
    scene's propagation angles: for each source-receiver pair, its straight-ray time t_iso through vp times the largest
    |1 - vp / V_g(theta)| over the domain's (epsilon, delta), theta the pair's angle from the vertical: an upper bound
    for any wave that travels at that angle (a head wave along an anisotropic layer, a direct wave inside one), beside
    ``direct`` = max |t_vti - t_iso| of the direct waves along straight rays. ``t_vti``, ``t_iso`` (n_sources,
    n_receivers) s; ``angle`` (degrees from the vertical) and ``pair`` (source, receiver) of the largest;
    ``threshold`` = ANISOTROPY_PERIODS / the dominant frequency f_dominant (Hz)."""

    error: float
    direct: float
    threshold: float
    f_dominant: float
    angle: float
    pair: tuple
    t_vti: np.ndarray
    t_iso: np.ndarray

    @property
    def needed(self) -> bool:
        return self.error >= self.threshold

    def describe(self) -> str:
        i, j = self.pair
        where = (f"source {i}, receiver {j} at {self.angle:.0f} deg from the vertical, {1e3 * self.t_iso[i, j]:.0f} ms; "
                 f"the direct waves: {1e3 * self.direct:.1f} ms")
        bound = (f"{ANISOTROPY_PERIODS:g} of the dominant period 1/{self.f_dominant:.3g} Hz = {1e3 * self.threshold:.3g} ms, "
                 f"where a waveform misfit starts to cycle-skip")
        if self.needed:
            return (f"physics vti needed: dropping the anisotropy (isotropic vp) moves qP arrivals by up to "
                    f"{1e3 * self.error:.3g} ms (>= {bound}; {where})")
        return (f"isotropic acoustic suffices (travel-time error {1e3 * self.error:.3g} ms < {bound}; {where}): physics: "
                f"acoustic with model: the vp spec gives the same arrival times, faster")


def _group_speed_ratios(eps, delta, angles) -> np.ndarray:
    """:func:`qp_group_speed_ratio` of each (eps, delta) sample at the same-shaped angles (radians), one evaluation per
    distinct (eps, delta) rounded to 1e-4."""
    keys, inverse = np.unique(np.round(np.stack([np.ravel(eps), np.ravel(delta)], 1), 4), axis=0, return_inverse=True)
    out, angles = np.empty(np.size(eps)), np.ravel(angles)
    for k, (e, d) in enumerate(keys):
        at = inverse.ravel() == k
        out[at] = qp_group_speed_ratio(e, d, angles[at])
    return out.reshape(np.shape(eps))


def vti_ray_times(model: VTIModel, sources: np.ndarray, receivers: np.ndarray) -> tuple:
    """(t_vti, t_iso, angle), each (n_sources, n_receivers): qP travel times (s) along straight rays with the group speed
    at the ray's angle and with vp alone, and the ray's angle (radians from the vertical, rounded to 1e-3); sources
    (n_s, 2), receivers (n_r, 2) world metres (z, x); vp, epsilon, delta sampled every half cell (linear
    interpolation, as :func:`straight_ray_times`)."""
    sources, receivers = np.asarray(sources, float), np.asarray(receivers, float)
    org, spc = np.array(model.origin), np.array(model.spacing)
    fields = (1.0 / model.vp.values, model.epsilon, model.delta)
    n_s, n_r = len(sources), len(receivers)
    t_vti, t_iso, angle = np.zeros((n_s, n_r)), np.zeros((n_s, n_r)), np.zeros((n_s, n_r))
    for i, s in enumerate(sources):
        seg = receivers - s
        length = np.linalg.norm(seg, axis=1)
        n = max(int(np.ceil(length.max() / (0.5 * min(spc)))), 1) + 1
        frac = np.linspace(0.0, 1.0, n)
        idx = ((s[None, None] + frac[None, :, None] * seg[:, None] - org) / spc).reshape(-1, 2).T
        slow, eps, delta = (map_coordinates(f, idx, order=1, mode="nearest").reshape(n_r, n) for f in fields)
        angle[i] = np.round(np.arctan2(np.abs(seg[:, 1]), np.abs(seg[:, 0])), 3)  # ~0.06 degree
        t_iso[i] = np.trapezoid(slow, frac, axis=1) * length
        rays = np.broadcast_to(angle[i][:, None], slow.shape)
        t_vti[i] = np.trapezoid(slow / _group_speed_ratios(eps, delta, rays), frac, axis=1) * length
    return t_vti, t_iso, angle


def anisotropy_check(model: VTIModel, rays: tuple, f_dominant: float, box=None) -> AnisotropyCheck:
    """:class:`AnisotropyCheck` of ``model`` for the scene's ``rays`` (:func:`vti_ray_times`), over the index box ``box``
    = (i0, i1) (per axis, end exclusive; None: the whole model); f_dominant (Hz) the wavelet's dominant frequency."""
    t_vti, t_iso, angle = rays
    sl = tuple(slice(None) for _ in range(2)) if box is None else tuple(slice(a, b) for a, b in zip(*box))
    media = np.unique(np.round(np.stack([model.epsilon[sl].ravel(), model.delta[sl].ravel()], 1), 4), axis=0)
    angles = np.unique(angle)
    grid = _group_speed_ratios(*np.broadcast_arrays(media[:, :1], media[:, 1:], angles[None]))  # (n_media, n_angles)
    worst = np.abs(1.0 - 1.0 / grid).max(0)
    bound = t_iso * worst[np.searchsorted(angles, angle)]
    k = np.unravel_index(int(np.argmax(bound)), bound.shape)
    return AnisotropyCheck(float(bound[k]), float(np.abs(t_vti - t_iso).max()), ANISOTROPY_PERIODS / f_dominant,
                           float(f_dominant), float(np.degrees(angle[k])), (int(k[0]), int(k[1])), t_vti, t_iso)


# --- Which physics a scene needs: attenuation (issue 26, item 7) ---------------------------------------------------

ATTENUATION_LOSS = 0.01  # relative amplitude lost to Q below which a lossless physics suffices: issue 26's amplitude
# target for every physics (items 1, 2, 4: amplitudes within 1% of the analytic solutions); a smaller loss is below the
# accuracy the solvers themselves are held to


@dataclass
class AttenuationCheck:
    """The settings a physics viscoacoustic run uses and what its Q does in the scene. ``q_band`` (f_min, f_max) Hz,
    ``f_ref`` Hz, ``mechanisms``: the model's, or the solver's defaults from the wavelet's dominant frequency
    ``f_dominant`` (Hz); over the planning box ``v_slowest`` (m/s) the slowest P phase velocity (at q_band's low end),
    ``v_unrelaxed`` (m/s) the fastest (w -> infinity) speed, ``q_min``, ``q_max`` its quality factors. ``loss`` = 1 -
    exp(-pi f_dominant t_longest / q_min): the amplitude lost at f_dominant by a wave that travels the longest direct
    time ``t_longest`` (s, straight rays through vp) at the smallest Q, the bound the decision uses (it covers a
    direct wave or a reflection through the low-Q parts); ``loss_ray`` = 1 - exp(-pi f_dominant t*) the largest along
    the straight source-receiver rays themselves, t* = integral ds / (vp Q) (``t_star`` (n_sources, n_receivers) s),
    on the ray ``pair`` (source, receiver)."""

    q_band: tuple
    f_ref: float
    mechanisms: int
    f_dominant: float
    v_slowest: float
    v_unrelaxed: float
    q_min: float
    q_max: float
    t_longest: float
    loss: float
    loss_ray: float
    pair: tuple
    t_star: np.ndarray

    @property
    def needed(self) -> bool:
        return self.loss >= ATTENUATION_LOSS

    def describe(self) -> str:
        i, j = self.pair
        setup = (f"Q {self.q_min:.3g}..{self.q_max:.3g}, flat over {self.q_band[0]:.3g}-{self.q_band[1]:.3g} Hz with "
                 f"{self.mechanisms} mechanisms, vp at f_ref {self.f_ref:.3g} Hz")
        where = (f"at the dominant {self.f_dominant:.3g} Hz over the longest direct path ({1e3 * self.t_longest:.3g} ms) at "
                 f"Q {self.q_min:.3g}; {100 * self.loss_ray:.2g}% along the straight rays themselves (source {i} to "
                 f"receiver {j}, t* = {1e3 * self.t_star[i, j]:.3g} ms)")
        if self.needed:
            return (f"{setup}; Q matters: up to {100 * self.loss:.3g}% of the amplitude is lost (>= "
                    f"{100 * ATTENUATION_LOSS:g}%) {where}; a lossless physics (acoustic, acoustic_vd) would overstate it")
        return (f"{setup}; lossless acoustic suffices (amplitude error {100 * self.loss:.2g}% < {100 * ATTENUATION_LOSS:g}% "
                f"{where}): physics acoustic_vd (acoustic where the density is constant) gives the same amplitudes, faster")


def p_speeds(vp, q, mechanisms, f_ref: float, f: float) -> tuple:
    """(the P phase velocity at f Hz, the unrelaxed (w -> infinity) speed), m/s arrays of vp's shape, of a medium of phase
    velocity vp (m/s) at f_ref (Hz) and quality factor q (arrays of one shape) with the relaxation `mechanisms`."""
    from adseismic.solve.viscoacoustic import unrelaxed_velocity

    y = mechanisms.y(np.asarray(q, float))
    unrelaxed = unrelaxed_velocity(vp, q, mechanisms, f_ref)
    wt = 2.0 * math.pi * f * mechanisms.tau
    c = unrelaxed / np.sqrt(1.0 + y.sum(-1)) * np.sqrt(1.0 + (y * (1j * wt) / (1.0 + 1j * wt)).sum(-1))  # sqrt(M / rho)
    return 1.0 / np.real(1.0 / c), unrelaxed


def attenuation_check(model: ViscoacousticModel, sources: np.ndarray, receivers: np.ndarray, wavelet, box=None) -> AttenuationCheck:
    """:class:`AttenuationCheck` of ``model`` for sources (n_s, 2) and receivers (n_r, 2) (world metres, (z, x)) and the
    config's ``wavelet`` (kind, params); speeds and Q over the index box ``box`` = (i0, i1) (per axis, end exclusive;
    None: the whole model), travel times over the whole model."""
    from adseismic.kernels.viscoacoustic import fit_mechanisms
    from adseismic.solve.viscoacoustic import DEFAULT_MECHANISMS

    w, dt0 = _sampled_wavelet(wavelet.kind, wavelet.params)
    f_dom = dominant_frequency(w[None], dt0)
    band = model.q_band or (f_dom / 3.0, 2.5 * f_dom)  # the solver's defaults (adseismic.solve.viscoacoustic)
    f_ref, count = model.f_ref or f_dom, model.mechanisms or DEFAULT_MECHANISMS
    mech = fit_mechanisms(*band, count)
    sl = tuple(slice(None) for _ in range(2)) if box is None else tuple(slice(a, b) for a, b in zip(*box))
    vp, q = model.vp.values[sl], model.q[sl]
    c_low, unrelaxed = p_speeds(vp, q, mech, f_ref, band[0])
    t_longest = float(straight_ray_times(model.vp, sources, receivers).max())
    t_star = straight_ray_times(model.vp, sources, receivers, slowness=1.0 / (model.vp.values * model.q))
    k = np.unravel_index(int(np.argmax(t_star)), t_star.shape)
    return AttenuationCheck(tuple(float(f) for f in band), float(f_ref), int(count), float(f_dom),
                            float(c_low.min()), float(unrelaxed.max()), float(q.min()), float(q.max()),
                            t_longest, float(1.0 - np.exp(-math.pi * f_dom * t_longest / q.min())),
                            float(1.0 - np.exp(-math.pi * f_dom * t_star[k])), (int(k[0]), int(k[1])), t_star)
