"""Print the accuracy figures of docs/accuracy.md: propagator against analytic solutions, convergence
orders, boundaries, and the gradient checks. Usage: python benchmarks/accuracy_report.py [--device cuda:0]
(~3 minutes on 2 CPU cores). The tests in tests/ assert the same quantities with tolerances."""

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from adseismic.analytic import acoustic_2d, acoustic_3d  # noqa: E402
from adseismic.solve import acoustic as G  # noqa: E402
from adseismic.solve.acoustic import forward  # noqa: E402
from adseismic.solve.misfits import MISFITS  # noqa: E402
from adseismic.wavelets import ricker  # noqa: E402

C, F = 2000.0, 15.0


def rel(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def slope(h, e):
    return float(np.polyfit(np.log(h), np.log(e), 1)[0])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    dev = ap.parse_args().device
    import tests.test_gradient as TG
    import tests.test_propagate as TP

    TP.forward.keywords["device"] = dev
    TG.gradient.keywords["device"] = dev

    print("## Convergence against the 2D analytic solution (absolute amplitude, relative L2 error)")
    dxs = [20.0, 15.0, 12.0, 10.0]
    for order in (2, 4, 8):
        errs = []
        for dx in dxs:
            d, s = TP.homogeneous_2d(dx, 2e-4, order)
            errs.append(rel(d[0], acoustic_2d(s, 2e-4, 240.0, C)))
        print(f"order {order}: dx {dxs} m -> errors {['%.2e' % e for e in errs]}, slope {slope(dxs, errs):.2f}")
    dts = [1e-3, 7.5e-4, 5e-4, 3.75e-4]
    errs = []
    for dt in dts:
        d, s = TP.homogeneous_2d(5.0, dt, 8)
        errs.append(rel(d[0], acoustic_2d(s, dt, 240.0, C)))
    print(f"time (order 8, dx 5 m): dt {dts} s -> errors {['%.2e' % e for e in errs]}, slope {slope(dts, errs):.2f}")

    print("\n## Off-grid source and receivers (Hicks operator), 2D, dx 5 m, order 8")
    src, recs = (301.3, 297.2), ((287.9, 541.7), (102.4, 150.6))
    d, s = TP.homogeneous_2d(5.0, 4e-4, 8, recs=recs, src=src)
    for i, r in enumerate(recs):
        print(f"receiver {r}: error {rel(d[i], acoustic_2d(s, 4e-4, np.hypot(r[0] - src[0], r[1] - src[1]), C)):.2e}")

    print("\n## 3D, 31^3 cells, dx 10 m, order 4, against s(t - r/c)/(4 pi r)")
    s = ricker(F, 260, 1e-3)
    src3 = np.array([[[150.0, 150.0, 150.0]]])
    rec3 = np.array([[[150.0, 150.0, 280.0], [153.0, 140.0, 262.0]]])
    r = forward(np.full((31, 31, 31), C), 10.0, 1e-3, s[None, None], src3, rec3, order=4, precision="float64", pml_width=10, device=dev)
    for i in range(2):
        print(f"receiver {rec3[0, i].tolist()}: error {rel(r.receiver_amplitudes[0, i], acoustic_3d(s, 1e-3, np.linalg.norm(rec3[0, i] - src3[0, 0]), C)):.2e}")

    print("\n## CPML reflection (receiver 100 m from a 20-cell layer; max |difference| / direct peak)")
    for order in (2, 4, 8):
        small, _ = TP.homogeneous_2d(10.0, 1e-3, order, T=0.699, L=600.0, src=(300.0, 300.0), recs=((300.0, 500.0),))
        big, _ = TP.homogeneous_2d(10.0, 1e-3, order, T=0.699, L=2400.0, src=(1200.0, 1200.0), recs=((1200.0, 1400.0),))
        print(f"order {order}: {np.abs(small - big).max() / np.abs(big).max():.2e}")

    print("\n## Gradients (float64): Taylor remainder slopes over h = 1e-1..1e-4 (first, second order)")
    v, s, src, rec, obs = TG.problem()
    base = {"velocity": v, "source_amplitudes": s, "source_locations": src}
    for kind in G.WRT:
        row = []
        for misfit in MISFITS:
            g = TG.gradient(v, TG.DX, TG.DT, s, src, rec, obs, misfit=misfit, wrt=(kind,))
            dm = TG.perturbation(kind, base[kind].shape, np.random.default_rng(1), getattr(g, kind))

            def evaluate(h, kind=kind, dm=dm, misfit=misfit):
                args = dict(base)
                args[kind] = base[kind] + h * dm
                return TG.loss(args["velocity"], args["source_amplitudes"], args["source_locations"], rec, obs, misfit)

            s1, s2 = TG.taylor_slopes(g.loss, float(np.sum(getattr(g, kind) * dm)), evaluate)
            row.append(f"{misfit} {s1:.3f}/{s2:.3f}")
        print(f"{kind}: " + ", ".join(row))
    rng = np.random.default_rng(2)
    dv = TG.perturbation("velocity", v.shape, rng)
    dd = rng.standard_normal(obs.shape)
    for precision in ("float64", "float32"):
        kw = dict(TG.KW, precision=precision, device=dev)
        a = np.sum(G.born(v, dv, TG.DX, TG.DT, s, src, rec, **kw) * dd)
        b = np.sum(dv * G.gradient(v, TG.DX, TG.DT, s, src, rec, misfit=lambda syn: (float(np.sum(syn * dd)), dd), **kw).velocity)
        print(f"dot-product test {precision}: <F dv, d> = {a:.12e}, <dv, F^T d> = {b:.12e}, relative mismatch {abs(a - b) / abs(a):.1e}")
    kw = dict(TG.KW, precision="float32", device=dev)
    every = G.gradient(v, TG.DX, TG.DT, s, src, rec, obs, wrt=G.WRT, segment_length=TG.NT, **kw)
    ckpt = G.gradient(v, TG.DX, TG.DT, s, src, rec, obs, wrt=G.WRT, **kw)
    for k in G.WRT:
        a, b = getattr(every, k), getattr(ckpt, k)
        print(f"checkpointed ({ckpt.n_segments} x {ckpt.segment_length}) vs all steps, {k}: relative L2 {np.linalg.norm(a - b) / np.linalg.norm(a):.1e}")


if __name__ == "__main__":
    main()
