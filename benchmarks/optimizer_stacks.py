"""Where fwi.log's "other" time goes (issue 22): run an adseismic command in this process while a thread samples the
main thread's stack every ~1 ms; the samples taken inside minimize() but outside the objective (the optimiser, the
journal, the history, the callback, and whatever else runs between two evaluations) are counted by innermost frame
and by call path. A sampling profiler in plain Python (py-spy is not on the GPU machines), cheap enough to leave the
timings' proportions intact.

    python benchmarks/optimizer_stacks.py bench --fwi --no-deepwave --device cuda:0 -o OUTDIR -q
    python benchmarks/optimizer_stacks.py fwi configs/fwi_demo.yaml -o OUTDIR -q --force
"""

import collections
import sys
import threading
import time

from adseismic.cli import main

MAIN = threading.get_ident()
leaf, paths, counts = collections.Counter(), collections.Counter(), [0, 0]
stop = threading.Event()


def sample():
    while not stop.is_set():
        f = sys._current_frames().get(MAIN)
        names = []
        while f is not None:
            names.append(f"{f.f_code.co_name}:{f.f_code.co_filename.rsplit('/', 1)[-1]}:{f.f_lineno}")
            f = f.f_back
        counts[0] += 1
        functions = [n.split(":")[0] for n in names]
        if "minimize" in functions and "objective" not in functions:
            counts[1] += 1
            leaf[names[0]] += 1
            paths[" <- ".join(names[:6])] += 1
        time.sleep(0.001)


threading.Thread(target=sample, daemon=True).start()
t0 = time.perf_counter()
try:
    main(sys.argv[1:])
except SystemExit:
    pass
stop.set()
print(f"run {time.perf_counter() - t0:.1f} s; {counts[0]} samples, {counts[1]} inside minimize() outside the objective")
for k, v in leaf.most_common(25):
    print(f"{v:6d}  {k}")
print("call paths (innermost first):")
for k, v in paths.most_common(15):
    print(f"{v:6d}  {k}")
