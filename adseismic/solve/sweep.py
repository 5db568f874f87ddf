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
    """Warp's generated adjoints: a forward sweep without a tape up to the last segment, keeping the state at the
    start of every segment; then each segment, last first, re-run under a fresh tape with its own arrays per level
    (su.new_level(), reused from segment to segment; the last segment's run is the forward sweep's end) and
    back-propagated with the data residual and the adjoint state carried from the later segment. The gradients
    accumulate in the .grad of the arrays su's model and sources were made with.

    loss(synthetic) -> (J, adjoints): synthetic, a tuple of NumPy arrays (S, n_rec, nt) in su.new_data's order;
    adjoints, dJ/dsynthetic in the same order (None for a component without). on_level(state, n): called once at
    every level of the forward sweep (untaped). Returns (synthetic, J)."""
    prop, nt = su.prop, su.nt
    levels = [su.new_level() for _ in range(seg)]
    starts = [prop.new_state(requires_grad=True) for _ in range(2)]

    def taped(k, st0, callback=None):
        """Segment k (levels n0 .. n1) from st0 under a fresh tape: (tape, state at n1, data)."""
        n0, n1 = k * seg, min((k + 1) * seg, nt)
        for lvl in levels:
            for a in lvl.arrays():
                a.grad.zero_()
        data_seg = su.new_data(n1 - n0, requires_grad=True)
        pool = iter(levels)
        tape = wp.Tape()
        with tape:
            st = run_levels(su, st0, su.model(on_tape=True), data_seg, range(n0, n1), next_state=lambda: next(pool), callback=callback)
        return tape, st, data_seg

    last = (n_seg - 1) * seg
    data = su.new_data(last)
    checkpoints = []

    def keep(st, n):
        if n % seg == 0:
            checkpoints.append([wp.clone(a) for a in st.arrays()])
        if on_level is not None:
            on_level(st, n)

    st = run_levels(su, prop.new_state(), su.model(), data, range(last), callback=keep)
    for dst, a in zip(starts[0].arrays(), st.arrays()):
        wp.copy(dst, a)
    pending = taped(n_seg - 1, starts[0], on_level)
    bar.update(n_seg)
    synthetic = tuple(np.concatenate([a.numpy(), b.numpy()], axis=2) for a, b in zip(data, pending[2]))
    J, adjoints = loss(synthetic)
    carry = None
    for i, k in enumerate(reversed(range(n_seg))):
        n0, n1 = k * seg, min((k + 1) * seg, nt)
        st0 = starts[i % 2]
        if i:
            for dst, src in zip(st0.arrays(), checkpoints[k]):
                wp.copy(dst, src)
            checkpoints[k] = None
            pending = taped(k, st0)
        for a in st0.arrays():
            a.grad.zero_()
        tape, st, data_seg = pending
        pending = None
        seeds = {d: wp.array(np.ascontiguousarray(a[:, :, n0:n1]), dtype=prop.dtype, device=prop.device)
                 for d, a in zip(data_seg, adjoints) if a is not None}  # fmt: skip
        if carry is not None:
            seeds.update(zip(st.arrays(), carry))
        tape.backward(grads=seeds)
        carry = [a.grad for a in st0.arrays()]
        del tape  # (not tape.reset(): that zeroes the gradients it holds, ours included)
        bar.update()
    return synthetic, J


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
