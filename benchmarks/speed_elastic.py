"""Check and time the 2D elastic propagator on one device: per-kernel microseconds (CUDA-graph replays on
a GPU, a synchronised loop on the CPU), one taped step's backward (hand-written vs Warp's generated
adjoints), the whole forward_elastic / gradient_elastic calls as adseismic/bench.py runs them (best of
--repeat after a warm-up that compiles the kernels) in Gcell/s (padded cells x steps x shots / s), and
the optimised traces against the per-cell reference kernels. One JSON line per measurement; a failing
measurement prints its error and the others still run.

    python benchmarks/speed_elastic.py --device cuda:0 [--scenes E2000 E600x16] [--modes forward gradient]
    python benchmarks/speed_elastic.py --device cpu --size 200 --steps 100
"""

import argparse
import json
import time
import traceback

import numpy as np
import warp as wp

import adseismic.elastic as E
from adseismic import bench
from adseismic.kernels.elastic import PSI_S, PSI_V

ORDER = 4


def emit(**row):
    print(json.dumps(row), flush=True)


def attempt(scene, what, fn):
    """Run fn() -> dict and print it as one JSON line (or its failure)."""
    try:
        emit(scene=scene, what=what, **fn())
    except Exception as exc:  # one failing measurement must not stop the others
        emit(scene=scene, what=what, status=f"failed: {type(exc).__name__}: {exc}"[:500], trace=traceback.format_exc()[-1500:])


def sync(device):
    wp.synchronize_device(device)


def per_call_us(fn, device, reps):
    """Mean microseconds of fn() (a few launches): one graph of reps calls replayed on a GPU, else a loop."""
    fn()
    sync(device)
    if wp.get_device(device).is_cuda:
        with wp.ScopedCapture(device=device) as cap:
            for _ in range(reps):
                fn()
        wp.capture_launch(cap.graph)
        sync(device)
        t = time.perf_counter()
        wp.capture_launch(cap.graph)
    else:
        t = time.perf_counter()
        for _ in range(reps):
            fn()
    sync(device)
    return (time.perf_counter() - t) / reps * 1e6


def setup(a, device):
    force = np.broadcast_to([1.0, 0.0], (*a.sources.shape[:2], 2))
    m = a.model
    return E.setup_elastic(m["vp"], m["vs"], m["rho"], bench.DX, bench.DT, a.amplitudes, a.sources, a.receivers, source_type="force",
                           source_components=force, order=ORDER, pml_width=bench.PML, device=device)  # fmt: skip


def kernel_times(su, device, reps):
    prop, k = su.prop, su.prop.k
    st, mat = prop.new_state(), su.materials()
    data = E._new_data(su, su.nt)
    src = su.source_args()
    P, (bx, bz, l2m, lam, mu, muh) = st.psi, mat
    common = [*prop.axes, prop.dt_device, prop.inv_dx, prop.top]
    pv, ps = [P[n] for n in PSI_V], [P[n] for n in PSI_S]
    vel = [st.vx, st.vz, st.sxx, st.szz, st.sxz, bx, bz, *pv, *pv, st.vx, st.vz, *common]
    sts = [st.vx, st.vz, st.sxx, st.szz, st.sxz, l2m, lam, mu, muh, *ps, *ps, st.sxx, st.szz, st.sxz, *common]
    jobs = {
        "step_in_place": lambda: prop.step(st, mat, src, 0),
        "velocity_reference": lambda: wp.launch(k.velocity, dim=prop.interior, inputs=vel, device=device),
        "stress_reference": lambda: wp.launch(k.stress, dim=prop.interior, inputs=sts, device=device),
        "velocity_core": lambda: prop._flat_launch(k.velocity_core, prop.core, [st.vx, st.vz, st.sxx, st.szz, st.sxz, bx, bz, st.vx, st.vz],
                                                   prop.dt_device, prop.inv_dx),  # fmt: skip
        "stress_core": lambda: prop._flat_launch(k.stress_core, prop.core, [st.vx, st.vz, st.sxx, st.szz, st.sxz, l2m, lam, muh, st.sxx, st.szz, st.sxz],
                                                 prop.dt_device, prop.inv_dx),  # fmt: skip
        "velocity_frame": lambda: wp.launch(k.velocity_frame, dim=(prop.n_shots, prop.frame_cells), inputs=[*vel, prop.core], device=device),
        "stress_frame": lambda: wp.launch(k.stress_frame, dim=(prop.n_shots, prop.frame_cells), inputs=[*sts, prop.core], device=device),
        "record": lambda: prop.record(st, data, su.receiver_op, 3),
        "inject_force": lambda: wp.launch(k.inject_force, dim=(prop.n_shots, su.sources.shape[1], k.operator_points),
                                          inputs=[st.vx, st.vz, bx, bz, su.amplitudes, su.components, su.sources, 3, prop.clock, prop.origin,
                                                  prop.dtype(prop.dt / prop.dx**2), prop.inv_dx, prop.top], device=device),  # fmt: skip
        "monitor": lambda: prop.monitor((st.vx, st.vz), wp.zeros(2, dtype=prop.dtype, device=device)),
    }
    out = {"core_cells": int((prop.core[1] - prop.core[0]) * (prop.core[3] - prop.core[2])), "frame_cells": prop.frame_cells}
    for name, fn in jobs.items():
        try:
            out[name + "_us"] = round(per_call_us(fn, device, reps), 2)
        except Exception as exc:
            out[name + "_us"] = f"failed: {type(exc).__name__}: {exc}"[:300]
    return out


