"""Shot parallelism on Dask (issue 25): the shot batches of one misfit + gradient evaluation on Dask workers.

A `ShotPool` is a Dask client on a LocalCluster (`scheduler: local`: one worker process per device, one thread
each; CPU workers when there is no GPU) or on a running scheduler (an address: e.g. a dask-jobqueue SLURM
cluster, docs/parallel.md). The workflow hands it, once per band, each shot batch's data (`keep`), and then, per
evaluation, only the model (`evaluate`):

- resident data: each batch's arrays (wavelets, geometry, weights, weighted observed data) are the result of a task
  `keep` submits once, placed round-robin on the workers; the evaluation tasks that need them run where they are
  (Dask's data locality), so an evaluation moves the model out (one task, fetched by the workers) and the
  (misfit, gradient) of each batch back, nothing else. The scheduler keeps the batch tasks' inputs, so a batch
  whose worker is lost is rebuilt on another worker;
- faults: a worker lost mid-evaluation (killed, out of memory) has its tasks re-run by the scheduler elsewhere
  (or on the worker its nanny restarts); the evaluation then completes with the fault-free result, as every task
  is a pure function of the model and its batch's data;
- reduction: `evaluate` returns the batches' results in batch order and the caller sums them on the client in
  float64 in that order (as the single-process loop does), so the result does not depend on the number of workers
  or on which worker ran what.

Each worker initialises Warp itself (solve.common.init_warp, through the gradient's setup); CPU kernels compile once
per process into the shared kernel cache. Dask is imported only here and only when a pool is used: the package runs
without it when a config has no `parallel:` section.
"""

from __future__ import annotations

import logging
import os
import time
import uuid

import numpy as np

log = logging.getLogger(__name__)

CONNECT_TIMEOUT = 5.0  # s to reach a scheduler address before the run is refused
WORKER_WAIT = 60.0  # s for the workers asked for (parallel.workers) to join a remote scheduler


def _import_dask(key="parallel.engine"):
    try:
        import distributed
    except ImportError:
        raise ValueError(f"{key}: dask is not installed; pip install 'adseismic[dask]' (dask[distributed]), "
                         f"or drop the parallel section to run in one process") from None
    return distributed


def _cuda_devices() -> list[str]:
    from adseismic.solve.common import init_warp

    init_warp()
    import warp as wp

    return [f"cuda:{i}" for i in range(wp.get_cuda_device_count())]


def local_devices(par, sim_device: str, n_shots: int) -> list[str]:
    """One device per worker of a LocalCluster (ValueError naming the key for a device that does not exist here or
    for more workers than shots)."""
    from adseismic.solve.common import resolve_device

    devices = par.devices
    if devices is None:
        devices = "cpu" if str(sim_device).startswith("cpu") else "all"
    if devices == "all":
        gpus = _cuda_devices()
        if gpus:
            n = par.workers or min(len(gpus), n_shots)
            devices = gpus
        else:  # CPU workers: one per core, at most one per shot
            n = par.workers or max(1, min(os.cpu_count() or 1, n_shots))
            devices = ["cpu"]
    else:
        for i, d in enumerate(devices):
            try:
                resolve_device(d)
            except ValueError as e:
                raise ValueError(f"parallel.devices[{i}]: {e}; list devices of this host, or all") from None
        n = par.workers or len(devices)
    if n > n_shots:
        raise ValueError(f"parallel.devices: {n} workers for {n_shots} shot(s); a worker needs at least one shot: "
                         f"give parallel.workers <= {n_shots}")
    return [devices[i % len(devices)] for i in range(n)]


def check_parallel(par, sim_device: str, n_shots: int) -> None:
    """Refuse (ValueError naming the key and the fix) a parallel section that cannot run, before any work: dask
    missing, a scheduler address that does not answer within CONNECT_TIMEOUT s, fewer workers than asked for,
    a device that does not exist, more workers than shots."""
    if par is None:
        return
    _import_dask()
    if par.scheduler == "local":
        local_devices(par, sim_device, n_shots)
        return
    client = _connect(par.scheduler)
    try:
        _remote_devices(client, par, sim_device)
    finally:
        client.close()


