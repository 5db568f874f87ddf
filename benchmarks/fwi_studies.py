"""FWI studies for docs/fwi.md (CPU-sized; each prints a Markdown table).

    python benchmarks/fwi_studies.py cycle-skipping -o out/studies [--device cuda:0]
    python benchmarks/fwi_studies.py optimizers -o out/studies [--device cuda:0]
    python benchmarks/fwi_studies.py band-filter -o out/studies [--device cuda:0]

cycle-skipping: a 2000 m/s model with a +300 m/s anomaly, started from 1600 m/s (20% too slow: the
travel-time error to the bottom receivers exceeds half a period at 8 Hz); a single
high-frequency band (the full 8 Hz Ricker) against the multiscale schedule 2 -> 4 Hz -> full, at
the same total number of iterations. optimizers: GD (Wolfe line search), Adam and L-BFGS-B on the
demo problem, each with the same number of gradient evaluations, in raw units of x = v / 1000 m/s.
band-filter: on configs/fwi_demo.yaml, the misfit of a band's data at the TRUE model on the plan's grid (observed
data simulated with the full wavelet, then filtered; synthetics from the filtered wavelet, the band's PML), for the
zero-phase and the causal Butterworth: what no model can explain (docs/fwi.md, "The band filter").
"""

import argparse
import copy
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from adseismic.config import parse_fwi_config
from adseismic.inversion.fwi import _observed, _simulator, band_pass, data_weights, prepare_fwi, run_fwi

BASE = {
    "model": {"kind": "constant", "shape": [61, 121], "spacing": 10.0, "velocity": 1600.0},
    "true_model": {"kind": "gaussian_anomaly", "shape": [61, 121], "spacing": 10.0, "background": 2000.0,
                   "perturbation": 300.0, "center": [300.0, 600.0], "radius": 120.0},
    "geometry": {"sources": {"line": {"start": {"x": 100, "z": 20}, "end": {"x": 1100, "z": 20}, "count": 6}},
                 "receivers": {"lines": [{"start": {"x": 0, "z": 10}, "end": {"x": 1200, "z": 10}, "count": 61},
                                         {"start": {"x": 0, "z": 590}, "end": {"x": 1200, "z": 590}, "count": 61}]}},
    "wavelet": {"kind": "ricker", "peak_frequency": 8.0},
    "simulation": {"order": 4, "pml_width": 12},
    "inversion": {"iterations": 10, "bounds": [1400, 2600]},
}  # fmt: skip


DEVICE = "cpu"


def run(cfg_dict, outdir):
    cfg = parse_fwi_config(copy.deepcopy(cfg_dict))
    cfg.forward.simulation.device = DEVICE
    res = run_fwi(cfg, outdir, progress=False, prepared=prepare_fwi(cfg))
    evals = sum(b["evaluations"] for b in res.bands)
    return res.errors, evals, res.seconds


def cycle_skipping(out: Path):
    rows = []
    for name, bands, iters in (("single band (full 8 Hz Ricker)", [None], 24), ("multiscale 2 -> 4 Hz -> full", [2.0, 4.0, None], 8)):
        cfg = copy.deepcopy(BASE)
        cfg["inversion"].update(bands=bands, iterations=iters)
        err, evals, sec = run(cfg, out / name.split()[0])
        rows.append((name, err, evals, sec))
    print("| schedule | model error start | final | change | gradient evaluations | seconds |")
    print("|---|---|---|---|---|---|")
    for name, e, evals, sec in rows:
        print(f"| {name} | {e['start_below_water']:.4f} | {e['final_below_water']:.4f} | "
              f"{100 * (e['final_below_water'] / e['start_below_water'] - 1):+.0f}% | {evals} | {sec:.0f} |")


def optimizers(out: Path, evaluations=16):
    from adseismic.config import load_fwi_config

    rows = []
    for method, extra in (("gd", {"step": 0.05}), ("adam", {"lr": 0.01}), ("lbfgs", {})):
        cfg = load_fwi_config(Path(__file__).resolve().parents[1] / "configs" / "fwi_demo.yaml")
        cfg.inversion.optimizer = method
        cfg.forward.simulation.device = DEVICE
        cfg.inversion.bands = [(None, None)]
        cfg.inversion.iterations = 1000
        cfg.inversion.evaluations = evaluations
        cfg.inversion.rel_decrease = 1e-12
        for k, v in extra.items():
            setattr(cfg.inversion, k, v)
        res = run_fwi(cfg, out / method, progress=False, prepared=prepare_fwi(cfg))
        rows.append((method, extra, res))
    print("| optimiser | settings | misfit / start | anomaly error start -> final | evaluations | iterations |")
    print("|---|---|---|---|---|---|")
    for method, extra, r in rows:
        b = r.bands[0]
        print(f"| {method} | {json.dumps(extra)} | {b['misfit']:.4f} | {r.errors['start_anomaly']:.4f} -> {r.errors['final_anomaly']:.4f} | {b['evaluations']} | {b['iterations']} |")


def band_filter_floor(out: Path, bands=(4.0, 2.5), order=4):
    from adseismic.config import load_fwi_config

    cfg = load_fwi_config(Path(__file__).resolve().parents[1] / "configs" / "fwi_demo.yaml")
    cfg.forward.simulation.device = DEVICE
    prep = prepare_fwi(cfg)
    sc, p = prep.scene, prep.plan
    sim = _simulator(cfg, prep, cfg.inversion, prep.bounds)
    out.mkdir(parents=True, exist_ok=True)
    observed = np.asarray(_observed(cfg, prep, Path(tempfile.mkdtemp(dir=out)), False), float)
    w = data_weights(sc, cfg.inversion, cfg.forward.geometry)
    v = cfg.true_model.resample(p.dx, p.origin, p.shape).values
    print(f"| band | zero-phase, order {order} | causal, order {order} |")
    print("|---|---|---|")
    for hi in bands:
        sim.kw["pml_frequency"] = hi / 2
        row = []
        for causal in (False, True):
            wavelet = band_pass(sc.wavelet, p.dt, (None, hi), order, causal)
            amp = np.broadcast_to(wavelet, sc.source_amplitudes.shape).copy()
            syn = np.asarray(sim.forward({"vp": v}, p.dx, p.dt, amp, sc.source_locations, sc.receiver_locations)["data"], float)
            obs = w * band_pass(observed, p.dt, (None, hi), order, causal)
            row.append(np.linalg.norm(w * syn - obs) / np.linalg.norm(obs))
        print(f"| <= {hi:g} Hz | {row[0]:.4f} | {row[1]:.4f} |")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("study", choices=["cycle-skipping", "optimizers", "band-filter"])
    ap.add_argument("-o", "--outdir", type=Path, default=Path("out/studies"))
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()
    global DEVICE
    DEVICE = a.device
    {"cycle-skipping": cycle_skipping, "optimizers": optimizers, "band-filter": band_filter_floor}[a.study](a.outdir / a.study)


if __name__ == "__main__":
    sys.exit(main())
