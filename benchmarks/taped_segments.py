"""The taped gradients of the staggered physics (the bench's physics scenes: VD1000, Q1000, VTI1000, E3D200) against
their segment length: the default (the memory minimum), nt / 25 and nt (every level kept, no re-run), each the best of
`--repeats` warm calls after a first one (which captures the sweep's graphs on a GPU). One JSON line a run: scene,
segment length asked, segments, first call and best seconds, the sweep's peak memory estimate (bytes).

    python benchmarks/taped_segments.py --device cuda:0 --scenes VD1000 Q1000

Run it at two commits to compare sweeps (docs/benchmarks.md, "The staggered family's taped gradients").
"""

import argparse
import json
import time

import numpy as np
import warp as wp

from adseismic.accel import graphs
from adseismic.bench import DT, DX, PEAK_FREQUENCY, PML, SCENES, build_arrays, physics


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--scenes", nargs="+", default=["VD1000", "Q1000"])
    ap.add_argument("--nt", type=int, default=None, help="time steps (default: the scene's)")
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    wp.config.quiet = True
    for name in a.scenes:
        spec = SCENES[name]
        arr = build_arrays(spec, a.nt)
        nt = arr.nt
        model = {k: wp.array(v, dtype=wp.float32, device=a.device) for k, v in arr.model.items()}
        observed = np.zeros((spec.shots, arr.receivers.shape[1], nt))

        def run(seg):
            wp.synchronize_device(a.device)
            t = time.perf_counter()
            g = physics.run_ours(spec.kind, "gradient", model, DX, DT, arr.amplitudes, arr.sources, arr.receivers, device=a.device,
                                 order=4, pml_width=PML, f_peak=PEAK_FREQUENCY, observed=observed, segment_length=seg)
            wp.synchronize_device(a.device)
            return time.perf_counter() - t, g

        for seg in (None, max(nt // 25, 1), nt):
            graphs.release()
            first, g = run(seg)
            best = min(run(seg)[0] for _ in range(a.repeats))
            print(json.dumps({"scene": name, "segment_length": seg, "segments": g.n_segments, "first_s": round(first, 4),
                              "best_s": round(best, 4), "peak_bytes_estimate": g.peak_bytes_estimate}), flush=True)


if __name__ == "__main__":
    main()
