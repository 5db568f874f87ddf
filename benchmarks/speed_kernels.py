"""Check and time the acoustic time loop on one device: the optimised path (core + frame kernels and
CUDA graphs on a GPU, row kernels and threads on a CPU) against the per-cell reference kernels, the time
of each kernel (the GPU core step at several cells per thread and block sizes, each checked against the
reference step), the time loop's rate (as forward runs it, without forward's host-side set-up) and
the whole forward() call. One JSON line each.

    python benchmarks/speed_kernels.py --device cuda:0 [--scenes S600x16 S4000] [--profile]
"""

import argparse
import cProfile
import io
import json
import pstats
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from speed import SCENES, scene  # noqa: E402

import adseismic.solve.acoustic as P  # noqa: E402
from adseismic.accel.graphs import graph_plan, replay  # noqa: E402
from adseismic.accel.reductions import field_stats  # noqa: E402
from adseismic.kernels.acoustic import DESCRIPTION  # noqa: E402
from adseismic.solve.common import BlowupGuard, init_warp, source_end  # noqa: E402
from adseismic.solve.loop import capture, run_levels  # noqa: E402

CORE_VARIANTS = [(4, 4, 128), (4, 2, 128), (8, 4, 128), (2, 4, 128), (4, 1, 128), (4, 4, 256)]  # (rows, columns per thread (one vector), threads per block) of the core kernels


def make(name, device, order, nt=None):
    n, shots, nt0 = SCENES[name]
    v, src, rec, s = scene(n, shots, nt or nt0)
    return P.setup(v, 10.0, 1e-3, s, src, rec, order=order, pml_width=20, device=device), s


def loop(su, s):
    """forward's time loop (graphs on a GPU, else run_steps); returns (seconds, data)."""
    prop = su.prop
    guard = BlowupGuard(prop, DESCRIPTION, lambda st: [st.u], source_end(s), 25)
    K, graphs = graph_plan(prop.cuda, su.nt, guard.every, su.period)
    data = su.new_data(max(su.nt, K * graphs))
    st, vpad = prop.new_state(), su.model()
    wp.synchronize_device(prop.device)
    t = time.perf_counter()
    if graphs:
        replay(capture(su, st, vpad, data, guard.every), su.nt, guard)
    else:
        run_levels(su, st, vpad, data, range(su.nt), callback=guard)
    wp.synchronize_device(prop.device)
    return time.perf_counter() - t, data[0].numpy()[:, :, : su.nt]


def reference(su):
    """Traces from the per-cell reference kernels (the path Warp differentiates), no graphs."""
    prop = su.prop
    data = su.new_data(su.nt)
    with wp.Tape():
        run_levels(su, prop.new_state(), su.model(), data, range(su.nt))
    return data[0].numpy()


def per_launch(fn, device, reps):
    """Seconds per call of fn (on a GPU replayed from a captured graph of `reps` calls: no launch overhead)."""
    fn()
    wp.synchronize_device(device)
    if wp.get_device(device).is_cuda:
        with wp.ScopedCapture(device=device) as capture:
            for _ in range(reps):
                fn()
        wp.capture_launch(capture.graph)
        wp.synchronize_device(device)
        t = time.perf_counter()
        wp.capture_launch(capture.graph)
        wp.synchronize_device(device)
        return (time.perf_counter() - t) / reps
    t = time.perf_counter()
    for _ in range(reps):
        fn()
    wp.synchronize_device(device)
    return (time.perf_counter() - t) / reps


