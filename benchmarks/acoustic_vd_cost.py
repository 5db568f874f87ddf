"""Step time of physics acoustic_vd's own kernel (adseismic.solve.acoustic_vd) beside constant-density acoustic and the
old path, the 2D elastic kernels with vs = 0 (3D: the 3D elastic kernels with vs = 0): one shot, order 4, PML 20 cells,
300 steps (3D: 100), float32, best of 3 after a warm-up run that compiles the kernels (docs/acoustic_vd.md, "cost").

    python benchmarks/acoustic_vd_cost.py [--device cuda:0] [--sizes 100 200 400] [--sizes3d 60]
"""

import argparse
import time

import numpy as np

from adseismic.solve.acoustic import forward
from adseismic.solve.acoustic_vd import forward_acoustic_vd
from adseismic.solve.elastic import forward_elastic
from adseismic.solve.elastic3d import forward_elastic3d
from adseismic.wavelets import ricker


def best(run, repeats=3):
    run()  # warm-up: compiles
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        run()
        times.append(time.perf_counter() - t)
    return min(times)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", type=int, nargs="*", default=[100, 200, 400])
    ap.add_argument("--sizes3d", type=int, nargs="*", default=[60])
    args = ap.parse_args()
    dx, dt = 10.0, 1e-3
    kw = dict(order=4, pml_width=20, precision="float32", device=args.device)
    print("| grid | acoustic (ms/step) | acoustic_vd (ms/step) | elastic, vs = 0 (ms/step) | vd / acoustic | elastic / vd |")
    print("|---|---|---|---|---|---|")
    for ndim, sizes, nt in ((2, args.sizes, 300), (3, args.sizes3d, 100)):
        for n in sizes:
            shape = (n,) * ndim
            vp, rho = np.full(shape, 2000.0), np.full(shape, 2000.0)
            amp = ricker(10.0, nt, dt)[None, None]
            src = np.full((1, 1, ndim), n * dx / 2)
            rec = src + 100.0
            el = forward_elastic if ndim == 2 else forward_elastic3d
            t = [best(lambda: forward(vp, dx, dt, amp, src, rec, **kw)),
                 best(lambda: forward_acoustic_vd(vp, rho, dx, dt, amp, src, rec, **kw)),
                 best(lambda: el(vp, 0 * vp, rho, dx, dt, amp, src, rec, source_type="explosive", **kw))]
            ms = [1e3 * x / nt for x in t]
            print(f"| {' x '.join([str(n)] * ndim)} | {ms[0]:.2f} | {ms[1]:.2f} | {ms[2]:.2f} | {ms[1] / ms[0]:.1f}x | {ms[2] / ms[1]:.1f}x |",
                  flush=True)


if __name__ == "__main__":
    main()
