"""Optimiser study for earthquake location (issue 6): the same 2D event (tests/test_locate.py scene,
noise-free), located from the same back-projection start by L-BFGS-B, Gauss-Newton, gradient
descent and Adam, with the parameters non-dimensionalised (position / dx, time / dt, f / f0, A / A0)
and in raw units (m, s, Hz, amplitude). Prints a Markdown table: final errors, evaluations used, and
the first evaluation count at which the position is within 1 m and the origin time within 1 ms.

    python benchmarks/location_optimizers.py [--device cuda:0] [--evaluations 40]
"""

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from adseismic import locate as L  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--evaluations", type=int, default=40)
    a = ap.parse_args()
    import tests.test_locate as T

    model, rec, clean = T.scene()
    sigma = 1e-3 * np.abs(clean).max(axis=1)
    start = L.back_projection(model, rec, clean, T.DT, [(lo + 40, hi - 40) for lo, hi in model.extent], 40.0)
    rows = []
    runs = (("lbfgs", True, None), ("lbfgs", False, None), ("gauss-newton", True, None), ("gd", True, {"step": 1.0}),
            ("gd", False, {"step": 1.0}), ("adam", True, {"lr": 0.1}), ("adam", False, {"lr": 0.1}))  # fmt: skip
    for method, scaled, options in runs:
        reached = {}

        def watch(iteration, evaluations, position, origin_time):
            if "hit" not in reached and np.linalg.norm(position - T.TRUTH) <= 1.0 and abs(origin_time - T.T0) <= 1e-3:
                reached["hit"] = evaluations

        r = L.locate(model, rec, clean, T.DT, noise_std=sigma, start=start, method=method, scaled=scaled, pml_width=10,
                     device=a.device, max_iterations=1000, max_evaluations=a.evaluations, options=options, callback=watch)  # fmt: skip
        rows.append((method, "scaled" if scaled else "raw (m, s, Hz)", json_opts(options), np.linalg.norm(r.position - T.TRUTH),
                     abs(r.origin_time - T.T0) * 1e3, r.evaluations, r.stop_reason, reached.get("hit", "never")))  # fmt: skip
    print("| method | parameters | options | position error (m) | origin-time error (ms) | evaluations | reached 1 m and 1 ms at evaluation |")
    print("|---|---|---|---|---|---|---|")
    for m, s, o, e, t, ev, stop, hit in rows:
        print(f"| {m} | {s} | {o} | {e:.3g} | {t:.3g} | {ev} ({stop}) | {hit} |")


def json_opts(options):
    return "" if not options else ", ".join(f"{k} {v:g}" for k, v in options.items())


if __name__ == "__main__":
    main()
