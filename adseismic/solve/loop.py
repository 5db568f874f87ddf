"""The time loop, one for every physics.

A physics hands the solver a setup (solve/<name>.py) that maps its propagator onto a few verbs:

    su.prop           launch helper (kernels/<name>): dtype, device, cuda, n_shots, new_state()
    su.nt, su.amplitudes   levels to run; source samples (S, n_src, nt) on the device
    su.physics        DESCRIPTION (kernels/<name>)
    su.model()        the padded model the steps read (on_tape=True: recorded on the active tape)
    su.sources_of(amp, fixed)  the steps' source arguments for samples amp (fixed: through the fixed operator)
    su.advance(st, model, src, data, k, n, out, clock, side=None)   record level n into sample k of data, step to
                      n + 1; side (a graphs.SideStream, in a captured loop): the record may run beside the step
    su.record(st, data, k, clock)                        record the last level
    su.new_data(n)    zero receiver data, a tuple of (S, n_rec, n) arrays
    su.fields(st)     the arrays the blow-up guard watches
    su.period, su.spare(st), su.out_state(st, spare), su.freed(st)   the buffer ring of a captured loop (period
                      steps to come round): advance st into
                      out_state(st, spare) (None: in place); freed(st) is the next spare (a GPU writes a fresh
                      array faster than it updates one in place, except where a step's fields fit its L2 cache)
    su.lookahead      source samples read past a level (a moment source reads n + 1)
    su.key(), su.loop_kernels(), su.inputs(src), su.fill_model(model)   what a kept loop bakes in, loads, and
                      refills from a later call with the same key

On a CPU (and under a tape) run_levels steps level by level; on a GPU K steps are captured once as a CUDA graph
(accel.graphs) and replayed, and the loop is kept with its arrays for the next call with the same key.
"""

from __future__ import annotations

from types import SimpleNamespace

import warp as wp

from adseismic.accel import graphs
from adseismic.accel.reductions import field_stats, reduction_kernels
from adseismic.runs import progress_bar
from adseismic.solve.common import padded_samples


def run_levels(su, st, model, data, steps: range, sources=None, next_state=None, callback=None, clock=None):
    """Record level n into sample n - steps.start of data and advance one step, for n in steps; returns the state at
    steps.stop (or at nt - 1, which is only recorded). sources: su.sources_of(...) (default: su.amplitudes through the
    located operator); next_state: callable giving the next level's arrays (each level needs its own under a tape),
    None steps in place; callback(state, n) runs at level n before it is recorded and stepped from; clock: a device
    clock holding steps.start, which the launches add to the index they are given (sample and level n - steps.start;
    one captured segment then serves every start)."""
    src = su.sources_of(su.amplitudes, fixed=False) if sources is None else sources
    for n in steps:
        if callback is not None:
            callback(st, n)
        k = n - steps.start
        if n == su.nt - 1:
            su.record(st, data, k, clock)
            break
        st = su.advance(st, model, src, data, k, n if clock is None else k, next_state() if next_state is not None else None, clock)
    return st


def capture(su, st, model, data, every: int) -> graphs.Loop:
    """run_levels's untaped loop with the guard's statistics every `every` levels, captured as CUDA graphs of K steps
    (graphs.graph_plan with su.period) stepping round the buffer ring; data must hold K * graphs samples."""
    prop = su.prop
    K, n_graphs = graphs.graph_plan(prop.cuda, su.nt, every, su.period)
    if data[0].shape[2] < K * n_graphs:
        raise ValueError(f"data has {data[0].shape[2]} samples; the graph replays record {K * n_graphs}")
    amplitudes = wp.array(padded_samples(su.amplitudes.numpy(), K * n_graphs + su.lookahead, prop.dtype), dtype=prop.dtype,
                          device=prop.device)  # fmt: skip
    src = su.sources_of(amplitudes, fixed=True)
    spare = su.spare(st)
    ring = [st, spare]
    side = graphs.SideStream(prop.device)

    def step(k, clock, stats):
        cur, free = ring
        if stats is not None:
            field_stats(su.fields(cur), stats)
        nxt = su.advance(cur, model, src, data, k, k, su.out_state(cur, free), clock, side)
        ring[:] = [nxt, su.freed(cur)]

    kernels = [reduction_kernels(prop.dtype)[0], *su.loop_kernels()]
    kept = SimpleNamespace(su=su, st=st, spare=spare, model=model, data=data, amplitudes=amplitudes, sources=src, side=side)
    return graphs.capture((*su.key(), every), prop.device, prop.dtype, K, n_graphs, every, step, kernels, kept, su.nt)


def kept_loop(su, every: int) -> graphs.Loop:
    """The time loop for su: the kept one refilled with su's inputs when its key matches, else a new capture (kept)."""
    loop = graphs.kept((*su.key(), every))
    prop = su.prop
    if loop is None:
        K, n_graphs = graphs.graph_plan(prop.cuda, su.nt, every, su.period)
        return graphs.keep(capture(su, prop.new_state(), su.model(), su.new_data(K * n_graphs), every))
    mine = loop.kept
    for a, b in zip(mine.su.inputs(mine.sources), su.inputs(su.sources_of(mine.amplitudes, fixed=True))):
        if a.ptr != b.ptr:
            wp.copy(a, b)
    su.fill_model(mine.model)
    wp.copy(mine.amplitudes[:, :, : su.amplitudes.shape[2]], su.amplitudes)  # device to device: the padding past nt stays zero
    for a in (*mine.st.arrays(), *_arrays(mine.spare), *mine.data, loop.clock):
        a.zero_()
    return loop


def _arrays(x):
    return x.arrays() if hasattr(x, "arrays") else [] if x is None else [x]


def run(su, guard, progress=False, callback=None):
    """Run every level of su with the blow-up guard; returns the receiver data, a tuple of (S, n_rec, >= nt) arrays
    on the device (a kept loop's own buffers on a GPU: copy them before the next call) and whether a kept loop ran.
    callback(state, n): called at every level (forces the level-by-level loop)."""
    bar = progress_bar(total=su.nt, desc="time steps", unit="steps", enabled=progress)
    use_graphs = callback is None and graphs.graph_plan(su.prop.cuda, su.nt, guard.every, su.period)[1] > 0
    if use_graphs:
        loop = kept_loop(su, guard.every)
        graphs.replay(loop, su.nt, guard, bar)
        data = loop.kept.data
    else:

        def each(st, n):
            guard(st, n)
            if callback is not None:
                callback(st, n)
            bar.update()

        data = su.new_data(su.nt)
        run_levels(su, su.prop.new_state(), su.model(), data, range(su.nt), callback=each)
    bar.close()
    return data, use_graphs


def traces(d: wp.array, nt: int, on_device: bool, kept: bool):
    """The first nt samples of receiver data d (S, n_rec, >= nt) in the simulation's precision (a float64 copy of
    S600x16's traces cost 6.7 ms of a 72 ms call): a NumPy array, or with on_device a Warp array on d's device (a
    copy where d is a kept loop's buffer, which the next call overwrites)."""
    if not on_device:
        return d.numpy()[:, :, :nt]
    if not kept:
        return d
    out = wp.empty((*d.shape[:2], nt), dtype=d.dtype, device=d.device)
    wp.copy(out, d[:, :, :nt])
    return out