def _connect(address: str):
    distributed = _import_dask()
    try:
        return distributed.Client(address, timeout=f"{CONNECT_TIMEOUT}s", set_as_default=False)
    except (OSError, TimeoutError) as e:
        raise ValueError(f"parallel.scheduler: no Dask scheduler answers at {address!r} within {CONNECT_TIMEOUT:g} s "
                         f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else 'timed out'}); start it (dask scheduler, or a "
                         f"dask-jobqueue cluster: docs/parallel.md) and give the address it prints, or write scheduler: local") from None


def _device_exists(device):
    from adseismic.solve.common import resolve_device

    try:
        resolve_device(device)
        return None
    except ValueError as e:
        return str(e)


def _remote_devices(client, par, sim_device) -> dict:
    """{worker name: device} on a running scheduler's workers: parallel.devices by worker (sorted by name), or the
    simulation device on every worker (each worker sees its own GPU, e.g. one per SLURM job)."""
    want = par.workers or 1
    try:
        client.wait_for_workers(want, timeout=WORKER_WAIT)
    except (TimeoutError, OSError):
        have = len(client.scheduler_info(n_workers=-1)["workers"])
        raise ValueError(f"parallel.workers: {want} worker(s) asked for but {have} joined {par.scheduler} within {WORKER_WAIT:g} s; "
                         f"start more workers or lower parallel.workers") from None
    workers = client.scheduler_info(n_workers=-1)["workers"]
    names = sorted(workers, key=lambda a: str(workers[a].get("name", a)))
    devices = par.devices if isinstance(par.devices, list) else [sim_device if par.devices is None else "cuda"]
    plan = {workers[a].get("name", a): devices[i % len(devices)] for i, a in enumerate(names)}
    for i, d in enumerate(devices):
        on = [a for j, a in enumerate(names) if j % len(devices) == i]
        bad = client.run(_device_exists, d, workers=on) if on else {}
        for addr, err in bad.items():
            if err:
                raise ValueError(f"parallel.devices[{i}]: worker {addr}: {err}; list devices its host has")
    return plan


def _identity(x):
    return x


def _resident(data):
    """A batch's data, kept on the worker that ran this task (rebuilt from the scheduler's copy of the input if that
    worker is lost)."""
    return data


def _my_device(devices: dict, default: str) -> str:
    try:
        from distributed import get_worker

        return devices.get(get_worker().name, default)
    except (ImportError, ValueError):
        return default


def batch_gradient(model, data, params) -> dict:
    """The acoustic misfit and velocity gradient of one shot batch (a Dask task). data: {amplitudes, sources,
    receivers, weights, observed (weights x observed), first (the batch's first shot)}; params: {dx, dt, misfit
    (a name of solve.misfits.MISFITS), illumination, kw (solve.acoustic.gradient's keywords), devices, device}.
    The weighted misfit is that of inversion.fwi's single-process loop, operation for operation."""
    from adseismic.solve.acoustic import gradient
    from adseismic.solve.misfits import misfit as named_misfit

    w, o = data["weights"], data["observed"]
    spent = [0.0]

    def weighted(syn):
        t = time.perf_counter()
        j, adj = named_misfit(params["misfit"], w * syn, o, params["dt"])
        adj = w * adj
        spent[0] += time.perf_counter() - t
        return j, adj

    t = time.perf_counter()
    kw = dict(params["kw"], device=_my_device(params["devices"], params["device"]))
    r = gradient(model, params["dx"], params["dt"], data["amplitudes"], data["sources"], data["receivers"], misfit=weighted,
                 illumination=params["illumination"], **kw)  # fmt: skip
    return {"loss": r.loss, "velocity": r.velocity, "illumination": r.illumination, "first": data["first"],
            "synthetic0": r.synthetic[0] if data["first"] == 0 else None, "seconds": time.perf_counter() - t,
            "misfit_seconds": spent[0], "pid": os.getpid()}  # fmt: skip


