"""The imaging run (``adseismic image CONFIG -o OUTDIR``): plan, background, data, RTM or LSRTM, outputs.

1. prepare_image (before OUTDIR is touched; ValueError on bad input): plan the grid for the range of the migration
   model and the true model (every simulation is stable and resolved), check the memory of a gradient of every
   shot, resample the model onto the grid and smooth its slowness by image.smoothing into the background (the
   water above image.water_depth kept as it is), read observed files as fwi reads them;
2. run_image: the observed data (simulated from true_model with the full wavelet, or the files'), then RTM or
   LSRTM (adseismic.imaging.born) in the background, the image zero above image.water_depth. Physics elastic
   (a synthetic study: data from true_model): RTM only, the image the adjoint of the data's derivative with respect
   to vp applied to the reflection data (solve.elastic.gradient_elastic), without illumination compensation;
3. outputs, each written atomically: image.h5 (the image, its raw form, illumination, background, the residual
   history, with the grid: dx, origin, axis order, units and what was computed), image.png, illumination.png,
   background.png and, for LSRTM, residual.png.
"""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from adseismic.data.atomic import write_h5_atomic
from adseismic.data.models import _smooth
from adseismic.imaging.born import BornOperator, ImageResult, lsrtm, rtm, rtm_filter
from adseismic.inversion.conditioning import mask as depth_mask
from adseismic.inversion.fwi import _simulator, read_observed
from adseismic.scene import build_scene, check_memory, gradient_memory_bytes, plan_scene
from adseismic.solve import distributed
from adseismic.solve.acoustic import forward
from adseismic.solve.common import dominant_frequency
from adseismic.solve.batch import shot_slices
from adseismic.solve.pools import check_pool, open_pool, pool_shots_per_batch

log = logging.getLogger(__name__)

UNITS = {"rtm": "relative amplitude: B^T r / (I / max I + epsilon), (data units)^2 per (m/s)",
         "lsrtm": "m/s: the velocity perturbation dm of the background that best explains the reflection data",
         "elastic": "relative amplitude: (dF/dvp)^T r, (data units)^2 per (m/s) summed over the components"}

OUTPUTS = ("image.h5", "image.png", "background.png", "illumination.png", "residual.png")


@dataclass
class PreparedImage:
    """What an imaging run needs before it writes anything: plan, scene (the migration model on the simulation
    grid), background {vp, [vs, rho]} (nz, [ny,] nx) m/s, kg/m^3, mask (image weights, 0 above image.water_depth),
    observed data from files (n_shots, n_receivers, nt) or None (simulated from true_model), vp_range (min, max) m/s
    of the models."""

    plan: object
    scene: object
    background: dict
    mask: np.ndarray
    observed: np.ndarray | None
    vp_range: tuple


def prepare_image(cfg) -> PreparedImage:
    """Plan, make the background and read observed files; raises ValueError (bad input) before any output exists."""
    fwd, im = cfg.forward, cfg.image
    models = [fwd.model] + ([cfg.true_model] if cfg.true_model is not None else [])
    vrange = (min(m.vmin for m in models), max(m.vmax for m in models))
    extra = {} if cfg.physics == "acoustic" else {"vs_range": (min(m.vs.vmin for m in models), max(m.vs.vmax for m in models))}
    plan = plan_scene(fwd, velocity_range=vrange, check_memory_of_run=False, **extra)
    n_shots = len(fwd.geometry.sources)
    grid = " x ".join(map(str, plan.shape))
    plan.reasons["memory"] = check_memory(
        gradient_memory_bytes(plan, n_shots), fwd.simulation,
        f"image: background and adjoint wavefields of {n_shots} shot(s) at once on a {grid} grid, {plan.nt:,} steps",
        "use fewer shots, a lower frequency or a smaller domain")
    scene = build_scene(fwd, plan)
    mask = depth_mask(plan.shape, plan.dx, plan.origin, water_depth=im.water_depth)
    parts = {"vp": scene.model} if cfg.physics == "acoustic" else {k: getattr(scene.model, k) for k in ("vp", "vs", "rho")}
    background = {}
    for name, m in parts.items():
        smooth = _smooth(m, im.smoothing).values if im.smoothing > 0 else m.values
        background[name] = np.where(mask > 0, smooth, m.values)  # the water stays as it is
    if cfg.parallel is not None:  # scheduler reachable, devices present, not more workers than shots
        check_pool(cfg.parallel, plan.device, n_shots)
    observed = read_observed(cfg.observed, scene, fwd.geometry) if cfg.observed is not None else None
    if observed is not None and not np.any(observed):
        raise ValueError(f"observed: every sample of the observed data is zero ({observed.shape[0]} shots x "
                         f"{observed.shape[1]} receivers x {observed.shape[2]} samples); check the files")
    return PreparedImage(plan, scene, background, mask, observed, vrange)