def backward_times(su, device, reps):
    """Microseconds of one taped step's backward, hand-written and generated adjoints."""
    prop = su.prop
    out = {}
    for adjoint in ("hand", "warp"):
        try:
            a, b = prop.new_state(requires_grad=True), prop.new_state(requires_grad=True)
            tape = wp.Tape()
            with tape:
                mat = prop.materials(*(prop.pad_model(m, True) for m in su.model), requires_grad=True)
            tape = wp.Tape()  # the step alone
            with tape:
                prop.step(a, mat, su.source_args(), 3, out=b, tape=tape if adjoint == "hand" else None)
            out[f"step_backward_{adjoint}_us"] = round(per_call_us(tape.backward, device, reps), 2)
        except Exception as exc:
            out[f"step_backward_{adjoint}_us"] = f"failed: {type(exc).__name__}: {exc}"[:300]
    return out


def traces_vs_reference(su):
    """Max |optimised - reference| / max |reference| over vx, vz, pressure (forward_elastic's path vs the
    per-cell reference kernels that an active tape selects)."""
    m = {k: v.numpy() for k, v in zip(("vp", "vs", "rho"), su.model)}
    force = su.components.numpy()
    fast = E.forward_elastic(m["vp"], m["vs"], m["rho"], bench.DX, bench.DT, su.amplitudes.numpy(), su.sources.numpy(),
                             su.receivers.numpy(), source_type="force", source_components=force, order=ORDER, pml_width=bench.PML,
                             device=su.prop.device)  # fmt: skip
    data = E._new_data(su, su.nt)
    with wp.Tape():
        E.run_elastic(su, su.prop.new_state(), su.materials(), data, range(su.nt))
    diffs = {}
    for name, ref in zip(E.COMPONENTS, data):
        ref = ref.numpy()
        diffs[name] = float(np.abs(getattr(fast, name) - ref).max() / max(np.abs(ref).max(), 1e-300))
    return {"max_rel_diff": max(diffs.values()), **diffs}


def whole(spec, a, mode, device, repeat):
    cells = bench.padded_cells(spec, ORDER) * spec.shots * a.amplitudes.shape[2]
    observed = np.zeros((spec.shots, a.receivers.shape[1], a.amplitudes.shape[2]))
    fn = lambda: bench.run_elastic(mode, a, device, ORDER, None, observed)  # noqa: E731
    times = []
    for _ in range(repeat):
        sync(device)
        t = time.perf_counter()
        res = fn()
        sync(device)
        times.append(time.perf_counter() - t)
    row = {"mode": mode, "seconds": min(times), "times": times, "gcells_per_s": cells / min(times) / 1e9}
    if mode == "gradient":
        row["segments"] = f"{res.n_segments} x {res.segment_length}"
    return row


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--scenes", nargs="+", default=["E2000", "E600x16"], help="bench.py scenes (ignored with --size)")
    p.add_argument("--size", type=int, help="a custom square elastic scene of this many cells per side instead")
    p.add_argument("--steps", type=int, help="time steps (default: the scene's)")
    p.add_argument("--shots", type=int, default=1, help="shots of the --size scene")
    p.add_argument("--modes", nargs="+", default=list(bench.MODES), choices=bench.MODES)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--reps", type=int, default=0, help="launches per kernel timing (default 200 on CUDA, 5 on the CPU)")
    args = p.parse_args()
    wp.init()
    device = args.device
    reps = args.reps or (200 if wp.get_device(device).is_cuda else 5)
    if args.size:
        specs = [bench.SceneSpec(f"E{args.size}x{args.shots}", "elastic", (args.size, args.size), args.shots, args.steps or 100, True, "custom")]
    else:
        specs = [bench.SCENES[s] for s in args.scenes]
    emit(what="device", device=device, name=wp.get_device(device).name, warp=wp.__version__)
    for spec in specs:
        nt = args.steps or spec.nt
        a = bench.build_arrays(spec, nt)
        w = bench.build_arrays(bench.small_version(spec))
        attempt(spec.name, "warm-up", lambda: {"forward": bench.run_elastic("forward", w, device, ORDER, None) is not None,
                                               "gradient": bench.run_elastic("gradient", w, device, ORDER, None,
                                                                             np.zeros((1, w.receivers.shape[1], w.amplitudes.shape[2]))) is not None})  # fmt: skip
        su = setup(a, device)
        attempt(spec.name, "kernels", lambda: kernel_times(su, device, reps))
        if "gradient" in args.modes:
            attempt(spec.name, "backward", lambda: backward_times(su, device, max(reps // 10, 2)))
        attempt(spec.name, "reference", lambda: traces_vs_reference(su))
        for mode in args.modes:
            attempt(spec.name, "whole", lambda: whole(spec, a, mode, device, args.repeat))


if __name__ == "__main__":
    main()
