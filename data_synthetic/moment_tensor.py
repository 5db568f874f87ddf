"""Synthetic moment-tensor events in an elastic 2D model, recorded on two-component (Z, X) surface stations and
written as MiniSEED + StationXML with latitude/longitude (what `adseismic locate configs/locate_mt_demo.yaml` reads).

Two events: "dc", a double couple on a fault dipping DIP degrees toward +x (reverse, striking along the section's
normal), and "general", an in-plane tensor with isotropic and CLVD parts. The traces are simulated on a grid twice
as fine as the inversion's (FINE_FACTOR) at order 8, at dt_fine = 0.5 ms (no inverse crime), moved from the
solver's velocity sample times (k - 1/2) dt to k dt, resampled (anti-aliased) to 200 samples/s and given Gaussian
noise of `noise` x each trace's peak. Channel ...HHZ is the vertical velocity, positive UP (SEED), = -vz; ...HHX the
horizontal velocity along the line's azimuth (+x), = vx; m/s.

    python -m adseismic.data_synthetic.moment_tensor configs/data/location_mt_demo
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np

REFERENCE = {"latitude": 46.0, "longitude": 7.0, "datum": 0.0, "azimuth": 90.0}
#: the model of the demo (physics elastic): m/s and kg/m^3; shape (nz, nx) nodes at `spacing` m
MODEL = {"shape": [37, 61], "spacing": 20.0, "vp": [2600.0, 3200.0], "vs": [1500.0, 1850.0], "rho": [2300.0, 2500.0],
         "interfaces": [300.0]}  # fmt: skip
DIP = 35.0  # degrees, the "dc" event's fault, dipping toward +x
M0 = 1.0e12  # N m per metre of line
EVENTS = {
    "dc": {"position": (452.3, 567.1), "origin_time": 0.5, "peak_frequency": 7.0, "constraint": "double_couple",
           "moment_tensor": None},  # set below from DIP and M0
    "general": {"position": (452.3, 567.1), "origin_time": 0.5, "peak_frequency": 7.0, "constraint": "none",
                "moment_tensor": (0.7e12, -0.3e12, 0.5e12)},
}  # fmt: skip
STATIONS_X = np.linspace(60.0, 1140.0, 10)  # m along the line, at STATION_Z depth
STATION_Z = 10.0
START = "2026-11-22T08:15:00"
RECORD = 1.6  # s
FINE_FACTOR = 2
NOISE = 0.05


def dc_tensor():
    from adseismic.location.moment_tensor import in_plane_double_couple

    return in_plane_double_couple(M0, DIP)


def model(spacing: float):
    """The demo's ElasticModel on a grid of `spacing` m (same extent)."""
    from adseismic.data.models import ElasticModel
    from adseismic.data_synthetic.generators import layered

    h0 = MODEL["spacing"]
    shape = [round((n - 1) * h0 / spacing) + 1 for n in MODEL["shape"]]
    return ElasticModel(*(layered(shape, spacing, MODEL[k], MODEL["interfaces"]) for k in ("vp", "vs", "rho")))


def stations() -> np.ndarray:
    """(n, 2) station positions (z, x) m."""
    return np.stack([np.full(len(STATIONS_X), STATION_Z), STATIONS_X], axis=1)


def simulate(event: str, dt: float = 0.005, noise: float = NOISE, seed: int = 1, noise_free: bool = False):
    """(vz, vx) each (n_stations, nt) at t = k dt after the record start (m/s) of EVENTS[event], with noise x each
    trace's peak of Gaussian noise (none when noise_free)."""
    from adseismic.data.preprocess import preprocess
    from adseismic.location.locate import source_wavelet
    from adseismic.solve.elastic import forward_elastic

    ev = EVENTS[event]
    m = dc_tensor() if ev["moment_tensor"] is None else np.asarray(ev["moment_tensor"], float)
    h = MODEL["spacing"] / FINE_FACTOR
    fine = model(h)
    dtf = 5e-4
    ntf = round(RECORD / dtf) + 2
    s, _ = source_wavelet(ntf, dtf, ev["origin_time"], ev["peak_frequency"], 1.0)
    r = forward_elastic(fine.vp.values, fine.vs.values, fine.rho.values, h, dtf, s[None, None], np.array(ev["position"])[None, None],
                        stations()[None], source_type="moment", source_components=m[None, None], order=8, precision="float64",
                        pml_width=30, pml_frequency=ev["peak_frequency"])  # fmt: skip
    t_solver, t = (np.arange(ntf) - 0.5) * dtf, np.arange(ntf - 1) * dtf  # velocities are recorded at (k - 1/2) dt
    out = []
    for d in (r.vz[0], r.vx[0]):
        d = np.stack([np.interp(t, t_solver, tr) for tr in d])
        d = preprocess(d, dtf, dt=dt, nt=round(RECORD / dt) + 1, detrend=False, taper=0.0)  # anti-aliased
        out.append(d)
    if not noise_free:
        rng = np.random.default_rng(seed)
        out = [d + noise * np.abs(d).max(axis=1, keepdims=True) * rng.standard_normal(d.shape) for d in out]
    return out[0], out[1]


def write_event(directory, event: str = "dc", seed: int = 1, noise: float = NOISE):
    """Simulate EVENTS[event] and write event.mseed + event.xml (channels HHZ = -vz, HHX = vx) into ``directory``."""
    from obspy import UTCDateTime

    from adseismic.data.geometry import Reference
    from adseismic.data.traces import StationTraces
    from adseismic.data.write import write_station_traces

    dt = 0.005
    vz, vx = simulate(event, dt, noise, seed)
    rec = stations()
    n = len(rec)
    data = np.concatenate([-vz, vx])  # Z positive up
    names = [f"AD.M{i:02d}..HHZ" for i in range(n)] + [f"AD.M{i:02d}..HHX" for i in range(n)]
    st = StationTraces(data=data, dt=dt, starttime=UTCDateTime(START), positions=np.concatenate([rec, rec]), names=names,
                       reference=Reference(**REFERENCE))  # fmt: skip
    return write_station_traces(pathlib.Path(directory), st)


if __name__ == "__main__":
    print(write_event(sys.argv[1] if len(sys.argv) > 1 else "configs/data/location_mt_demo"))
