"""One captured step of acoustic_vd's 2D tiled forward on a bench scene (in place, the receivers recorded in the
step's launches, as the captured loop runs it), three ways: no source, the sources added by an inject launch, their
terms added in the tiled pressure launch (AcousticVD.source_operator's plan, the default). Microseconds a step,
STEPS steps a CUDA graph, one device in one run.

    python benchmarks/vd_sources.py [VD1000 ...]       # a GPU: cuda:0
"""

import sys
from pathlib import Path

import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bandwidth import timed  # noqa: E402
from staggered_tiles import STEPS, graphed  # noqa: E402

from adseismic import bench  # noqa: E402
from adseismic.solve import acoustic_vd as api  # noqa: E402


def main(scenes):
    wp.init()
    dev = wp.get_device("cuda:0")
    for name in scenes:
        a = bench.build_arrays(bench.SCENES[name])
        m = {k: wp.array(v, dtype=wp.float32, device=dev) for k, v in a.model.items()}
        su = api.setup_acoustic_vd(m["vp"], m["rho"], bench.DX, bench.DT, a.amplitudes, a.sources, a.receivers, order=4,
                                   pml_width=bench.PML, device="cuda:0")  # fmt: skip
        prop, mat = su.prop, su.model()
        amp, op = su.sources_of(su.amplitudes, fixed=True)
        data = su.new_data(1000)
        st = prop.new_state()

        def variant(sources):
            return lambda: prop.step(st, mat, sources, 0, record=(data, su.receiver_op, 0))

        for label, sources in (("no source", None), ("inject launch", (amp, op[:2])), ("terms in the pressure launch", (amp, op))):
            print(f"{name} {label:30s} {timed(graphed(variant(sources), dev), dev, 20) / STEPS:6.2f} us", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:] or ["VD1000"])
