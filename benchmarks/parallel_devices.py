"""Several devices for one FWI evaluation (issue 25, items 4 and 6): the wall time of one misfit + gradient evaluation
of SHOTS shots (2D, N x N grid, dx 10 m, NT steps) in one process on one device (fwi's plain loop over shot batches,
observed data and weights resident there, "l2" formed on the device), on 1, 2, ... devices with the threads engine
(adseismic.solve.devices.DevicePool: a thread and a stream per device in this process) and on 1 and all devices with
Dask (solve.distributed.ShotPool, a LocalCluster worker process per device; skipped without dask). Each time is the
best of REPEATS warm evaluations (a first one builds the kernels and captures the graphs); every path's gradient is
compared with the plain one. Prints the efficiency of N devices against the plain path, T1 / (N x TN), the
overhead of each pool on one device against it, and the seconds spent inside solve.acoustic.gradient per device
(the rest of an evaluation is the path's own: dispatch, transfers, reduction). The pools' task (batch_gradient) also
runs in the plain loop, on the main thread without a pool, which separates the task's own cost from the pool's. The
plain path runs again last, so a drift of the device's speed over the run shows beside the pools' overheads. The
batches are fwi's defaults (all shots at once in one process, one batch per device in a pool: solve.pools.pool_shots_per_batch)
unless --per-batch sets one size for every path.

    python benchmarks/parallel_devices.py                       # every GPU of this host (32 shots, < 3 min on H100s)
    python benchmarks/parallel_devices.py --device cpu --cpus 2 --shots 4 --n 150 --nt 800   # CPU threads

--fault adds issue 25's fault check on this host's devices: a Dask pool of max(2, devices) workers (two on one
device where there is one), one warm evaluation, then one during which a worker holding a task is killed
(SIGKILL); its shots run elsewhere and the gradient must equal the fault-free one to the device's summation-order
noise (bit for bit on a CPU).
"""

