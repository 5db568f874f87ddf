"""Network-model FWI beside pixel FWI on the same scene (docs/nn_fwi.md): model error, evaluations, wall time.

    python benchmarks/nn_fwi.py [configs/nn_fwi.yaml]

Runs the config as given (model: {kind: nn}: L-BFGS over the network's weights) and again with the model replaced
by the constant v0 on the same grid (L-BFGS-B over every cell, the same bounds, bands and iteration limits), each in
a temporary run directory, one after the other in this process, and prints a Markdown table: the relative L2 model
error in the anomaly (cells where the true model differs from the start by > 1%) and over the whole grid below the
masks, before and after, the gradient evaluations, the final misfit of each band (of its start) and the wall time.
"""

from __future__ import annotations

import copy
import sys
import tempfile
import time
from pathlib import Path

import yaml

from adseismic.config import parse_fwi_config
from adseismic.inversion.fwi import prepare_fwi, run_fwi


def run(raw: dict, base_dir: Path) -> dict:
    cfg = parse_fwi_config(raw, base_dir=base_dir)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        res = run_fwi(cfg, Path(d), progress=False, prepared=prepare_fwi(cfg))
    return {"seconds": time.perf_counter() - t0, "evaluations": sum(b["evaluations"] for b in res.bands),
            "misfits": [b["misfit"] for b in res.bands], **res.errors}  # fmt: skip


def main(path="configs/nn_fwi.yaml") -> None:
    path = Path(path)
    raw = yaml.safe_load(path.read_text())
    net = raw["model"]
    pixel = copy.deepcopy(raw)
    pixel["model"] = {"kind": "constant", "velocity": net["v0"], **{k: net[k] for k in ("shape", "spacing", "origin") if k in net}}
    rows = {"network (nn)": run(raw, path.parent), "pixels": run(pixel, path.parent)}
    print(f"{path}: relative model error (L2, of the true model)\n")
    print("| model | unknowns | anomaly error start -> final | below-mask error start -> final | evaluations | misfit per band | wall time |")
    print("|---|---|---|---|---|---|---|")
    h = int(net.get("hidden", 8))
    unknowns = {"network (nn)": f"{3 * h + h + h * h + h + h + 1} weights", "pixels": "every cell"}
    for name, r in rows.items():
        print(f"| {name} | {unknowns[name]} | {r['start_anomaly']:.4f} -> {r['final_anomaly']:.4f} | "
              f"{r['start_below_water']:.4f} -> {r['final_below_water']:.4f} | {r['evaluations']} | "
              f"{', '.join(f'{m:.3g}' for m in r['misfits'])} | {r['seconds']:.0f} s |")


if __name__ == "__main__":
    main(*sys.argv[1:])
