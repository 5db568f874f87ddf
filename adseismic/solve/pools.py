"""The `parallel:` section's entry points (issue 25): the pool of its engine, its checks before work, and a forward
run of a scene's shots over the pool's workers.

- engine dask: solve.distributed.ShotPool (Dask worker processes; Dask imported only when used);
- engine threads: solve.devices.DevicePool (one thread and one Warp stream per device in this process).

Both have the same face (keep, evaluate, close, workers) and run the same tasks (distributed.batch_gradient,
distributed.batch_forward), which keep each batch's observed data on the device that runs it the same way
(residency.resident, per process, freed at the next keep or close), so a workflow uses either without branching.
"""

from __future__ import annotations

import numpy as np

from adseismic.solve import distributed
from adseismic.solve.devices import DevicePool, check_devices


def check_pool(par, sim_device: str, n_shots: int) -> None:
    """Refuse (ValueError naming the key and the fix) a parallel section that cannot run, before any work: its
    engine's checks (distributed.check_parallel, devices.check_devices). None: nothing to check."""
    if par is None:
        return
    if par.engine == "threads":
        check_devices(par, sim_device, n_shots)
    else:
        distributed.check_parallel(par, sim_device, n_shots)


def open_pool(par, sim_device: str, n_shots: int, progress: bool = False):
    """The pool of par.engine: a ShotPool (dask) or a DevicePool (threads), each a context manager. progress: a bar per
    evaluation over the finished shot batches (a terminal; one log line per evaluation in any case)."""
    if par.engine == "threads":
        return DevicePool(par, sim_device, n_shots, progress)
    return distributed.ShotPool(par, sim_device, n_shots, progress)


def pool_shots_per_batch(n_shots: int, pool) -> int:
    """Shots per batch of a pool's evaluations when inversion.shots_per_batch is unset: one batch per worker, as the
    single-process loop runs all shots at once. A batch of many shots is what keeps a GPU busy: one 2D evaluation of
    32 shots on one H200 took 1.40 s in batches of one shot, 0.325 s in batches of 8 and 0.240 s in one batch
    (docs/benchmarks.md). The batches then depend on the number of workers, and the sum over them differs by the
    rounding of the devices' sums (float32 ~1e-7, float64 ~1e-16); a fixed inversion.shots_per_batch gives the
    same result, bit for bit, on any number of workers."""
    return -(-int(n_shots) // max(len(pool.workers()), 1))


def forward_on_workers(scene, par, snapshot_every: int = 0, progress: bool = False):
    """scene.run_forward(scene, snapshot_every) with the shots partitioned over the workers of the parallel section
    `par` and gathered in shot order: the same ForwardResult (acoustic), ElasticResult or AcousticVDResult, bit for
    bit (the shots are independent; the CPML frequency is the one of all shots' wavelets, as in one process). Batches
    of consecutive shots: one shot first on each worker (a DevicePool runs its devices' first batches one after the
    other while it builds the kernels), then the other shots in one batch per worker."""
    from adseismic.data.models import ElasticModel
    from adseismic.solve.common import dominant_frequency

    p, n, m = scene.plan, len(scene.source_amplitudes), scene.model
    model = m.materials() if isinstance(m, ElasticModel) else {"vp": m.values}
    if isinstance(m, ElasticModel) and m.vs is None:  # acoustic_vd: its own solver, {vp, rho}
        model = {"vp": model["vp"], "rho": model["rho"]}
    kw = {"order": p.order, "pml_width": p.pml_width, "pml_reflection": p.pml_reflection, "free_surface": p.free_surface,
          "precision": p.precision, "pml_frequency": dominant_frequency(np.asarray(scene.source_amplitudes, float), p.dt)}
    params = {"dx": p.dx, "dt": p.dt, "kw": kw, "snapshot_every": snapshot_every, "source_type": scene.source_type}
    with open_pool(par, p.device, n, progress) as pool:
        comp, w = scene.source_components, len(pool.workers())
        rest = [slice(w + i * (n - w) // w, w + (i + 1) * (n - w) // w) for i in range(w)]
        slices = [slice(i, i + 1) for i in range(w)] + [sl for sl in rest if sl.stop > sl.start]
        pool.keep([{"amplitudes": scene.source_amplitudes[sl], "sources": scene.source_locations[sl],
                    "receivers": scene.receiver_locations[sl], "source_components": None if comp is None else comp[sl],
                    "first": sl.start} for sl in slices])  # fmt: skip
        return distributed.gather_forward(pool.evaluate(model, params, fn=distributed.batch_forward, desc="forward"))
