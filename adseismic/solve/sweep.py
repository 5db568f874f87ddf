"""The checkpointed gradient, one for every physics: reverse-mode differentiation of the time stepping.

Differentiating the discrete scheme is the discrete adjoint-state method, so the gradient is exact for the
simulated data. Memory is bounded by checkpointing: a forward sweep keeps the state at the start of every
segment of `seg` levels; the backward sweep runs the segments last first, each forward again from its
checkpoint and then backward. Peak memory ~ n_segments x checkpoint + seg x level, minimised near seg ~ sqrt(nt);
the cost is one extra forward run (none when every step fits in one segment).

Two ways through a segment:
- taped_sweep: Warp's generated adjoints of every kernel, recorded on a wp.Tape with the arrays of every level
  (the reference), for any setup that run_levels drives (solve/loop.py); on a GPU its full segments (the last one
  too, when nt is a multiple of the segment length) are captured as CUDA graphs (the tape's launches each way) and
  kept with their arrays for the next call with the same key;
- Sweep: the physics' hand-written adjoint time loop (a physics' "levels" object: its arrays and its two segment
  functions, solve/<name>.py), on a GPU captured once per direction as CUDA graphs (accel.graphs.Segments) and
  kept with its arrays for the next call with the same key.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from adseismic.accel import graphs
from adseismic.solve.loop import run_levels


def choose_segment(nt: int, step: int, total, memory_budget: float | None, segment_length: int | None):
    """(segment length, total(it)) of a checkpointed sweep of nt steps whose segments are a multiple of `step`
    long and whose peak bytes are total(segment length): segment_length (clipped to 1..nt, rounded up) if
    given, else every step in one segment if that fits memory_budget, else the memory minimum (budget None)
    or the longest segment that fits; raises ValueError when none fits."""

    def length(seg):
        return -(-seg // step) * step

    if segment_length is not None:
        seg = length(min(max(int(segment_length), 1), nt))
    elif memory_budget is not None and total(length(nt)) <= memory_budget:
        seg = length(nt)
    else:
        candidates = range(step, length(nt) + 1, step)
        fits = [s for s in candidates if memory_budget is None or total(s) <= memory_budget]
        if not fits:
            need = min(total(s) for s in candidates)
            raise ValueError(f"memory_budget = {memory_budget / 2**20:.1f} MiB is below the minimum {need / 2**20:.1f} MiB this gradient needs; raise it or use fewer shots per call")
        seg = min(fits, key=total) if memory_budget is None else max(fits)
    return int(seg), int(total(seg))


def taped_sweep(su, seg: int, n_seg: int, loss, bar, on_level=None):
    """Warp's generated adjoints: a forward sweep up to the last segment, keeping the state at the start of every
    segment; then each segment, last first, re-run under a tape with its own arrays per level (su.new_level()) and
    back-propagated with the data residual and the adjoint state carried from the later segment (_TapedSegments:
    on a GPU each full segment's two directions are captured once as CUDA graphs and replayed, and kept with their
    arrays for the next call with the same key). The model and the sources are made once, on a tape of their own that
    is back-propagated at the end, so the gradients accumulate in the .grad of the arrays su's model and sources were
    made with.

    loss(synthetic) -> (J, adjoints): synthetic, a tuple of NumPy arrays (S, n_rec, nt) in su.new_data's order;
    adjoints, dJ/dsynthetic in the same order (None for a component without). on_level(state, n): called once at
    every level of the forward sweep (untaped; the forward sweep is then run launch by launch, nothing kept). Returns
    (synthetic, J)."""
    prop, nt = su.prop, su.nt
    setup_tape = wp.Tape()
    with setup_tape:
        # the samples padded with su.lookahead zeros: a full last segment steps from level nt - 1 too, as the others do,
        # reading sample nt (past su.amplitudes: uninitialised, at times a NaN, which made a moment's adjoints NaN)
        amp = su.amplitudes
        shape = (*amp.shape[:2], amp.shape[2] + su.lookahead)
        amplitudes = wp.zeros(shape, dtype=amp.dtype, device=amp.device, requires_grad=amp.requires_grad)
        wp.copy(amplitudes[:, :, : amp.shape[2]], amp)  # on the tape: its backward adds the samples' adjoints to amp.grad
        model, src = su.model(on_tape=True), su.sources_of(amplitudes, fixed=False)
    if on_level is None and _keeps(prop):
        ts = graphs.kept(_taped_key(su, seg, src)) or graphs.keep(_TapedSegments(su, seg, model, src))
    else:
        ts = _TapedSegments(su, seg, model, src)
    ts.load(su, model, src)
    data, last = ts.data, (n_seg - 1) * seg
    checkpoints = []  # without .grad: wp.copy would copy it over start's carried adjoint
    if on_level is None:
        for k in range(n_seg - 1):
            checkpoints.append([wp.clone(a, requires_grad=False) for a in ts.start.arrays()])
            ts.run(0, k * seg)
    else:

        def keep(st, n):
            if n % seg == 0:
                checkpoints.append([wp.clone(a, requires_grad=False) for a in st.arrays()])
            on_level(st, n)

        st = run_levels(ts.su, prop.new_state(), ts.model, data, range(last), ts.src, callback=keep)
        _copy(ts.start.arrays(), st.arrays())
    tape = None
    if on_level is None and nt - last == seg:  # a full last segment: its taped levels and their backward as captured
        ts.run(1, last)
    else:
        ts.clock.fill_(last)
        tape, _ = ts.taped(range(last, nt), on_level)
    bar.update(n_seg)
    synthetic = tuple(np.array(d.numpy()) for d in data)  # (a copy: the re-runs record into data again)
    J, adjoints = loss(synthetic)
    for d, a in zip(data, adjoints):
        if a is not None:
            d.grad.assign(wp.array(np.ascontiguousarray(a), dtype=prop.dtype, device=prop.device))
    for a in ts.start.arrays():
        a.grad.zero_()
    if tape is None:
        ts.run(2, last)
    else:
        tape.backward()
        del tape  # (not tape.reset(): that zeroes the gradients it holds, ours included)
    bar.update()
    for k in reversed(range(n_seg - 1)):
        _copy(ts.start.arrays(), checkpoints[k])
        checkpoints[k] = None
        ts.run(1, k * seg)
        ts.run(2, k * seg)
        bar.update()
    ts.unload(su, model, src)
    setup_tape.backward()
    return synthetic, J


class _TapedSegments:
    """taped_sweep's arrays and its three passes over a full segment (seg levels from `start`, the time indices read
    from `clock`; graphs.Segments, made at the first run, which loads the kernels launch by launch): forward_segment,
    untaped, leaves the end state in start; taped_segment runs the levels from start under a tape (recording the data),
    and backward_segment back-propagates that tape, seeded with the adjoint state that start's .grad carries from the
    later segment, leaving the earlier one there. The two halves of the adjoint are apart so that the last segment's
    data, recorded by taped_segment, give the misfit and its residual before backward_segment runs, all captured. A
    kept one serves a later Setup with the same key: load copies that call's inputs (model, sources, operators, CPML)
    into the arrays the graphs read, unload its gradients back."""

    def __init__(self, su, seg, model, src):
        self.key = _taped_key(su, seg, src)
        self.su, self.seg, self.model, self.src = su, seg, model, src
        self.data = su.new_data(su.nt, requires_grad=True)
        self.levels = [su.new_level() for _ in range(seg)]
        self.start = su.prop.new_state(requires_grad=True)
        self.carry = [wp.empty_like(a) for a in self.start.arrays()]
        self.clock = wp.zeros(1, dtype=wp.int32, device=su.prop.device)
        self.segments = self.tape = self.end = None

    def _inputs(self, su, model, src):
        return [*_warp_arrays(model), *_warp_arrays(src), *su.inputs(src)]

    def load(self, su, model, src):
        """Take su's inputs (a kept sweep's first use: its own; wp.copy copies their zero .grad too, clearing what the last
        call accumulated) and clear the state and data."""
        for a, b in zip(self._inputs(self.su, self.model, self.src), self._inputs(su, model, src)):
            if a.ptr != b.ptr:
                wp.copy(a, b)
        for a in (*self.start.arrays(), *self.data):
            a.zero_()
            a.grad.zero_()

    def unload(self, su, model, src):
        """Hand the gradients accumulated in the kept arrays to su's model and sources (as they were made: load)."""
        for a, b in zip(self._inputs(self.su, self.model, self.src), self._inputs(su, model, src)):
            if a.ptr != b.ptr and a.grad is not None and b.grad is not None:
                wp.copy(b.grad, a.grad)

    def run(self, which: int, n0: int):
        """One pass over the full segment from level n0 (which: 0 forward, 1 taped, 2 backward, after a taped one)."""
        passes = (self.forward_segment, self.taped_segment, self.backward_segment)
        if self.segments is None:
            self.clock.fill_(n0)
            passes[which]()
            self.segments = graphs.Segments(self.su.prop.device, self.clock, [], passes)
        else:
            self.segments.run(which, n0)

    def _levels(self, steps, callback=None):
        pool = iter(self.levels)
        return run_levels(self.su, self.start, self.model, self.data, steps, self.src, lambda: next(pool), callback, self.clock)

    def forward_segment(self):
        _copy(self.start.arrays(), self._levels(range(self.seg)).arrays())

    def taped(self, steps, callback=None):
        """The levels of `steps` from start under a fresh tape (clock[0] holding steps.start): (tape, end state)."""
        for lvl in self.levels:
            for a in lvl.arrays():
                a.grad.zero_()
        tape = wp.Tape()
        with tape:
            end = self._levels(steps, callback)
        return tape, end

    def taped_segment(self):
        self.tape, self.end = self.taped(range(self.seg))  # kept: a captured graph's launches read the arrays the tape holds

    def backward_segment(self):
        _copy(self.carry, [a.grad for a in self.start.arrays()])
        for a in self.start.arrays():
            a.grad.zero_()
        for a, c in zip(self.end.arrays(), self.carry):
            wp.copy(a.grad, c)
        self.tape.backward()