import argparse
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from adseismic.config.parallel import ParallelConfig  # noqa: E402
from adseismic.solve import distributed  # noqa: E402
from adseismic.solve.acoustic import forward, gradient  # noqa: E402
from adseismic.solve.batch import shot_slices  # noqa: E402
from adseismic.solve.common import init_warp  # noqa: E402
from adseismic.solve.devices import DevicePool  # noqa: E402
from adseismic.wavelets import ricker  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shots", type=int, default=32)
    ap.add_argument("--n", type=int, default=400, help="cells per side (dx 10 m)")
    ap.add_argument("--nt", type=int, default=1000)
    ap.add_argument("--device", default=None, help="cuda (every GPU; the default where there is one) or cpu")
    ap.add_argument("--gpus", type=int, default=None, help="use the first GPUS GPUs (default all)")
    ap.add_argument("--cpus", type=int, default=2, help="--device cpu: the CPU device threads / Dask workers")
    ap.add_argument("--per-batch", type=int, default=None, help="shots per batch (inversion.shots_per_batch) of every path; default: "
                    "each path's own, all shots at once in one process and one batch per device in a pool")
    ap.add_argument("--precision", default="float32")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--no-dask", action="store_true", help="skip the Dask rows")
    ap.add_argument("--fault", action="store_true", help="kill a Dask worker during an evaluation (needs dask)")
    args = ap.parse_args()

    init_warp()
    import warp as wp

    n_gpu = wp.get_cuda_device_count()
    cpu = args.device == "cpu" or (args.device is None and n_gpu == 0)
    devices = ["cpu"] * args.cpus if cpu else [f"cuda:{i}" for i in range(args.gpus or n_gpu)]
    if not devices:
        sys.exit("no CUDA device: give --device cpu")
    n, dx, dt, nt, S = args.n, 10.0, 1e-3, args.nt, args.shots
    z, x = np.meshgrid(np.arange(n) * dx, np.arange(n) * dx, indexing="ij")
    v0 = np.full((n, n), 2000.0)
    v_true = v0 + 200.0 * np.exp(-((z - n * dx / 2) ** 2 + (x - n * dx / 2) ** 2) / (2 * (n * dx / 8) ** 2))
    src = np.stack([[[20.0, xs]] for xs in np.linspace(0.05, 0.95, S) * (n - 1) * dx])
    rec = np.broadcast_to(np.stack([np.full(n // 2, 10.0), np.linspace(0, (n - 1) * dx, n // 2)], axis=1), (S, n // 2, 2)).copy()
    amp = np.broadcast_to(ricker(12.0, nt, dt), (S, 1, nt)).copy()
    kw = dict(order=4, pml_width=20, device=devices[0], precision=args.precision, pml_frequency=6.0, pml_velocity=2400.0)
    t = time.perf_counter()
    obs = forward(v_true, dx, dt, amp, src, rec, **kw).receiver_amplitudes.astype(float)
    w = np.ones_like(obs)
    per = f"{args.per_batch} shot(s) per batch" if args.per_batch else "one batch in one process, one batch per device in a pool"
    print(f"{S} shots, {n} x {n} cells, {nt} steps, {args.precision}, {per}; devices "
          f"{', '.join(devices)}; observed data simulated in {time.perf_counter() - t:.1f} s")  # fmt: skip
    def slices_for(nd):  # the shot batches of a pool of nd devices (0: the single-process loop)
        return shot_slices(S, args.per_batch or (-(-S // nd) if nd else None))

    def batches_for(nd):
        return [{"amplitudes": amp[sl], "sources": src[sl], "receivers": rec[sl], "weights": w[sl], "observed": obs[sl],
                 "first": sl.start} for sl in slices_for(nd)]  # fmt: skip

    slices = slices_for(0)
    params = {"dx": dx, "dt": dt, "misfit": "l2", "illumination": False, "kw": kw}
    resident = [tuple(wp.array(a[sl], dtype=wp.float64, device=devices[0]) for a in (obs, w)) for sl in slices]

    inside = {}  # path -> seconds inside solve.acoustic.gradient in its last evaluation (the rest is the path's own)

    def plain():  # fwi's single-process loop: one batch after the other on one device, data resident there
        loss, grad, spent = 0.0, np.zeros(v0.shape), 0.0
        for sl, (o, ww) in zip(slices, resident):
            t = time.perf_counter()
            r = gradient(v0, dx, dt, amp[sl], src[sl], rec[sl], o, weights=ww, **kw)
            spent += time.perf_counter() - t
            loss, grad = loss + r.loss, grad + r.velocity
        inside["plain"] = spent
        return loss, grad

    def best(fn):
        out = fn()  # warm: kernels built, graphs captured
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return min(times), out

    t1, (loss1, grad1) = best(plain)
    rows = [("one process, one device (plain)", 1, t1, 0.0, inside["plain"])]

    def direct():  # the pools' task (batch_gradient) in the plain loop: on the main thread, no pool, no stream of its own
        rs = [distributed.batch_gradient(v0, dict(b, key=f"direct-{k}"), dict(params, device=devices[0]))
              for k, b in enumerate(batches_for(1))]
        inside["direct"] = sum(r["seconds"] for r in rs)
        return distributed.reduce_in_order(rs, v0.shape)[:2]

    td, (_, grad_d) = best(direct)
    rows.append(("one process, one device (the pools' task)", 1, td, float(np.linalg.norm(grad_d - grad1) / np.linalg.norm(grad1)), inside["direct"]))

    def pooled(name, pool, nd):
        def evaluate():
            rs = pool.evaluate(v0, params)
            inside[name] = sum(r["seconds"] for r in rs) / nd
            return distributed.reduce_in_order(rs, v0.shape)

        with pool:
            pool.keep(batches_for(nd))
            tn, (loss, grad, _) = best(evaluate)
        rows.append((name, nd, tn, float(np.linalg.norm(grad - grad1) / np.linalg.norm(grad1)), inside[name]))

    for nd in range(1, len(devices) + 1):
        pooled(f"threads, {nd} device(s)", DevicePool(ParallelConfig(engine="threads", devices=devices[:nd]), devices[0], S), nd)
    try:
        import distributed as _  # noqa: F401

        dask = not args.no_dask
    except ImportError:
        dask = False
    for nd in sorted({1, len(devices)}) if dask else ():
        pooled(f"Dask, {nd} worker(s)", distributed.ShotPool(ParallelConfig(devices=devices[:nd]), devices[0], S), nd)

    t1_again, _ = best(plain)  # the same path after the pools: how far one device's speed drifted over the run
    rows.append(("one process, one device (plain, again)", 1, t1_again, 0.0, inside["plain"]))

    if dask and args.fault:
        with distributed.ShotPool(ParallelConfig(devices=devices, workers=max(2, len(devices))), devices[0], S) as pool:
            pool.keep(batches_for(len(devices)))
            fault(pool, lambda: pool.evaluate(v0, params), v0.shape)

    print("| path | devices | s an evaluation | efficiency T1 / (N TN) | gradient vs plain (rel. L2) | s inside gradient() a device |")
    print("|---|---|---|---|---|---|")
    for name, nd, tn, err, spent in rows:
        print(f"| {name} | {nd} | {tn:.3f} | {t1 / (nd * tn):.0%} | {err:.1e} | {spent:.3f} |")
    one = {name.split(",")[0]: tn for name, nd, tn, *_ in rows if nd == 1 and "one process" not in name}
    print(f"the plain path again after the pools: {t1_again:.3f} s ({t1_again / t1 - 1:+.1%} against its first measurement); "
          f"the pools' task in the plain loop: {td / t1 - 1:+.1%}")
    print("overhead on one device against the plain path: "
          + ", ".join(f"{k} {v / t1 - 1:+.1%}" for k, v in one.items()) + f"; load average {os.getloadavg()[0]:.2f}")


def fault(pool, evaluate, shape):
    """Kill (SIGKILL) a worker holding a task of an evaluation; print how far the evaluation's misfit and gradient are
    from a fault-free one's, against how far two fault-free ones are apart (the device's summation-order noise: GPU
    gradients accumulate with atomics), and the times."""
    t = time.perf_counter()
    clean = distributed.reduce_in_order(evaluate(), shape)
    t_clean = time.perf_counter() - t
    again = distributed.reduce_in_order(evaluate(), shape)
    pids = pool.client.run(os.getpid)  # {worker address: pid}
    out = {}
    t = time.perf_counter()
    runner = threading.Thread(target=lambda: out.setdefault("rs", evaluate()))
    runner.start()
    victim = None
    while victim is None and runner.is_alive():
        victim = next((a for a in pool.busy() if a in pids), None)
    if victim is None:
        sys.exit("fault: the evaluation ended before a worker could be killed")
    os.kill(pids[victim], signal.SIGKILL)
    runner.join()
    t_fault = time.perf_counter() - t
    loss, grad, _ = distributed.reduce_in_order(out["rs"], shape)

    def apart(a, b):
        return f"misfit {abs(a[0] - b[0]) / abs(b[0]):.1e}, gradient {np.linalg.norm(a[1] - b[1]) / np.linalg.norm(b[1]):.1e}"

    print(f"fault: worker {victim} (pid {pids[victim]}) of {len(pids)} on {sorted(set(pool.devices.values()))} killed during "
          f"an evaluation; its batches ran in pids {sorted({r['pid'] for r in out['rs']})}. Relative to a fault-free "
          f"evaluation: {apart((loss, grad), clean)} (bit for bit: {loss == clean[0] and np.array_equal(grad, clean[1])}); "
          f"two fault-free ones: {apart(again, clean)}. Evaluation {t_fault:.2f} s against {t_clean:.2f} s without the fault")

if __name__ == "__main__":
    main()
