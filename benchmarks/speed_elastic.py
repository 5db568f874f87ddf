"""Check and time the 2D elastic propagator on one device: per-kernel microseconds (CUDA-graph replays on
a GPU, a synchronised loop on the CPU), with --variants every core layout of kernels/elastic.LAYOUTS (its vector
width, half steps and whole step, and its step against the per-cell reference kernels on random fields), one
step's adjoint (with --modes gradient: the hand-written one with the device's AdjointLayout, each of its launches,
the per-cell kernels', and Warp's generated adjoints), with --adjoint-variants every AdjointLayout of
kernels/elastic.ADJOINT_LAYOUTS (its adjoint step and launches, and its step against the per-cell kernels' on
random fields), the whole forward_elastic / gradient_elastic calls as adseismic/bench.py runs them (best of
--repeat after a warm-up that compiles the kernels; the forward with the model on the host and on the device) in
Gcell/s (padded cells x steps x shots / s), and the optimised traces against the per-cell reference kernels. One
JSON line per measurement; a failing measurement prints its error and the others still run.

    python benchmarks/speed_elastic.py --device cuda:0 --scenes E2000 E600x16 --modes forward --variants
    python benchmarks/speed_elastic.py --device cuda:0 --scenes E2000 E600x16 --modes gradient --adjoint-variants
    python benchmarks/speed_elastic.py --device cpu --size 60 --steps 20 --modes forward --variants
"""

import argparse
import dataclasses
import json
import time
import traceback

import numpy as np
import warp as wp

import adseismic.solve.elastic as E
from adseismic import bench
from adseismic.accel.reductions import field_stats
from adseismic.kernels.elastic import ADJOINT_LAYOUTS, CORE_LAYOUT, LAYOUTS
from adseismic.solve.loop import run_levels

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


def timings(jobs, device, reps):
    """{name + "_us": per_call_us(fn)} for the jobs {name: fn}, a failure recorded in place of its time."""
    out = {}
    for name, fn in jobs.items():
        try:
            out[name + "_us"] = round(per_call_us(fn, device, reps), 2)
        except Exception as exc:
            out[name + "_us"] = f"failed: {type(exc).__name__}: {exc}"[:300]
    return out


def setup(a, device):
    force = np.broadcast_to([1.0, 0.0], (*a.sources.shape[:2], 2))
    m = a.model
    return E.setup_elastic(m["vp"], m["vs"], m["rho"], bench.DX, bench.DT, a.amplitudes, a.sources, a.receivers, source_type="force",
                           source_components=force, order=ORDER, pml_width=bench.PML, device=device)  # fmt: skip


def kernel_times(su, device, reps):
    """The default layout's step and its parts, the reference kernels, and the step's other kernels."""
    prop, k = su.prop, su.prop.k
    st, other, mat = prop.new_state(), prop.new_state(), su.model()
    data = su.new_data(su.nt)
    src = su.sources_of(su.amplitudes, fixed=False)
    bx, bz = mat[0], mat[1]
    jobs = {
        "step_in_place": lambda: prop.step(st, mat, src, 0),
        "velocity_reference": lambda: prop.update(0, st, other, mat, generated=True),
        "stress_reference": lambda: prop.update(1, st, other, mat, generated=True),
        "velocity_update": lambda: prop.update(0, st, st, mat),
        "stress_update": lambda: prop.update(1, st, st, mat),
        "velocity_core": lambda: prop.update(0, st, st, mat, part="core"),
        "stress_core": lambda: prop.update(1, st, st, mat, part="core"),
        "velocity_frame": lambda: prop.update(0, st, st, mat, part="frame"),
        "stress_frame": lambda: prop.update(1, st, st, mat, part="frame"),
        "record": lambda: prop.record(st, data, su.receiver_op, 3),
        "inject_force": lambda: wp.launch(k.inject_force, dim=(prop.n_shots, su.sources.shape[1], k.operator_points),
                                          inputs=[st.vx, st.vz, bx, bz, su.amplitudes, su.components, su.sources, 3, prop.clock, prop.origin,
                                                  prop.dtype(prop.dt / prop.dx**2), prop.inv_dx, prop.top], device=device),  # fmt: skip
        "monitor": lambda: field_stats((st.vx, st.vz), wp.zeros(2, dtype=prop.dtype, device=device)),
    }
    out = {"layout": CORE_LAYOUT._asdict(), "width": prop.width, "core_cells": int((prop.core[1] - prop.core[0]) * (prop.core[3] - prop.core[2])),
           "frame_cells": prop.frame_cells, **timings(jobs, device, reps)}  # fmt: skip
    if isinstance(out["step_in_place_us"], float):
        out["step_gcells_per_s"] = round(prop.n_shots * np.prod(prop.padded) / out["step_in_place_us"] / 1e3, 3)
    return out


