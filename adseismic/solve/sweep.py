"""The checkpointed gradient, one for every physics: reverse-mode differentiation of the time stepping.

Differentiating the discrete scheme is the discrete adjoint-state method, so the gradient is exact for the
simulated data. Memory is bounded by checkpointing: a forward sweep keeps the state at the start of every
segment of `seg` levels; the backward sweep runs the segments last first, each forward again from its
checkpoint and then backward. Peak memory ~ n_segments x checkpoint + seg x level, minimised near seg ~ sqrt(nt);
the cost is one extra forward run (none when every step fits in one segment).

Two ways through a segment:
- taped_sweep: Warp's generated adjoints of every kernel, recorded on a wp.Tape with the arrays of every level
  (the reference), for any setup that run_levels drives (solve/loop.py);
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
    on a GPU each full segment's two directions are captured once as CUDA graphs and replayed). The model and the
    sources are made once, on a tape of their own that is back-propagated at the end, so the gradients accumulate in
    the .grad of the arrays su's model and sources were made with.

    loss(synthetic) -> (J, adjoints): synthetic, a tuple of NumPy arrays (S, n_rec, nt) in su.new_data's order;
    adjoints, dJ/dsynthetic in the same order (None for a component without). on_level(state, n): called once at
    every level of the forward sweep (untaped; the forward sweep is then run launch by launch). Returns
    (synthetic, J)."""
    prop, nt = su.prop, su.nt
    setup_tape = wp.Tape()
    with setup_tape:
        model, src = su.model(on_tape=True), su.sources_of(su.amplitudes, fixed=False)
    data = su.new_data(nt, requires_grad=True)
    ts = _TapedSegments(su, seg, model, src, data)
    last = (n_seg - 1) * seg
    checkpoints, segments = [], None  # the checkpoints have no .grad: wp.copy would copy it over start's carried adjoint
    fns = (ts.forward_segment, ts.adjoint_segment)
    if on_level is None:
        for k in range(n_seg - 1):
            checkpoints.append([wp.clone(a, requires_grad=False) for a in ts.start.arrays()])
            if k == 0:  # launch by launch: loads the modules (forward and adjoint) that the captures need
                ts.clock.zero_()
                ts.forward_segment()
                segments = graphs.Segments(prop.device, ts.clock, [], fns)
            else:
                segments.run(0, k * seg)
    else:

        def keep(st, n):
            if n % seg == 0:
                checkpoints.append([wp.clone(a, requires_grad=False) for a in st.arrays()])
            on_level(st, n)

        st = run_levels(su, prop.new_state(), model, data, range(last), src, callback=keep)
        _copy(ts.start.arrays(), st.arrays())
        segments = graphs.Segments(prop.device, ts.clock, [], fns) if n_seg > 1 else None
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
    tape.backward()
    del tape  # (not tape.reset(): that zeroes the gradients it holds, ours included)
    bar.update()
    for k in reversed(range(n_seg - 1)):
        _copy(ts.start.arrays(), checkpoints[k])
        checkpoints[k] = None
        segments.run(1, k * seg)
        bar.update()
    setup_tape.backward()
    return synthetic, J


class _TapedSegments:
    """taped_sweep's arrays and its two directions of a full segment (seg levels from `start`, the time indices read
    from `clock`; graphs.Segments): forward_segment, untaped, leaves the end state in start; adjoint_segment re-runs
    the levels from start under a tape and back-propagates them, seeded with the adjoint state that start's .grad
    carries from the later segment, leaving the earlier one there."""

    def __init__(self, su, seg, model, src, data):
        self.su, self.seg, self.model, self.src, self.data = su, seg, model, src, data
        self.levels = [su.new_level() for _ in range(seg)]
        self.start = su.prop.new_state(requires_grad=True)
        self.carry = [wp.empty_like(a) for a in self.start.arrays()]
        self.clock = wp.zeros(1, dtype=wp.int32, device=su.prop.device)
        self.tape = None

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

    def adjoint_segment(self):
        tape, end = self.taped(range(self.seg))
        _copy(self.carry, [a.grad for a in self.start.arrays()])
        for a in self.start.arrays():
            a.grad.zero_()
        for a, c in zip(end.arrays(), self.carry):
            wp.copy(a.grad, c)
        tape.backward()
        self.tape = tape  # a captured graph's launches read the arrays the tape holds


class Sweep:
    """A physics' hand-written adjoint time loop, checkpointed.

    levels: the physics' arrays and segment functions (solve/<name>.py): start() and end(), the arrays of a
    segment's start and end state; forward_segment() and adjoint_segment(), one segment of `seg` levels each way,
    their time indices j + clock[0] (the segment's first level, so that one captured graph per direction serves
    every segment); kernels(), every kernel they launch; finish(), run once after the backward sweep; device, clock.
    The forward sweep keeps the start of every segment but the first (zero) and the last (still in the levels when
    the backward sweep begins) as a checkpoint; nt is padded to n_seg * seg levels with zero source samples and
    residuals."""

    def __init__(self, key, levels, seg: int, n_seg: int):
        self.key, self.levels, self.seg, self.n_seg = key, levels, seg, n_seg
        self.checkpoints = [[wp.empty_like(a) for a in levels.start()] for _ in range(n_seg - 2)]
        self.segments = graphs.Segments(levels.device, levels.clock, levels.kernels(), (levels.forward_segment, levels.adjoint_segment))

    def forward_sweep(self, bar):
        """The forward steps of every segment (the synthetic data recorded)."""
        start, end = self.levels.start(), self.levels.end()
        for k in range(self.n_seg):
            if k > 0:
                _copy(start, end)
                if k < self.n_seg - 1:
                    _copy(self.checkpoints[k - 1], end)
            self.segments.run(0, k * self.seg)
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
                self.segments.run(0, k * self.seg)
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
