"""Shot parallelism on Dask (issue 25): the shot batches of one misfit + gradient evaluation on Dask workers.

A `ShotPool` is a Dask client on a LocalCluster (`scheduler: local`: one worker process per device, one thread
each; CPU workers when there is no GPU) or on a running scheduler (an address: e.g. a dask-jobqueue SLURM
cluster, docs/parallel.md). The workflow hands it, once per band, each shot batch's data (`keep`), and then, per
evaluation, only the model (`evaluate`):

- resident data: each batch's arrays (wavelets, geometry, weights, observed data: NumPy) are the result of a task
  `keep` submits once, placed round-robin on the workers. An evaluation runs the batches through one Dask actor
  (`_Caller`) on each worker that holds some: one call a worker, which runs them on the data it holds and answers
  with their results (from the client straight to a LocalCluster's workers; through a remote scheduler, as a
  message it passes on). So an evaluation moves the model out and the (misfit, gradient) of each batch back,
  nothing else, and pays one round trip a worker instead of a task's way through the scheduler's queue (on one H200
  a 32-shot evaluation 3-5 ms shorter, docs/benchmarks.md). The first evaluation of a batch on a worker also
  uploads its observed data and weights to the worker's device, where they stay until the next keep or close
  (solve.residency.resident and evict, the threads engine's code). The scheduler keeps the batch tasks' inputs, so
  a batch whose worker is lost is rebuilt on another worker (whose first run of it uploads it there);
- faults: a worker lost mid-evaluation (killed, out of memory) fails its actor's call; its batches then run as
  ordinary Dask tasks, which the scheduler places on the workers left (or on the worker its nanny restarts), with
  their data rebuilt there; the evaluation completes with the fault-free result, as every batch is a pure function
  of the model and its data. The next evaluation routes the batches afresh to wherever their data now are;
- reduction: `evaluate` returns the batches' results in batch order and the caller sums them on the client in
  float64 in that order (as the single-process loop does), so the result does not depend on the number of workers
  or on which worker ran what.

solve.pools.open_pool gives a ShotPool or, for `engine: threads`, a solve.devices.DevicePool (one thread and one
stream per device in this process, no Dask) with the same face; batch_gradient (fwi) and batch_forward
(`adseismic forward` with a parallel section) are the tasks of both, gather_forward and reduce_in_order put their
results together in shot order, and count_batches follows them over the workers (one bar and one log line per
evaluation).

Each worker initialises Warp itself (solve.common.init_warp, through the gradient's setup); CPU kernels compile once
per process into the shared kernel cache. Dask is imported only here and only when a pool is used: the package runs
without it when a config has no `parallel:` section.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import sys
import threading
import time
import uuid

import numpy as np

log = logging.getLogger(__name__)

CONNECT_TIMEOUT = 5.0  # s to reach a scheduler address before the run is refused
WORKER_WAIT = 60.0  # s for the workers asked for (parallel.workers) to join a remote scheduler
TASK_MODEL_BYTES = 10e6  # largest model an evaluation's tasks carry (distributed.admin.large-graph-warning-threshold)


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


def _resident(data):
    """A batch's data, kept on the worker that ran this task (rebuilt from the scheduler's copy of the input if that
    worker is lost)."""
    return data


# one batch at a time in a worker process: a caller's batches and a task re-run there after a fault share its kept graphs
_RUN = threading.Lock()


def _run(fn, model, data, params):
    """fn(model, data, params), one at a time in this process."""
    with _RUN:
        return fn(model, data, params)


class _Caller:
    """A ShotPool's actor on one worker: runs an evaluation's batches on the data this worker holds (the results of
    their `_resident` tasks, by key), in one call that the client sends to the worker directly."""

    def evaluate(self, fn, model, params, keys):
        """[fn's result, or None where the worker does not hold that batch's data] in the order of keys."""
        from distributed import get_worker

        data = get_worker().data
        return [_run(fn, model, data[k], params) if k in data else None for k in keys]


def _evict(token):
    """solve.residency.evict on a worker."""
    from adseismic.solve.residency import evict

    evict(token)


def _my_device(devices: dict, default: str) -> str:
    try:
        from distributed import get_worker

        return devices.get(get_worker().name, default)
    except (ImportError, ValueError):
        return default


def _device_of(params) -> str:
    """The batch's device: this Dask worker's (params["devices"], by worker name), else params["device"]."""
    return _my_device(params["devices"], params["device"]) if "devices" in params else params["device"]


def batch_gradient(model, data, params) -> dict:
    """The acoustic misfit and velocity gradient of one shot batch (a task of a ShotPool or a DevicePool). data:
    {amplitudes, sources, receivers, weights, observed (both (n_shots, n_receivers, nt), NumPy arrays), first (the
    batch's first shot), key (unique per pool, band and batch: the key of its resident device arrays)}; params: {dx,
    dt, misfit (a name of solve.misfits.MISFITS), illumination, kw (solve.acoustic.gradient's keywords), device,
    [devices]}. The weighted misfit is that of inversion.fwi's single-process loop, operation for operation: "l2"
    formed on the device from the observed data and weights kept there (solve.residency.resident: uploaded once per
    batch, device and process, whichever pool runs it), any other on the host."""
    import warp as wp

    from adseismic.solve.acoustic import gradient
    from adseismic.solve.residency import resident
    from adseismic.solve.misfits import misfit as named_misfit

    spent = [0.0]
    kw = dict(params["kw"], device=_device_of(params))
    data = resident(data, kw["device"], params["misfit"])
    w, o = data["weights"], data["observed"]
    if params["misfit"] == "l2":  # resident: the weighted residual formed on the device
        misfit = {"observed": o, "weights": w, "misfit": "l2"}
    else:

        def weighted(syn):
            t = time.perf_counter()
            j, adj = named_misfit(params["misfit"], w * syn, w * o, params["dt"])
            adj = w * adj
            spent[0] += time.perf_counter() - t
            return j, adj

        misfit = {"misfit": weighted}
    t = time.perf_counter()
    r = gradient(model, params["dx"], params["dt"], data["amplitudes"], data["sources"], data["receivers"],
                 illumination=params["illumination"], **misfit, **kw)  # fmt: skip
    syn0 = None
    if data["first"] == 0:
        syn0 = r.synthetic[0].numpy() if isinstance(r.synthetic, wp.array) else r.synthetic[0]
    return {"loss": r.loss, "velocity": r.velocity, "illumination": r.illumination, "first": data["first"],
            "synthetic0": None if syn0 is None else np.asarray(syn0), "seconds": time.perf_counter() - t,
            "misfit_seconds": spent[0], "pid": os.getpid()}  # fmt: skip


def batch_born(model, data, params) -> dict:
    """The Born (linearised) data of one shot batch (imaging's Born operator over workers): {first, data (n_shots,
    n_receivers, nt)}, solve.acoustic.born of model {background, dm} (m/s). data: {amplitudes, sources, receivers,
    first}; params: {dx, dt, kw (the solver's keywords), device, [devices]}."""
    from adseismic.solve.acoustic import born

    kw = dict(params["kw"], device=_device_of(params))
    d = born(model["background"], model["dm"], params["dx"], params["dt"], data["amplitudes"], data["sources"], data["receivers"], **kw)
    return {"first": data["first"], "data": np.asarray(d, float)}


def batch_born_adjoint(model, data, params) -> dict:
    """The Born operator's adjoint applied to one shot batch's data d: {first, image (B^T d, the model's shape),
    illumination or None, data (d where it was simulated, else None)}, the gradient of <F(v), d> at the background `model` (m/s) with d held fixed.
    data: {amplitudes, sources, receivers, first} and either residual (d itself) or observed (d = observed - F(v0),
    the reflection data, simulated in the same run); params: {dx, dt, kw, illumination, device, [devices]}."""
    from adseismic.solve.acoustic import gradient

    kept = {}

    def misfit(syn):
        kept["d"] = np.asarray(data["residual"], float) if "residual" in data else np.asarray(data["observed"], float) - syn
        return float(np.vdot(syn, kept["d"])), kept["d"]

    kw = dict(params["kw"], device=_device_of(params))
    g = gradient(model, params["dx"], params["dt"], data["amplitudes"], data["sources"], data["receivers"], misfit=misfit,
                 illumination=params["illumination"], **kw)  # fmt: skip
    return {"first": data["first"], "image": np.asarray(g.velocity, float), "illumination": g.illumination,
            "data": kept["d"] if "observed" in data else None}  # (a residual given is not sent back)


def batch_forward(model, data, params) -> dict:
    """The forward run of one shot batch (a task of either pool): {first, result (scene.run_forward's: a
    ForwardResult, an ElasticResult for physics elastic, an AcousticVDResult for acoustic_vd)}. model: {vp[, vs], [rho]}
    (m/s, kg/m^3; acoustic_vd: no vs); data: {amplitudes,
    sources, receivers, [source_components], first}; params: {dx, dt, kw (the solver's keywords), snapshot_every,
    source_type, device, [devices]}."""
    kw = dict(params["kw"], device=_device_of(params), progress=False)
    if "rho" in model and "vs" not in model:  # acoustic_vd: the explosive source's moment M0 x the wavelet
        from adseismic.solve.acoustic_vd import forward_acoustic_vd

        amp = data["amplitudes"] * data["source_components"][:, :, :1]
        r = forward_acoustic_vd(model["vp"], model["rho"], params["dx"], params["dt"], amp, data["sources"], data["receivers"], **kw)
    elif "vs" in model:
        from adseismic.solve.elastic import forward_elastic

        r = forward_elastic(model["vp"], model["vs"], model["rho"], params["dx"], params["dt"], data["amplitudes"], data["sources"],
                            data["receivers"], source_type=params["source_type"], source_components=data["source_components"],
                            **kw)  # fmt: skip
    else:
        from adseismic.solve.acoustic import forward

        r = forward(model["vp"], params["dx"], params["dt"], data["amplitudes"], data["sources"], data["receivers"],
                    snapshot_every=params["snapshot_every"], **kw)  # fmt: skip
    return {"first": data["first"], "result": r}


def count_batches(completions, total: int, desc: str, n_workers: int, progress: bool) -> None:
    """Follow one evaluation: a bar over its `total` shot batches, advanced as each finishes on any worker
    (completions: an iterator yielding once per finished batch; a terminal only, with progress), then one log line
    (the run's log file, e.g. fwi.log) with the batches, the workers and the wall time."""
    from adseismic.runs import progress_bar

    t = time.perf_counter()
    bar = progress_bar(total=total, desc=desc, unit="batch", enabled=progress and sys.stderr.isatty())
    with contextlib.closing(bar):
        for _ in completions:
            bar.update(1)
    log.info("%s: %d shot batch(es) on %d worker(s) in %.2f s", desc, total, n_workers, time.perf_counter() - t)


class ShotPool:
    """A Dask client and its workers for one run; use as a context manager (closes the cluster it started)."""

    def __init__(self, par, sim_device: str, n_shots: int, progress: bool = False):
        distributed = _import_dask()
        import dask
        self.par, self.cluster, self.token, self.progress = par, None, uuid.uuid4().hex[:12], progress
        # distributed's nanny writes its workers' settings (OMP/MKL/OPENBLAS_NUM_THREADS=1, MALLOC_TRIM_THRESHOLD_) into
        # this process's os.environ and leaves them there: every process started later (a forward, a resumed fwi in a
        # subprocess) would then run one BLAS thread where it ran several, and its sums would differ in the last bit.
        # close() puts the environment back.
        self.environ = dict(os.environ)
        self.generation, self.evaluations, self.futures = 0, 0, []
        # worker address -> (its _Caller's future, the actor); worker -> its batches; the running calls; how many batches
        # the last evaluation ran as tasks
        self.callers, self.route, self.calls, self.reruns = {}, None, {}, 0
        if par.scheduler == "local":
            devices = local_devices(par, sim_device, n_shots)
            # without the workers' sampling profiler: every 10 ms it takes the GIL from the task's thread, whose Python
            # launches the kernels and graphs
            with dask.config.set({"distributed.worker.profile.enabled": False}):
                self.cluster = distributed.LocalCluster(n_workers=len(devices), threads_per_worker=1, processes=True,
                                                        dashboard_address=":0", silence_logs=logging.WARNING)  # fmt: skip
            # a caller's calls and the results go between this process and the workers directly (all on this host)
            self.client = distributed.Client(self.cluster, set_as_default=False, direct_to_workers=True)
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
        self.futures, self.callers, self.route, self.calls = [], {}, None, {}
        if self.cluster is None:  # a remote cluster's workers outlive the run: free their device arrays of it
            with contextlib.suppress(OSError, TimeoutError):
                self.client.run(_evict, self.token, on_error="ignore")
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        os.environ.clear()
        os.environ.update(self.environ)

    def workers(self) -> list[str]:
        """The addresses of the workers now connected."""
        return sorted(self.client.scheduler_info(n_workers=-1)["workers"])

    def keep(self, batches: list[dict]) -> None:
        """Place each batch's data (a dict of NumPy arrays) on a worker, round-robin, until the next keep (which
        releases them, and the workers' resident device arrays of them): the data of every later evaluate. The
        first evaluation of a batch on a worker uploads its observed data and weights to the worker's device
        (solve.residency.resident), where they stay."""
        self.futures = []  # releases the previous band's data
        self.client.run(_evict, self.token)
        self.generation += 1
        addrs = self.workers()
        keys = [f"{self.token}-{self.generation}-{k}" for k in range(len(batches))]
        self.futures = [self.client.submit(_resident, dict(d, key=key), key=f"adseismic-data-{key}",
                                           workers=[addrs[k % len(addrs)]], allow_other_workers=True)
                        for k, (d, key) in enumerate(zip(batches, keys))]  # fmt: skip
        with self.client.as_current():
            _import_dask().wait(self.futures)
        self.route = self._route()

    def _route(self) -> dict:
        """{worker address: [batch index]}: each kept batch on the worker that holds its data, given a caller there
        (made for a worker that has none); a batch whose data no worker holds now (being rebuilt) is left out."""
        holders = self.client.who_has(self.futures)
        route = {}
        for k, f in enumerate(self.futures):
            if holders.get(f.key):
                route.setdefault(holders[f.key][0], []).append(k)
        self.callers = {a: c for a, c in self.callers.items() if c[0].status == "finished"}  # those of lost workers gone
        with self.client.as_current():  # an actor binds to the current client
            for addr in route:
                if addr not in self.callers:
                    fut = self.client.submit(_Caller, actor=True, workers=[addr], allow_other_workers=False,
                                             key=f"adseismic-caller-{self.token}-{uuid.uuid4().hex[:8]}")  # fmt: skip
                    self.callers[addr] = (fut, fut.result())
        return route

    def busy(self) -> set[str]:
        """The workers running batches of the evaluation in progress (a caller's call not answered, a task
        processing)."""
        return {a for a, (_, call) in self.calls.items() if not call.done()} | {a for a, ts in self.client.processing().items() if ts}

    def evaluate(self, model, params: dict, fn=batch_gradient, desc: str | None = None) -> list[dict]:
        """fn(model, batch data, params) for every kept batch on the workers; the results in batch order. model: an
        array or a dict of arrays; desc: the progress's name (default "evaluation K"). Each worker's batches go in one
        call to its caller; the batches of a lost worker, or whose data moved, run as Dask tasks."""
        self.evaluations += 1
        tag = f"{self.token}-{self.generation}-{self.evaluations}"
        params = dict(params, devices=self.devices, device=params.get("device", self.default_device))
        if self.route is None:
            self.route = self._route()
        calls, rest = {}, []
        with self.client.as_current():
            for addr, ks in self.route.items():
                try:
                    calls[addr] = (ks, self.callers[addr][1].evaluate(fn, model, params, [self.futures[k].key for k in ks]))
                except RuntimeError:  # "Worker holding Actor was lost"
                    rest += ks
        self.calls = calls  # whole, for busy() from another thread
        routed = {k for ks in self.route.values() for k in ks}
        rest += [k for k in range(len(self.futures)) if k not in routed]
        results = {}

        def completions():  # each worker's results as its call returns, then those of the batches run as tasks
            for ks, call in calls.values():
                try:
                    out = call.result()
                except OSError:  # the worker was lost during the call (fn's own OSError: raised again by its task)
                    out = [None] * len(ks)
                for k, r in zip(ks, out):
                    if r is None:
                        rest.append(k)
                    else:
                        results[k] = r
                        yield
            self.reruns = len(rest)
            if rest:
                log.info("%d shot batch(es) run as Dask tasks: their worker was lost or their data moved", len(rest))
                self.route = None  # routed afresh next time, to where the data are then
                yield from self._tasks(sorted(rest), model, params, tag, fn, results)

        count_batches(completions(), len(self.futures), desc or f"evaluation {self.evaluations}", len(self.devices), self.progress)
        return [results[k] for k in range(len(self.futures))]

    def _tasks(self, ks: list, model, params, tag, fn, results):
        """Batches ks as Dask tasks (after a fault): results[k] set as each ends; yields once per batch."""
        distributed = _import_dask()
        # No task fetches the model from a peer, so a worker lost now takes no input of the others with it (fetching
        # from a dead peer waits out distributed.comm.timeouts.connect, 30 s): with at most one batch per worker each
        # task carries its own copy, unless the model is larger than Dask's large-graph threshold; else it is first
        # sent to every worker (broadcast)
        arrays = model.values() if isinstance(model, dict) else [model]
        if len(ks) > len(self.devices) or sum(np.asarray(a).nbytes for a in arrays) > TASK_MODEL_BYTES:
            [model] = self.client.scatter([model], broadcast=True, hash=False)
        futures = {self.client.submit(_run, fn, model, self.futures[k], params, key=f"adseismic-eval-{tag}-{k}"): k for k in ks}
        for fut, result in distributed.as_completed(list(futures), with_results=True, loop=self.client.loop):
            results[futures[fut]] = result
            yield


def gather_forward(results: list[dict]):
    """The batches' batch_forward results (batch order, consecutive shots) as the result of all shots at once, in shot
    order: every array with a shot axis concatenated (receiver data and vx, vz, pressure on axis 0, snapshots on
    axis 1); dt and snapshot_times those of the first batch."""
    rs = [r["result"] for r in results]
    joined = {}
    for f in dataclasses.fields(rs[0]):
        if f.name in ("dt", "snapshot_times") or getattr(rs[0], f.name) is None:
            continue
        joined[f.name] = np.concatenate([getattr(r, f.name) for r in rs], axis=1 if f.name == "snapshots" else 0)
    return dataclasses.replace(rs[0], **joined)


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

