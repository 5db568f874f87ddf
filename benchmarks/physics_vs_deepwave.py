"""Receiver data of the physics family against Deepwave 0.1.0 at any grid size and record length (the accuracy that
``adseismic bench --physics`` reports at the bench's own sizes): relative L2 difference and least-squares scale
(bench/physics.py: models, on-node geometry, the conventions aligned). Needs torch and Deepwave.

    python benchmarks/physics_vs_deepwave.py --kinds acoustic_vd viscoacoustic vti --n 160 --nt 700
    python benchmarks/physics_vs_deepwave.py --kinds elastic3d --n 40 --nt 150
    python benchmarks/physics_vs_deepwave.py --kinds acoustic_vd vti --n 160 --nt 700 --uniform-density
"""

import argparse
import time

import numpy as np

DX, DT, F_PEAK, PML, ORDER = 10.0, 1e-3, 15.0, 20, 4


def compare(kind: str, n: int, nt: int, device: str, uniform_density: bool) -> dict:
    """Our forward and Deepwave's on one physics scene of n cells an axis (n^3 for elastic3d) and nt steps."""
    from adseismic.bench import physics
    from adseismic.wavelets import ricker

    shape = (n,) * (3 if kind == "elastic3d" else 2)
    model, src, rec = physics.scene(kind, shape, DX)
    if uniform_density:
        model["rho"] = np.full(shape, 2000.0)
    amp = ricker(F_PEAK, nt, DT)[None, None]
    kw = dict(device=device, order=ORDER, pml_width=PML, f_peak=F_PEAK)
    t0 = time.perf_counter()
    ours = physics.run_ours(kind, "forward", model, DX, DT, amp, src, rec, **kw).receiver_amplitudes
    t1 = time.perf_counter()
    (theirs,) = physics.deepwave_call(kind, False, model, DX, DT, amp, src, rec, **kw)()
    t2 = time.perf_counter()
    l2, scale = physics.difference(ours, theirs.detach().cpu().numpy())
    return dict(kind=kind, shape=shape, nt=nt, rel_l2=l2, scale=scale, ours_s=t1 - t0, deepwave_s=t2 - t1)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kinds", nargs="+", default=["acoustic_vd", "viscoacoustic", "vti", "elastic3d"])
    p.add_argument("--n", type=int, default=160, help="cells an axis (default 160)")
    p.add_argument("--nt", type=int, default=700, help="time steps of 1 ms (default 700)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--uniform-density", action="store_true", help="rho 2000 kg/m^3 everywhere (no density averaging at the interface)")
    a = p.parse_args()
    print("| physics | shape | nt | rel. L2 difference | scale a | ours s | Deepwave s |\n|---|---|---|---|---|---|---|")
    for kind in a.kinds:
        r = compare(kind, a.n, a.nt, a.device, a.uniform_density)
        print(f"| {kind} | {'x'.join(map(str, r['shape']))} | {r['nt']} | {r['rel_l2']:.3g} | {r['scale']:.6g} | {r['ours_s']:.1f} | "
              f"{r['deepwave_s']:.1f} |")  # fmt: skip


if __name__ == "__main__":
    main()