def born_operator(prep: PreparedImage) -> BornOperator:
    """The Born operator of the prepared background, with the plan's numerics (the CPML's reference speed pinned to
    the models' highest: the true model's simulation absorbs as the background's, and no PML difference is left in
    the reflection data)."""
    s, p = prep.scene, prep.plan
    return BornOperator(prep.background["vp"], p.dx, p.dt, s.source_amplitudes, s.source_locations, s.receiver_locations,
                        {"order": p.order, "pml_width": p.pml_width, "pml_reflection": p.pml_reflection,
                         "pml_velocity": prep.vp_range[1], "free_surface": p.free_surface, "device": p.device,
                         "precision": p.precision})


def observed_data(cfg, prep: PreparedImage, progress: bool = False) -> np.ndarray:
    """The observed data (n_shots, n_receivers, nt) on the simulation's time axis: the files' or simulated from
    true_model with the same numerics."""
    if prep.observed is not None:
        return prep.observed
    p, s = prep.plan, prep.scene
    true = cfg.true_model.resample(p.dx, p.origin, p.shape)
    log.info("simulating the observed data from the true model (%d shots, %s)", len(s.source_amplitudes), cfg.physics)
    if cfg.physics == "elastic":  # {component: (n_shots, n_receivers, nt)}
        physical = {k: getattr(true, k).values for k in ("vp", "vs", "rho")}
        data = elastic_simulator(cfg, prep).forward(physical, p.dx, p.dt, s.source_amplitudes, s.source_locations,
                                                     s.receiver_locations, progress=progress)  # fmt: skip
        return {c: np.asarray(d, float) for c, d in data.items()}
    op = born_operator(prep)
    return forward(true.values, p.dx, p.dt, s.source_amplitudes, s.source_locations, s.receiver_locations,
                   progress=progress, **op.options).receiver_amplitudes.astype(float)


def elastic_simulator(cfg, prep: PreparedImage):
    """The elastic side of the fwi workflow's Simulator for this run (components, source mechanism, numerics)."""
    return _simulator(cfg, prep, SimpleNamespace(memory_budget_gb=None), prep.vp_range)


def rtm_elastic(cfg, prep: PreparedImage, observed: dict) -> ImageResult:
    """Elastic RTM: minus the gradient with respect to vp of 1/2 sum over components of |d_obs - F(background)|^2,
    i.e. (dF/dvp)^T r, r the reflection data of every recorded component; zero above image.water_depth. No
    illumination (the elastic solver returns none). ImageResult.residual: the components stacked (n_components,
    n_shots, n_receivers, nt)."""
    p, s = prep.plan, prep.scene
    kept = {}

    def misfit(syn):
        kept["r"] = {c: observed[c] - np.asarray(syn[c], float) for c in observed}
        return 0.5 * sum(float(np.vdot(r, r)) for r in kept["r"].values()), {c: -r for c, r in kept["r"].items()}

    _, grads, _, _ = elastic_simulator(cfg, prep).gradient(prep.background, p.dx, p.dt, s.source_amplitudes,
                                                           s.source_locations, s.receiver_locations, misfit, ("vp",))
    raw = -np.asarray(grads["vp"], float)
    r = np.stack([kept["r"][c] for c in observed])
    image = rtm_filter(raw, p.dx, mask=prep.mask, laplacian=cfg.image.laplacian)
    return ImageResult("rtm", image, raw, None, [float(np.linalg.norm(r))], r)


