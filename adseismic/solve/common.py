"""What every physics' driver shares: devices and precisions, the models' upload and value checks (on a GPU on the
device, checked_models), the input checks (geometry, the CFL limit), the PML defaults and the blow-up guard. A
physics is handed in as its launch helper and its DESCRIPTION (adseismic.kernels.<name>)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import warp as wp

from adseismic.accel.reductions import field_stats, value_ranges
from adseismic.kernels.common import HICKS_RADIUS, Description

DTYPES = {"float32": wp.float32, "float64": wp.float64}
DEFAULT_PML_WIDTH = 20
DEFAULT_PML_REFLECTION = {2: 1e-3, 4: 1e-3, 8: 1e-5}  # reference.md section 3
BLOWUP_FACTOR = 1e3  # max|u| after the source ends vs. its peak during injection


class PropagationError(RuntimeError):
    """The simulation became unstable (non-finite or runaway wavefield)."""


def init_warp():
    """Initialise Warp without its banner and per-module load lines (they drown progress bars)."""
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.init()


def resolve_device(device: str) -> str:
    """Validate a device string ("cpu", "cuda", "cuda:N") against what Warp sees."""
    init_warp()
    try:
        return str(wp.get_device(device))
    except Exception as exc:  # Warp raises RuntimeError/ValueError depending on the failure
        have = ", ".join(d.alias for d in wp.get_devices())
        raise ValueError(f"device {device!r} is not available ({exc}); available: {have}") from None


def precision_dtype(precision: str):
    if precision not in DTYPES:
        raise ValueError(f"precision {precision!r} is not one of {sorted(DTYPES)}")
    return DTYPES[precision]


def model_shape(models: dict, ndims=(2,)) -> tuple:
    """The one shape of the models {name: NumPy or Warp array}, each with one of ndims dimensions; ValueError naming
    them and their shapes otherwise."""
    shapes = [tuple(a.shape) if isinstance(a, wp.array) else np.shape(a) for a in models.values()]
    if len(shapes[0]) not in ndims or any(s != shapes[0] for s in shapes):
        axes = " or ".join({2: "(nz, nx)", 3: "(nz, ny, nx)"}[n] for n in ndims)
        raise ValueError(f"{', '.join(models)} must be {axes} arrays of one shape; got {', '.join(map(str, shapes))}")
    return shapes[0]


def upload_models(models: dict, dtype, device: str, requires_grad=()):
    """models {name: NumPy or Warp array (one shape)} as Warp arrays of dtype on device, requires_grad for the names
    in requires_grad. A Warp array of dtype is used as it is where it is on device and not differentiated (the runs
    only read their models), else copied device to device (a model on the GPU never visits the host); anything else
    is read once into a float64 host copy and uploaded. Returns (arrays, host, exact): host[k] the float64 copy, None
    where none was made; exact: no value was rounded on its way to dtype (every input of dtype or of a type dtype
    holds exactly)."""
    arrays, host, exact = [], [], True
    for name, a in models.items():
        grad = name in requires_grad
        if isinstance(a, wp.array) and a.dtype == dtype:
            if grad or a.device != wp.get_device(device) or not a.is_contiguous:
                arrays.append(wp.empty(a.shape, dtype=dtype, device=device, requires_grad=grad))
                wp.copy(arrays[-1], a)
            else:
                arrays.append(a)
            host.append(None)
        else:
            given = a.numpy() if isinstance(a, wp.array) else np.asarray(a)
            exact = exact and np.can_cast(given.dtype, wp.dtype_to_numpy(dtype), "safe")
            host.append(np.ascontiguousarray(given, dtype=float))
            arrays.append(wp.array(host[-1], dtype=dtype, device=device, requires_grad=grad))
    return tuple(arrays), host, exact


def elementwise(kernel, arrays, *params, dtype=wp.float64) -> wp.array:
    """A flat array (size of arrays[0]) of dtype derived cell by cell on the arrays' device: kernel(flat arrays...,
    out, *params) launched a thread a cell."""
    out = wp.empty(arrays[0].size, dtype=dtype, device=arrays[0].device)
    wp.launch(kernel, dim=out.size, inputs=[*(a.flatten() for a in arrays), out, *params], device=arrays[0].device)
    return out


@dataclass(frozen=True)
class ModelChecks:
    """A physics' checks of its model values and its CFL speed, over its models in MODELS order.

    exact(*host): the NumPy check of float64 arrays, raising ValueError (naming the model, the index, the fix) at the
    first bad value; speed(*host): the CFL speed (m/s) per cell; derive(arrays): flat Warp arrays derived on the
    device from the models (elementwise); clear(ranges, exact): True only where the (min, max, non-finite count) of
    the models then of the derived arrays (value_ranges) show every value valid beyond doubt, exact telling whether
    the device arrays hold the values the NumPy check would see (no rounding to dtype on upload); speed_range: the
    index in ranges whose max is max(speed)."""

    exact: Callable
    speed: Callable
    clear: Callable
    derive: Callable = lambda arrays: []
    speed_range: int = 0


def fast_check(arrays, checks: ModelChecks, exact: bool):
    """The device check of the models (Warp arrays of one device, MODELS order): value_ranges of them and of
    checks.derive's arrays, read back at once. Returns vmax (m/s, the max speed in float64 of the device's values)
    where checks.clear passes them, else None (a bad value, or not clearly valid: the NumPy check decides)."""
    ranges = value_ranges([*arrays, *checks.derive(arrays)])
    return ranges[checks.speed_range][1] if checks.clear(ranges, exact) else None


def checked_models(models: dict, checks: ModelChecks, dtype, device: str, requires_grad=()):
    """Upload the models {name: NumPy or Warp array} (upload_models) and check them: on a GPU by fast_check, and only
    where it does not clear them (or on the CPU) by checks.exact on float64 host copies, which raises its message or
    passes (vmax then the host's max speed, bit-equal to the checks before the device ones). Returns (arrays, vmax
    m/s)."""
    arrays, host, exact = upload_models(models, dtype, device, requires_grad)
    vmax = fast_check(arrays, checks, exact) if wp.get_device(device).is_cuda else None
    if vmax is not None:
        return arrays, vmax
    host = [a.numpy().astype(float) if h is None else h for a, h in zip(arrays, host)]
    checks.exact(*host)
    return arrays, float(checks.speed(*host).max())


def host_array(a) -> np.ndarray:
    """a (a NumPy-like or Warp array) as a float64 NumPy array."""
    return np.asarray(a.numpy() if isinstance(a, wp.array) else a, dtype=float)


def float64_on_device(a, device: str, name: str, shape: tuple) -> wp.array:
    """a (n_shots, n_receivers, nt) as a float64 Warp array on device: a contiguous float64 Warp array already there
    as it is (an FWI's data kept on the device), anything else copied; ValueError naming `name` if its shape is not
    shape."""
    if not (isinstance(a, wp.array) and a.dtype == wp.float64 and str(a.device) == str(wp.get_device(device)) and a.is_contiguous):
        a = wp.array(host_array(a), dtype=wp.float64, device=device)
    if tuple(a.shape) != tuple(shape):
        raise ValueError(f"{name} has shape {tuple(a.shape)} but the synthetics have {tuple(shape)} (n_shots, n_receivers, nt)")
    return a


def dominant_frequency(source_amplitudes: np.ndarray, dt: float) -> float:
    """Peak of the summed amplitude spectrum of all source traces (Hz)."""
    spec = np.abs(np.fft.rfft(source_amplitudes.reshape(-1, source_amplitudes.shape[-1]), n=4 * source_amplitudes.shape[-1])).sum(0)
    freqs = np.fft.rfftfreq(4 * source_amplitudes.shape[-1], dt)
    return float(freqs[1:][np.argmax(spec[1:])])


def check_geometry(shape, dx, source_amplitudes, source_locations, receiver_locations, axes: str):
    """Shapes of the sources' samples (n_shots, n_src, nt) and of the locations (n_shots, n, ndim) metres
    in axis order `axes` ("z, x" or "z, y, x"), every location inside the grid of `shape` nodes of
    spacing dx (m). Raises ValueError naming the array, the index and the fix."""
    ndim = len(shape)
    amp = np.asarray(source_amplitudes)
    if amp.ndim != 3:
        raise ValueError(f"source_amplitudes must be (n_shots, n_sources, nt); got shape {amp.shape}")
    extent = (np.array(shape) - 1) * dx
    for name, loc in (("source_locations", np.asarray(source_locations)), ("receiver_locations", np.asarray(receiver_locations))):
        if loc.ndim != 3 or loc.shape[0] != amp.shape[0] or loc.shape[2] != ndim:
            raise ValueError(f"{name} must be (n_shots={amp.shape[0]}, n, {ndim}) metres ({axes}); got shape {loc.shape}")
        outside = np.any((loc < 0) | (loc > extent), axis=-1)
        if outside.any():
            i = np.argwhere(outside)[0]
            raise ValueError(f"{name}[{i[0]}, {i[1]}] = {loc[i[0], i[1]].tolist()} m lies outside the grid [0, {extent.tolist()}] m")
    if np.shape(source_locations)[1] != amp.shape[1]:
        raise ValueError(f"source_locations has {np.shape(source_locations)[1]} sources per shot but source_amplitudes has {amp.shape[1]}")


def check_courant(physics: Description, order: int, ndim: int, vmax: float, dx: float, dt: float):
    """Refuse a time step above the physics' stability limit (ValueError with the largest stable dt)."""
    limit = physics.cfl_limit(order, ndim)
    courant = vmax * dt / dx
    if courant > limit:
        raise ValueError(
            f"dt = {dt:.6g} s is unstable with dx = {dx:g} m and {physics.courant_speed}_max = {vmax:.0f} m/s: Courant number "
            f"{courant:.4f} exceeds the exact limit {limit:.4f} of the {physics.name} scheme (order {order}, {ndim}D); "
            f"use dt <= {limit * dx / vmax:.6g} s"
        )


def pml_settings(order: int, pml_width, pml_reflection, pml_frequency, pml_velocity, source_amplitudes, dt: float, vmax: float):
    """(width in cells, target reflection, alpha frequency in Hz, reference speed in m/s) of the CPML with the
    defaults filled in: 20 cells, DEFAULT_PML_REFLECTION, the sources' dominant frequency, the model's maximum
    speed (fix pml_velocity when the model changes between runs)."""
    width = DEFAULT_PML_WIDTH if pml_width is None else int(pml_width)
    if width < HICKS_RADIUS:
        raise ValueError(f"pml_width = {width} cells is below the source/receiver operator's half-width {HICKS_RADIUS}; use >= {HICKS_RADIUS}")
    refl = DEFAULT_PML_REFLECTION[order] if pml_reflection is None else float(pml_reflection)
    f_pml = dominant_frequency(np.asarray(source_amplitudes, dtype=float), dt) if pml_frequency is None else float(pml_frequency)
    vref = float(vmax) if pml_velocity is None else float(pml_velocity)
    return width, refl, f_pml, vref


def source_end(source_amplitudes: np.ndarray, lag: int = 1, rate: bool = False) -> int:
    """The first level after the sources' last sample above 1e-3 of their peak, plus lag - 1; rate: judge
    the samples' differences (sources that act through their rate, as moment tensors)."""
    s = np.asarray(source_amplitudes, dtype=float)
    a = np.abs(np.diff(s, axis=-1) if rate else s).max(axis=(0, 1))
    active = np.nonzero(a > 1e-3 * a.max())[0] if a.max() > 0 else np.array([0])
    return int(active[-1]) + lag


def padded_samples(amplitudes: np.ndarray, levels: int, dtype) -> np.ndarray:
    """Source samples (S, n_src, nt) zero-padded to `levels` samples (the replays' levels past nt)."""
    out = np.zeros((*amplitudes.shape[:2], levels), dtype=wp.dtype_to_numpy(dtype))
    out[:, :, : amplitudes.shape[2]] = amplitudes
    return out


class BlowupGuard:
    """Stops a run whose monitored fields turn non-finite or keep growing after the source has ended.

    prop: the physics' launch helper (dtype, device, dt, order, ndim); physics: its DESCRIPTION; fields(state):
    the arrays to watch; end: the level after which the sources are silent (source_end); every: levels between
    checks; what: the watched quantity's name in messages."""

    def __init__(self, prop, physics: Description, fields, end: int, every: int, what: str = "u"):
        self.prop, self.physics, self.fields, self.what = prop, physics, fields, what
        self.every, self.source_end = max(int(every), 1), end
        self.peak = 0.0
        self.stats = wp.zeros(2, dtype=prop.dtype, device=prop.device)

    def __call__(self, state, n: int):
        if n % self.every:
            return
        field_stats(self.fields(state), self.stats)
        self.check(n, *self.stats.numpy())

    def check(self, n: int, amax: float, nonfinite: float):
        """Judge the statistics (max |field|, count of non-finite values) of level n; raises PropagationError."""
        if n <= self.source_end:
            self.peak = max(self.peak, float(amax))
        runaway = n > self.source_end and self.peak > 0 and amax > BLOWUP_FACTOR * self.peak
        if nonfinite or runaway:
            p, w = self.prop, self.what
            what = f"{int(nonfinite)} non-finite values" if nonfinite else f"max|{w}| = {amax:.3g}, {amax / self.peak:.3g} x its peak while the source was active"
            raise PropagationError(
                f"{self.physics.name} wavefield blew up at step {n} (t = {n * p.dt:.6g} s): {what}. Likely cause: dt = {p.dt:.6g} s is too "
                f"close to the stability limit for this model (order {p.order}, {p.ndim}D, CFL limit {self.physics.cfl_limit(p.order, p.ndim):.4f}), "
                "a velocity model with extreme contrasts, or a PML whose damping is too strong for its width"
            )
