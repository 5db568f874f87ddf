"""Earthquake location by waveform inversion through the differentiable simulator.

Unknowns: source position (m, axis order (z,[y,]x), relative to grid node 0), origin time T (s, the
peak of the source-time function), its peak frequency f (Hz) and amplitude A: the source-time
function is s(t) = A ricker(t - T; f). Misfit: J = 1/2 sum_i sum_t ((d_i(t) - o_i(t)) / sigma_i)^2,
sigma_i the noise standard deviation of trace i (from a pre-event window), so that at the solution
the Gauss-Newton matrix J_r^T J_r (J_r the Jacobian of the whitened residuals) is the inverse
covariance of the estimate (white noise; coloured noise makes it optimistic).

Steps: (1) start: back-projection of the data envelopes with straight-ray travel times through the
model over a grid of candidate positions (no picks needed), origin time from the stack's peak;
(2) amplitude by linear least squares; (3) L-BFGS-B (default), Gauss-Newton (Levenberg-Marquardt
steps, Jacobian by central differences in position and exact derivatives of the wavelet), GD or
Adam, in non-dimensional parameters (position / dx, time / dt, f / f0, log A) or, for the optimiser
study, in raw units (m, s, Hz); (4) covariance C = (J_r^T J_r)^-1 at the solution.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import hilbert

from adseismic.gradient import gradient
from adseismic.models import Model
from adseismic.optimize import minimize
from adseismic.propagate import dominant_frequency, forward
from adseismic.scene import straight_ray_times

log = logging.getLogger(__name__)
N_PHYS = 3  # T, f, A after the position


@dataclass
class LocationResult:
    """position (ndim,) m relative to grid node 0 (axis order (z,[y,]x)); origin_time s (peak of the
    source-time function, on the data's time axis); peak_frequency Hz; amplitude; covariance
    (ndim + 3, ndim + 3) over (position..., T, f, A) in m, s, Hz, amplitude units (1 sigma);
    noise_std (n_receivers,); synthetic (n_receivers, nt); start: the back-projection result."""

    position: np.ndarray
    origin_time: float
    peak_frequency: float
    amplitude: float
    covariance: np.ndarray
    noise_std: np.ndarray
    misfit: float
    iterations: int
    evaluations: int
    stop_reason: str
    synthetic: np.ndarray
    start: dict = field(default_factory=dict)
    history: list = field(default_factory=list)

    @property
    def position_covariance(self):
        """(ndim + 1, ndim + 1) covariance of (position..., origin time)."""
        n = len(self.position) + 1
        return self.covariance[:n, :n]


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


def back_projection(model: Model, receivers, observed, dt, bounds, spacing):
    """Start position and origin time from envelope back-projection: maximise over candidate points
    x (every `spacing` m inside bounds) and times T the stack sum_i env_i(T + tau_i(x)) / max env_i.
    receivers (n, ndim) and bounds ((lo, hi) per axis) in the model's world metres."""
    env = np.abs(hilbert(observed, axis=-1))
    env /= env.max(axis=1, keepdims=True) + 1e-30
    axes = [np.arange(lo, hi + 1e-9, spacing) for lo, hi in bounds]
    cand = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(bounds))
    tau = straight_ray_times(model, cand, receivers)  # (n_cand, n_rec)
    nt = observed.shape[1]
    t = np.arange(nt) * dt
    best = (-1.0, None, None)
    for c in range(len(cand)):
        stack = sum(np.interp(t + tau[c, i], t, env[i], right=0.0) for i in range(len(receivers)))
        k = int(np.argmax(stack))
        if stack[k] > best[0]:
            best = (float(stack[k]), cand[c], k * dt)
    return {"position": best[1], "origin_time": best[2], "stack": best[0] / len(receivers)}


class _Problem:
    """The forward problem of one event: data at the receivers for a source at `pos` (world m)."""

    def __init__(self, model: Model, receivers, nt, dt, kw):
        self.model, self.nt, self.dt, self.kw = model, nt, dt, kw
        self.dx = float(model.spacing[0])
        self.origin = np.asarray(model.origin, float)
        self.rec = (np.asarray(receivers, float) - self.origin)[None]

    def data(self, pos, wavelet):
        """(n_rec, nt) for source-time function `wavelet` (nt,)."""
        return forward(self.model.values, self.dx, self.dt, wavelet[None, None], (pos - self.origin)[None, None], self.rec, **self.kw).receiver_amplitudes[0]

    def simulate(self, p):
        ndim = len(p) - N_PHYS
        return self.data(p[:ndim], source_wavelet(self.nt, self.dt, *p[ndim:])[0])

    def jacobian(self, p):
        """d(data)/d(parameters) (n_params, n_rec, nt): central differences in position (h = 0.05 dx;
        the source operator is C^1 in the position) and exact derivatives for (T, f, A): the data are
        linear in the source-time function, so d(data)/dT is the data of d(s)/dT."""
        ndim = len(p) - N_PHYS
        cols = []
        for a in range(ndim):
            e = np.zeros_like(p)
            e[a] = 0.05 * self.dx
            cols.append((self.simulate(p + e) - self.simulate(p - e)) / (0.1 * self.dx))
        _, ds = source_wavelet(self.nt, self.dt, *p[ndim:])
        cols += [self.data(p[:ndim], ds[k]) for k in range(N_PHYS)]
        return np.stack(cols)