def random_materials(prop, rng):
    """MATERIALS of a random model on prop's padded grid, with a fluid patch (zero shear moduli)."""
    shape = prop.padded
    vp = 2000.0 + 400.0 * rng.random(shape)
    vs = vp / 1.8 * (0.7 + 0.3 * rng.random(shape))
    vs[: shape[0] // 3, : shape[1] // 3] = 0.0
    rho = 1800.0 + 500.0 * rng.random(shape)
    return prop.materials(*(wp.array(m, dtype=prop.dtype, device=prop.device) for m in (vp, vs, rho)))


def random_state(prop, rng):
    """A State of standard normal fields and memory variables."""
    st = prop.new_state()
    for a in st.arrays():
        a.assign(rng.standard_normal(a.shape, dtype=np.float32))
    return st


class VariantCheck:
    """Random fields, CPML memory variables and model (with a fluid patch) on su's grid, and the per-cell
    reference kernels' step from them (no source), for checking each layout's in-place step."""

    def __init__(self, su, seed=11):
        prop = self.prop = su.prop
        rng = np.random.default_rng(seed)
        self.mat = random_materials(prop, rng)
        self.start = random_state(prop, rng)
        self.ref = prop.new_state()
        self.copy(self.ref)  # cells the reference does not write (halo) keep their values, as in place
        with wp.Tape():  # an active tape selects the reference kernels
            prop.step(self.start, self.mat, None, 0, out=self.ref)
        self.expected = [a.numpy() for a in self.ref.arrays()]
        self.work = prop.new_state()

    def copy(self, st):
        for dst, src in zip(st.arrays(), self.start.arrays()):
            wp.copy(dst, src)

    def max_rel_diff(self):
        """max over fields and memory variables of max |step - reference| / max |reference|, the step in place
        with the propagator's current layout."""
        self.copy(self.work)
        self.prop.step(self.work, self.mat, None, 0)
        return max(float(np.abs(a.numpy() - b).max() / max(np.abs(b).max(), 1e-30)) for a, b in zip(self.work.arrays(), self.expected))


def variant_times(check, layout, device, reps):
    """One layout: its half steps as launched, their core parts alone, its whole step, and its step's difference
    from the reference kernels."""
    prop, mat, st = check.prop, check.mat, check.work
    prop.layout = layout
    try:
        out = {"layout": layout._asdict(), "width": prop.width, "max_rel_diff": check.max_rel_diff()}
        jobs = {
            "velocity": lambda: prop.update(0, st, st, mat),
            "stress": lambda: prop.update(1, st, st, mat),
            "velocity_core": lambda: prop.update(0, st, st, mat, part="core"),
            "stress_core": lambda: prop.update(1, st, st, mat, part="core"),
            "step": lambda: prop.step(st, mat, None, 0),
        }
        out.update(timings(jobs, device, reps))
    finally:
        prop.layout = CORE_LAYOUT
    if isinstance(out["step_us"], float):
        out["step_gcells_per_s"] = round(prop.n_shots * np.prod(prop.padded) / out["step_us"] / 1e3, 3)
    return out


def adjoint_jobs(prop, st, nxt, mat, adj, adj_mat, src, adj_src, scratch):
    """Timing jobs of the hand-written adjoint step with prop.adjoint_layout: the whole Elastic.adjoint_step (as
    adseismic.solve.elastic.Levels launches it, without the receivers' adjoint) and each half step's launches
    (Elastic.adjoint_update's parts: pass 1, pass 2 and, fused, pass 2's tiles alone and, split, the sums' tiles)."""
    jobs = {"step_backward_hand": lambda: prop.adjoint_step(st, nxt, mat, adj, adj_mat, src, adj_src, scratch, 3)}
    lay = prop.adjoint_layout
    parts = ("pass1", "pass2") + (("tiles",) if lay else ()) + (("sums",) if lay and lay.split else ())
    for kind, half in ((1, "stress"), (0, "velocity")):
        for part in parts:
            jobs[f"{half}_adjoint_{part}"] = lambda kind=kind, part=part: prop.adjoint_update(kind, st, nxt, mat, adj, adj_mat,
                                                                                               scratch, part)  # fmt: skip
    return jobs


def backward_times(su, device, reps):
    """Microseconds of one step's adjoint: the hand-written one and its launches (adjoint_jobs) with the device's
    AdjointLayout, the per-cell kernels' whole step (step_backward_cells, the CPU's path), and the backward of one
    taped step with Warp's generated adjoints."""
    prop, located = su.prop, su.sources_of(su.amplitudes, fixed=False)
    src = (*located[:3], prop.operator(located[3]))  # as the sweep injects sources whose locations are not differentiated

    def zeros(shape):
        return wp.zeros(shape, dtype=prop.dtype, device=device)

    st, nxt, adj = (prop.new_state() for _ in range(3))
    mat = su.model()
    prop.step(st, mat, src, 3, out=nxt)
    adj_mat = [zeros(prop.padded) for _ in mat[:-1]]
    adj_src = [zeros(a.shape) for a in located[1:]]
    scratch = [zeros((prop.n_shots, *prop.padded)) for _ in range(4)]
    a, b = prop.new_state(requires_grad=True), prop.new_state(requires_grad=True)
    tape = wp.Tape()
    with tape:
        prop.step(a, su.model(on_tape=True), src, 3, out=b)
    layout = prop.adjoint_layout
    out = {"adjoint_layout": layout._asdict() if layout else None}
    out.update(timings({**adjoint_jobs(prop, st, nxt, mat, adj, adj_mat, src, adj_src, scratch), "step_backward_warp": tape.backward},
                       device, reps))  # fmt: skip
    prop.adjoint_layout = None
    try:
        out.update(timings({"step_backward_cells": lambda: prop.adjoint_step(st, nxt, mat, adj, adj_mat, src, adj_src, scratch, 3)},
                           device, reps))  # fmt: skip
    finally:
        prop.adjoint_layout = layout
    return out


class AdjointCheck:
    """Random states, adjoint States, model (with a fluid patch) and materials' adjoints on su's grid, and the per-cell
    kernels' adjoint step (no source) from them, for checking each AdjointLayout's."""

    def __init__(self, su, seed=12):
        prop = self.prop = su.prop
        rng = np.random.default_rng(seed)
        self.mat = random_materials(prop, rng)
        self.st, self.nxt = random_state(prop, rng), prop.new_state()
        prop.step(self.st, self.mat, None, 0, out=self.nxt)
        self.start = random_state(prop, rng).arrays()
        self.start += [wp.array(rng.standard_normal(prop.padded, dtype=np.float32), dtype=prop.dtype, device=prop.device) for _ in self.mat[:-1]]
        self.adj = prop.new_state()
        self.adj_mat = [wp.empty(prop.padded, dtype=prop.dtype, device=prop.device) for _ in self.mat[:-1]]
        self.scratch = [wp.zeros((prop.n_shots, *prop.padded), dtype=prop.dtype, device=prop.device) for _ in range(4)]
        layout = prop.adjoint_layout
        prop.adjoint_layout = None
        try:
            self.expected = [a.numpy() for a in self.run()]
        finally:
            prop.adjoint_layout = layout

    def outputs(self):
        return [*self.adj.arrays(), *self.adj_mat]

    def run(self):
        """One adjoint step from the start values with the propagator's current AdjointLayout; its outputs."""
        for dst, src in zip(self.outputs(), self.start):
            wp.copy(dst, src)
        self.prop.adjoint_step(self.st, self.nxt, self.mat, self.adj, self.adj_mat, None, (), self.scratch, 0)
        return self.outputs()

    def max_rel_diff(self):
        """max over the outputs of max |step - per-cell step| / max |per-cell step|."""
        return max(float(np.abs(a.numpy() - b).max() / max(np.abs(b).max(), 1e-30)) for a, b in zip(self.run(), self.expected))


def adjoint_variant_times(check, layout, device, reps):
    """One AdjointLayout: its adjoint step's difference from the per-cell kernels' and its timing jobs (adjoint_jobs)."""
    prop = check.prop
    default, prop.adjoint_layout = prop.adjoint_layout, layout
    try:
        if not prop.has_adjoint_box:
            raise ValueError("the grid has no adjoint box")
        out = {"layout": layout._asdict(), "max_rel_diff": check.max_rel_diff()}
        out.update(timings(adjoint_jobs(prop, check.st, check.nxt, check.mat, check.adj, check.adj_mat, None, (), check.scratch),
                           device, reps))  # fmt: skip
    finally:
        prop.adjoint_layout = default
    if isinstance(out["step_backward_hand_us"], float):
        out["step_gcells_per_s"] = round(prop.n_shots * np.prod(prop.padded) / out["step_backward_hand_us"] / 1e3, 3)
    return out


def traces_vs_reference(su):
    """Max |optimised - reference| / max |reference| over vx, vz, pressure (forward_elastic's path vs the
    per-cell reference kernels that an active tape selects)."""
    m = {k: v.numpy() for k, v in zip(("vp", "vs", "rho"), su.models)}
    force = su.components.numpy()
    fast = E.forward_elastic(m["vp"], m["vs"], m["rho"], bench.DX, bench.DT, su.amplitudes.numpy(), su.sources.numpy(),
                             su.receivers.numpy(), source_type="force", source_components=force, order=ORDER, pml_width=bench.PML,
                             device=su.prop.device)  # fmt: skip
    data = su.new_data(su.nt)
    with wp.Tape():
        run_levels(su, su.prop.new_state(), su.model(), data, range(su.nt))
    diffs = {}
    for name, ref in zip(E.COMPONENTS, data):
        ref = ref.numpy()
        diffs[name] = float(np.abs(getattr(fast, name) - ref).max() / max(np.abs(ref).max(), 1e-300))
    return {"max_rel_diff": max(diffs.values()), **diffs}


def whole(spec, a, mode, device, repeat, model_on_device=False):
    """bench.run_elastic timed; model_on_device: vp, vs, rho passed as float32 Warp arrays on the device."""
    cells = bench.padded_cells(spec, ORDER) * spec.shots * a.amplitudes.shape[2]
    if model_on_device:
        a = dataclasses.replace(a, model={k: wp.array(v, dtype=wp.float32, device=device) for k, v in a.model.items()})
    observed = np.zeros((spec.shots, a.receivers.shape[1], a.amplitudes.shape[2]))
    fn = lambda: bench.run_elastic(mode, a, device, ORDER, None, observed)  # noqa: E731
    times = []
    for _ in range(repeat):
        sync(device)
        t = time.perf_counter()
        res = fn()
        sync(device)
        times.append(time.perf_counter() - t)
    row = {"mode": mode, "model": "device" if model_on_device else "host", "seconds": min(times), "times": times,
           "gcells_per_s": cells / min(times) / 1e9}  # fmt: skip
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
    p.add_argument("--variants", action="store_true", help="time and check every layout of kernels/elastic.LAYOUTS")
    p.add_argument("--adjoint-variants", action="store_true", help="time and check every layout of kernels/elastic.ADJOINT_LAYOUTS")
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

        def warm_up():
            out = {"forward": bench.run_elastic("forward", w, device, ORDER, None) is not None}
            if "gradient" in args.modes:
                observed = np.zeros((1, w.receivers.shape[1], w.amplitudes.shape[2]))
                out["gradient"] = bench.run_elastic("gradient", w, device, ORDER, None, observed) is not None
            return out

        attempt(spec.name, "warm-up", warm_up)
        su = setup(a, device)
        attempt(spec.name, "kernels", lambda: kernel_times(su, device, reps))
        if args.variants:
            checks, rows = [], []  # the VariantCheck, once made; the variants' rows

            def make_check():
                checks.append(VariantCheck(su))
                return {"reference_step": "done"}

            def variant(layout):
                rows.append(variant_times(checks[0], layout, device, reps))
                return rows[-1]

            attempt(spec.name, "variant-check", make_check)
            for layout in LAYOUTS if checks else ():
                attempt(spec.name, "variant", lambda: variant(layout))
            checks.clear()  # frees its fields before the whole runs
            timed = [r for r in rows if isinstance(r.get("step_us"), float)]
            if timed:
                best = min(timed, key=lambda r: r["step_us"])
                emit(scene=spec.name, what="variant-best", layout=best["layout"], step_us=best["step_us"], max_rel_diff=best["max_rel_diff"])
        if "gradient" in args.modes:
            attempt(spec.name, "backward", lambda: backward_times(su, device, max(reps // 10, 2)))
        if args.adjoint_variants:
            checks, rows = [], []

            def make_adjoint_check():
                checks.append(AdjointCheck(su))
                return {"reference_adjoint_step": "done"}

            def adjoint_variant(layout):
                rows.append(adjoint_variant_times(checks[0], layout, device, max(reps // 10, 2)))
                return rows[-1]

            attempt(spec.name, "adjoint-variant-check", make_adjoint_check)
            for layout in ADJOINT_LAYOUTS if checks else ():
                attempt(spec.name, "adjoint-variant", lambda: adjoint_variant(layout))
            checks.clear()
            timed = [r for r in rows if isinstance(r.get("step_backward_hand_us"), float)]
            if timed:
                best = min(timed, key=lambda r: r["step_backward_hand_us"])
                emit(scene=spec.name, what="adjoint-variant-best", layout=best["layout"], step_us=best["step_backward_hand_us"],
                     max_rel_diff=best["max_rel_diff"])  # fmt: skip
        attempt(spec.name, "reference", lambda: traces_vs_reference(su))
        for mode in args.modes:
            attempt(spec.name, "whole", lambda: whole(spec, a, mode, device, args.repeat))
            if mode == "forward":
                attempt(spec.name, "whole", lambda: whole(spec, a, mode, device, args.repeat, model_on_device=True))


if __name__ == "__main__":
    main()