def kernel_times(su, reps):
    """Per-kernel seconds; on a GPU each core variant's step is also checked against the reference step
    on random fields (max |difference| / max |reference|)."""
    prop = su.prop
    st, vpad = prop.new_state(), prop.pad_model(su.velocity)
    rng = np.random.default_rng(0)
    for a in (st.u, st.u_prev):
        a.assign(rng.standard_normal(a.shape).astype(np.float32) * 1e-3)
    S, nz, ny, _ = prop.interior
    dev = prop.device
    ref_next, fast_next = wp.zeros_like(st.u), wp.zeros_like(st.u)
    zeta_new = prop.new_state().zeta  # the steps below read st.zeta and write here, so every launch sees the same input
    psi_ref = prop.new_state().psi  # psi[n] from st.psi by the psi kernels, for the reference step
    for a in (0, 2):
        wp.launch(prop.k.psi[a][0], dim=prop.strip_shape(a), inputs=[st.u, st.psi[a], psi_ref[a], prop.axes[a], prop.inv_dx], device=dev)

    def args(u_next):
        return [st.u, st.u_prev, u_next, vpad, *psi_ref, *st.zeta, *zeta_new, *prop.axes, prop.dt2, prop.inv_dx, prop.top]

    out, checks = {}, {}
    out["step_reference"] = per_launch(lambda: wp.launch(prop.k.step, dim=prop.interior, inputs=args(ref_next), device=dev), dev, reps)
    data = wp.zeros((S, su.receivers.shape[1], su.nt), dtype=prop.dtype, device=dev)
    if prop.cuda and prop.has_core:
        def part(name):
            return lambda: prop.step_core(args(fast_next), st.u, st.u_prev, fast_next, vpad, part=name)

        out["step_frame"] = per_launch(part("frame"), dev, reps)
        ref = ref_next.numpy()
        default = prop.core_rows, prop.core_cols, prop.core_threads
        for rows, cols, block in CORE_VARIANTS:
            prop.core_rows, prop.core_cols, prop.core_threads = rows, cols, block
            name = f"step_core_r{rows}_c{cols}_b{block}"
            out[name] = per_launch(part("core"), dev, reps)
            out[name + "_with_frame"] = per_launch(part(None), dev, reps)
            checks[name] = float(np.abs(fast_next.numpy() - ref).max() / np.abs(ref).max())
            fast_next.zero_()
        prop.core_rows, prop.core_cols, prop.core_threads = default
        out["pre_step"] = per_launch(lambda: prop._pre_step(st, st, (data, su.receiver_op, 3, None)), dev, reps)
    out["step_in_place"] = per_launch(lambda: prop.step(st, vpad), dev, reps)

    def whole():  # a time step as forward's loop runs it
        prop.step(st, vpad, record=(data, su.receiver_op, 3, None))
        prop.inject(st.u, vpad, su.amplitudes, su.source_op, 3)

    out["step_record_inject"] = per_launch(whole, dev, reps)
    out.update(adjoint_times(prop, st, vpad, su.receiver_op, reps, checks))
    for a in (0, 2):
        out[f"psi_{a}"] = per_launch(lambda: wp.launch(prop.k.psi[a][0], dim=prop.strip_shape(a), inputs=[st.u, st.psi[a], st.psi[a], prop.axes[a], prop.inv_dx], device=dev), dev, reps)  # fmt: skip
    stats = wp.zeros(2, dtype=prop.dtype, device=dev)
    out["monitor"] = per_launch(lambda: field_stats([st.u], stats), dev, reps)
    out["record"] = per_launch(lambda: prop.record(st.u, data, su.receiver_op, 3), dev, reps)
    out["inject"] = per_launch(lambda: prop.inject(st.u, vpad, su.amplitudes, su.source_op, 3), dev, reps)
    cells = S * np.prod(prop.padded)
    times = {k: {"us": round(v * 1e6, 1), "gcells": round(cells / v / 1e9, 1)} for k, v in out.items()}
    for k, v in checks.items():
        times[k]["max_rel_diff"] = v
    return times


def adjoint_times(prop, st, vpad, residual_op, reps, checks):
    """Per-launch seconds of the adjoint step (core variants on a GPU, each checked against the per-cell
    adjoint_step kernel on the same inputs) and of the whole adjoint step (core, frame, psi and, through
    residual_op (the receiver operator), the receivers), writing into fresh arrays as the Sweep does."""
    dev, out = prop.device, {}
    rng = np.random.default_rng(1)
    lam, adj, g = (wp.array(rng.standard_normal(st.u.shape).astype(np.float32) * 1e-3, device=dev) for _ in range(3))
    adj_out, g_out = wp.zeros_like(adj), wp.zeros_like(g)
    w = wp.zeros_like(vpad)
    wp.launch(prop.k.squared, dim=prop.padded, inputs=[vpad, prop.dt2, w], device=dev)
    nxt = prop.new_state(with_prev=False)
    ap = [prop.new_state(with_prev=False).psi for _ in range(2)]
    az = [prop.new_state(with_prev=False).zeta for _ in range(2)]
    args = [st.u, vpad, *nxt.psi, *st.zeta, lam, adj, g, adj_out, g_out, *ap[0], *az[1], *az[0], *prop.axes, prop.dt2, prop.inv_dx, prop.top]
    if prop.cuda and prop.has_core:
        ref_a, ref_g = wp.zeros_like(adj), wp.zeros_like(g)
        scattered = prop.new_state(with_prev=False)  # its strips' scatters, kept from the cores' inputs (pre_adjoint's output)
        wp.launch(prop.k.adjoint_step, dim=prop.interior, inputs=[*args[:11], ref_a, ref_g, *scattered.psi, *scattered.zeta, *args[19:]],
                  device=dev)
        ref_a, ref_g = ref_a.numpy(), ref_g.numpy()

        def part(name):
            return lambda: prop.adjoint_core(args, st.u, lam, adj, g, adj_out, g_out, w, part=name)

        default = prop.core_rows, prop.core_cols, prop.core_threads
        for rows, cols, block in CORE_VARIANTS:
            prop.core_rows, prop.core_cols, prop.core_threads = rows, cols, block
            name = f"adjoint_core_r{rows}_c{cols}_b{block}"
            adj_out.zero_(), g_out.zero_()
            part(None)()
            checks[name] = float(max(np.abs(adj_out.numpy() - ref_a).max() / np.abs(ref_a).max(), np.abs(g_out.numpy() - ref_g).max() / np.abs(ref_g).max()))
            out[name] = per_launch(part("core"), dev, reps)
            out[name + "_with_frame"] = per_launch(part(None), dev, reps)
        prop.core_rows, prop.core_cols, prop.core_threads = default
        out["adjoint_frame"] = per_launch(part("frame"), dev, reps)
    res = wp.zeros((prop.n_shots, residual_op[1].shape[1], 8), dtype=prop.dtype, device=dev)
    out["adjoint_step"] = per_launch(lambda: prop.adjoint_step(st, nxt, vpad, w, lam, adj, g, ap, az, residual=(res, residual_op, 3, None), out=(adj_out, g_out)),
                                     dev, reps)  # fmt: skip
    return out


