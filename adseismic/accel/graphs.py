"""CUDA-graph time loops, shared by the acoustic and elastic forward runs (and the kept store that the
acoustic gradient's Sweep also uses).

Without a tape a time step launches the same few kernels every step, so on a GPU K steps are captured
once as a CUDA graph and replayed to cover the nt levels; the source and receiver kernels read the
time index from a device clock that each replay advances. A blow-up guard's statistics (max |u| and
the count of non-finite values, every `every` levels) are copied to pinned host memory after each replay and
checked while the next replay runs (a blow-up is then reported one replay late; the GPU never waits on the host). The last captured
loop of each kind (key[0]: acoustic or elastic forward, gradient) is kept, with the arrays its launches
read, for the next call with the same key (grid, time step, steps, shots, sources, receivers, device), which
copies its inputs into those arrays and replays: no capture, no allocation. One per kind and device, so that an
inversion's forward and gradient calls do not evict each other, nor do the devices of one process
(solve.devices: a thread per device).
"""

from __future__ import annotations

import contextlib
import math
import weakref
from dataclasses import dataclass

import warp as wp

from adseismic.accel.reductions import tick

GRAPH_STEPS = 50  # time steps per captured graph (rounded to a multiple of the guard's interval)


def graph_plan(cuda: bool, nt: int, every: int, period: int = 2) -> tuple[int, int]:
    """(K, graphs): K steps per graph (a multiple of `period`, after which the steps' buffers are back in
    their roles, and of `every`), replayed `graphs` times to cover the nt levels (the last replay runs up to
    K - 1 levels past them, into padding, unless capture was given nt); graphs = 0 where none are used
    (CPU, or fewer than two replays)."""
    K = math.lcm(period, every)
    K *= max(1, GRAPH_STEPS // K)
    graphs = -(-nt // K)
    return K, graphs if cuda and graphs >= 2 else 0


@dataclass
class Loop:
    """A captured time loop: the graph of K steps, replayed `graphs` times (the last time `tail`, the
    graph of the remaining steps, where there is one), the guard's statistics (K // every, 2), the device
    clock, and `kept`: the arrays its launches read (physics-specific); `host` (2, K // every, 2), pinned, and two
    events: where replay reads the statistics of alternate replays."""

    key: tuple
    graph: object
    K: int
    graphs: int
    every: int
    stats: wp.array
    clock: wp.array
    kept: object
    tail: object = None
    host: wp.array = None
    events: tuple = ()


def capture(key, device, dtype, K: int, graphs: int, every: int, step, kernels, kept, nt: int | None = None) -> Loop:
    """Capture step(k, clock, stats) for k < K, stats being the guard's row (2,) at levels k % every == 0
    and None otherwise, then the clock's advance; kernels: every kernel the steps launch (loaded first,
    as a capture cannot compile). With nt, the last replay's steps past nt are left out (a second graph of
    the steps before them)."""
    stats = wp.zeros((K // every, 2), dtype=dtype, device=device)
    clock = wp.zeros(1, dtype=wp.int32, device=device)
    for k in (*kernels, tick):
        wp.load_module(k.module, device=device)

    def graph(steps):
        with wp.ScopedCapture(device=device, force_module_load=False) as cap:
            for k in range(steps):
                step(k, clock, stats[k // every] if k % every == 0 else None)
            wp.launch(tick, dim=1, inputs=[clock, steps], device=device)
        return cap.graph

    last = K if nt is None else nt - (graphs - 1) * K
    host = wp.empty((2, *stats.shape), dtype=dtype, device="cpu", pinned=wp.get_device(device).is_cuda)
    events = tuple(wp.Event(device) for _ in range(2)) if wp.get_device(device).is_cuda else ()
    return Loop(key, graph(K), K, graphs, every, stats, clock, kept, graph(last) if last < K else None, host, events)


def replay(loop: Loop, nt: int, guard, progress=None):
    """Run the levels up to K * graphs >= nt; guard.check(n, max, nonfinite) for each checked level n < nt,
    replay g's levels checked after replay g + 1 is queued (the levels past nt - 1 are padding)."""
    K, every = loop.K, loop.every

    def check(g):
        wp.synchronize_event(loop.events[g % 2])
        for j, (amax, nonfinite) in enumerate(loop.host.numpy()[g % 2]):
            if g * K + j * every < nt:
                guard.check(g * K + j * every, float(amax), float(nonfinite))
        if progress is not None:
            progress.update(min(K, nt - g * K))

    for g in range(loop.graphs):
        wp.capture_launch(loop.tail if g == loop.graphs - 1 and loop.tail is not None else loop.graph)
        wp.copy(loop.host[g % 2], loop.stats)
        wp.record_event(loop.events[g % 2])
        if g > 0:
            check(g - 1)
    check(loop.graphs - 1)


_KEPT: dict = {}  # (kind, device) -> the last captured loop of that kind on that device (a full set of wavefields)


def _slot(key) -> tuple:
    """(kind, device) of a key: key[0] and the device in it (the setups' keys hold the device they were given, a
    wp.Device or its name, cpu or cuda[:N], which no other entry of a key spells)."""
    names = (str(k) for k in key[1:] if isinstance(k, (str, wp.Device)))
    return key[0], next((k for k in names if k.split(":")[0] in ("cpu", "cuda")), None)


def kept(key) -> Loop | None:
    """The kept loop captured under `key`, or None; a miss frees the kept loop of that kind on that device (the
    caller captures a new one, which needs the memory)."""
    loop = _KEPT.get(_slot(key))
    if loop is not None and loop.key == key:
        return loop
    _KEPT.pop(_slot(key), None)
    return None


def keep(loop):
    """Keep `loop` (anything with a `key`), replacing the kept one of its kind on its device."""
    _KEPT[_slot(loop.key)] = loop
    return loop


def release():
    """Free the device memory of the kept time loops."""
    _KEPT.clear()


class SideStream:
    """A second stream on a GPU for launches that may overlap the current stream's later ones (a record of a level
    that the following steps do not write): launches inside `with side():` wait for the current stream's earlier
    work, then run beside it; join() makes the current stream wait for them (before a graph's capture ends). On a
    CPU the launches run in order."""

    def __init__(self, device):
        self.stream = wp.Stream(device) if wp.get_device(device).is_cuda else None

    def __call__(self):
        return wp.ScopedStream(self.stream) if self.stream is not None else contextlib.nullcontext()

    def join(self):
        if self.stream is not None:
            wp.wait_stream(self.stream)


class Segments:
    """The two directions of a checkpointed sweep (forward and adjoint segment functions, whose launches read
    the time index from `clock`): on a GPU each captured once as a CUDA graph (after loading `kernels`) and
    replayed, on a CPU called; run(which, n0) runs one with clock[0] = n0. fns are a sweep's bound methods,
    held weakly (no reference cycle keeps a sweep's device memory after graphs.release())."""

    def __init__(self, device, clock, kernels, fns):
        self.clock, self.fns, self.graphs = clock, [weakref.WeakMethod(f) for f in fns], None
        if wp.get_device(device).is_cuda:
            for k in kernels:
                wp.load_module(k.module, device=device)
            self.graphs = []
            for fn in fns:
                with wp.ScopedCapture(device=device, force_module_load=False) as cap:
                    fn()
                self.graphs.append(cap.graph)

    def run(self, which: int, n0: int):
        self.clock.fill_(n0)
        if self.graphs is None:
            self.fns[which]()()
        else:
            wp.capture_launch(self.graphs[which])