def locate(model: Model, receivers, observed, dt, *, noise_std=None, noise_window=None, bounds=None,
           start=None, peak_frequency=None, method="lbfgs", scaled=True, max_iterations=60, max_evaluations=None,
           order=4, pml_width=None, device="cpu", precision="float64", journal_path=None, options=None,
           callback=None) -> LocationResult:  # fmt: skip
    """Locate one event. model: the velocity Model on the simulation grid (uniform spacing dx, node 0
    at model.origin); receivers (n, ndim) world metres; observed (n, nt) at t = k dt. bounds: ((lo, hi)
    per axis) world metres (default: the model less 2 cells); start: dict(position, origin_time) to skip
    the back-projection. method: "lbfgs" (L-BFGS-B), "gauss-newton", "gd", "adam"; scaled=False works
    in raw units (m, s, Hz), which plain gradient descent cannot handle (the optimiser study).
    callback(iteration, evaluations, position, origin_time) after every iteration."""
    from adseismic.traces import check_inside, check_samples

    dx = float(model.spacing[0])
    rec = np.asarray(receivers, float)
    obs = np.asarray(observed, float)
    n_rec, nt = obs.shape
    ndim = model.ndim
    check_inside(rec, model, "receiver")
    check_samples(obs, [f"trace {i}" for i in range(n_rec)])  # NaN/inf refused, clipped traces warned about
    if bounds is None:
        bounds = [(lo + 2 * dx, hi - 2 * dx) for lo, hi in model.extent]
    if noise_std is None:
        if noise_window is None:
            raise ValueError("noise_std or noise_window (s, a pre-event window) is needed to weight the data")
        noise_std = noise_from_window(obs, dt, noise_window)
    sigma = np.asarray(noise_std, float)
    if np.any(sigma <= 0):
        raise ValueError("noise_std: a trace has zero noise; give a window with noise or noise_std explicitly")
    if start is None:
        start = back_projection(model, rec, obs, dt, bounds, max(2 * dx, 0.02 * max(hi - lo for lo, hi in bounds)))
        log.info("back-projection start: position %s m, origin time %.4f s (stack %.2f)", start["position"], start["origin_time"], start["stack"])
    f0 = float(peak_frequency or dominant_frequency(obs[None], dt))
    kw = dict(order=order, pml_width=pml_width, device=device, precision=precision, pml_velocity=model.vmax, pml_frequency=f0)
    prob = _Problem(model, rec, nt, dt, kw)
    w2 = 1.0 / sigma[:, None] ** 2

    # amplitude at the start by linear least squares (the data are linear in A)
    d1 = prob.simulate(np.concatenate([start["position"], [start["origin_time"], f0, 1.0]]))
    A0 = float(np.sum(w2 * d1 * obs) / max(np.sum(w2 * d1 * d1), 1e-300))
    phys0 = np.concatenate([start["position"], [start["origin_time"], f0, A0]])
    scale = np.concatenate([np.full(ndim, dx), [dt, f0, abs(A0) or 1.0]]) if scaled else np.ones(ndim + N_PHYS)
    lo = np.concatenate([[b[0] for b in bounds], [0.0, 0.3 * f0, -np.inf]]) / scale
    hi = np.concatenate([[b[1] for b in bounds], [nt * dt, 3.0 * f0, np.inf]]) / scale

    def objective(x):
        p = x * scale
        s, ds = source_wavelet(nt, dt, *p[ndim:])

        def misfit(syn):
            r = (syn[0] - obs) * w2
            return 0.5 * float(np.sum((syn[0] - obs) * r)), r[None]

        g = gradient(model.values, dx, dt, s[None, None], (p[:ndim] - prob.origin)[None, None], prob.rec, misfit=misfit,
                     wrt=("source_amplitudes", "source_locations"), **kw)  # fmt: skip
        grad = np.concatenate([g.source_locations[0, 0], ds @ g.source_amplitudes[0, 0]])
        return g.loss, grad * scale

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
        res = minimize(counted, phys0 / scale, method=method, bounds=(lo, hi), max_iterations=max_iterations,
                       max_evaluations=max_evaluations, rel_decrease=1e-12, grad_tol=1e-9, journal_path=journal_path,
                       callback=report, options=options)  # fmt: skip
        x, it, ev, reason, hist = res.x, res.iterations, res.evaluations, res.stop_reason, res.history
    p = x * scale
    jr = (prob.jacobian(p) / sigma[None, :, None]).reshape(len(p), -1)
    syn = prob.simulate(p)
    return LocationResult(position=p[:ndim], origin_time=float(p[ndim]), peak_frequency=float(p[ndim + 1]),
                          amplitude=float(p[ndim + 2]), covariance=np.linalg.inv(jr @ jr.T), noise_std=sigma,
                          misfit=0.5 * float(np.sum(((syn - obs) / sigma[:, None]) ** 2)), iterations=it, evaluations=ev,
                          stop_reason=reason, synthetic=syn, start=start, history=hist)  # fmt: skip


def _gauss_newton(prob: _Problem, x, scale, lo, hi, obs, sigma, max_iterations, tol=1e-6, report=None):
    """Levenberg-Marquardt on the whitened residuals in scaled parameters; returns like minimize.
    Evaluations count forward simulations (a Jacobian costs 2 ndim + 3 of them)."""
    lam, hist, evals = 1e-3, [], 0
    r = ((prob.simulate(x * scale) - obs) / sigma[:, None]).ravel()
    f = 0.5 * float(r @ r)
    for it in range(1, max_iterations + 1):
        J = (prob.jacobian(x * scale) / sigma[None, :, None]).reshape(len(x), -1) * scale[:, None]
        evals += 2 * (len(x) - N_PHYS) + N_PHYS
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
