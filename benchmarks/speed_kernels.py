"""Check and time the acoustic time loop on one device: the optimised path (line kernels, CUDA graphs,
CPU threads) against the per-cell reference kernels, the time of each kernel (tile kernel at several block sizes) and the
time loop's rate (as forward runs it, without forward's host-side set-up). One JSON line each.

    python benchmarks/speed_kernels.py --device cuda:0 [--scenes S600x16 S4000]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from speed import SCENES, scene  # noqa: E402

import adseismic.propagate as P  # noqa: E402
from adseismic.kernels import acoustic as K  # noqa: E402


def make(name, device, order, nt=None):
    n, shots, nt0 = SCENES[name]
    v, src, rec, s = scene(n, shots, nt or nt0)
    return P.setup(v, 10.0, 1e-3, s, src, rec, order=order, pml_width=20, device=device), s


def loop(su, s):
    """forward's time loop (graphs where possible, then run_steps); returns (seconds, data)."""
    prop = su.prop
    data = wp.zeros((prop.n_shots, su.receivers.shape[1], su.nt), dtype=prop.dtype, device=prop.device)
    guard = P.BlowupGuard(prop, s, 25)
    st, vpad = prop.new_state(), prop.pad_model(su.velocity)
    wp.synchronize_device(prop.device)
    t = time.perf_counter()
    st, start = P.run_graphs(su, st, vpad, data, guard)
    P.run_steps(su, st, vpad, data if start == 0 else data[:, :, start:], range(start, su.nt), callback=lambda st, n: guard(st.u, n))
    wp.synchronize_device(prop.device)
    return time.perf_counter() - t, data.numpy()


def reference(su):
    """Traces from the per-cell reference kernels (the path Warp differentiates), no graphs."""
    prop = su.prop
    data = wp.zeros((prop.n_shots, su.receivers.shape[1], su.nt), dtype=prop.dtype, device=prop.device)
    with wp.Tape():
        P.run_steps(su, prop.new_state(), prop.pad_model(su.velocity), data, range(su.nt))
    return data.numpy()


def per_launch(fn, device, reps):
    fn()
    wp.synchronize_device(device)
    t = time.perf_counter()
    for _ in range(reps):
        fn()
    wp.synchronize_device(device)
    return (time.perf_counter() - t) / reps


def kernel_times(su, reps):
    prop = su.prop
    st, vpad = prop.new_state(), prop.pad_model(su.velocity)
    rng = np.random.default_rng(0)
    for a in (st.u, st.u_prev):
        a.assign(rng.standard_normal(a.shape).astype(np.float32) * 1e-3)
    S, nz, ny, nx = prop.interior
    R = prop.k.halo
    args = [st.u, st.u_prev, st.u_prev, vpad, *st.psi, *st.zeta, *st.zeta, *prop.axes, prop.dt2, prop.inv_dx, prop.top]
    dev = prop.device
    out = {}
    out["step_reference"] = per_launch(lambda: wp.launch(prop.k.step, dim=prop.interior, inputs=args, device=dev), dev, reps)
    if prop.cuda:
        rows = st.u.reshape((S * prop.padded[0], prop.padded[2]))
        tz, tx = K.GPU_TILE
        for block in (128, 256, 512):
            out[f"step_tile_b{block}"] = per_launch(lambda: wp.launch_tiled(prop.k.step_tile, dim=(S, -(-nz // tz), -(-nx // tx)),
                                                    inputs=[st.u, rows, *args[1:]], block_dim=block, device=dev), dev, reps)  # fmt: skip
    out["step_in_place"] = per_launch(lambda: prop.step(st, vpad), dev, reps)
    grads = prop.new_state(requires_grad=True)
    adj = [grads.u.grad, grads.u_prev.grad, st.u, vpad, *(a.grad for a in grads.psi), *(a.grad for a in grads.zeta), *(a.grad for a in grads.zeta)]
    shape = prop.interior if prop.cuda else (S, nz, ny, 1)
    out["step_adjoint"] = per_launch(lambda: wp.launch(prop.k.step_adjoint[not prop.cuda], dim=shape,
                                     inputs=[st.u, vpad, *st.psi, *st.zeta, *adj, *prop.axes, prop.dt2, prop.inv_dx, prop.top], device=dev), dev, reps)  # fmt: skip
    for a in (0, 2):
        out[f"psi_{a}"] = per_launch(lambda: wp.launch(prop.k.psi[a][0], dim=prop.strip_shape(a), inputs=[st.u, st.psi[a], st.psi[a], prop.axes[a], prop.inv_dx], device=dev), dev, reps)  # fmt: skip
    stats = wp.zeros(2, dtype=prop.dtype, device=dev)
    out["monitor"] = per_launch(lambda: prop.monitor(st.u, stats), dev, reps)
    data = wp.zeros((S, su.receivers.shape[1], su.nt), dtype=prop.dtype, device=dev)
    out["record"] = per_launch(lambda: prop.record(st.u, data, su.receiver_op, 3), dev, reps)
    out["inject"] = per_launch(lambda: prop.inject(st.u, vpad, su.amplitudes, su.source_op, 3), dev, reps)
    cells = S * np.prod(prop.padded)
    return {k: {"us": round(v * 1e6, 1), "gcells": round(cells / v / 1e9, 1)} for k, v in out.items()}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--scenes", nargs="+", default=["S600x16", "S4000"])
    ap.add_argument("--reps", type=int, default=50)
    a = ap.parse_args()
    P.init_warp()
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


if __name__ == "__main__":
    main()
