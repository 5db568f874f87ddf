"""acoustic_vd's 2D step with its half steps as register tiles (the untaped path) against the per-cell kernels (the
taped path), on one device in one run: the time of one step (velocity and pressure half steps, no sources), replayed
from a CUDA graph on a GPU, and the largest difference of the fields after a few steps from the same random start
(relative to each field's largest value; 0 on a CPU, where the two are equal bit for bit).

    python benchmarks/staggered_tiles.py --device cuda:0 [--n 1000] [--shots 1] [--order 4]
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bandwidth import timed  # noqa: E402

from adseismic.kernels.acoustic_vd import AcousticVD  # noqa: E402

STEPS = 20  # steps of one timed call, captured once as a CUDA graph on a GPU (Python's launch cost left out)


def graphed(fn, dev):
    """A call of fn STEPS times, captured once as a CUDA graph on a GPU."""

    def many():
        for _ in range(STEPS):
            fn()

    if not dev.is_cuda:
        return many
    many()
    with wp.ScopedCapture(device=dev) as cap:
        many()
    return lambda: wp.capture_launch(cap.graph)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--n", type=int, default=1000, help="physical cells along z and x")
    ap.add_argument("--shots", type=int, default=1)
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=20)
    a = ap.parse_args()
    wp.init()
    dev = wp.get_device(a.device)
    prop = AcousticVD((a.n, a.n), 10.0, 1e-3, a.order, a.shots, 20, 1e-3, 15.0, 2500.0, device=dev)
    lz, lx = prop.padded
    rng = np.random.default_rng(0)
    vp, rho = (wp.array(2000.0 + rng.uniform(0, 500, (lz, lx)), dtype=wp.float32, device=dev) for _ in range(2))
    mat = prop.materials(vp, rho)
    R = prop.k.halo
    start = rng.standard_normal((3, a.shots, lz, lx)).astype(np.float32)
    start[:, :, :R], start[:, :, -R:], start[:, :, :, :R], start[:, :, :, -R:] = 0, 0, 0, 0
    tiles, cells = prop.tiles, a.shots * (lz - 2 * R) * (lx - 2 * R)
    rows, fields = [], []
    for name, t in (("tiles", tiles), ("per cell", None)):
        prop.tiles = t
        st = prop.new_state()
        for f, s in zip((st.vx, st.vz, st.p), start):
            f.assign(s)
        for n in range(5):
            prop.step(st, mat, None, n)
        fields.append([f.numpy() for f in (st.vx, st.vz, st.p)])
        us = timed(graphed(lambda: prop.step(st, mat, None, 0), dev), dev, a.repeats) / STEPS
        rows.append(dict(kernels=name, us_a_step=round(us, 2), Gcell_s=round(cells / us / 1e3, 1)))
    prop.tiles = tiles
    diff = max(float(np.abs(x - y).max() / np.abs(y).max()) for x, y in zip(*fields))
    V, box = tiles[0], tuple(tiles[1])
    for r in rows:
        print(json.dumps({"device": dev.name, "n": a.n, "shots": a.shots, "order": a.order, "lanes": V, "core_box": box, **r,
                          "speedup": round(rows[1]["us_a_step"] / r["us_a_step"], 2), "max_rel_diff": diff}))  # fmt: skip


if __name__ == "__main__":
    main()
