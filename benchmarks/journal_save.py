"""Cost of saving the optimisation journal per evaluation (issue 22, item 3): N evaluations of an n-cell gradient,
each saved as `minimize` saves it (append to the tail), against the whole-file rewrite (compact=True).

    python benchmarks/journal_save.py --evaluations 80 --cells 70000
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from adseismic.inversion.optimize import Journal, hash_x

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--evaluations", type=int, default=80)
ap.add_argument("--cells", type=int, default=70_000)
args = ap.parse_args()
rng = np.random.default_rng(0)
for compact in (True, False):
    path, journal, seconds = Path(tempfile.mkdtemp()) / "journal.h5", Journal(), []
    for i in range(args.evaluations):
        g = rng.standard_normal(args.cells)
        journal.append(hash_x(g), float(i), g)
        t = time.perf_counter()
        journal.save(path, compact=compact)
        seconds.append(time.perf_counter() - t)
    print(f"{'rewrite' if compact else 'append '}: first 10 {1e3 * np.mean(seconds[:10]):.1f} ms each, "
          f"last 10 {1e3 * np.mean(seconds[-10:]):.1f} ms each, all {sum(seconds):.2f} s")
