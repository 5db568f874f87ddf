"""The built-in location example: one 2D event recorded by 12 surface stations, written as MiniSEED +
StationXML with latitude/longitude (what `adseismic locate configs/locate_demo.yaml` reads).

The traces are simulated on a finer grid and a higher order than the locator will plan (dx 10 m,
order 8, vs the planner's choice for 1% accuracy), so the example carries discretisation error
like real data, then decimated to 100 samples/s, given 5% Gaussian noise and a 1 s pre-event window.

    python -m adseismic.data_synthetic.location configs/data/location_demo
"""
from __future__ import annotations

import pathlib
import sys

import numpy as np

from adseismic.data_synthetic.generators import layered

REFERENCE = {"latitude": 46.0, "longitude": 7.0, "datum": 0.0, "azimuth": 90.0}
EVENT = {"position": (703.7, 1612.3), "origin_time": 1.0, "peak_frequency": 6.0}  # z, x (m); s after the record start
MODEL = {"kind": "layered", "shape": [61, 111], "spacing": 20.0, "velocities": [1800.0, 2400.0, 3000.0], "interfaces": [300.0, 800.0]}
START = "2026-11-21T04:44:00"
NOISE = 0.05  # of each trace's peak


def write_location_demo(directory, seed: int = 1):
    """Simulate the example event and write event.mseed + event.xml into ``directory``."""
    from obspy import UTCDateTime

    from adseismic.data.geometry import Reference
    from adseismic.data.preprocess import preprocess
    from adseismic.data.traces import StationTraces
    from adseismic.data.write import write_station_traces
    from adseismic.location.locate import source_wavelet
    from adseismic.solve.acoustic import forward

    fine = layered([121, 221], 10.0, MODEL["velocities"], MODEL["interfaces"])
    rec = np.array([[10.0, x] for x in np.linspace(100.0, 2100.0, 12)])
    dt, record = 1e-3, 3.0
    nt = int(round(record / dt)) + 1
    s, _ = source_wavelet(nt, dt, EVENT["origin_time"], EVENT["peak_frequency"], 1.0)
    d = forward(fine.values, 10.0, dt, s[None, None], np.array(EVENT["position"])[None, None], rec[None], order=8,
                precision="float64", pml_width=20, pml_frequency=EVENT["peak_frequency"]).receiver_amplitudes[0]  # fmt: skip
    d = preprocess(d, dt, dt=0.01, nt=int(round(record / 0.01)) + 1, detrend=False, taper=0.0)  # anti-aliased to 100 Hz
    d += NOISE * np.abs(d).max(axis=1, keepdims=True) * np.random.default_rng(seed).standard_normal(d.shape)
    st = StationTraces(data=d, dt=0.01, starttime=UTCDateTime(START), positions=rec,
                       names=[f"AD.S{i:02d}..HHZ" for i in range(len(rec))], reference=Reference(**REFERENCE))  # fmt: skip
    return write_station_traces(pathlib.Path(directory), st)


if __name__ == "__main__":
    print(write_location_demo(sys.argv[1] if len(sys.argv) > 1 else "configs/data/location_demo"))
