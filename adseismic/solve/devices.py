"""Several devices in one process (issue 25 item 4, `parallel: {engine: threads, devices: ...}`): the shot batches of
one evaluation spread over the devices of this host, without Dask.

A `DevicePool` has the face of solve.distributed.ShotPool (keep / evaluate / close / workers; solve.pools.open_pool
picks one by engine), so a workflow uses either without branching:

- one Python thread per device (a single-thread executor; its tasks run under wp.ScopedDevice, and every allocation
  and launch of the solvers names its device), on that device's own stream: a GPU is used by one thread only
  (thread_devices), so its stream is that thread's. While a second stream of a GPU that had run a gradient existed,
  every gradient on that GPU ran ~8% slower, on its own stream too (docs/benchmarks.md, 2026-11-29). Kernel
  launches on different GPUs run concurrently; CPU kernels too (Warp calls them with the GIL released), so
  `devices: [cpu, cpu]` uses two cores;
- resident data: `keep` places batch k on device k % n (round-robin, as the Dask pool does); the first evaluation
  uploads its observed data and weights there as float64 Warp arrays (solve.residency's `resident`, the same code in a Dask worker
  process), kept until the next keep or close (`evict`); an evaluation then moves only the model in and each
  batch's (misfit, gradient) out. With the "l2" misfit the weighted residual is formed on the device
  (solve.acoustic.gradient's resident path, that of the single-process loop); other misfits read the host arrays;
- faults: a batch that raises on a device (a CUDA error, out of memory) drops that device for the rest of the run,
  with a warning naming it and the error, and runs again, with the device's batches not yet started, on the
  remaining devices; the evaluation's result is the fault-free one (the same batches, reduced in batch order).
  When every device has failed, a RuntimeError says so. Bad input (ValueError) and a blow-up (PropagationError)
  are no device's fault: raised as in one process;
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
import uuid
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

import warp as wp

from adseismic.solve.common import PropagationError, init_warp, resolve_device
from adseismic.solve.distributed import batch_gradient, count_batches, local_devices
from adseismic.solve.residency import evict

log = logging.getLogger(__name__)


def thread_devices(par, sim_device: str, n_shots: int) -> list[str]:
    """The device of each thread, resolved (cuda -> cuda:N): parallel.devices, or all (every GPU, else one CPU thread
    per core, at most one per shot). ValueError naming the key for a device that does not exist here, a GPU listed
    twice (Warp keeps one current stream and one capture state per GPU for the whole process: two threads on one GPU
    would launch into each other's stream and graph captures) or more devices than shots."""
    from adseismic.solve.common import resolve_device  # looked up at call time (tests stand in for it)

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
        init_warp()
        _tape_per_thread()
        self.devices = thread_devices(par, sim_device, n_shots)
        self.token, self.generation, self.progress, self.evaluations = uuid.uuid4().hex[:12], 0, progress, 0
        self.batches, self.place, self.alive = [], [], list(range(len(self.devices)))
        self.threads = [ThreadPoolExecutor(1, thread_name_prefix=f"adseismic-{i}-{d}") for i, d in enumerate(self.devices)]
        log.info("parallel: %d thread(s) in this process on %s", len(self.devices), ", ".join(self.devices))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        for t in self.threads:
            t.shutdown(wait=True)
        evict(self.token)
        self.batches = []

    def workers(self) -> list[str]:
        """One name per thread still in use (a failed device's is dropped): "<index>: <device>"."""
        return [f"{i}: {self.devices[i]}" for i in self.alive]

    def keep(self, batches: list[dict]) -> None:
        """Hold the batches (dicts of NumPy arrays) until the next keep, batch k on device k % n: the data of every later
        evaluate. The previous batches' resident device arrays are freed; the new ones' are uploaded by the first
        evaluation that needs them (`resident`) and stay on their device."""
        evict(self.token)
        self.generation += 1
        self.batches = [dict(d, key=f"{self.token}-{self.generation}-{k}") for k, d in enumerate(batches)]
        self.place = [self.alive[k % len(self.alive)] for k in range(len(batches))]

    def evaluate(self, model, params: dict, fn=batch_gradient, desc: str | None = None) -> list[dict]:
        """fn(model, batch data, params with its device) for every kept batch on its device's thread; the results in
        batch order. A device whose batch raises is dropped for the rest of the run (a warning naming it and the
        error) and its batches re-run on the others; RuntimeError when every device has failed. desc: the progress's
        name (default "evaluation K")."""
        self.evaluations += 1
        results, default = [None] * len(self.batches), wp.get_device()
        try:
            count_batches(self._completions(model, params, fn, results), len(results), desc or f"evaluation {self.evaluations}",
                          len(self.alive), self.progress)  # fmt: skip
        finally:
            wp.set_device(default)  # the caller's default device, whatever the threads' scopes did to it
        return results

    def _call(self, i, fn, model, data, params, after):
        if after is not None:
            wait([after])
        with wp.ScopedDevice(self.devices[i]):
            return fn(model, data, dict(params, device=self.devices[i]))

    def _completions(self, model, params, fn, results):
        """Run every batch on the thread of its device (self.place), filling results; yield once per finished batch.
        The first evaluation runs each device's first batch after the previous device's (kernels built one thread
        at a time). A batch that raises drops its device (`_drop`) and runs again where its batches now go, with
        the dropped device's batches not yet started; a ValueError (bad input) or PropagationError (a blow-up), the
        same on any device, is raised as in one process, once the running batches have finished."""
        running = {}  # future -> (batch, device index)

        def submit(k, after=None):
            i = self.place[k]
            f = self.threads[i].submit(self._call, i, fn, model, self.batches[k], params, after)
            running[f] = (k, i)
            return f

        prev, started = None, set()
        for k in range(len(self.batches)):
            if self.evaluations == 1 and self.place[k] not in started:
                started.add(self.place[k])
                prev = submit(k, prev)
            else:
                submit(k)
        try:
            while running:
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for f in done:
                    k, i = running.pop(f)
                    try:
                        results[k] = f.result()
                    except (ValueError, PropagationError):  # the input's or the physics' error, alike on every device
                        raise
                    except Exception as e:  # a device fault (a CUDA error, out of memory): the batch runs elsewhere
                        if i in self.alive:
                            self._drop(i, e)
                            queued = [g for g, (_, j) in running.items() if j == i and g.cancel()]
                            for g in queued:
                                submit(running.pop(g)[0])
                        submit(k)
                    else:
                        yield
        finally:  # on an error: no batch left running on the caller's arrays
            for f in running:
                f.cancel()
            wait(running)

    def _drop(self, i, error):
        """Stop using device i for the rest of the run: its batches go round-robin to the remaining devices (a
        warning names it and the error); RuntimeError from the error when no device remains."""
        self.alive.remove(i)
        what = f"{i}: {self.devices[i]} ({type(error).__name__}: {error})"
        if not self.alive:
            raise RuntimeError(f"parallel: every device failed; the last, {what}; run on fewer or other devices "
                               f"(parallel.devices), or without a parallel section") from error
        moved = [k for k, j in enumerate(self.place) if j == i]
        for n, k in enumerate(moved):
            self.place[k] = self.alive[n % len(self.alive)]
        log.warning("parallel: device %s failed; dropped for the rest of the run, its %d shot batch(es) re-run on %s",
                    what, len(moved), ", ".join(self.devices[j] for j in self.alive))  # fmt: skip
