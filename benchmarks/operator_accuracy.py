"""Print the off-grid source/receiver operator's accuracy (docs/benchmarks.md, "Source and receiver weights"; CPU ~2
minutes): its per-axis wavenumber response and moments (kernels/common.hicks_axis), and the waveform and peak
amplitude errors of off-grid sources and receivers against the 2D analytic acoustic and elastic solutions.

    python benchmarks/operator_accuracy.py [--device cuda:0]
"""

import argparse

import numpy as np
import warp as wp

from adseismic.analytic import acoustic_2d, elastic_2d_force
from adseismic.kernels.common import HICKS_RADIUS, hicks_axis
from adseismic.solve.acoustic import forward
from adseismic.solve.elastic import forward_elastic
from adseismic.wavelets import ricker

C, VP, VS, RHO, F = 2000.0, 2000.0, 1000.0, 2000.0, 15.0  # m/s, kg/m^3, Hz
FORCE = np.array([0.6, 0.8])  # (f_z, f_x)
# (order, dx m, dt s, [(source (z, x) m, receivers)]): order 8 at dx 5 m is the planner's grid for this scene at order 8,
# order 4 at 9.5 m / 1.7 ms its default order's; the last case of each is on nodes (the scheme's own error)
ACOUSTIC = [
    (8, 5.0, 4e-4, [((301.3, 297.2), ((287.9, 541.7), (102.4, 150.6))), ((302.5, 297.5), ((287.5, 542.5),)), ((300.0, 300.0), ((300.0, 540.0),))]),
    (4, 9.5, 1.7e-3, [((301.3, 297.2), ((287.9, 541.7), (102.4, 150.6))), ((308.75, 308.75), ((308.75, 546.25),)), ((304.0, 304.0), ((304.0, 541.5),))]),
]  # fmt: skip
ELASTIC = [((251.3, 247.2), ((237.9, 451.7), (102.4, 390.6))), ((252.5, 252.5), ((252.5, 452.5), (102.5, 392.5))),
           ((251.25, 251.25), ((251.25, 448.75), (103.75, 391.25))), ((250.0, 250.0), ((250.0, 450.0), (100.0, 390.0)))]  # fmt: skip


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def peak(a, b):
    return np.abs(a).max() / np.abs(b).max() - 1


def axis_weights(fractions):
    """(len(fractions), 2 HICKS_RADIUS) float64 weights of the nodes j - f, j = -(r - 1)..r, at positions f cells."""
    axis = hicks_axis(wp.float64)

    @wp.kernel
    def weights(c: wp.array(dtype=wp.float64), w: wp.array2d(dtype=wp.float64)):
        i, j = wp.tid()
        w[i, j] = axis(wp.float64(float(j - wp.static(HICKS_RADIUS - 1))) - c[i], c[i])

    w = wp.zeros((len(fractions), 2 * HICKS_RADIUS), dtype=wp.float64, device="cpu")
    wp.launch(weights, dim=w.shape, inputs=[wp.array(np.asarray(fractions, float), dtype=wp.float64, device="cpu"), w], device="cpu")
    return w.numpy()


def response(ppws=(26.7, 20, 12, 8, 6.3, 4), fractions=(0.1, 0.25, 0.5)):
    d = np.arange(-(HICKS_RADIUS - 1), HICKS_RADIUS + 1)[None, :] - np.array(fractions)[:, None]
    w = axis_weights(fractions)
    print("per-axis operator: |response| - 1 (%) at points per wavelength " + ", ".join(f"{p:g}" for p in ppws))
    for f, wf, df in zip(fractions, w, d):
        r = [abs(np.sum(wf * np.exp(-2j * np.pi / p * df))) - 1 for p in ppws]
        m = [np.sum(wf * df**k) for k in range(3)]
        print(f"  f = {f:<4g}: " + " ".join(f"{100 * x:+.4f}" for x in r) + f"   sum - 1 {m[0] - 1:.1e}, moments {m[1]:.1e} {m[2]:.1e}")


def acoustic(device):
    for order, dx, dt, cases in ACOUSTIC:
        n, nt = int(round(600.0 / dx)) + 1, int(round(0.35 / dt)) + 1
        s = ricker(F, nt, dt)
        for src, recs in cases:
            r = forward(np.full((n, n), C), dx, dt, s[None, None], np.array([[src]]), np.array([list(recs)]), order=order,
                        precision="float64", device=device).receiver_amplitudes[0]  # fmt: skip
            for got, rc in zip(r, recs):
                a = acoustic_2d(s, dt, np.hypot(rc[0] - src[0], rc[1] - src[1]), C)
                print(f"acoustic order {order}, dx {dx:g} m, source {src}, receiver {rc}: waveform {rel(got, a):.3e}, "
                      f"peak {100 * peak(got, a):+.3f}%")


def elastic(device):
    dx, dt = 5.0, 4e-4
    n, nt = int(round(500.0 / dx)) + 1, int(round(0.45 / dt)) + 1
    s = ricker(F, nt, dt)
    model = [np.full((n, n), v) for v in (VP, VS, RHO)]
    for src, recs in ELASTIC:
        rec = np.array(recs)
        r = forward_elastic(*model, dx, dt, s[None, None], np.array([[src]]), rec[None], source_components=FORCE[None, None], order=8,
                            precision="float64", device=device)  # fmt: skip
        az, ax = elastic_2d_force(ricker(F, nt, dt, delay=1.5 / F + dt / 2), dt, rec - np.array(src), VP, VS, RHO, FORCE)
        for i, rc in enumerate(recs):
            print(f"elastic order 8, dx 5 m, source {src}, receiver {rc}: vz waveform {rel(r.vz[0, i], az[i]):.3e}, peak "
                  f"{100 * peak(r.vz[0, i], az[i]):+.3f}%; vx waveform {rel(r.vx[0, i], ax[i]):.3e}, "
                  f"peak {100 * peak(r.vx[0, i], ax[i]):+.3f}%")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    response()
    acoustic(args.device)
    elastic(args.device)