class ShotPool:
    """A Dask client and its workers for one run; use as a context manager (closes the cluster it started)."""

    def __init__(self, par, sim_device: str, n_shots: int):
        distributed = _import_dask()
        self.par, self.cluster, self.token = par, None, uuid.uuid4().hex[:12]
        # distributed's nanny writes its workers' settings (OMP/MKL/OPENBLAS_NUM_THREADS=1, MALLOC_TRIM_THRESHOLD_) into
        # this process's os.environ and leaves them there: every process started later (a forward, a resumed fwi in a
        # subprocess) would then run one BLAS thread where it ran several, and its sums would differ in the last bit.
        # close() puts the environment back.
        self.environ = dict(os.environ)
        self.generation, self.evaluations, self.futures = 0, 0, []
        if par.scheduler == "local":
            devices = local_devices(par, sim_device, n_shots)
            self.cluster = distributed.LocalCluster(n_workers=len(devices), threads_per_worker=1, processes=True,
                                                    dashboard_address=":0", silence_logs=logging.WARNING)  # fmt: skip
            self.client = distributed.Client(self.cluster, set_as_default=False)
            info = self.client.scheduler_info(n_workers=-1)["workers"]
            names = sorted(info[a]["name"] for a in info)  # LocalCluster names its workers 0, 1, ... (kept across restarts)
            self.devices = dict(zip(names, devices))
        else:
            self.client = _connect(par.scheduler)
            self.devices = _remote_devices(self.client, par, sim_device)
        self.default_device = sim_device
        log.info("parallel: %d Dask worker(s) on %s (%s)", len(self.devices), par.scheduler if self.cluster is None else "a LocalCluster",
                 ", ".join(f"{k}: {v}" for k, v in self.devices.items()))  # fmt: skip

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        self.futures = []
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        os.environ.clear()
        os.environ.update(self.environ)

    def workers(self) -> list[str]:
        """The addresses of the workers now connected."""
        return sorted(self.client.scheduler_info(n_workers=-1)["workers"])

    def keep(self, batches: list[dict]) -> None:
        """Place each batch's data (a dict of arrays) on a worker, round-robin, until the next keep (which releases
        them): the data of every later evaluate."""
        self.futures = []  # releases the previous band's data
        self.generation += 1
        addrs = self.workers()
        self.futures = [self.client.submit(_resident, d, key=f"adseismic-data-{self.token}-{self.generation}-{k}",
                                           workers=[addrs[k % len(addrs)]], allow_other_workers=True)
                        for k, d in enumerate(batches)]  # fmt: skip

    def evaluate(self, model, params: dict, fn=batch_gradient) -> list[dict]:
        """fn(model, batch data, params) for every kept batch on the workers; the results in batch order."""
        self.evaluations += 1
        tag = f"{self.token}-{self.generation}-{self.evaluations}"
        params = dict(params, devices=self.devices, device=params.get("device", self.default_device))
        model = self.client.submit(_identity, np.asarray(model), key=f"adseismic-model-{tag}")
        futures = [self.client.submit(fn, model, d, params, key=f"adseismic-eval-{tag}-{k}") for k, d in enumerate(self.futures)]
        try:
            return self.client.gather(futures)
        finally:
            del futures, model


def reduce_in_order(results: list[dict], shape) -> tuple:
    """(loss, gradient, illumination or None) summed in float64 in the order of the list (batch order)."""
    loss, grad = 0.0, np.zeros(shape)
    illum = np.zeros(shape) if results and results[0]["illumination"] is not None else None
    for r in results:
        loss += r["loss"]
        grad += r["velocity"]
        if illum is not None:
            illum += r["illumination"]
    return loss, grad, illum

