"""Several devices in one process (issue 25 item 4, `parallel: {engine: threads, devices: ...}`): the shot batches of
one evaluation spread over the devices of this host, without Dask.

A `DevicePool` has the face of solve.distributed.ShotPool (keep / evaluate / close / workers; solve.pools.open_pool
picks one by engine), so a workflow uses either without branching:

- one Python thread and one Warp stream per device (a single-thread executor; its tasks run under wp.ScopedStream
  on a GPU, wp.ScopedDevice on the CPU, and every allocation and launch of the solvers names its device). Kernel
  launches on different GPUs run concurrently; CPU kernels too (Warp calls them with the GIL released), so
  `devices: [cpu, cpu]` uses two cores;
- resident data: `keep` places batch k on device k % n (round-robin, as the Dask pool does) and uploads its
  observed data and weights there as float64 Warp arrays, kept until the next keep; an evaluation then moves only
  the model in and each batch's (misfit, gradient) out. With the "l2" misfit the weighted residual is formed on the
  device (solve.acoustic.gradient's resident path, that of the single-process loop);
- reduction: `evaluate` returns the batches' results in batch order; the caller sums them on the host in float64 in
  that order (distributed.reduce_in_order), so the result does not depend on the number of devices;
- the kept CUDA-graph time loops are per device (accel.graphs), so two devices do not evict each other's.

Warp 1.19 is not thread-safe in three ways that matter here (its issues 224, 1491, 1705), and the pool works around
each: (1) the default device is process-wide (wp.ScopedDevice sets it for every thread): the solvers name the device
of every allocation and launch, and the pool restores the caller's default after each call; (2) the active wp.Tape
is process-wide (runtime.tape): the gradient's tape of its padded model (solve.acoustic) would record the other
threads' launches, or refuse to open while another thread's is open, so the pool makes it per thread
(`_tape_per_thread`); (3) building kernels (this package's lru_cache'd kernel factories, Warp's codegen) from two
threads at once fails: the first evaluation runs each device's first batch after the previous device's, so every
kernel is built once, one thread at a time; later evaluations (the same kernels) run all batches at once.
"""

from __future__ import annotations

import logging
import threading
from concurrent.futures import ThreadPoolExecutor, as_completed, wait

import numpy as np
import warp as wp

from adseismic.solve.distributed import batch_gradient, count_batches, local_devices

log = logging.getLogger(__name__)


def thread_devices(par, sim_device: str, n_shots: int) -> list[str]:
    """The device of each thread, resolved (cuda -> cuda:N): parallel.devices, or all (every GPU, else one CPU thread
    per core, at most one per shot). ValueError naming the key for a device that does not exist here, a GPU listed
    twice (Warp keeps one current stream and one capture state per GPU for the whole process: two threads on one GPU
    would launch into each other's stream and graph captures) or more devices than shots."""
    from adseismic.solve.common import resolve_device

    devices = [resolve_device(d) for d in local_devices(par, sim_device, n_shots)]
    for i, d in enumerate(devices):
        if d != "cpu" and d in devices[:i]:
            raise ValueError(f"parallel.devices[{i}]: {d} is listed twice; engine threads runs one thread per GPU (Warp's "
                             f"current stream and graph capture are per GPU, not per thread): list each GPU once, or use "
                             f"engine: dask for several workers on one GPU")
    return devices


def check_devices(par, sim_device: str, n_shots: int) -> None:
    """Refuse (ValueError naming the key and the fix) a threads section that cannot run, before any work."""
    thread_devices(par, sim_device, n_shots)


class _ThreadTape(threading.local):
    tape = None


def _tape_per_thread() -> None:
    """Make Warp's active tape (runtime.tape, process-wide in Warp 1.19) one per thread: a property of the runtime's
    class over a threading.local, so a tape records the launches of the thread that opened it only. Once per
    process; nothing changes for a single thread."""
    from warp._src import context

    cls = type(context.runtime)
    if not isinstance(cls.__dict__.get("tape"), property):
        local = _ThreadTape()
        cls.tape = property(lambda self: local.tape, lambda self, tape: setattr(local, "tape", tape))


class DevicePool:
    """Threads of this process, one per device, for one run; use as a context manager. progress: a bar per
    evaluation counting the finished shot batches (a terminal), and one log line per evaluation."""

    def __init__(self, par, sim_device: str, n_shots: int, progress: bool = False):
        from adseismic.solve.common import init_warp

        init_warp()
        _tape_per_thread()
        self.devices = thread_devices(par, sim_device, n_shots)
        self.progress, self.evaluations, self.placed = progress, 0, []
        self.streams = [wp.Stream(d) if wp.get_device(d).is_cuda else None for d in self.devices]
        self.threads = [ThreadPoolExecutor(1, thread_name_prefix=f"adseismic-{i}-{d}") for i, d in enumerate(self.devices)]
        log.info("parallel: %d thread(s) in this process on %s", len(self.devices), ", ".join(self.devices))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        for t in self.threads:
            t.shutdown(wait=True)
        self.placed, self.streams = [], []

    def workers(self) -> list[str]:
        """One name per thread: "<index>: <device>"."""
        return [f"{i}: {d}" for i, d in enumerate(self.devices)]

    def _scope(self, i):
        s = self.streams[i]
        return wp.ScopedStream(s) if s is not None else wp.ScopedDevice(self.devices[i])

    def _run(self, jobs, desc=None):
        """jobs: (thread index, fn, args) in order; each fn(*args) runs on its thread under its device's scope. The
        results in the order of jobs (every job finished; the first error raised)."""
        default = wp.get_device()

        def call(i, fn, args, after):
            if after is not None:
                after.result()
            with self._scope(i):
                return fn(*args)

        futures, started, prev = [], set(), None
        for i, fn, args in jobs:
            serial = desc is not None and self.evaluations == 1 and i not in started  # the first evaluation's first batches
            futures.append(self.threads[i].submit(call, i, fn, args, prev if serial else None))
            if serial:
                started.add(i)
                prev = futures[-1]
        try:
            if desc is not None:
                count_batches(as_completed(futures), len(futures), desc, len(self.devices), self.progress)
            wait(futures)
            return [f.result() for f in futures]
        finally:
            wp.set_device(default)

    def keep(self, batches: list[dict]) -> None:
        """Place batch k's data (a dict of arrays) on device k % n until the next keep, its observed data and weights
        (when present) uploaded as float64 Warp arrays: the data of every later evaluate."""
        self.placed = []
        n = len(self.devices)
        self.placed = self._run([(k % n, _upload, (d, self.devices[k % n])) for k, d in enumerate(batches)])

    def evaluate(self, model, params: dict, fn=batch_gradient, desc: str | None = None) -> list[dict]:
        """fn(model, batch data, params with its device) for every kept batch on its device's thread; the results in
        batch order. desc: the progress's name (default "evaluation K")."""
        self.evaluations += 1
        n = len(self.devices)
        jobs = [(k % n, fn, (model, d, dict(params, device=self.devices[k % n]))) for k, d in enumerate(self.placed)]
        return self._run(jobs, desc=desc or f"evaluation {self.evaluations}")


def _upload(data: dict, device: str) -> dict:
    """The batch's data with observed and weights (n_shots, n_receivers, nt) as float64 Warp arrays on device."""
    out = dict(data)
    for k in ("observed", "weights"):
        if data.get(k) is not None:
            out[k] = wp.array(np.ascontiguousarray(data[k], dtype=float), dtype=wp.float64, device=device)
    return out
