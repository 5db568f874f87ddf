"""Print the elastic propagator's acceptance numbers (docs/accuracy.md, "Elastic"; CPU ~3 minutes).

    python benchmarks/elastic_accuracy.py [--device cuda:0]
"""

import argparse
import time

import numpy as np

from adseismic.analytic import elastic_2d_force, lamb_2d
from adseismic.kernels.numerics import rayleigh_speed, staggered_cfl_limit
from adseismic.solve.acoustic import forward as acoustic_forward
from adseismic.solve.elastic import forward_elastic
from adseismic.wavelets import ricker


def rel(a, b):
    return np.linalg.norm(a - b, axis=-1) / np.linalg.norm(b, axis=-1)


def full(shape, *values):
    return [np.full(shape, v) for v in values]


def full_space(dx, dt, order, device):
    vp, vs, rho, f = 2000.0, 1000.0, 2000.0, 15.0
    force, src = np.array([0.6, 0.8]), np.array([240.0, 240.0])
    recs = np.array([[240.0, 440.0], [100.0, 380.0], [403.3, 117.1]])
    n, nt = int(round(480.0 / dx)) + 1, int(round(0.45 / dt)) + 1
    r = forward_elastic(*full((n, n), vp, vs, rho), dx, dt, ricker(f, nt, dt)[None, None], src[None, None], recs[None],
                        source_components=force[None, None], order=order, precision="float64", device=device)  # fmt: skip
    az, ax = elastic_2d_force(ricker(f, nt, dt, delay=1.5 / f + dt / 2), dt, recs - src, vp, vs, rho, force)
    return rel(r.vz[0], az), rel(r.vx[0], ax)


def lamb(dx, order, device, offs=(100.0, 200.0)):
    vp, vs, rho = np.sqrt(3.0) * 1000.0, 1000.0, 2000.0
    dt = 0.5 * dx / vp
    nt = int(round(0.42 / dt)) + 1
    nz, nx = int(round(200 / dx)) + 1, int(round(500 / dx)) + 1
    offs = np.asarray(offs)
    rec = np.array([[[0.0, 200.0 + o] for o in offs] + [[dx / 2, 200.0 + o] for o in offs]])
    r = forward_elastic(*full((nz, nx), vp, vs, rho), dx, dt, ricker(10.0, nt, dt)[None, None], np.array([[[dx / 2, 200.0]]]),
                        rec, free_surface=True, order=order, precision="float64", device=device)  # fmt: skip
    sh = ricker(10.0, nt, dt, delay=0.15 + dt / 2)
    _, ax = lamb_2d(sh, dt, offs, vp, vs, rho, 0.0)
    az, _ = lamb_2d(sh, dt, offs, vp, vs, rho, dx / 2)
    return rel(r.vx[0, : len(offs)], ax), rel(r.vz[0, len(offs) :], az), rayleigh_speed(vp, vs) / (22.1 * dx)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    dev = ap.parse_args().device
    t0 = time.time()
    print("CFL limits (staggered, 2D):", {o: round(staggered_cfl_limit(o, 2), 4) for o in (2, 4, 8)})
    print("\nFull space, line force (0.6, 0.8), offsets ~200 m; relative L2 of vz / vx per receiver")
    for order, dxs in ((2, (4.0, 2.0)), (4, (6.0, 5.0, 4.0)), (8, (6.0, 4.0))):
        errs = []
        for dx in dxs:
            ez, ex = full_space(dx, 2e-4, order, dev)
            errs.append(ez[0])
            print(f"  order {order} dx {dx:4.1f} m dt 0.2 ms: vz {np.round(100 * ez, 3)} %  vx {np.round(100 * ex, 3)} %")
        print(f"  order {order}: measured convergence order (vz, receiver 0) {np.log(errs[0] / errs[-1]) / np.log(dxs[0] / dxs[-1]):.2f}")
    ez, ex = full_space(4.0, 4e-4, 4, dev)
    print(f"  test setting (order 4, dx 4 m, dt 0.4 ms): vz {np.round(100 * ez, 2)} %  vx {np.round(100 * ex, 2)} %")
    print("\nLamb's problem (vp/vs = sqrt 3), vx on the surface / vz at dx/2, offsets 100, 200 m")
    for order in (4, 8):
        errs = []
        for dx in (4.0, 2.0):
            ex, ez, ppw = lamb(dx, order, dev)
            errs.append(max(ex.max(), ez.max()))
            print(f"  order {order} dx {dx} m ({ppw:.1f} points per Rayleigh wavelength at f_max): vx {np.round(100 * ex, 2)} %  vz {np.round(100 * ez, 2)} %")
        print(f"  order {order}: convergence order (worst trace) {np.log2(errs[0] / errs[1]):.2f}")
    print("\nFluid (vs = 0) vs acoustic propagator, explosive source, two layers")
    dx, dt, f, nt = 5.0, 5e-4, 15.0, 900
    vp = np.full((100, 120), 1500.0)
    vp[60:] = 2200.0
    tau = np.arange(nt) * dt - 1.5 / f
    moment = -np.exp(-((np.pi * f * tau) ** 2)) / (2 * np.pi**2 * f**2)
    src, rec = np.array([[[150.0, 300.0]]]), np.array([[[100.0, 450.0], [420.0, 200.0]]])
    el = forward_elastic(vp, 0 * vp, 0 * vp + 1000.0, dx, dt, moment[None, None], src, rec, source_type="explosive", precision="float64", device=dev)
    ac = acoustic_forward(vp, dx, dt, (ricker(f, nt, dt) / 1500.0**2)[None, None], src, rec, precision="float64", device=dev)
    print(f"  pressure relative L2: {np.round(100 * rel(el.pressure[0], ac.receiver_amplitudes[0]), 3)} %")
    print("\nCPML reflection at normal incidence (order 4, 20 cells, R = 1e-3)")
    s = ricker(15.0, 700, 5e-4)

    def trace(nx, shift):
        r = forward_elastic(*full((121, nx), 2000.0, 1000.0, 2000.0), 5.0, 5e-4, s[None, None], np.array([[[300.0, 150.0 + shift]]]),
                            np.array([[[300.0, 50.0 + shift]]]), precision="float64", pml_velocity=2000.0, pml_frequency=15.0,
                            source_components=np.array([[[0.6, 0.8]]]), device=dev)  # fmt: skip
        return np.concatenate([r.vx[0, 0], r.vz[0, 0]])

    small, big = trace(121, 0.0), trace(281, 800.0)
    print(f"  max |reflection| / direct peak: {np.abs(small - big).max() / np.abs(big).max():.2e}")
    print("\nStability, vp/vs = 3, 0.99 x CFL, 10,000 steps")
    for fs in (False, True):
        dt = 0.99 * staggered_cfl_limit(4, 2) * 10.0 / 3000.0
        r = forward_elastic(*full((40, 40), 3000.0, 1000.0, 2000.0), 10.0, dt, ricker(10.0, 10_000, dt)[None, None], np.array([[[150.0, 200.0]]]),
                            np.array([[[100.0, 100.0], [0.0, 300.0]]]), free_surface=fs, pml_width=10, device=dev)  # fmt: skip
        v = np.abs(np.concatenate([r.vx, r.vz], axis=1))
        print(f"  free surface {fs}: last 1000 steps max |v| / peak = {v[..., -1000:].max() / v.max():.2e}")
    print(f"\n({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