def _keeps(prop) -> bool:
    """Whether a taped sweep is kept for the next call (on a GPU: its graphs and arrays)."""
    return prop.cuda


def _taped_key(su, seg: int, src) -> tuple:
    """A kept taped sweep's key: the Setup's (its first entry, the kind, renamed: graphs keeps one a kind), seg, and
    which of the sources' arrays are differentiated (a graph without their adjoints cannot give them)."""
    return ("taped " + str(su.key()[0]), *su.key()[1:], seg, tuple(a.grad is not None for a in _warp_arrays(src)))


def _warp_arrays(x) -> list:
    """The Warp arrays in x (an array, or nested tuples and lists of them and other values), in order."""
    if isinstance(x, wp.array):
        return [x]
    if isinstance(x, (tuple, list)):
        return [a for item in x for a in _warp_arrays(item)]
    return []


class Sweep:
    """A physics' hand-written adjoint time loop, checkpointed.

    levels: the physics' arrays and segment functions (solve/<name>.py): start() and end(), the arrays of a
    segment's start and end state; forward_segment() and adjoint_segment(), one segment of `seg` levels each way,
    their time indices j + clock[0] (the segment's first level, so that one captured graph per direction serves
    every segment); kernels(), every kernel they launch; finish(), run once after the backward sweep; device, clock;
    optionally in_place_segment(), the forward segment's steps in place on start() (no levels kept), which the
    forward sweep then runs for every segment but the last (a VD1000 step 15.1 against 17.6 us on an H200), and
    rerun_segment(), the forward segment without recording the data, for the backward sweep's re-runs.
    The forward sweep keeps the start of every segment but the first (zero) and the last (still in the levels when
    the backward sweep begins) as a checkpoint; nt is padded to n_seg * seg levels with zero source samples and
    residuals."""

    def __init__(self, key, levels, seg: int, n_seg: int):
        self.key, self.levels, self.seg, self.n_seg = key, levels, seg, n_seg
        self.checkpoints = [[wp.empty_like(a) for a in levels.start()] for _ in range(n_seg - 2)]
        fns, self.passes = [levels.forward_segment, levels.adjoint_segment], {}  # passes: an optional function's index in fns
        for name in ("in_place_segment", "rerun_segment"):
            if hasattr(levels, name) and n_seg > 1:
                self.passes[name] = len(fns)
                fns.append(getattr(levels, name))
        self.segments = graphs.Segments(levels.device, levels.clock, levels.kernels(), fns)

    def forward_sweep(self, bar):
        """The forward steps of every segment (the synthetic data recorded)."""
        start, end = self.levels.start(), self.levels.end()
        for k in range(self.n_seg):
            last = k == self.n_seg - 1
            if k > 0:
                if "in_place_segment" not in self.passes:
                    _copy(start, end)
                if not last:
                    _copy(self.checkpoints[k - 1], start)
            self.segments.run(0 if last else self.passes.get("in_place_segment", 0), k * self.seg)
            bar.update()

    def backward_sweep(self, bar):
        """The adjoint steps of every segment, last first (the residual set)."""
        start = self.levels.start()
        for k in reversed(range(self.n_seg)):
            if k < self.n_seg - 1:
                if k == 0:
                    for a in start:
                        a.zero_()
                else:
                    _copy(start, self.checkpoints[k - 1])
                self.segments.run(self.passes.get("rerun_segment", 0), k * self.seg)
            self.segments.run(1, k * self.seg)
            bar.update()
        self.levels.finish()


def _copy(dst, src):
    for a, b in zip(dst, src):
        wp.copy(a, b)


def kept_sweep(key, make, cuda: bool) -> Sweep:
    """The kept Sweep under key (CUDA), else make() (kept on CUDA: its graphs and arrays serve the next call)."""
    sw = graphs.kept(key)
    if sw is None:
        sw = make()
        if cuda:
            graphs.keep(sw)
    return sw
