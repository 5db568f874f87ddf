"""Shot parallelism on Dask (issue 25, item 6): the wall time of one misfit + gradient evaluation of SHOTS shots on
an N x N grid in one process (one batch per shot, and all shots in one batch) and on a LocalCluster of 1 and of
WORKERS Dask workers (adseismic.solve.distributed.ShotPool, one shot per batch, data resident on the workers), each
the best of REPEATS warm evaluations; prints the efficiency of WORKERS workers against the best one-process time
(T1 / (WORKERS x TW)) and the Dask overhead on one worker.

    python benchmarks/dask_shots.py --shots 4 --n 150 --device cpu --workers 2 [--per-batch 2]
"""

import argparse
import os
import time

import numpy as np

from adseismic.config.parallel import ParallelConfig
from adseismic.solve import distributed
from adseismic.solve.acoustic import forward, gradient
from adseismic.wavelets import ricker


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shots", type=int, default=4)
    ap.add_argument("--n", type=int, default=150, help="cells per side (dx 10 m)")
    ap.add_argument("--nt", type=int, default=800)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--precision", default="float32")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--per-batch", type=int, default=1, help="shots per batch on the workers (inversion.shots_per_batch)")
    args = ap.parse_args()

    n, dx, dt, nt = args.n, 10.0, 1e-3, args.nt
    z, x = np.meshgrid(np.arange(n) * dx, np.arange(n) * dx, indexing="ij")
    v0 = np.full((n, n), 2000.0)
    v_true = v0 + 200.0 * np.exp(-((z - n * dx / 2) ** 2 + (x - n * dx / 2) ** 2) / (2 * (n * dx / 8) ** 2))
    src = np.stack([[[20.0, xs]] for xs in np.linspace(0.1, 0.9, args.shots) * (n - 1) * dx])
    rec = np.broadcast_to(np.stack([np.full(n // 2, 10.0), np.linspace(0, (n - 1) * dx, n // 2)], axis=1), (args.shots, n // 2, 2)).copy()
    amp = np.broadcast_to(ricker(12.0, nt, dt), (args.shots, 1, nt)).copy()
    kw = dict(order=4, pml_width=20, device=args.device, precision=args.precision)
    obs = forward(v_true, dx, dt, amp, src, rec, **kw).receiver_amplitudes.astype(float)
    w = np.ones_like(obs)

    def one_process(per_batch):
        loss, grad = 0.0, np.zeros(v0.shape)
        for s0 in range(0, args.shots, per_batch):
            sl = slice(s0, s0 + per_batch)
            r = gradient(v0, dx, dt, amp[sl], src[sl], rec[sl], obs[sl], **kw)
            loss, grad = loss + r.loss, grad + r.velocity
        return loss, grad

    def best(fn):
        fn()  # warm: kernels loaded, caches filled
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return min(times)

    t_shot = best(lambda: one_process(1))
    t_all = best(lambda: one_process(args.shots))
    print(f"one process, one batch per shot: {t_shot:.2f} s; all {args.shots} shots in one batch: {t_all:.2f} s")
    sls = [slice(k, k + args.per_batch) for k in range(0, args.shots, args.per_batch)]
    batches = [{"amplitudes": amp[sl], "sources": src[sl], "receivers": rec[sl], "weights": w[sl], "observed": obs[sl],
                "first": sl.start} for sl in sls]  # fmt: skip
    params = {"dx": dx, "dt": dt, "misfit": "l2", "illumination": False, "kw": kw}
    t_pool = {}
    for nw in sorted({1, args.workers}):
        dev = [args.device] if args.device == "cpu" else [f"cuda:{i}" for i in range(nw)]
        with distributed.ShotPool(ParallelConfig(devices=dev, workers=nw), args.device, args.shots) as pool:
            pool.keep(batches)
            t_pool[nw] = best(lambda: pool.evaluate(v0, params))
        print(f"Dask, {nw} worker(s), {args.per_batch} shot(s) per batch: {t_pool[nw]:.2f} s")
    t1 = min(t_shot, t_all)
    print(f"efficiency of {args.workers} workers against one process: {t1 / (args.workers * t_pool[args.workers]):.0%} "
          f"(speed-up {t1 / t_pool[args.workers]:.2f}); Dask overhead on 1 worker: {t_pool[1] / t_shot - 1:+.1%} against "
          f"one batch per shot in one process; load average {os.getloadavg()[0]:.2f} at the end")  # fmt: skip


if __name__ == "__main__":
    main()
