"""Forward and forward+gradient speed on the reference scenes of ../shared/docs/reference.md section 6.

Rates are padded-grid cell updates per second (cells incl. PML x steps x shots / seconds), the unit of
the Deepwave anchors. Usage: python benchmarks/speed.py --device cuda:0 [--scenes S600 S600x16 S4000] [--modes forward]
"""

import argparse
import json
import time

import numpy as np
import warp as wp

from adseismic.solve.acoustic import forward, gradient
from adseismic.wavelets import ricker

SCENES = {  # name: (n, shots, nt)
    "S600": (600, 1, 1000),
    "S600x16": (600, 16, 1000),
    "S4000": (4000, 1, 500),
}


def scene(n, shots, nt):
    v = np.full((n, n), 1500.0)
    v[n // 2 :] = 2000.0
    x = np.linspace(100.0, (n - 11) * 10.0, shots) if shots > 1 else np.array([n * 5.0])
    src = np.stack([np.full(shots, 20.0), x], axis=1)[:, None, :]
    rec = np.broadcast_to(np.array([[20.0, xr] for xr in np.linspace(0.0, (n - 1) * 10.0, n // 2)]), (shots, n // 2, 2)).copy()
    return v, src, rec, ricker(15.0, nt, 1e-3)[None, None].repeat(shots, axis=0)


def timed(fn, device):
    wp.synchronize_device(device)
    t = time.perf_counter()
    out = fn()
    wp.synchronize_device(device)
    return time.perf_counter() - t, out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--budget-gb", type=float, default=None, help="memory budget of the gradient (GB)")
    ap.add_argument("--repeat", type=int, default=1, help="forward runs timed (the best is reported)")
    ap.add_argument("--modes", nargs="+", default=["forward", "gradient"], choices=["forward", "gradient"])
    a = ap.parse_args()
    for name in a.scenes:
        n, shots, nt = SCENES[name]
        v, src, rec, s = scene(n, shots, nt)
        kw = dict(order=a.order, device=a.device, pml_width=20)
        small = (v[:60, :60], 10.0, 1e-3, s[:1, :, :120], src[:1] * 0 + 100, rec[:1, :2] * 0 + 100)
        forward(*small, **kw)  # compile
        cells = (n + 40 + a.order) ** 2 * nt * shots
        tf, _ = timed(lambda: forward(v, 10.0, 1e-3, s, src, rec, **kw), a.device)
        row = {"scene": name, "device": a.device, "order": a.order}
        if "gradient" in a.modes:
            gradient(*small, np.zeros((1, 2, 120)), segment_length=30, **kw)
            obs = np.zeros((shots, rec.shape[1], nt))
            budget = None if a.budget_gb is None else a.budget_gb * 1e9
            tg, g = timed(lambda: gradient(v, 10.0, 1e-3, s, src, rec, obs, memory_budget=budget, **kw), a.device)
            row.update({"gradient_s": round(tg, 3), "gradient_gcells": round(cells / tg / 1e9, 3), "segments": g.n_segments,
                        "segment_length": g.segment_length, "peak_estimate_gb": round(g.peak_bytes_estimate / 1e9, 2)})  # fmt: skip
        if a.repeat > 1:  # best of several forward runs (the first one above includes compiling)
            tf = min([tf] + [timed(lambda: forward(v, 10.0, 1e-3, s, src, rec, **kw), a.device)[0] for _ in range(a.repeat - 1)])
        row.update({"forward_s": round(tf, 4), "forward_gcells": round(cells / tf / 1e9, 3)})
        if "gradient" in a.modes:
            row["gradient_over_forward"] = round(row["gradient_s"] / tf, 2)
        row["peak_device_gb"] = round(wp.get_mempool_used_mem_high(a.device) / 1e9, 2) if wp.get_device(a.device).is_cuda else None
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
