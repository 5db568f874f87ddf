"""Peak resident memory and time of a checkpointed gradient vs. a forward run (issue 3 targets).

Scene: 600 x 600 cells, dx 10 m, dt 1 ms, order 4, one shot, two-layer model (reference.md S600).
Run one configuration per process so the peak RSS is that run's alone:
    python benchmarks/gradient_memory.py --nt 1000 --mode gradient
    python benchmarks/gradient_memory.py --all        # runs every mode/nt in subprocesses, prints the table
"""

import argparse
import json
import resource
import subprocess
import sys
import time

import numpy as np


def scene(nt):
    from adseismic.wavelets import ricker

    v = np.full((600, 600), 1500.0)
    v[300:] = 2000.0
    src = np.array([[[20.0, 3000.0]]])
    rec = np.array([[[20.0, x] for x in np.linspace(0.0, 5990.0, 300)]])
    return v, 10.0, 1e-3, ricker(15.0, nt, 1e-3)[None, None], src, rec


def run(mode, nt, device):
    from adseismic.solve.acoustic import forward, gradient

    v, dx, dt, s, src, rec = scene(nt)
    kw = dict(device=device, pml_width=20)
    # compile (or load from Warp's cache) the forward and adjoint kernels outside the timing
    forward(v[:50, :50], dx, dt, s[..., :10], src * 0 + 100, rec[:, :2] * 0 + 50, **kw)
    gradient(v[:50, :50], dx, dt, s[..., :10], src * 0 + 100, rec[:, :2] * 0 + 50, np.zeros((1, 2, 10)), segment_length=5, **kw)
    t = time.perf_counter()
    if mode == "forward":
        forward(v, dx, dt, s, src, rec, **kw)
        extra = {}
    else:
        obs = np.zeros((1, rec.shape[1], nt))
        g = gradient(v, dx, dt, s, src, rec, obs, **kw)
        extra = {"segment_length": g.segment_length, "n_segments": g.n_segments}
    seconds = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {"mode": mode, "nt": nt, "device": device, "seconds": seconds, "peak_rss_bytes": peak, **extra}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--mode", choices=["forward", "gradient"], default="gradient")
    ap.add_argument("--nt", type=int, default=1000)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--all", action="store_true")
    a = ap.parse_args()
    if not a.all:
        print(json.dumps(run(a.mode, a.nt, a.device)))
        return
    rows = []
    for nt in (1000, 4000):
        for mode in ("forward", "gradient"):
            out = subprocess.run([sys.executable, __file__, "--mode", mode, "--nt", str(nt), "--device", a.device], capture_output=True, text=True, check=True)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print("| nt | mode | seconds | peak RSS (MB) | segments |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['nt']} | {r['mode']} | {r['seconds']:.1f} | {r['peak_rss_bytes'] / 1e6:.0f} | {r.get('n_segments', '')} x {r.get('segment_length', '')} |")
    by = {(r["nt"], r["mode"]): r for r in rows}
    for nt in (1000, 4000):
        print(f"nt={nt}: gradient/forward time = {by[(nt, 'gradient')]['seconds'] / by[(nt, 'forward')]['seconds']:.2f}")
    print(f"peak RSS gradient nt=4000 / nt=1000 = {by[(4000, 'gradient')]['peak_rss_bytes'] / by[(1000, 'gradient')]['peak_rss_bytes']:.2f}")


if __name__ == "__main__":
    main()