class PooledBorn:
    """The Born operator `op` with its shots over the workers of a parallel section (solve.pools; one batch of shots a
    worker, solve.distributed.batch_born / batch_born_adjoint), data joined and images summed in shot order: apply, adjoint
    and migrate as op's, the one-process results to rounding, so rtm and lsrtm run on it unchanged. The background
    and dm go to every worker per call; each call's shot data (geometry, observed data or the residual) are kept on
    the workers for that call. A context manager: it opens and closes the pool."""

    def __init__(self, op: BornOperator, par, progress: bool = False):
        self.op, self.dx, self.progress = op, op.dx, progress
        amp = np.asarray(op.source_amplitudes, float)
        kw = {k: v for k, v in op.options.items() if k != "device"}  # (each task runs on its worker's device)
        kw["pml_frequency"] = dominant_frequency(amp, op.dt)  # all shots', as one process
        self.params = {"dx": op.dx, "dt": op.dt, "kw": kw, "illumination": False}
        self.pool = open_pool(par, op.options.get("device", "cpu"), len(amp), progress)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.pool.close()

    def _run(self, model, fn, per_shot: dict, desc: str, illumination: bool = False) -> list:
        op = self.op
        n = len(op.source_amplitudes)
        self.pool.keep([{"amplitudes": op.source_amplitudes[sl], "sources": op.source_locations[sl], "receivers": op.receiver_locations[sl],
                         "first": sl.start, **{k: a[sl] for k, a in per_shot.items()}}
                        for sl in shot_slices(n, pool_shots_per_batch(n, self.pool))])  # fmt: skip
        return self.pool.evaluate(model, dict(self.params, illumination=illumination), fn=fn, desc=desc)

    def _summed(self, results, illumination):
        image, illum = np.zeros(self.op.background.shape), np.zeros(self.op.background.shape) if illumination else None
        for r in results:  # in shot order
            image += r["image"]
            if illum is not None:
                illum += r["illumination"]
        return image, illum

    def apply(self, dm: np.ndarray) -> np.ndarray:
        """B dm (n_shots, n_receivers, nt), as BornOperator.apply."""
        results = self._run({"background": self.op.background, "dm": np.asarray(dm, float)}, distributed.batch_born, {}, "born")
        return np.concatenate([r["data"] for r in results])

    def adjoint(self, data: np.ndarray, illumination: bool = False):
        """(B^T data, illumination or None), as BornOperator.adjoint."""
        results = self._run(self.op.background, distributed.batch_born_adjoint, {"residual": np.asarray(data, float)}, "adjoint",
                            illumination)  # fmt: skip
        return self._summed(results, illumination)

    def migrate(self, observed: np.ndarray, illumination: bool = False):
        """(B^T r, illumination or None, r = observed - F(v0)), as BornOperator.migrate."""
        results = self._run(self.op.background, distributed.batch_born_adjoint, {"observed": np.asarray(observed, float)}, "migrate",
                            illumination)  # fmt: skip
        return (*self._summed(results, illumination), np.concatenate([r["data"] for r in results]))


