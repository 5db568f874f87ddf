"""Where an FWI evaluation's time goes on a GPU (issue 22, item 3): configs/marmousi_fwi.yaml with 32 shots and
a few iterations a band, run twice by `adseismic fwi` in one process (the first compiles and captures, the second
is warm); prints each band's "band k time:" line of fwi.log (simulation vs misfit+weights, journal, history, other,
the non-kernel fraction, the figures) and the wall time of each run.

    python benchmarks/fwi_breakdown.py --device cuda:0 --iterations 5 -o OUTDIR
"""

import argparse
import pathlib
import re
import time

import yaml

from adseismic.cli import main

ROOT = pathlib.Path(__file__).resolve().parents[1]

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--device", default="cuda:0")
ap.add_argument("--shots", type=int, default=32)
ap.add_argument("--iterations", type=int, default=5, help="iterations per band")
ap.add_argument("-o", "--outdir", type=pathlib.Path, required=True)
args = ap.parse_args()

cfg = yaml.safe_load((ROOT / "configs" / "marmousi_fwi.yaml").read_text())
for key in ("model", "true_model"):
    cfg[key]["path"] = str(ROOT / "data" / "marmousi2" / "marmousi2_resampled_1601x401_7.5m_kms.f32")
cfg["geometry"]["sources"]["line"]["count"] = args.shots
cfg["simulation"]["device"] = args.device
cfg["inversion"]["iterations"] = [args.iterations] * len(cfg["inversion"]["bands"])
args.outdir.mkdir(parents=True, exist_ok=True)
path = args.outdir / "fwi_breakdown.yaml"
path.write_text(yaml.safe_dump(cfg))
for run in ("cold", "warm"):
    t0 = time.perf_counter()
    code = main(["fwi", str(path), "-o", str(args.outdir / run), "-q"])
    seconds = time.perf_counter() - t0
    print(f"{run}: exit {code}, {seconds:.1f} s wall ({args.shots} shots, {args.iterations} iterations a band, {args.device})")
    for line in (args.outdir / run / "fwi.log").read_text().splitlines():
        if re.search(r"band \d+ time:|simulating observed", line):
            print("   ", line.split(": ", 1)[1] if "INFO" in line else line)
