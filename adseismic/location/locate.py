"""Earthquake location by waveform inversion through the differentiable simulator.

Unknowns: source position (m, axis order (z,[y,]x), world coordinates of the model), origin time T
(s, the peak of the source-time function, on the data's time axis) and the source-time function
(STF) s(t), either parametric, s(t) = A ricker(t - T; f) with unknown peak frequency f (Hz) and
amplitude A, or free: one value per time sample with a smoothness penalty. Misfit:
J = 1/2 sum_i sum_t ((d_i(t) - o_i(t)) / sigma_i)^2, sigma_i the noise standard deviation of trace i
(from a pre-event window), so that at the solution the Gauss-Newton matrix J_r^T J_r (J_r the
Jacobian of the whitened residuals) is the inverse covariance of the estimate (white noise;
coloured noise, e.g. band-passed data, makes it optimistic).

Steps:
1. start: back-projection of the data envelopes with straight-ray travel times through the model
   over a grid of candidate positions (no picks needed); the origin time from the stack's peak;
   with multi_start > 1 the best well-separated stack maxima are all tried (local minima: cycle
   skipping between wavelet periods);
2. amplitude by linear least squares (the data are linear in the STF);
3. L-BFGS-B (default), Gauss-Newton (Levenberg-Marquardt steps, Jacobian by central differences in
   position and exact derivatives of the wavelet), GD or Adam on (position, T, f, A), in
   non-dimensional parameters (position / dx, time / dt, f / f0, A / A0) or, for the optimiser
   study, in raw units (m, s, Hz);
4. stf="free": from the Ricker solution, variable projection: for a position the data are a
   convolution of the STF with the impulse response h(x) (one simulation with a one-sample
   source), so the best STF is a regularised linear least-squares solution; the position is
   refined by Gauss-Newton steps on the projected problem; the origin time is the STF's peak;
5. covariance C = (J_r^T J_r + R)^-1 at the solution (R: the smoothness penalty's Hessian for a
   free STF, else 0).

Physics: acoustic (model a Model; pressure traces; the amplitude A) or elastic (model an ElasticModel, 2D;
traces of vx, vz or pressure; a moment-tensor source whose in-plane components (Mxx, Mzz, Mxz) = a @ BASIS[constraint]
replace A: the data are linear in the coefficients a, which the same estimators fit; docs/moment_tensor.md). The
forward problem of each physics is a _Problem: data, the Jacobian and the adjoint misfit gradient.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import hilbert

from adseismic.data.model import Model
from adseismic.inversion.optimize import minimize
from adseismic.runs import format_position
from adseismic.scene import straight_ray_times
from adseismic.solve.acoustic import forward, gradient
from adseismic.solve.batch import shot_slices
from adseismic.solve.common import dominant_frequency

log = logging.getLogger(__name__)
METHODS = ("lbfgs", "gauss-newton", "gd", "adam")
STFS = ("ricker", "free")
# the Ricker fit's stop: an iteration that lowers J by less than this moves the event by ~0.1 sigma (J rises by
# k^2 / 2 at k standard deviations from its minimum); the first-order methods' iterations past it only polish digits
STOP_HALF_CHI2 = 0.005


@dataclass
class LocationResult:
    """position (ndim,) world metres, axis order (z,[y,]x); origin_time s (peak of the source-time
    function, on the data's time axis); peak_frequency Hz and amplitude of the Ricker fit;
    covariance (ndim + 1, ndim + 1) 1-sigma over (position..., origin time) in m^2, m s, s^2;
    parameter_covariance: over every unknown (Ricker: position, T, f, A; free STF: position, the
    STF samples); stf (nt,) the source-time function at t = k dt (elastic: at t = k dt - dt/2, the solver's input,
    whose velocity samples are recorded half a step earlier); noise_std (n_receivers,);
    synthetic (n_receivers, nt); start: the start of the best run; candidates: every start tried
    (position, origin_time, stack, misfit, final position), best first; inflation: the factor the
    Gauss-Newton covariance was multiplied by (noise correlation x reduced chi-square if > 1).
    amplitudes: what the STF multiplies in the data (acoustic [1], the STF carries A; moment tensor: its free
    coefficients). ricker_covariance: over the Ricker fit's parameters (position, T, f, amplitudes), not inflated.
    Moment-tensor source (elastic physics): moment_tensor (3,) the in-plane (Mxx, Mzz, Mxz) in N m per metre of
    line for the unit-peak STF, its covariance (3, 3) (inflated like the rest), the constraint, and components
    (n_traces,) what each trace records; amplitude is then the in-plane scalar moment sqrt(sum M_ij^2 / 2)."""

    position: np.ndarray
    origin_time: float
    peak_frequency: float
    amplitude: float
    covariance: np.ndarray
    parameter_covariance: np.ndarray
    stf: np.ndarray
    stf_kind: str
    noise_std: np.ndarray
    misfit: float
    iterations: int
    evaluations: int
    stop_reason: str
    synthetic: np.ndarray
    start: dict = field(default_factory=dict)
    candidates: list = field(default_factory=list)
    history: list = field(default_factory=list)
    inflation: float = 1.0
    amplitudes: np.ndarray = field(default_factory=lambda: np.ones(1))
    ricker_covariance: np.ndarray | None = None
    moment_tensor: np.ndarray | None = None
    moment_tensor_covariance: np.ndarray | None = None
    constraint: str | None = None
    components: list | None = None


def source_wavelet(nt, dt, T, f, A):
    """A ricker(t - T; f) and its derivatives with respect to (T, f, A): arrays (nt,) and (3, nt)."""
    t = np.arange(nt) * dt - T
    a = (np.pi * f * t) ** 2
    e = np.exp(-a)
    r = (1 - 2 * a) * e
    dr_da = (2 * a - 3) * e
    d_T = -A * dr_da * 2 * np.pi**2 * f**2 * t
    d_f = A * dr_da * 2 * np.pi**2 * f * t**2
    return A * r, np.stack([d_T, d_f, r])


def noise_from_window(observed, dt, window):
    """Standard deviation of each trace over window = (start, end) s."""
    i0, i1 = int(round(window[0] / dt)), int(round(window[1] / dt))
    if i1 - i0 < 10:
        raise ValueError(f"noise window {window} s holds {i1 - i0} samples; give a pre-event window of at least 10 samples")
    return observed[:, i0:i1].std(axis=1)


def phase_models(model) -> list:
    """The velocity Models of the phases a back-projection stacks: [model] (acoustic); elastic [vs]: a moment-tensor
    source radiates most of its energy as S (amplitude ~ (vp/vs)^3 that of P for a double couple), and stacking P as
    well maps that S energy to shallower P positions (the demo's event: S alone starts 12 m from it, P + S 390 m)."""
    return [model.vs] if hasattr(model, "vs") else [model]


def back_projection(model, receivers, observed, dt, bounds, spacing, n_best=1, separation=None):
    """Start candidates from envelope back-projection: the stack S(x, T) = sum_i env_i(T + tau_i(x)) /
    max env_i over candidate points x (every `spacing` m inside bounds) and times T; model: a velocity Model
    or a list of them (phases, e.g. [vp, vs]), whose stacks are summed (phase_models() picks them per physics). receivers (n, ndim)
    and bounds ((lo, hi) per axis) in the model's world metres. Returns up to n_best dicts
    {position, origin_time, stack (0..1)}, best first, at least `separation` m (default 4 spacing)
    apart; also "grid": the axes and the stack maximum over T per candidate (for the figures)."""
    env = np.abs(hilbert(observed, axis=-1))
    env /= env.max(axis=1, keepdims=True) + 1e-30
    axes = [np.arange(lo, hi + 1e-9, spacing) for lo, hi in bounds]
    cand = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(bounds))
    phases = model if isinstance(model, (list, tuple)) else [model]
    taus = [straight_ray_times(m, cand, receivers) for m in phases]  # (n_cand, n_rec) each
    nt = observed.shape[1]
    t = np.arange(nt) * dt
    peak, when = np.empty(len(cand)), np.empty(len(cand))
    for c in range(len(cand)):
        stack = sum(np.interp(t + tau[c, i], t, env[i], right=0.0) for tau in taus for i in range(len(receivers)))
        k = int(np.argmax(stack))
        peak[c], when[c] = stack[k] / (len(receivers) * len(phases)), k * dt
    sep = 4.0 * spacing if separation is None else float(separation)
    picked = []
    for c in np.argsort(-peak):
        if len(picked) == n_best:
            break
        if all(np.linalg.norm(cand[c] - cand[p]) >= sep for p in picked):
            picked.append(c)
    out = [{"position": cand[c].copy(), "origin_time": float(when[c]), "stack": float(peak[c])} for c in picked]
    out[0]["grid"] = {"axes": axes, "stack": peak.reshape([len(a) for a in axes])}
    return out


class _Problem:
    """The forward problem of one event in acoustic physics: data at the receivers (pressure) for a source at
    `pos` (world m). Parameters p = (position (ndim), T s, f Hz, amplitudes (n_amp,)); the data are linear in the
    amplitudes (acoustic: one, A) and in the source-time function."""

    n_amp = 1
    time_offset = 0.0  # s: the solver's sample k of the data is at time k dt - time_offset
    impulse_sample = 0  # where _fit_free puts its spike: the first sample whose response is a shift of every later one's

    def __init__(self, model: Model, receivers, nt, dt, kw, stf_filter=None):
        self.model, self.grid, self.nt, self.dt, self.kw = model, model, nt, dt, kw
        self.filter = stf_filter or (lambda x: x)
        self.ndim = self.grid.ndim
        self.dx = float(self.grid.spacing[0])
        self.origin = np.asarray(self.grid.origin, float)
        self.rec = (np.asarray(receivers, float) - self.origin)[None]

    def _run(self, positions, wavelet, amps):
        """(n, n_rec, nt) data of sources at positions (n, ndim) world m with the STF (nt,) and amplitudes
        amps (n, n_amp), one simulation of n shots."""
        n = len(positions)
        rec = np.broadcast_to(self.rec, (n, *self.rec.shape[1:]))
        amp = np.broadcast_to(wavelet, (n, 1, self.nt)) * np.asarray(amps)[:, :1, None]
        return forward(self.model.values, self.dx, self.dt, amp, (positions - self.origin)[:, None], rec, **self.kw).receiver_amplitudes

    def data_many(self, positions, wavelet, amps):
        """(n_positions, n_rec, nt) for sources at positions (n, ndim) world m with amplitudes amps (n_amp,)."""
        pos = np.asarray(positions, float)
        return self._run(pos, wavelet, np.broadcast_to(np.asarray(amps, float), (len(pos), self.n_amp)))

    def data(self, pos, wavelet, amps):
        """(n_rec, nt) for source-time function `wavelet` (nt,) and amplitudes amps (n_amp,)."""
        return self.data_many(np.asarray(pos, float)[None], wavelet, amps)[0]

    def data_basis(self, pos, wavelet):
        """(n_amp, n_rec, nt): the data of each amplitude alone at 1 (the columns of the linear part), one run."""
        pos = np.asarray(pos, float)
        return self._run(np.repeat(pos[None], self.n_amp, axis=0), wavelet, np.eye(self.n_amp))

    def held_amplitudes(self, amps):
        """The amplitudes a source-time function multiplies in the data (data(pos, stf, held)): acoustic [1]
        (the STF carries A); a moment tensor its coefficients (the STF is the unit-peak shape)."""
        return np.ones(1)

    def split(self, p):
        """p -> (position (ndim,), T, f, amplitudes (n_amp,))."""
        d = self.ndim
        return p[:d], p[d], p[d + 1], p[d + 2 :]

    def wavelet(self, p):
        """The (filtered) unit Ricker source-time function of parameters p and its derivatives with respect to
        (T, f): (nt,), (2, nt)."""
        _, T, f, _ = self.split(p)
        s, ds = source_wavelet(self.nt, self.dt, T - self.time_offset, f, 1.0)
        return self.filter(s), self.filter(ds[:2])

    def simulate(self, p):
        pos, _, _, amps = self.split(p)
        return self.data(pos, self.wavelet(p)[0], amps)

    def position_derivatives(self, pos, wavelet, amps):
        """d(data)/d(position) (ndim, n_rec, nt) by central differences (h = 0.05 dx; the source
        operator is C^1 in the position), all 2 ndim simulations in one batched run."""
        ndim, h = len(pos), 0.05 * self.dx
        steps = np.concatenate([np.eye(ndim), -np.eye(ndim)]) * h
        d = self.data_many(pos[None] + steps, wavelet, amps)
        return (d[:ndim] - d[ndim:]) / (2 * h)

    def jacobian(self, p):
        """d(data)/d(parameters) (n_params, n_rec, nt): central differences in position and exact
        derivatives for (T, f, amplitudes): the data are linear in the source-time function, so d(data)/dT
        is the data of d(s)/dT, and linear in the amplitudes."""
        pos, _, _, amps = self.split(p)
        s, ds = self.wavelet(p)
        cols = list(self.position_derivatives(pos, s, amps))
        cols += [self.data(pos, ds[k], amps) for k in range(2)]
        cols += list(self.data_basis(pos, s))
        return np.stack(cols)

    def loss_gradient(self, p, obs, w2):
        """Misfit 1/2 sum w2 (d(p) - obs)^2 and its gradient with respect to p (the adjoint state)."""
        pos, _, _, amps = self.split(p)
        s, ds = self.wavelet(p)

        def misfit(syn):
            r = (syn[0] - obs) * w2
            return 0.5 * float(np.sum((syn[0] - obs) * r)), r[None]

        g = gradient(self.model.values, self.dx, self.dt, amps[0] * s[None, None], (pos - self.origin)[None, None], self.rec,
                     misfit=misfit, wrt=("source_amplitudes", "source_locations"), **self.kw)  # fmt: skip
        ga = g.source_amplitudes[0, 0]
        return g.loss, np.concatenate([g.source_locations[0, 0], amps[0] * (ds @ ga), [s @ ga]])


class _ElasticProblem(_Problem):
    """The forward problem of one event in 2D elastic physics with a moment-tensor source: trace i records
    components[i] ("vx", "vz" m/s or "pressure" Pa) at receivers[i]. The in-plane tensor (Mxx, Mzz, Mxz) N m/m is
    basis^T a for the free amplitudes a (n_amp,) (moment_tensor.BASIS: the constraint). Every trace is returned at
    t = k dt: the solver records velocities at (k - 1/2) dt, so the STF is advanced by dt/2 (time_offset) and pressure
    (recorded at k dt) is averaged onto (k - 1/2) dt as well."""

    def __init__(self, model, receivers, components, basis, nt, dt, kw, stf_filter=None):
        super().__init__(model.vp, receivers, nt, dt, kw, stf_filter)
        self.model, self.basis = model, np.asarray(basis, float)
        self.n_amp = len(self.basis)
        self.components = list(components)
        self.time_offset = 0.5 * dt
        self.impulse_sample = 1  # a moment source injects -(s[k+1] - s[k]): a spike at 0 lacks its s[0] - s[-1] step
        self.materials = (model.vp.values, model.vs.values, model.rho.values)

    def held_amplitudes(self, amps):
        return np.asarray(amps, float)

    def _rows(self, syn):
        """{component: (n, n_rec, nt)} -> (n, n_traces, nt): trace i = components[i] at receiver i."""
        out = np.stack([syn[c][:, i] for i, c in enumerate(self.components)], axis=1)
        p = [i for i, c in enumerate(self.components) if c == "pressure"]
        if p:
            out[:, p, 1:] = 0.5 * (out[:, p, 1:] + out[:, p, :-1])
        return out

    def _rows_adjoint(self, r):
        """Adjoint of _rows for one shot: (n_traces, nt) -> {component: (1, n_rec, nt)}."""
        adj = {c: np.zeros((1, *r.shape)) for c in ("vx", "vz", "pressure")}
        for i, c in enumerate(self.components):
            if c == "pressure":
                adj[c][0, i, :-1] += 0.5 * r[i, 1:]
                adj[c][0, i, 1:] += 0.5 * r[i, 1:]
                adj[c][0, i, 0] += r[i, 0]
            else:
                adj[c][0, i] = r[i]
        return adj

    def _run(self, positions, wavelet, amps):
        from adseismic.solve.elastic import forward_elastic

        n = len(positions)
        rec = np.broadcast_to(self.rec, (n, *self.rec.shape[1:]))
        res = forward_elastic(*self.materials, self.dx, self.dt, np.broadcast_to(wavelet, (n, 1, self.nt)).copy(),
                              (positions - self.origin)[:, None], rec.copy(), source_type="moment",
                              source_components=(np.asarray(amps) @ self.basis)[:, None], **self.kw)  # fmt: skip
        return self._rows({"vx": res.vx, "vz": res.vz, "pressure": res.pressure})

    def loss_gradient(self, p, obs, w2):
        from adseismic.solve.elastic import gradient_elastic

        pos, _, _, amps = self.split(p)
        s, ds = self.wavelet(p)

        def misfit(syn):
            d = self._rows({c: np.asarray(v) for c, v in syn.items()})[0]
            r = (d - obs) * w2
            return 0.5 * float(np.sum((d - obs) * r)), self._rows_adjoint(r)

        g = gradient_elastic(*self.materials, self.dx, self.dt, s[None, None], (pos - self.origin)[None, None], self.rec.copy(),
                             misfit=misfit, wrt=("source_amplitudes", "source_components", "source_locations"), source_type="moment",
                             source_components=(amps @ self.basis)[None, None], **self.kw)  # fmt: skip
        return g.loss, np.concatenate([g.source_locations[0, 0], ds @ g.source_amplitudes[0, 0], self.basis @ g.source_components[0, 0]])


def _problem(model, receivers, components, constraint, nt, dt, kw, stf_filter=None) -> _Problem:
    """The forward problem of the model's physics: _Problem (a Model) or _ElasticProblem (vp, vs, rho)."""
    if not hasattr(model, "vs"):
        return _Problem(model, receivers, nt, dt, kw, stf_filter)
    from adseismic.location.moment_tensor import BASIS

    return _ElasticProblem(model, receivers, components, BASIS[constraint], nt, dt, kw, stf_filter)


def _simulation_kw(model, f0, order, pml_width, free_surface, device, precision):
    return dict(order=order, pml_width=pml_width, device=device, precision=precision, pml_velocity=model.vmax,
                pml_frequency=f0, free_surface=free_surface)  # fmt: skip


def _grid(model):
    """The Model that carries the geometry (spacing, origin, extent): the model itself (acoustic) or its vp
    (an ElasticModel: vp, vs, rho Models on one grid)."""
    return model.vp if hasattr(model, "vs") else model


def _check_physics(model, n_traces, components, constraint):
    """Acoustic (a Model): pressure traces, no moment-tensor constraint. Elastic (vp, vs, rho): 2D, one component
    per trace among vx, vz, pressure, constraint one of moment_tensor.CONSTRAINTS."""
    from adseismic.location.moment_tensor import CONSTRAINTS

    if not hasattr(model, "vs"):
        if constraint is not None:
            raise ValueError(f"constraint: {constraint!r} needs a moment-tensor source, which needs elastic physics (a model with vp, "
                             f"vs, rho); an acoustic model has a pressure source only: drop the constraint or give an elastic model")
        if components is not None and set(components) != {"pressure"}:
            raise ValueError(f"components: {sorted(set(components) - {'pressure'})} need elastic physics; an acoustic model records pressure")
        return
    if _grid(model).ndim != 2:
        raise ValueError(f"model: {_grid(model).ndim}D; the elastic moment-tensor locator is 2D (P-SV); give a 2D model")
    if constraint not in CONSTRAINTS:
        raise ValueError(f"constraint: {constraint!r} is not one of {', '.join(CONSTRAINTS)}")
    if components is None or len(components) != n_traces:
        raise ValueError(f"components: give one of vx, vz, pressure per trace ({n_traces} traces), not {components!r}")
    bad = sorted(set(components) - {"vx", "vz", "pressure"})
    if bad:
        raise ValueError(f"components: {bad} are not among vx, vz, pressure")


def _check_options(method, stf, multi_start, frequency_range, smoothness):
    if method not in METHODS:
        raise ValueError(f"method: {method!r} is not one of {', '.join(METHODS)}")
    if stf not in STFS:
        raise ValueError(f"stf: {stf!r} is not one of {', '.join(STFS)}")
    if int(multi_start) < 1:
        raise ValueError(f"multi_start: {multi_start!r} < 1; give the number of starts to try (1: the best back-projection point)")
    lo, hi = frequency_range
    if not 0 < lo < 1 < hi:
        raise ValueError(f"frequency_range: {frequency_range!r} must bracket 1 (factors of the start peak frequency), e.g. (0.3, 3)")
    if smoothness < 0:
        raise ValueError(f"smoothness: {smoothness!r} is negative; give 0 (none) or a positive weight")


def locate(model, receivers, observed, dt, *, components=None, constraint=None, noise_std=None, noise_window=None, bounds=None,
           start=None, multi_start=1, peak_frequency=None, frequency_range=(0.3, 3.0), stf="ricker", smoothness=0.01,
           method="lbfgs", scaled=True, max_iterations=60, max_evaluations=None, order=4, pml_width=None,
           free_surface=False, device="cpu", precision="float64", stf_filter=None, noise_correlation=1.0,
           journal_path=None, options=None, callback=None) -> LocationResult:  # fmt: skip
    """Locate one event. model: the velocity Model on the simulation grid (uniform spacing dx, node 0
    at model.origin), acoustic physics, or an ElasticModel (vp, vs, rho Models on one 2D grid), elastic
    physics with a moment-tensor source whose in-plane components (Mxx, Mzz, Mxz) are estimated under
    `constraint` (moment_tensor.CONSTRAINTS: none, deviatoric, double_couple); receivers (n, ndim) world
    metres, one row per trace; components (n,) what trace i records in elastic physics ("vx", "vz" m/s,
    "pressure" Pa); observed (n, nt) at t = k dt. bounds: ((lo, hi)
    per axis) world metres (default: the model less 2 cells); start: dict(position, origin_time), or a
    list of them, to skip the back-projection; multi_start: how many back-projection maxima to start
    from (the lowest final misfit wins). peak_frequency: start f0 (Hz, default the data's dominant
    frequency), bounded to frequency_range x f0. stf: "ricker" or "free" (samples with a smoothness
    penalty of relative weight `smoothness`, see _fit_free). method: "lbfgs" (L-BFGS-B),
    "gauss-newton", "gd", "adam"; scaled=False works in raw units (m, s, Hz), which plain gradient
    descent cannot handle (the optimiser study). stf_filter: linear filter (callable on (..., nt)
    arrays) applied to the Ricker STF, the data's preprocessing band-pass, so synthetics see the same
    band. noise_correlation: the noise's integrated autocorrelation time in samples (1: white), by
    which the covariance is inflated (band-limited noise has fewer independent samples); the
    covariance is also inflated by the reduced chi-square of the fit when above 1 (misfit the noise
    does not explain: model or STF error). callback(iteration, evaluations, position, origin_time)
    after every iteration."""
    from adseismic.data.geometry import check_inside, check_samples

    _check_options(method, stf, multi_start, frequency_range, smoothness)
    obs = np.asarray(observed, float)
    n_rec, nt = obs.shape
    _check_physics(model, n_rec, components, constraint)
    grid = _grid(model)
    dx = float(grid.spacing[0])
    rec = np.asarray(receivers, float)
    check_inside(rec, grid, "receiver")
    check_samples(obs, [f"trace {i}" for i in range(n_rec)])  # NaN/inf refused, clipped traces warned about
    if bounds is None:
        bounds = [(lo + 2 * dx, hi - 2 * dx) for lo, hi in grid.extent]
    if noise_std is None:
        if noise_window is None:
            raise ValueError("noise_std or noise_window (s, a pre-event window) is needed to weight the data")
        noise_std = noise_from_window(obs, dt, noise_window)
    sigma = np.asarray(noise_std, float)
    if np.any(sigma <= 0):
        raise ValueError("noise_std: a trace has zero noise; give a window with noise or noise_std explicitly")
    if start is None:
        starts = back_projection(phase_models(model), rec, obs, dt, bounds, max(2 * dx, 0.02 * max(hi - lo for lo, hi in bounds)), n_best=int(multi_start))
    else:
        starts = [start] if isinstance(start, dict) else list(start)
    f0 = float(peak_frequency or dominant_frequency(obs[None], dt))
    prob = _problem(model, rec, components, constraint, nt, dt, _simulation_kw(grid, f0, order, pml_width, free_surface, device, precision),
                    stf_filter)  # fmt: skip
    fit = dict(obs=obs, sigma=sigma, bounds=bounds, f0=f0, frequency_range=frequency_range, method=method, scaled=scaled,
               max_iterations=max_iterations, max_evaluations=max_evaluations, journal_path=journal_path, options=options,
               callback=callback)  # fmt: skip
    runs = []
    for k, st in enumerate(starts):
        log.info("start %d/%d: %s, origin time %.4f s%s", k + 1, len(starts), format_position(st["position"], digits=2),
                 st["origin_time"], f" (stack {st['stack']:.2f})" if "stack" in st else "")  # fmt: skip
        runs.append(_fit_ricker(prob, st, **fit))
        log.info("start %d/%d: misfit %.6g at %s after %d evaluations (%s)", k + 1, len(starts), runs[-1]["misfit"],
                 format_position(runs[-1]["p"][: grid.ndim], digits=2), runs[-1]["evaluations"], runs[-1]["stop_reason"])  # fmt: skip
    order_ = sorted(range(len(runs)), key=lambda i: runs[i]["misfit"])
    best = runs[order_[0]]
    candidates = [{**{k: v for k, v in starts[i].items() if k != "grid"}, "misfit": runs[i]["misfit"],
                   "final_position": runs[i]["p"][: grid.ndim]} for i in order_]  # fmt: skip
    res = _ricker_result(prob, best, sigma) if stf == "ricker" else _fit_free(prob, best, obs, sigma, smoothness, bounds, max_iterations)
    res.start, res.candidates = starts[order_[0]], candidates
    res.inflation = float(noise_correlation) * max(1.0, 2 * res.misfit / obs.size)
    res.covariance, res.parameter_covariance = res.covariance * res.inflation, res.parameter_covariance * res.inflation
    if constraint is not None:
        from adseismic.location.moment_tensor import BASIS

        B = np.asarray(BASIS[constraint], float)
        a, ca = best["p"][grid.ndim + 2 :], res.ricker_covariance[grid.ndim + 2 :, grid.ndim + 2 :] * res.inflation
        res.moment_tensor, res.moment_tensor_covariance, res.constraint = a @ B, B.T @ ca @ B, constraint
        res.components = list(components)
        mxx, mzz, mxz = res.moment_tensor
        res.amplitude = float(np.sqrt((mxx**2 + mzz**2 + 2 * mxz**2) / 2))
    return res


def _fit_ricker(prob: _Problem, start, *, obs, sigma, bounds, f0, frequency_range, method, scaled, max_iterations,
                max_evaluations, journal_path, options, callback) -> dict:  # fmt: skip
    """One parametric (Ricker) fit from `start`; returns a dict with p = (position, T, f, amplitudes)."""
    ndim, nt, dt, dx, n_amp = prob.ndim, prob.nt, prob.dt, prob.dx, prob.n_amp
    w2 = 1.0 / sigma[:, None] ** 2
    pos0 = np.asarray(start["position"], float)
    # amplitudes at the start by weighted linear least squares (the data are linear in them)
    s0 = prob.wavelet(np.concatenate([pos0, [start["origin_time"], f0], np.zeros(n_amp)]))[0]
    Dw = (prob.data_basis(pos0, s0) / sigma[None, :, None]).reshape(n_amp, -1)
    a0 = np.linalg.lstsq(Dw.T, (obs / sigma[:, None]).ravel(), rcond=None)[0]
    phys0 = np.concatenate([pos0, [start["origin_time"], f0], a0])
    scale = np.concatenate([np.full(ndim, dx), [dt, f0], np.full(n_amp, np.linalg.norm(a0) or 1.0)]) if scaled else np.ones(len(phys0))
    flo, fhi = frequency_range
    lo = np.concatenate([[b[0] for b in bounds], [0.0, flo * f0], np.full(n_amp, -np.inf)]) / scale
    hi = np.concatenate([[b[1] for b in bounds], [nt * dt, fhi * f0], np.full(n_amp, np.inf)]) / scale

    def objective(x):
        loss, grad = prob.loss_gradient(x * scale, obs, w2)
        return loss, grad * scale

    count = {"evaluations": 0}

    def counted(x):
        count["evaluations"] += 1
        return objective(x)

    def report(iteration, x, *rest):
        # rest: (f, g) from minimize, or (forward runs,) from Gauss-Newton
        if callback is not None:
            p = x * scale
            callback(iteration, rest[0] if len(rest) == 1 else count["evaluations"], p[:ndim], float(p[ndim]))

    if method == "gauss-newton":
        x, it, ev, reason, hist = _gauss_newton(prob, phys0 / scale, scale, lo, hi, obs, sigma, max_iterations, report=report)
    else:
        # stop once an iteration lowers 1/2 chi^2 by less than STOP_HALF_CHI2 (a step of ~0.1 sigma), taken relative
        # to its expected minimum, half the number of data samples (a misfit above it stops later, never earlier)
        res = minimize(counted, phys0 / scale, method=method, bounds=(lo, hi), max_iterations=max_iterations,
                       max_evaluations=max_evaluations, rel_decrease=STOP_HALF_CHI2 / (0.5 * obs.size), grad_tol=1e-9,
                       journal_path=journal_path,
                       callback=report, options=options)  # fmt: skip
        x, it, ev, reason, hist = res.x, res.iterations, res.evaluations, res.stop_reason, res.history
    p = x * scale
    syn = prob.simulate(p)
    return {"p": p, "iterations": it, "evaluations": ev, "stop_reason": reason, "history": hist, "synthetic": syn,
            "misfit": 0.5 * float(np.sum(((syn - obs) / sigma[:, None]) ** 2))}  # fmt: skip


def _ricker_result(prob: _Problem, run: dict, sigma) -> LocationResult:
    p, ndim = run["p"], prob.ndim
    cov = _gn_covariance(prob, p, sigma)
    amps = p[ndim + 2 :]
    held = prob.held_amplitudes(amps)
    return LocationResult(position=p[:ndim], origin_time=float(p[ndim]), peak_frequency=float(p[ndim + 1]),
                          amplitude=float(p[ndim + 2]), covariance=cov[: ndim + 1, : ndim + 1], parameter_covariance=cov,
                          ricker_covariance=cov, stf=prob.wavelet(p)[0] * (amps[0] / held[0]), amplitudes=held, stf_kind="ricker",
                          noise_std=sigma,
                          misfit=run["misfit"], iterations=run["iterations"], evaluations=run["evaluations"],
                          stop_reason=run["stop_reason"], synthetic=run["synthetic"], history=run["history"])  # fmt: skip


def _gn_covariance(prob: _Problem, p, sigma):
    """(J_r^T J_r)^-1 over the Ricker parameters p (J_r: the Jacobian of the whitened residuals)."""
    jr = (prob.jacobian(p) / sigma[None, :, None]).reshape(len(p), -1)
    return np.linalg.inv(jr @ jr.T)


def _convolve(g, h):
    """Data (n_rec, nt) of the source-time function g (nt,) for impulse responses h (n_rec, nt): the
    scheme is time-invariant and starts at rest, so a source at sample k gives h delayed by k."""
    return np.stack([np.convolve(g, hr)[: len(g)] for hr in h])


def _correlate(y, h):
    """Adjoint of _convolve: c[k] = sum_i sum_t y_i(t) h_i(t - k), (nt,) for y, h (n_rec, nt)."""
    nt = y.shape[1]
    return sum(np.correlate(yr, hr, "full")[nt - 1 :] for yr, hr in zip(y, h))


def _normal_matrix(h):
    """(nt, nt) matrix G^T G of _convolve: sum_i sum_t h_i(t - k) h_i(t - l), built from running sums
    of lagged products (memory nt^2, not n_rec nt^2)."""
    nt = h.shape[1]
    P = np.zeros((nt, nt))
    for m in range(nt):
        P[m, : nt - m] = np.cumsum(np.sum(h[:, m:] * h[:, : nt - m], axis=0))
    k, l = np.indices((nt, nt))
    return P[np.abs(k - l), nt - 1 - np.maximum(k, l)]


def _peak_time(g, dt):
    """Time (s) of max |g| by parabolic interpolation, and its gradient with respect to g (nt,)."""
    k = int(np.clip(np.argmax(np.abs(g)), 1, len(g) - 2))
    sgn = np.sign(g[k])
    a, b, c = g[k - 1 : k + 2] * sgn
    den = a - 2 * b + c
    off = 0.5 * (a - c) / den
    grad = np.zeros_like(g)
    grad[k - 1 : k + 2] = sgn * 0.5 * np.array([(den - (a - c)) / den**2, 2 * (a - c) / den**2, (-den - (a - c)) / den**2])
    return (k + off) * dt, grad * dt


def _fit_free(prob: _Problem, run: dict, obs, sigma, smoothness, bounds, max_iterations, tol=1e-6) -> LocationResult:
    """Free source-time function by variable projection, from the Ricker solution `run`.

    For a position x the data are d = G(x) g (G: the impulse response delayed per sample), so the
    best STF solves (G^T W G + mu D^T D) g = G^T W o (W = diag 1/sigma^2, D the second difference);
    the position takes Levenberg-Marquardt steps on the projected residual with Kaufman's Jacobian
    (G'(x) g with its part that a change of the STF can absorb projected out). mu = smoothness x (data curvature per STF sample) / (2 pi f0
    dt)^4: at the Ricker's peak frequency the penalty weighs `smoothness` times the data term, and
    it grows as f^4 above it.
    """
    ndim, nt, dt = prob.ndim, prob.nt, prob.dt
    f0 = float(run["p"][ndim + 1])
    amps = prob.held_amplitudes(run["p"][ndim + 2 :])  # fixed at the Ricker fit's
    k0 = prob.impulse_sample
    spike = np.zeros(nt)
    spike[k0] = 1.0
    w = 1.0 / sigma[:, None]
    ow = obs * w
    DtD = np.diff(np.eye(nt), 2, axis=0)
    DtD = DtD.T @ DtD
    lo, hi = np.array([b[0] for b in bounds]), np.array([b[1] for b in bounds])

    def project(pos):
        h = prob.data(pos, spike, amps)
        h = np.concatenate([h[:, k0:], np.zeros((len(h), k0))], axis=1)  # the response to a spike at sample 0
        hw = h * w  # whitened impulse responses
        H = _normal_matrix(hw)
        mu = smoothness * np.trace(H) / nt / (2 * np.pi * f0 * dt) ** 4
        g = np.linalg.solve(H + mu * DtD, _correlate(ow, hw))
        r = _convolve(g, hw) - ow
        return {"pos": pos, "hw": hw, "H": H, "mu": mu, "g": g, "r": r, "f": 0.5 * float(np.sum(r * r) + mu * g @ DtD @ g)}

    def jac_position(cur, projected=True):
        # d(residual)/d(position) (ndim, n_rec, nt), whitened; projected: with the STF re-solved for
        # every position (Kaufman's variable-projection Jacobian), else at a fixed STF
        J = prob.position_derivatives(cur["pos"], cur["g"], amps) * w
        if projected:
            J = np.stack([j - _convolve(np.linalg.solve(cur["H"] + cur["mu"] * DtD, _correlate(j, cur["hw"])), cur["hw"]) for j in J])
        return J

    cur, lam, hist, evals = project(np.asarray(run["p"][:ndim], float)), 1e-3, [], 1
    reason = "max_iterations"
    for it in range(1, max_iterations + 1):
        Jx = jac_position(cur).reshape(ndim, -1)
        evals += 2 * ndim
        Hx, gx = Jx @ Jx.T, Jx @ cur["r"].ravel()
        new = None
        while lam <= 1e8:
            step = -np.linalg.solve(Hx + lam * np.diag(np.diag(Hx)), gx)
            if np.abs(step).max() < 1e-4 * prob.dx:
                break
            trial = project(np.clip(cur["pos"] + step, lo, hi))
            evals += 1
            if trial["f"] < cur["f"]:
                new = trial
                break
            lam *= 10.0
        if new is None:  # no step of a useful size decreases the misfit
            reason = "converged"
            break
        decrease = cur["f"] - new["f"]
        cur, lam = new, max(lam / 10.0, 1e-7)
        hist.append({"iteration": it, "f": cur["f"], "step": float(np.abs(step).max()), "evaluations": evals})
        if decrease < tol * cur["f"]:
            reason = "rel_decrease"
            break
    # covariance over (position, STF samples) with the smoothness prior, then over (position, peak time)
    Jx = jac_position(cur, projected=False)
    H = np.zeros((ndim + nt, ndim + nt))
    H[:ndim, :ndim] = Jx.reshape(ndim, -1) @ Jx.reshape(ndim, -1).T
    H[:ndim, ndim:] = [_correlate(j, cur["hw"]) for j in Jx]
    H[ndim:, :ndim] = H[:ndim, ndim:].T
    H[ndim:, ndim:] = cur["H"] + cur["mu"] * DtD
    C = np.linalg.inv(H)
    T, dT = _peak_time(cur["g"], dt)
    T += prob.time_offset
    M = np.zeros((ndim + 1, ndim + nt))
    M[:ndim, :ndim] = np.eye(ndim)
    M[ndim, ndim:] = dT
    syn = (cur["r"] + ow) / w
    ricker = run["p"]
    return LocationResult(position=cur["pos"], origin_time=float(T), peak_frequency=float(ricker[ndim + 1]),
                          amplitude=float(ricker[ndim + 2]), covariance=M @ C @ M.T, parameter_covariance=C,
                          ricker_covariance=_gn_covariance(prob, run["p"], sigma), stf=cur["g"], amplitudes=amps,
                          stf_kind="free", noise_std=sigma, misfit=0.5 * float(np.sum(((syn - obs) / sigma[:, None]) ** 2)),
                          iterations=run["iterations"] + len(hist), evaluations=run["evaluations"] + evals,
                          stop_reason=reason, synthetic=syn, history=run["history"] + hist)  # fmt: skip


def _gauss_newton(prob: _Problem, x, scale, lo, hi, obs, sigma, max_iterations, tol=1e-6, report=None):
    """Levenberg-Marquardt on the whitened residuals in scaled parameters; returns like minimize.
    Evaluations count forward simulations (a Jacobian costs 2 ndim + 2 + n_amp of them)."""
    lam, hist, evals = 1e-3, [], 0
    r = ((prob.simulate(x * scale) - obs) / sigma[:, None]).ravel()
    f = 0.5 * float(r @ r)
    for it in range(1, max_iterations + 1):
        J = (prob.jacobian(x * scale) / sigma[None, :, None]).reshape(len(x), -1) * scale[:, None]
        evals += 2 * prob.ndim + 2 + prob.n_amp
        H, g = J @ J.T, J @ r
        while True:
            step = -np.linalg.solve(H + lam * np.diag(np.diag(H)), g)
            x_new = np.clip(x + step, lo, hi)
            r_new = ((prob.simulate(x_new * scale) - obs) / sigma[:, None]).ravel()
            evals += 1
            f_new = 0.5 * float(r_new @ r_new)
            if f_new < f or lam > 1e8:
                break
            lam *= 10.0
        done = f - f_new < tol * f
        x, r, f, lam = x_new, r_new, f_new, max(lam / 10.0, 1e-7)
        hist.append({"iteration": it, "f": f, "step": float(np.abs(step).max()), "evaluations": evals})
        if report is not None:
            report(it, x, evals)
        if done:
            return x, it, evals, "rel_decrease", hist
    return x, max_iterations, evals, "max_iterations", hist


def misfit_map(model, receivers, observed, dt, result: LocationResult, *, n=15, half_width=None, order=4,
               pml_width=None, free_surface=False, device="cpu", precision="float64") -> dict:  # fmt: skip
    """Misfit over an n x n grid of positions in the (z, x) plane through the solution (y fixed in 3D),
    with the source-time function (and moment tensor) fixed at the solution's: a picture of the minimum that the
    covariance ellipse describes. model, receivers: as located (locate()). half_width (m): default max(4 sigma, 3 dx).
    Returns dict z, x (n,) world metres and misfit (n, n) indexed [z, x]; positions outside the model are NaN."""
    grid = _grid(model)
    ndim, dx = grid.ndim, float(grid.spacing[0])
    sd = np.sqrt(np.diag(result.covariance)[:ndim])
    hw = float(half_width or max(4 * sd.max(), 3 * dx))
    z = result.position[0] + np.linspace(-hw, hw, n)
    x = result.position[-1] + np.linspace(-hw, hw, n)
    pts = np.repeat(result.position[None], n * n, axis=0)
    pts[:, 0], pts[:, -1] = np.repeat(z, n), np.tile(x, n)
    inside = grid.contains(pts)
    obs = np.asarray(observed, float)
    kw = _simulation_kw(grid, result.peak_frequency, order, pml_width, free_surface, device, precision)
    prob = _problem(model, receivers, result.components, result.constraint, obs.shape[1], dt, kw)
    out = np.full(n * n, np.nan)
    idx = np.nonzero(inside)[0]
    for sl in shot_slices(len(idx), 64):  # trial positions as the shots of one simulation a batch
        k = idx[sl]
        d = prob.data_many(pts[k], result.stf, result.amplitudes)
        out[k] = 0.5 * np.sum(((d - obs[None]) / result.noise_std[None, :, None]) ** 2, axis=(1, 2))
    return {"z": z, "x": x, "misfit": out.reshape(n, n)}


def compare_optimizers(model: Model, receivers, observed, dt, noise_std, start, reference, *, max_evaluations=30,
                       peak_frequency=None, progress=None, **kw) -> dict:  # fmt: skip
    """The optimiser study on one event: L-BFGS-B, Gauss-Newton, gradient descent (strong-Wolfe
    line search, first step 1) and Adam (lr 0.1) from the same start, each with the parameters
    non-dimensionalised (position / dx, time / dt, f / f0, A / A0) and in raw units (m, s, Hz,
    amplitude), at most max_evaluations evaluations (misfit + gradient; Gauss-Newton: forward runs).
    reference: dict(position, origin_time) the distances are measured to (the converged location,
    or the truth of a synthetic event). Also the condition number of the Gauss-Newton matrix at
    the reference in both unit systems. kw: locate() options (order, pml_width, device, ...).
    Returns {"rows": [...], "condition": {"scaled": c, "raw": c}}."""
    runs = (("lbfgs", True, None), ("lbfgs", False, None), ("gauss-newton", True, None), ("gauss-newton", False, None),
            ("gd", True, {"step": 1.0}), ("gd", False, {"step": 1.0}), ("adam", True, {"lr": 0.1}), ("adam", False, {"lr": 0.1}))  # fmt: skip
    ref_pos, ref_t = np.asarray(reference["position"], float), float(reference["origin_time"])
    rows = []
    for method, scaled, options in runs:
        hit = {}

        def watch(iteration, evaluations, position, origin_time):
            if "at" not in hit and np.linalg.norm(position - ref_pos) <= 1.0 and abs(origin_time - ref_t) <= 1e-3:
                hit["at"] = evaluations

        r = locate(model, receivers, observed, dt, noise_std=noise_std, start=start, method=method, scaled=scaled,
                   peak_frequency=peak_frequency, max_iterations=1000 if method != "gauss-newton" else max_evaluations,
                   max_evaluations=max_evaluations, options=options, callback=watch, **kw)  # fmt: skip
        row = {"method": method, "parameters": "scaled" if scaled else "raw (m, s, Hz)", "options": options or {},
               "position_error_m": float(np.linalg.norm(r.position - ref_pos)), "origin_time_error_ms": 1e3 * abs(r.origin_time - ref_t),
               "evaluations": int(r.evaluations), "stop_reason": r.stop_reason, "reached_at": hit.get("at")}  # fmt: skip
        rows.append(row)
        if progress is not None:
            progress(row)
    # conditioning of the Gauss-Newton matrix at the reference, raw vs scaled
    f0 = float(peak_frequency or dominant_frequency(np.asarray(observed)[None], dt))
    prob = _Problem(model, receivers, np.shape(observed)[1], dt, _simulation_kw(model, f0, kw.get("order", 4), kw.get("pml_width"),
                    kw.get("free_surface", False), kw.get("device", "cpu"), kw.get("precision", "float64")), kw.get("stf_filter"))  # fmt: skip
    p_ref = np.concatenate([ref_pos, [ref_t, f0, 1.0]])
    J = (prob.jacobian(p_ref) / np.asarray(noise_std)[None, :, None]).reshape(len(p_ref), -1)
    scale = np.concatenate([np.full(model.ndim, float(model.spacing[0])), [dt, f0, 1.0]])
    cond = {"raw": float(np.linalg.cond(J @ J.T)), "scaled": float(np.linalg.cond((J * scale[:, None]) @ (J * scale[:, None]).T))}
    return {"rows": rows, "condition": cond}


def optimizer_table(study: dict) -> str:
    """Markdown table of compare_optimizers' result."""
    lines = ["| method | parameters | options | position error (m) | origin-time error (ms) | evaluations | within 1 m and 1 ms at evaluation |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in study["rows"]:
        opts = ", ".join(f"{k} {v:g}" for k, v in r["options"].items())
        lines.append(f"| {r['method']} | {r['parameters']} | {opts} | {r['position_error_m']:.3g} | {r['origin_time_error_ms']:.3g} | "
                     f"{r['evaluations']} ({r['stop_reason']}) | {r['reached_at'] or 'never'} |")  # fmt: skip
    c = study["condition"]
    lines.append("")
    lines.append(f"Condition number of the Gauss-Newton matrix at the solution: {c['raw']:.3g} in raw units (m, s, Hz), "
                 f"{c['scaled']:.3g} non-dimensionalised.")  # fmt: skip
    return "\n".join(lines)

