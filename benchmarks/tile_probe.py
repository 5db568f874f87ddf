"""Can Warp's tile API stage a stencil in shared memory as fast as per-thread code reads it from the caches? The
interior update of the 2D constant-density acoustic step (order 4, u_next = 2u - u_prev + w Lap u on every cell of a
padded (S, Lz, Lx) grid but its halo), timed three ways on one device: one cell a thread; a block's tile of u plus
its halo loaded into shared memory (`wp.tile_load(storage="shared")`), each thread reading its cells' neighbours
there; and the same tile loaded then its cells computed as whole-tile operations on shifted views
(`wp.tile_view`). The three outputs are compared, and each rate is set against the 12 bytes a cell the step must
move (u, u_prev read, u_next written; w, the model, is shared by the shots and read from L2 when there are several;
with one shot on a large grid it adds 4 B a cell, which the 12 B leave out). The probe of the kernel redesign that
docs/benchmarks.md's "open speed targets" section ends with; it is not the adseismic propagator.

    python benchmarks/tile_probe.py --device cuda:0 [--shots 16] [--n 640]
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bandwidth import timed  # noqa: E402

R = 2  # order 4
A0, A1, A2 = -2.5, 4.0 / 3.0, -1.0 / 12.0  # second-derivative weights, per axis
TZ, TX = 16, 64  # a block's output tile
HZ, HX = TZ + 2 * R, TX + 2 * R  # with its halo
BLOCK = 256


@wp.kernel
def per_cell(u: wp.array3d(dtype=float), up: wp.array3d(dtype=float), w: wp.array2d(dtype=float), un: wp.array3d(dtype=float)):
    s, zi, xi = wp.tid()
    z = zi + R
    x = xi + R
    c = u[s, z, x]
    lap = 2.0 * A0 * c + A1 * (u[s, z - 1, x] + u[s, z + 1, x] + u[s, z, x - 1] + u[s, z, x + 1])
    lap += A2 * (u[s, z - 2, x] + u[s, z + 2, x] + u[s, z, x - 2] + u[s, z, x + 2])
    un[s, z, x] = 2.0 * c - up[s, z, x] + w[z, x] * lap


def make_staged(tz: int, tx: int):
    """The shared-memory tile kernel for output tiles of tz x tx cells."""
    hz, hx = tz + 2 * R, tx + 2 * R

    @wp.kernel(module="unique")
    def staged(u: wp.array3d(dtype=float), up: wp.array3d(dtype=float), w: wp.array2d(dtype=float), un: wp.array3d(dtype=float)):
        s, bz, bx, lane = wp.tid()
        z0 = bz * tz
        x0 = bx * tx
        t = wp.tile_load(u, shape=(1, hz, hx), offset=(s, z0, x0), storage="shared")
        nb = wp.block_dim()
        for k in range((tz * tx + nb - 1) // nb):
            q = lane + k * nb
            if q < tz * tx:
                i = q // tx + R
                j = q % tx + R
                c = t[0, i, j]
                lap = 2.0 * A0 * c + A1 * (t[0, i - 1, j] + t[0, i + 1, j] + t[0, i, j - 1] + t[0, i, j + 1])
                lap += A2 * (t[0, i - 2, j] + t[0, i + 2, j] + t[0, i, j - 2] + t[0, i, j + 2])
                z = z0 + i
                x = x0 + j
                un[s, z, x] = 2.0 * c - up[s, z, x] + w[z, x] * lap

    return staged


STAGED = [(16, 64, 256), (32, 64, 256), (16, 128, 256), (32, 128, 512), (8, 256, 256), (64, 64, 512)]  # (rows, columns, threads)


@wp.kernel
def whole_tile(u: wp.array3d(dtype=float), up: wp.array3d(dtype=float), w: wp.array2d(dtype=float), un: wp.array3d(dtype=float)):
    s, bz, bx = wp.tid()
    z0 = bz * TZ
    x0 = bx * TX
    t = wp.tile_load(u, shape=(1, HZ, HX), offset=(s, z0, x0), storage="shared")

    c = wp.tile_view(t, offset=(0, R, R), shape=(1, TZ, TX))
    near = wp.tile_view(t, offset=(0, R - 1, R), shape=(1, TZ, TX)) + wp.tile_view(t, offset=(0, R + 1, R), shape=(1, TZ, TX))
    near += wp.tile_view(t, offset=(0, R, R - 1), shape=(1, TZ, TX)) + wp.tile_view(t, offset=(0, R, R + 1), shape=(1, TZ, TX))
    far = wp.tile_view(t, offset=(0, R - 2, R), shape=(1, TZ, TX)) + wp.tile_view(t, offset=(0, R + 2, R), shape=(1, TZ, TX))
    far += wp.tile_view(t, offset=(0, R, R - 2), shape=(1, TZ, TX)) + wp.tile_view(t, offset=(0, R, R + 2), shape=(1, TZ, TX))
    lap = c * (2.0 * A0) + near * A1 + far * A2
    p = wp.tile_load(up, shape=(1, TZ, TX), offset=(s, z0 + R, x0 + R))
    m = wp.tile_load(w, shape=(TZ, TX), offset=(z0 + R, x0 + R))
    out = c * 2.0 - p + wp.tile_map(wp.mul, wp.tile_reshape(m, shape=(1, TZ, TX)), lap)
    wp.tile_store(un, out, offset=(s, z0 + R, x0 + R))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--shots", type=int, default=16)
    ap.add_argument("--n", type=int, default=640, help="interior cells a side (a multiple of 64)")
    ap.add_argument("--repeats", type=int, default=200)
    a = ap.parse_args()
    if a.n % TX or a.n % TZ:
        raise SystemExit(f"--n {a.n}: give a multiple of {TX}")  # whole_tile's tiles; staged shapes that do not divide n are skipped
    wp.init()
    dev = wp.get_device(a.device)
    rng = np.random.default_rng(0)
    shape = (a.shots, a.n + 2 * R, a.n + 2 * R)
    u = wp.array(rng.standard_normal(shape).astype(np.float32), device=dev)
    up = wp.array(rng.standard_normal(shape).astype(np.float32), device=dev)
    w = wp.array(rng.uniform(0.1, 0.2, shape[1:]).astype(np.float32), device=dev)
    outs = {}

    def add(name, kernel, dim, block=None):
        outs[name] = out = wp.zeros(shape, dtype=float, device=dev)
        if block is None:
            return lambda: wp.launch(kernel, dim=dim, inputs=[u, up, w, out], device=dev)
        return lambda: wp.launch_tiled(kernel, dim=dim, inputs=[u, up, w, out], block_dim=block, device=dev)

    launches = {"per_cell": add("per_cell", per_cell, (a.shots, a.n, a.n))}
    for tz, tx, nb in STAGED:
        if a.n % tz == 0 and a.n % tx == 0:
            launches[f"staged_{tz}x{tx}_b{nb}"] = add(f"staged_{tz}x{tx}_b{nb}", make_staged(tz, tx), [a.shots, a.n // tz, a.n // tx], nb)
    launches["whole_tile"] = add("whole_tile", whole_tile, [a.shots, a.n // TZ, a.n // TX], BLOCK)
    cells = a.shots * a.n * a.n
    ref = None
    for name, launch in launches.items():
        us = timed(launch, dev, a.repeats)
        got = outs[name].numpy()
        ref = got if ref is None else ref
        diff = float(np.abs(got - ref).max() / np.abs(ref).max())
        row = dict(kernel=name, device=dev.name, cells=cells, us=round(us, 1), Gcell_s=round(cells / us / 1e3, 1),
                   TB_s_at_12B=round(12 * cells / us / 1e6, 2), max_rel_diff_vs_per_cell=diff)  # fmt: skip
        print(json.dumps(row))


if __name__ == "__main__":
    main()
