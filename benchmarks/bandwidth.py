"""The device memory bandwidth a Warp kernel reaches: streaming kernels that read 1, 2 or 4 float32 arrays and
write one (64 Mi elements an array, far past the L2 cache), timed over repeated launches after a warm one. The bound
the speed targets are measured against (docs/benchmarks.md). One JSON line per kernel: bytes moved a launch, us a
launch, GB/s.

    python benchmarks/bandwidth.py --device cuda:0 [--n 67108864] [--repeats 50]
"""

import argparse
import json
import time

import warp as wp


@wp.kernel
def copy1(a: wp.array(dtype=float), o: wp.array(dtype=float)):
    i = wp.tid()
    o[i] = a[i]


@wp.kernel
def sum2(a: wp.array(dtype=float), b: wp.array(dtype=float), o: wp.array(dtype=float)):
    i = wp.tid()
    o[i] = a[i] + b[i]


@wp.kernel
def sum4(a: wp.array(dtype=float), b: wp.array(dtype=float), c: wp.array(dtype=float), d: wp.array(dtype=float), o: wp.array(dtype=float)):
    i = wp.tid()
    o[i] = (a[i] + b[i]) + (c[i] + d[i])


def timed(launch, dev, repeats: int) -> float:
    """Microseconds a call of launch() takes on dev: one warm call, then the mean of `repeats` calls between syncs."""
    launch()
    wp.synchronize_device(dev)
    t0 = time.perf_counter()
    for _ in range(repeats):
        launch()
    wp.synchronize_device(dev)
    return (time.perf_counter() - t0) * 1e6 / repeats


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--n", type=int, default=1 << 26, help="elements an array")
    ap.add_argument("--repeats", type=int, default=50)
    a = ap.parse_args()
    wp.init()
    dev = wp.get_device(a.device)
    arrays = [wp.full(a.n, 1.0, dtype=float, device=dev) for _ in range(5)]
    for kernel, k in ((copy1, 1), (sum2, 2), (sum4, 4)):
        inputs = [*arrays[:k], arrays[4]]
        us = timed(lambda: wp.launch(kernel, dim=a.n, inputs=inputs, device=dev), dev, a.repeats)
        moved = (k + 1) * 4 * a.n
        row = dict(kernel=kernel.key, device=dev.name, arrays_read=k, bytes=moved, us=round(us, 1), GB_s=round(moved / us / 1e3, 1))
        print(json.dumps(row))


if __name__ == "__main__":
    main()