def forward_call(name, device, order, on_device=False):
    """Seconds of the whole forward() call on a scene (best of 3, after a warm-up that also captures the time
    loop forward keeps), the model from the host or (on_device) already on the device, and the inputs."""
    n, shots, nt = SCENES[name]
    v, src, rec, s = scene(n, shots, nt)
    if on_device:
        v = wp.array(v, dtype=wp.float32, device=device)

    def run():
        wp.synchronize_device(device)
        t = time.perf_counter()
        P.forward(v, 10.0, 1e-3, s, src, rec, order=order, pml_width=20, device=device)
        wp.synchronize_device(device)
        return time.perf_counter() - t

    run()
    return min(run() for _ in range(3)), (v, src, rec, s)


def adjoint_only(a):
    """--adjoint-only: the adjoint step's kernels, and those of the source and receiver adjoints."""
    for name in a.scenes:
        su, _ = make(name, a.device, a.order)
        prop, checks = su.prop, {}
        st, vpad = prop.new_state(), prop.pad_model(su.velocity, requires_grad=True)
        times = adjoint_times(prop, st, vpad, su.receiver_op, a.reps, checks)
        res = wp.zeros((prop.n_shots, su.receivers.shape[1], su.nt), dtype=prop.dtype, device=prop.device)
        times["record_adjoint"] = per_launch(lambda: prop.record_adjoint(st.u, res, su.receiver_op, 3), prop.device, a.reps)
        times["inject_adjoint"] = per_launch(lambda: prop.inject_adjoint(st.u, vpad, su.amplitudes, su.source_op, 3), prop.device, a.reps)
        print(json.dumps({"adjoint": name, **{k: round(v * 1e6, 1) for k, v in times.items()}, "checks": checks}), flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--scenes", nargs="+", default=["S600x16", "S4000"])
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--profile", action="store_true", help="also profile one forward() call per scene (host time)")
    ap.add_argument("--adjoint-only", action="store_true", help="only the adjoint step's kernels")
    a = ap.parse_args()
    init_warp()
    if a.adjoint_only:
        adjoint_only(a)
        return
    # correctness: optimised vs reference traces, on a short run of each scene
    for name in a.scenes:
        su, s = make(name, a.device, a.order, nt=300)
        _, fast = loop(su, s)
        ref = reference(su)
        print(json.dumps({"check": name, "device": a.device, "max_rel_diff": float(np.abs(fast - ref).max() / np.abs(ref).max()),
                          "bitwise": bool(np.array_equal(fast, ref))}), flush=True)  # fmt: skip
    for name in a.scenes:
        su, s = make(name, a.device, a.order)
        print(json.dumps({"kernels": name, **kernel_times(su, a.reps)}), flush=True)
        cells = su.prop.n_shots * np.prod(su.prop.padded) * su.nt
        loop(su, s)  # warm-up (compile, first capture)
        times = [loop(su, s)[0] for _ in range(3)]
        print(json.dumps({"loop": name, "seconds": [round(t, 4) for t in times], "gcells": round(cells / min(times) / 1e9, 1)}), flush=True)
        del su
        for on_device in (False, True):
            tf, inputs = forward_call(name, a.device, a.order, on_device)
            print(json.dumps({"forward": name, "model_on_device": on_device, "seconds": round(tf, 4), "gcells": round(cells / tf / 1e9, 1)}), flush=True)
        if a.profile:
            prof = cProfile.Profile()
            v, src, rec, s = inputs
            prof.runcall(P.forward, v, 10.0, 1e-3, s, src, rec, order=a.order, pml_width=20, device=a.device)
            text = io.StringIO()
            pstats.Stats(prof, stream=text).sort_stats("cumulative").print_stats(20)
            print(text.getvalue(), flush=True)


if __name__ == "__main__":
    main()
