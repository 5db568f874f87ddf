"""Coverage of the moment-tensor locator's stated uncertainty over repeated noise draws (issue 23, item 2).

The synthetic event EVENTS[event] of adseismic.data_synthetic.moment_tensor (data simulated on a grid twice as fine
at order 8) gets `draws` independent draws of white Gaussian noise of `noise` x each trace's peak; each draw is
located on the demo's 20 m grid (Gauss-Newton from the noise-free solution, the noise level given as noise_std) and
its error is compared with the stated covariance: the fraction of draws whose position lies inside the 68% / 95%
ellipse (chi-square, 2 dof), whose origin time and each in-plane tensor component lie within 1 / 1.96 sigma, about
the truth and about the noise-free solution (the covariance describes the noise; the discretisation error of the
20 m, order-4 grid against the data's 10 m, order-8 one is a bias it does not include). Expected for a correct
covariance: 0.68 and 0.95 (binomial 1-sigma over 20 draws: +-0.10 and +-0.05).

    python benchmarks/moment_tensor_coverage.py --event dc --draws 20 --noise 0.1 -o out/mt_coverage.json
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from scipy.stats import chi2

from adseismic.data_synthetic import moment_tensor as syn
from adseismic.location.locate import locate

DT = 0.0025  # s, the data's sample interval (the solver's at 20 m: CFL 0.55 for vp 3200 m/s, order 4)


def run(event: str, draws: int, noise: float, order: int = 4) -> dict:
    ev = syn.EVENTS[event]
    sta = syn.stations()
    rec, comps = np.concatenate([sta, sta]), ["vz"] * len(sta) + ["vx"] * len(sta)
    model = syn.model(syn.MODEL["spacing"])
    m_true = syn.dc_tensor() if ev["moment_tensor"] is None else np.asarray(ev["moment_tensor"], float)
    vz, vx = syn.simulate(event, dt=DT, noise_free=True)
    clean = np.concatenate([vz, vx])
    peak = np.abs(clean).max(axis=1)
    kw = {"components": comps, "constraint": ev["constraint"], "peak_frequency": ev["peak_frequency"], "method": "gauss-newton",
          "max_iterations": 15, "order": order, "pml_width": 20}  # fmt: skip
    ref = locate(model, rec, clean, DT, noise_std=noise * peak,
                 start={"position": np.asarray(ev["position"]) + [15.0, -15.0], "origin_time": ev["origin_time"] + 0.01}, **kw)  # fmt: skip
    start = {"position": ref.position, "origin_time": ref.origin_time}
    rng = np.random.default_rng(12345)
    rows = []
    for i in range(draws):
        t0 = time.perf_counter()
        obs = clean + noise * peak[:, None] * rng.standard_normal(clean.shape)
        r = locate(model, rec, obs, DT, noise_std=noise * peak, start=start, **kw)
        rows.append({"position": r.position.tolist(), "origin_time": r.origin_time, "moment_tensor": r.moment_tensor.tolist(),
                     "covariance": r.covariance.tolist(), "moment_tensor_covariance": r.moment_tensor_covariance.tolist(),
                     "inflation": r.inflation, "reduced_chi_square": 2 * r.misfit / obs.size, "seconds": time.perf_counter() - t0})  # fmt: skip
        print(json.dumps({"draw": i, **{k: rows[-1][k] for k in ("position", "origin_time", "moment_tensor", "reduced_chi_square", "seconds")}}),
              flush=True)  # fmt: skip
    truth = {"position": np.asarray(ev["position"], float), "origin_time": ev["origin_time"], "moment_tensor": m_true}
    noise_free = {"position": ref.position, "origin_time": ref.origin_time, "moment_tensor": ref.moment_tensor}
    return {"event": event, "constraint": ev["constraint"], "draws": draws, "noise": noise, "order": order,
            "noise_free_position_error_m": (ref.position - ev["position"]).tolist(),
            "noise_free_origin_time_error_s": ref.origin_time - ev["origin_time"],
            "noise_free_moment_tensor": ref.moment_tensor.tolist(), "true_moment_tensor": m_true.tolist(),
            "coverage_about_truth": coverage(rows, truth), "coverage_about_noise_free_solution": coverage(rows, noise_free),
            "rows": rows}  # fmt: skip


def coverage(rows, centre) -> dict:
    """Fractions of the draws whose stated 68% / 95% regions hold `centre`: the position in its 2D ellipse (chi-square,
    2 dof), the origin time and each in-plane tensor component within 1 / 1.96 sigma. About the truth: noise and
    modelling (discretisation) error together; about the noise-free solution: the noise alone, which the covariance
    describes."""
    out = {}
    for p, z in ((0.68, 1.0), (0.95, 1.96)):
        k2 = chi2.ppf(p, 2)
        pos, t, mt = [], [], []
        for r in rows:
            c = np.asarray(r["covariance"])
            e = np.asarray(r["position"]) - centre["position"]
            pos.append(float(e @ np.linalg.solve(c[:2, :2], e)) <= k2)
            t.append(abs(r["origin_time"] - centre["origin_time"]) <= z * np.sqrt(c[2, 2]))
            mt.append(
                np.abs(np.asarray(r["moment_tensor"]) - centre["moment_tensor"]) <= z * np.sqrt(np.diag(r["moment_tensor_covariance"]))
            )
        mt = np.mean(mt, axis=0)
        out[f"{p:.2f}"] = {"position (2D ellipse)": float(np.mean(pos)), "origin time": float(np.mean(t)),
                           "Mxx": float(mt[0]), "Mzz": float(mt[1]), "Mxz": float(mt[2])}  # fmt: skip
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--event", default="dc", choices=sorted(syn.EVENTS))
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--noise", type=float, default=0.1)
    ap.add_argument("-o", "--output", default=None)
    a = ap.parse_args()
    out = run(a.event, a.draws, a.noise)
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}, indent=1, default=float))
    if a.output:
        from adseismic.data.atomic import write_text_atomic

        write_text_atomic(a.output, json.dumps(out, indent=1, default=float))


if __name__ == "__main__":
    main()
