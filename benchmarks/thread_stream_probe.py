"""Is solve.acoustic.gradient slower off the main thread or on a second stream (issue 25: the threads engine's
one-GPU overhead)? One shot's gradient (N x N cells, dx 10 m, NT steps, float32, observed data and weights resident
on the device as fwi keeps them) timed for SHOTS shots in a row four ways: on the main thread and on a worker thread
(a single-thread executor, as solve.devices.DevicePool runs a device), each on the device's current stream and under
wp.ScopedStream of a new stream (the pool's way). Best of 3 per way, two rounds in turn.

    python benchmarks/thread_stream_probe.py                  # cuda:0, 400^2, 1000 steps, 8 shots
"""

import argparse
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from adseismic.solve.acoustic import forward, gradient  # noqa: E402
from adseismic.solve.common import init_warp  # noqa: E402
from adseismic.wavelets import ricker  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--n", type=int, default=400)
    ap.add_argument("--nt", type=int, default=1000)
    ap.add_argument("--shots", type=int, default=8)
    args = ap.parse_args()
    init_warp()
    import warp as wp

    n, dx, dt, nt, S, dev = args.n, 10.0, 1e-3, args.nt, args.shots, args.device
    v0 = np.full((n, n), 2000.0)
    v1 = v0.copy()
    v1[3 * n // 8 : 5 * n // 8, 3 * n // 8 : 5 * n // 8] = 2200.0
    src = np.stack([[[20.0, xs]] for xs in np.linspace(0.05, 0.95, S) * (n - 1) * dx])
    rec = np.broadcast_to(np.stack([np.full(n // 2, 10.0), np.linspace(0, (n - 1) * dx, n // 2)], axis=1), (S, n // 2, 2)).copy()
    amp = np.broadcast_to(ricker(12.0, nt, dt), (S, 1, nt)).copy()
    kw = dict(order=4, pml_width=20, device=dev, precision="float32", pml_frequency=6.0, pml_velocity=2400.0)
    obs = forward(v1, dx, dt, amp, src, rec, **kw).receiver_amplitudes.astype(float)
    def on_device(a):
        return wp.array(a, dtype=wp.float64, device=dev)

    resident = [(on_device(obs[i : i + 1]), on_device(np.ones_like(obs[i : i + 1]))) for i in range(S)]

    def shots():
        t = time.perf_counter()
        for i, (o, w) in enumerate(resident):
            gradient(v0, dx, dt, amp[i : i + 1], src[i : i + 1], rec[i : i + 1], o, weights=w, **kw)
        return time.perf_counter() - t

    stream = wp.Stream(dev) if wp.get_device(dev).is_cuda else None

    def scoped():
        if stream is None:
            return shots()
        with wp.ScopedStream(stream):
            return shots()

    pool = ThreadPoolExecutor(1)
    ways = {"main thread, device stream": shots, "main thread, new stream": scoped,
            "worker thread, device stream": lambda: pool.submit(shots).result(),
            "worker thread, new stream": lambda: pool.submit(scoped).result()}  # fmt: skip
    for fn in ways.values():
        fn()  # warm: kernels built, loops captured
    print(f"{S} shots, {n} x {n} cells, {nt} steps, float32, {dev}: ms a shot, best of 3 (each of the 3)")
    for _ in range(2):
        for name, fn in ways.items():
            ts = [fn() / S * 1e3 for _ in range(3)]
            print(f"  {name:30s} {min(ts):7.2f}  ({', '.join(f'{t:.2f}' for t in ts)})")


if __name__ == "__main__":
    main()