def run_image(cfg, outdir, progress: bool = False, prepared: PreparedImage | None = None) -> ImageResult:
    """Image the reflectors of cfg (an ImageConfig, adseismic.config.image) into the folder outdir: image.h5 and the
    PNGs. Returns the ImageResult (arrays on the simulation grid, axis order (z, [y,] x))."""
    from adseismic import plotting

    outdir = Path(outdir)
    prep = prepared or prepare_image(cfg)
    im, p = cfg.image, prep.plan
    stale = [outdir / n for n in OUTPUTS if (outdir / n).exists()]  # an earlier run's, which this one may not rewrite
    if stale:
        log.info("replacing the outputs of an earlier run in %s: %s", outdir, ", ".join(q.name for q in stale))
        for q in stale:
            q.unlink()
    t0 = time.perf_counter()
    observed = observed_data(cfg, prep, progress)
    op = born_operator(prep)
    log.info("%s in a background smoothed over %g m (water kept above %g m), %d shot(s)", im.method, im.smoothing,
             im.water_depth, p.n_shots)
    options = {"mask": prep.mask, "illumination": im.illumination, "epsilon": im.epsilon}
    if cfg.physics == "elastic":
        res = rtm_elastic(cfg, prep, observed)
    else:
        with contextlib.ExitStack() as stack:
            if cfg.parallel is not None:  # the shots over the workers
                op = stack.enter_context(PooledBorn(op, cfg.parallel, progress))
            if im.method == "rtm":
                res = rtm(op, observed, laplacian=im.laplacian, **options)
            else:
                res = lsrtm(op, observed, im.iterations, **options)
    seconds = time.perf_counter() - t0
    log.info("%s done in %.1f s", im.method, seconds)
    write_image_h5(outdir / "image.h5", res, prep, cfg, seconds)
    src, rec = cfg.forward.geometry.sources, cfg.forward.geometry.receivers
    what = {"rtm": "RTM image" + (" (-laplacian)" if im.laplacian else "") + (", illumination-compensated" if im.illumination else ""),
            "lsrtm": f"LSRTM image, {len(res.residual_norms) - 1} iterations"}[im.method]  # fmt: skip
    plotting.plot_model(outdir / "image.png", res.image, p.dx, p.origin, src, rec, title=what, cmap="gray",
                        symmetric=True, label="dm (m/s)" if im.method == "lsrtm" else "image (relative)")
    plotting.plot_model(outdir / "background.png", prep.background["vp"], p.dx, p.origin, src, rec,
                        title=f"migration background (slowness smoothed over {im.smoothing:g} m)")
    if res.illumination is not None:
        plotting.plot_model(outdir / "illumination.png", res.illumination / res.illumination.max(), p.dx, p.origin, src,
                            rec, title="source illumination I / max I", label="I / max I", cmap="magma")
    if im.method == "lsrtm":
        rows = [(0, k, n / res.residual_norms[0]) for k, n in enumerate(res.residual_norms)]
        plotting.plot_misfit(outdir / "residual.png", rows, title="LSRTM: data residual |B dm - r| / |r|",
                             ylabel="|B dm - r| / |r|")
    return res


def write_image_h5(path, res: ImageResult, prep: PreparedImage, cfg, seconds: float) -> None:
    """image.h5 (atomic): datasets image, raw, background (m/s), mask, illumination (when computed), residual_norms;
    attributes dx (m), origin (m), axes, units, method and the settings."""
    p, im = prep.plan, cfg.image

    def fill(f):
        f.create_dataset("image", data=res.image)
        f.create_dataset("raw", data=res.raw)
        for k, v in prep.background.items():
            f.create_dataset("background" if k == "vp" else f"background_{k}", data=v)
        f.create_dataset("mask", data=prep.mask)
        if res.illumination is not None:
            f.create_dataset("illumination", data=res.illumination)
        f.create_dataset("residual_norms", data=np.asarray(res.residual_norms))
        f.attrs.update({
            "method": res.method, "dx": p.dx, "origin": np.asarray(p.origin), "axes": "z, y, x" if p.ndim == 3 else "z, x",
            "units": UNITS[res.method] if cfg.physics == "acoustic" else UNITS["elastic"],
            "computed": _computed(res.method, im, cfg.physics), "physics": cfg.physics, "smoothing_m": im.smoothing,
            "water_depth_m": im.water_depth, "illumination_compensation": im.illumination, "epsilon": im.epsilon,
            "laplacian": im.laplacian, "iterations": len(res.residual_norms) - 1, "dt": p.dt, "nt": p.nt,
            "n_shots": p.n_shots, "seconds": seconds,
            "raw_units": "B^T r before any filter, (data units)^2 per (m/s)" if res.method == "rtm" else
                         "the first conjugate-gradient direction W B^T r",
            "residual_norms_units": "|r_k| of the data residual, data units; k = 0: the reflection data d_obs - F(v0)",
        })  # fmt: skip
    write_h5_atomic(path, fill)


def _computed(method: str, im, physics: str) -> str:
    if physics == "elastic":
        return ("elastic reverse-time migration: (dF/dvp)^T r summed over the recorded components, r = d_obs - "
                "F(background)" + (", then -laplacian" if im.laplacian else "") + ", zero above water_depth")
    if method == "rtm":
        return ("reverse-time migration: B^T r, r = d_obs - F(background)" + (", then -laplacian" if im.laplacian else "")
                + (", divided by I / max I + epsilon (I: source illumination)" if im.illumination else "")
                + ", zero above water_depth")
    return (f"least-squares RTM: {im.iterations} CGLS iterations on min |B dm - r|^2, r = d_obs - F(background)"
            + (", preconditioned by 1 / sqrt(I / max I + epsilon)" if im.illumination else "") + ", zero above water_depth")
