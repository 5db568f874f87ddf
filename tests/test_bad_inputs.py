"""The bad-input catalogue (issue 24): every class of bad input ends with a clear refusal (exit status 2, one message
naming the key or file, the value and the fix, no traceback) and leaves no file in the output directory; legal but
suspicious input runs with a warning that gives the numbers.

Each row of CATALOGUE: name, the files to write (name -> text, bytes or a function of the directory), the command
line (``{d}`` is the case's directory, ``{out}`` its output directory), the expected exit status and fragments
that must all appear in the output. Everything is refused before any simulation runs, so the whole table takes
seconds on a CPU.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from adseismic.cli import main

# --------------------------------------------------------------------------- building blocks

MODEL = "model: {kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0}\n"
GEOMETRY = ("geometry:\n  sources: {points: [{x: 100, z: 20}, {x: 200, z: 20}]}\n"
            "  receivers: {line: {start: {x: 0, z: 10}, end: {x: 300, z: 10}, count: 16}}\n")
WAVELET = "wavelet: {kind: ricker, peak_frequency: 10.0}\n"
SIM = "simulation: {order: 4, pml_width: 8}\n"
FORWARD = MODEL + GEOMETRY + WAVELET + SIM
TRUE = "true_model: {kind: gaussian_anomaly, shape: [21, 31], spacing: 10.0, background: 2000.0, perturbation: 100.0, center: [100, 150], radius: 30}\n"


def fwi(inversion: str = "{bands: [null], iterations: 1}", data: str = TRUE, sim: str = SIM, model: str = MODEL) -> str:
    return model + GEOMETRY + WAVELET + sim + data + f"inversion: {inversion}\n"


def npy(array):
    def write(d: Path, name: str):
        np.save(d / name, array)
    return write


def h5(fill):
    def write(d: Path, name: str):
        import h5py

        with h5py.File(d / name, "w") as f:
            fill(f)
    return write


def truncated(writer, keep: float):
    """The file `writer` makes, cut to the fraction `keep` of its bytes."""
    def write(d: Path, name: str):
        writer(d, name)
        data = (d / name).read_bytes()
        (d / name).write_bytes(data[: int(len(data) * keep)])
    return write


def forward_data(zero=False, dt=1e-3, nt=400):
    """An 'adseismic forward' data.h5 for the FWI geometry above (written directly, no simulation)."""
    def write(d: Path, name: str):
        from adseismic.data.store import write_forward

        src = np.array([[20.0, 100.0], [20.0, 200.0]])
        rec = np.stack([np.full(16, 10.0), np.linspace(0, 300, 16)], axis=1)
        rng = np.random.default_rng(0)
        data = np.zeros((2, 16, nt)) if zero else rng.standard_normal((2, 16, nt))
        write_forward(d / name, receiver_data=data, source_wavelet=np.zeros(nt), dt=dt, source_coordinates=src,
                      receiver_coordinates=rec, velocity=np.full((21, 31), 2000.0), spacing=10.0, origin=(0.0, 0.0))
    return write


def miniseed(d: Path, name: str, truncate=False):
    import obspy

    tr = obspy.Trace(np.random.default_rng(1).standard_normal(20000).astype(np.float32),
                     {"network": "XX", "station": "A", "channel": "HHZ", "sampling_rate": 100.0})
    obspy.Stream([tr]).write(str(d / name), format="MSEED", reclen=512, encoding="FLOAT32")
    if truncate:
        data = (d / name).read_bytes()
        (d / name).write_bytes(data[: len(data) // 2 + 100])  # half the file, ending inside a record


def stations_off_line(d: Path, name: str):
    """MiniSEED + StationXML of three stations on an east-west line through (45 N, 7 E) and one 10 degrees
    (~1,112 km) north of it."""
    from adseismic.data.traces import StationTraces
    from adseismic.data.write import write_station_traces

    rng = np.random.default_rng(2)
    st = StationTraces(data=rng.standard_normal((4, 400)), dt=0.005, starttime=0.0, positions=np.zeros((4, 2)),
                       names=[f"XX.S{i}..HHZ" for i in range(4)])
    lat = [45.0, 45.0, 45.0, 55.0]
    lon = [7.0 + k for k in (0.0, 0.002, 0.004, 0.002)]
    write_station_traces(d, st, latitude=lat, longitude=lon, elevation=[0.0] * 4, stem=Path(name).stem)


def two_component(d: Path, name: str, lacking_x=("S2",)):
    """MiniSEED of three stations XX.S0..S2 with channels HHZ and HHX (noise), but no HHX at the stations in lacking_x."""
    import obspy

    rng = np.random.default_rng(3)
    traces = [obspy.Trace(rng.standard_normal(400), {"network": "XX", "station": f"S{i}", "channel": f"HH{c}", "delta": 0.005})
              for i in range(3) for c in "ZX" if not (c == "X" and f"S{i}" in lacking_x)]  # fmt: skip
    obspy.Stream(traces).write(str(d / name), format="MSEED", encoding="FLOAT64")


def judi_segy(d: Path, name: str):
    """A SEG-Y shot file written the way JUDI.jl writes one: positive depths (m) x 1000 in the elevation fields with
    scalar -1000, for the FWI geometry above (sources z = 20 m, receivers z = 10 m)."""
    import obspy
    from obspy.core import AttribDict
    from obspy.io.segy.segy import SEGYBinaryFileHeader, SEGYTraceHeader

    traces = []
    for s, sx in enumerate((100.0, 200.0)):
        for r, gx in enumerate(np.linspace(0, 300, 16)):
            h = SEGYTraceHeader()
            h.original_field_record_number, h.trace_number_within_the_original_field_record = s + 1, r + 1
            h.scalar_to_be_applied_to_all_coordinates = -1000
            h.scalar_to_be_applied_to_all_elevations_and_depths = -1000
            h.source_coordinate_x, h.group_coordinate_x = int(sx * 1000), int(gx * 1000)
            h.surface_elevation_at_source, h.receiver_group_elevation = 20_000, 10_000  # depths, as JUDI writes them
            h.sample_interval_in_ms_for_this_trace = 1000  # microseconds
            tr = obspy.Trace(np.random.default_rng(r).standard_normal(400).astype(np.float32), {"delta": 1e-3})
            tr.stats.segy = AttribDict(trace_header=h)
            traces.append(tr)
    st = obspy.Stream(traces)
    st.stats = AttribDict(binary_file_header=SEGYBinaryFileHeader())
    st.stats.binary_file_header.number_of_data_traces_per_ensemble = 16
    st.write(str(d / name), format="SEGY", data_encoding=5, byteorder=">")


LOCATE = ("preprocess: {noise_window: [0.0, 0.3]}\n"
          "model: {kind: constant, shape: [41, 61], spacing: 10.0, velocity: 2000.0, origin: [0, -300]}\n")


@dataclass
class Case:
    name: str
    files: dict
    argv: list
    status: int
    fragments: tuple
    absent: tuple = ()  # fragments that must NOT appear
    files_after: bool = field(default=False)  # the command may write outputs (status 0)


def C(name, files, argv, status, *fragments, absent=()):  # noqa: N802 - a table row
    return Case(name, files, argv, status, fragments, absent)


PLAN = ["plan", "{d}/c.yaml"]
FWD = ["forward", "{d}/c.yaml", "-o", "{out}"]


def elastic(vp="{kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0}", vs="{vp_ratio: 1.8}",
            rho="{gardner: true}", receivers="{line: {start: {x: 0, z: 10}, end: {x: 300, z: 10}, count: 16}}") -> str:
    """A forward config with physics elastic (the FORWARD scene's geometry, wavelet and simulation)."""
    return (f"physics: elastic\nmodel:\n  vp: {vp}\n  vs: {vs}\n  rho: {rho}\n"
            + GEOMETRY.replace("{line: {start: {x: 0, z: 10}, end: {x: 300, z: 10}, count: 16}}", receivers) + WAVELET + SIM)
FWI = ["fwi", "{d}/c.yaml", "-o", "{out}"]
AVD = elastic().replace("physics: elastic", "physics: acoustic_vd").replace("  vs: {vp_ratio: 1.8}\n", "")  # acoustic_vd: {vp, rho}
ATRUE = "true_model:\n  vp: {kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2100.0}\n  rho: {gardner: true}\n"
ETRUE = "true_model:\n  vp: {kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2100.0}\n  vs: {vp_ratio: 1.8}\n  rho: {gardner: true}\n"
VTI = AVD.replace("physics: acoustic_vd", "physics: vti").replace("  rho:", "  epsilon: 0.1\n  delta: 0.05\n  rho:")  # {vp, epsilon, delta, rho}
VQ = AVD.replace("physics: acoustic_vd", "physics: viscoacoustic").replace("  rho:", "  q: 30.0\n  rho:")  # viscoacoustic: {vp, q, rho}
VTRUE = ATRUE.replace("  rho:", "  epsilon: 0.1\n  delta: 0.05\n  rho:")  # a vti true model
VQTRUE = ATRUE.replace("  rho:", "  q: 30.0\n  rho:")  # a viscoacoustic true model
LOC = ["locate", "{d}/c.yaml", "-o", "{out}"]
IMAGE = ["image", "{d}/c.yaml", "-o", "{out}"]
ELOCATE = ("physics: elastic\npreprocess: {noise_window: [0.0, 0.3]}\nmodel:\n"
           "  vp: {kind: constant, shape: [41, 61], spacing: 10.0, velocity: 2000.0, origin: [0, -300]}\n  vs: {vp_ratio: 1.8}\n"
           "  rho: {gardner: true}\ntraces: {paths: [ev.mseed], local_coordinates: {XX.S0: [10, -100], XX.S1: [10, 0], XX.S2: [10, 100]}}\n")
ACOUSTIC_TRACES = "traces: {paths: [ev.mseed], local_coordinates: {XX.A: [10, 0]}}\n"


def image(settings: str, data: str = TRUE) -> str:
    """An `adseismic image` config of the FORWARD scene with the image section `settings`."""
    return FORWARD + data + f"image: {settings}\n"


CATALOGUE = [
    # --- 1. the config loader
    C("non-utf8 config", {"c.yaml": FORWARD.encode() + b"# caf\xe9\n"}, PLAN, 2, "not UTF-8", "byte 305", "line 7", "c.yaml"),
    C("binary file as config", {"c.yaml": bytes(range(256))}, PLAN, 2, "not UTF-8", "byte 128"),
    C("duplicate key", {"c.yaml": FORWARD + "wavelet: {kind: ricker, peak_frequency: 5.0}\n"}, PLAN, 2,
      "'wavelet' appears twice", "line 5 and line 7"),
    C("duplicate nested key", {"c.yaml": MODEL + GEOMETRY + "wavelet: {kind: ricker, peak_frequency: 10.0, peak_frequency: 5}\n"},
      PLAN, 2, "'peak_frequency' appears twice"),
    C("spacing: true", {"c.yaml": FORWARD.replace("spacing: 10.0", "spacing: true")}, PLAN, 2,
      "model.spacing", "True", "true/false are not numbers"),
    C("dx: true", {"c.yaml": FORWARD.replace("pml_width: 8", "pml_width: 8, dx: true")}, PLAN, 2,
      "simulation.dx", "true/false are not numbers"),
    C("velocity: yes", {"c.yaml": FORWARD.replace("velocity: 2000.0", "velocity: yes")}, PLAN, 2, "model.velocity", "True"),
    C("1.4e15 receivers on a line", {"c.yaml": FORWARD.replace("count: 16", "count: 1.4e15")}, PLAN, 2,
      "geometry.receivers.line.count", "1.4e15", "more than 1,000,000"),
    C("impossible date", {"c.yaml": FORWARD.replace("kind: constant,", "kind: constant, name: 2001-02-30,")}, PLAN, 2,
      "could not be parsed", "day is out of range"),
    C("nested too deeply", {"c.yaml": "model: " + "[" * 5000 + "]" * 5000 + "\n"}, PLAN, 2, "c.yaml"),
    C("wavelet kind a list", {"c.yaml": FORWARD.replace("kind: ricker", "kind: []")}, PLAN, 2, "wavelet.kind", "[]"),
    C("bands high to low", {"c.yaml": fwi("{bands: [8.0, 4.0], iterations: 1}")}, FWI, 2,
      "inversion.bands", "band 1 (up to 4 Hz) is lower than band 0 (up to 8 Hz)", "reorder"),
    C("full band before a low-pass", {"c.yaml": fwi("{bands: [null, 4.0], iterations: 1}")}, FWI, 2,
      "inversion.bands", "null (full band)"),
    # --- 2. model loading
    C("empty npy array", {"m.npy": npy(np.zeros((0, 5))), "c.yaml": FORWARD.replace(
        "kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0", "kind: npy, path: m.npy, spacing: 10.0")},
      PLAN, 2, "model.path", "m.npy", "empty array"),
    C("empty npy file", {"m.npy": b"", "c.yaml": FORWARD.replace(
        "kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0", "kind: npy, path: m.npy, spacing: 10.0")},
      PLAN, 2, "model.path", "empty file"),
    C("truncated npy", {"m.npy": truncated(npy(np.full((21, 31), 2000.0)), 0.5), "c.yaml": FORWARD.replace(
        "kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0", "kind: npy, path: m.npy, spacing: 10.0")},
      PLAN, 2, "model.path", "not a readable .npy", "truncated"),
    C("complex npy", {"m.npy": npy(np.full((21, 31), 2000.0 + 1j)), "c.yaml": FORWARD.replace(
        "kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0", "kind: npy, path: m.npy, spacing: 10.0")},
      PLAN, 2, "model.path", "complex", "numpy.real"),
    C("NaN in npy", {"m.npy": npy(np.where(np.eye(21, 31) > 0, np.nan, 2000.0)), "c.yaml": FORWARD.replace(
        "kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0", "kind: npy, path: m.npy, spacing: 10.0")},
      PLAN, 2, "model.path", "non-finite"),
    C("inf in npy", {"m.npy": npy(np.full((21, 31), np.inf)), "c.yaml": FORWARD.replace(
        "kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0", "kind: npy, path: m.npy, spacing: 10.0")},
      PLAN, 2, "model.path", "non-finite"),
    C("empty HDF5 file", {"m.h5": b"", "c.yaml": FORWARD.replace(
        "kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0", "kind: hdf5, path: m.h5, dataset: v, spacing: 10.0")},
      PLAN, 2, "model.path", "m.h5", "not a readable HDF5 file"),
    C("corrupt HDF5 file", {"m.h5": b"\x89HDF\r\n\x1a\n" + bytes(300), "c.yaml": FORWARD.replace(
        "kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0", "kind: hdf5, path: m.h5, dataset: v, spacing: 10.0")},
      PLAN, 2, "model.path", "not a readable HDF5 file"),
    C("truncated HDF5 file", {"m.h5": truncated(h5(lambda f: f.create_dataset("v", data=np.full((21, 31), 2000.0))), 0.6),
                              "c.yaml": FORWARD.replace("kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0",
                                                        "kind: hdf5, path: m.h5, dataset: v, spacing: 10.0")},
      PLAN, 2, "model.path", "m.h5"),
    C("HDF5 string dataset", {"m.h5": h5(lambda f: f.create_dataset("v", data="fast")), "c.yaml": FORWARD.replace(
        "kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0", "kind: hdf5, path: m.h5, dataset: v, spacing: 10.0")},
      PLAN, 2, "model.path", "not numbers"),
    C("model of 1e16 nodes", {"c.yaml": FORWARD.replace("shape: [21, 31]", "shape: [100000000, 100000000]")}, PLAN, 2,
      "model.shape", "GiB", "more than this machine can hold"),
    C("observed HDF5 corrupt", {"obs.h5": truncated(forward_data(), 0.3), "c.yaml": fwi(data="observed: {kind: hdf5, path: obs.h5}\n")},
      FWI, 2, "observed.path", "obs.h5"),
    C("observed HDF5 empty", {"obs.h5": b"", "c.yaml": fwi(data="observed: {kind: hdf5, path: obs.h5}\n")},
      FWI, 2, "observed.path", "not a readable HDF5 file"),
    C("observed HDF5 without datasets", {"obs.h5": h5(lambda f: f.create_dataset("x", data=1.0)),
                                         "c.yaml": fwi(data="observed: {kind: hdf5, path: obs.h5}\n")},
      FWI, 2, "observed.path", "not a complete 'adseismic forward' data file"),
    C("true model smaller than the geometry", {"c.yaml": fwi(data=TRUE.replace("shape: [21, 31]", "shape: [21, 11]")
                                                          .replace("center: [100, 150]", "center: [100, 50]"))},
      FWI, 2, "true_model", "smaller than the geometry", "geometry.sources point 1"),
    # --- 3. traces
    C("half-truncated MiniSEED", {"ev.mseed": lambda d, n: miniseed(d, n, truncate=True),
                                  "c.yaml": LOCATE + "traces: {paths: [ev.mseed], local_coordinates: {XX.A: [10, 0]}}\n"},
      LOC, 2, "ev.mseed", "truncated or corrupt", "bytes"),
    C("JUDI SEG-Y read as elevations", {"shots.segy": judi_segy,
                                        "c.yaml": fwi(data="observed: {kind: segy, path: shots.segy, depth_convention: elevation}\n")},
      FWI, 2, "observed.path", "only the depths differ", "depth_convention: depth"),
    C("depth_convention for station data", {"c.yaml": fwi(data="observed: {kind: mseed, paths: [a.mseed, b.mseed], depth_convention: depth}\n")},
      FWI, 2, "observed.depth_convention", "only for kind segy or su"),
    C("depth_convention misspelt", {"shots.segy": judi_segy, "c.yaml": fwi(data="observed: {kind: segy, path: shots.segy, depth_convention: down}\n")},
      FWI, 2, "observed.depth_convention", "'down'", "auto, elevation, depth"),
    # --- 4. 2D locate with a station far off the model's line
    C("station 1,112 km off the 2D line", {"ev.mseed": stations_off_line,
                                           "c.yaml": LOCATE + "traces: {paths: [ev.mseed], inventory: ev.xml, reference: [45.0, 7.0]}\n"},
      LOC, 2, "traces.reference", "XX.S3..HHZ (1,11", "km)", "off the 2D model's line"),
    # --- 5. the planner
    C("velocities in km/s", {"c.yaml": FORWARD.replace("velocity: 2000.0", "velocity: 2.0")}, PLAN, 2,
      "model", "2 m/s", "km/s? multiply by 1000"),
    C("layered velocities in km/s", {"c.yaml": FORWARD.replace("kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2000.0",
                                                              "kind: layered, shape: [21, 31], spacing: 10.0, velocities: [1.5, 3.0], interfaces: [100]")},
      PLAN, 2, "1.5..3 m/s", "km/s? multiply by 1000"),
    C("memory budget", {"c.yaml": FORWARD.replace("pml_width: 8", "pml_width: 8, memory_budget_gb: 1e-6")}, PLAN, 2,
      "simulation.memory_budget_gb", "estimated", "GiB", "simulation.force: true"),
    C("memory budget forced", {"c.yaml": FORWARD.replace("pml_width: 8", "pml_width: 8, memory_budget_gb: 1e-6, force: true")},
      PLAN, 0, "running anyway"),
    C("more memory than the machine has", {"c.yaml": FORWARD.replace("shape: [21, 31], spacing: 10.0", "shape: [21, 1001], spacing: 1000.0")
                                           .replace("end: {x: 300, z: 10}, count: 16", "end: {x: 1000000, z: 10}, count: 16")
                                           .replace("pml_width: 8", "pml_width: 8, dx: 0.2, domain: model")},  # ~11 TiB
      PLAN, 2, "simulation: the run needs an estimated", "e+04 GiB", "free on cpu"),
    C("pinned dt without dx", {"c.yaml": FORWARD.replace("pml_width: 8", "pml_width: 8, dt: 0.004")}, PLAN, 0,
      "the smallest dx for which the pinned dt = 0.004 s is stable", "under-resolved", absent=("e-07", "e-08", "e-09")),
    C("force must be a boolean", {"c.yaml": FORWARD.replace("pml_width: 8", "pml_width: 8, force: 1")}, PLAN, 2,
      "simulation.force", "true or false"),
    # --- 6. FWI selections and bands
    C("time window after the record", {"c.yaml": fwi("{bands: [null], iterations: 1, time_window: [50, 60]}")}, FWI, 2,
      "inversion.time_window", "[50, 60] s keeps no sample"),
    C("time window before any arrival", {"c.yaml": fwi("{bands: [null], iterations: 1, time_window: [0.0, 0.02], offsets: [200, 400]}")},
      FWI, 2, "inversion.time_window", "earliest possible arrival"),
    C("offsets select nothing", {"c.yaml": fwi("{bands: [null], iterations: 1, offsets: [5000, 6000]}")}, FWI, 2,
      "inversion.offsets", "selects none of the 32 source-receiver pairs"),
    C("all-zero observed data", {"obs.h5": forward_data(zero=True), "c.yaml": fwi(data="observed: {kind: hdf5, path: obs.h5}\n")},
      FWI, 2, "every sample of the observed data is zero"),
    C("400 Hz band above the simulation's Nyquist", {"c.yaml": fwi("{bands: [4.0, 400.0], iterations: 1}")}, FWI, 2,
      "inversion.bands[1]", "400 Hz", "Nyquist", absent=("inf%",)),
    C("band above the data's Nyquist", {"obs.h5": forward_data(dt=0.01, nt=60),
                                        "c.yaml": fwi("{bands: [60.0], iterations: 1}", data="observed: {kind: hdf5, path: obs.h5}\n",
                                                      sim=SIM.replace("pml_width: 8", "pml_width: 8, dt: 0.001, dx: 5"))},
      FWI, 2, "inversion.bands[0]", "60 Hz", "Nyquist frequency 50 Hz of the observed data", absent=("inf%",)),
    C("checkpoint budget below the minimum", {"c.yaml": fwi("{bands: [null], iterations: 1, memory_budget_gb: 1e-9}")}, FWI, 2,
      "inversion.memory_budget_gb", "too small"),
    C("fwi above the memory budget", {"c.yaml": fwi(sim=SIM.replace("pml_width: 8", "pml_width: 8, memory_budget_gb: 1e-6"))}, FWI, 2,
      "simulation.memory_budget_gb", "inversion: gradients of 2 shot(s)"),
    C("fwi velocities in km/s", {"c.yaml": fwi("{bands: [null], iterations: 1, bounds: [1.0, 3.0]}", data=TRUE,
                                               model=MODEL.replace("2000.0", "2.0"))}, FWI, 2, "km/s? multiply by 1000"),
    # --- physics elastic (issue 23): bad combinations refused before any work
    C("elastic vs > vp / sqrt(2)", {"c.yaml": elastic(vs="{kind: constant, velocity: 1500.0}")}, FWD, 2,
      "model.vs: vs = 1500 m/s > vp / sqrt(2) = 1414.21 m/s", "negative Lame lambda", "vp/vs >= 1.414"),
    C("elastic vs >= vp", {"c.yaml": elastic(vs="{kind: constant, velocity: 2500.0}")}, FWD, 2,
      "model.vs: vs = 2500 m/s", "S faster than P"),
    C("elastic vp_ratio below sqrt(2)", {"c.yaml": elastic(vs="{vp_ratio: 1.2}")}, FWD, 2,
      "model.vs.vp_ratio: 1.2 is below sqrt(2)", "1.732"),
    C("elastic vs = 0 everywhere", {"c.yaml": elastic(vs="{kind: constant, velocity: 0.0}")}, FWD, 2,
      "model.vs.velocity: 0", "use physics: acoustic"),
    C("elastic vs in km/s", {"c.yaml": elastic(vs="{kind: constant, velocity: 1.1}")}, FWD, 2,
      "model.vs: shear speeds down to 1.1 m/s", "km/s? multiply by 1000"),
    C("elastic zero density", {"c.yaml": elastic(rho="{kind: constant, velocity: 0.0}")}, FWD, 2,
      "model.rho.velocity: 0.0 is not a positive density", "kg/m^3"),
    C("elastic negative density", {"c.yaml": elastic(rho="{kind: constant, velocity: -2000.0}")}, FWD, 2,
      "model.rho.velocity: -2000", "kg/m^3"),
    C("elastic density in g/cm^3", {"c.yaml": elastic(rho="{kind: constant, velocity: 2.2}")}, FWD, 2,
      "model.rho: densities down to 2.2 kg/m^3", "multiply by 1000"),
    C("elastic physics with one velocity model", {"c.yaml": "physics: elastic\n" + FORWARD}, FWD, 2,
      "model: ", "physics elastic needs three", "vp_ratio", "set physics: acoustic"),
    C("elastic model keys with acoustic physics", {"c.yaml": elastic().replace("physics: elastic\n", "")}, FWD, 2,
      "model: vp, vs, rho are the keys of an elastic model", "set physics: elastic"),
    C("DAS with acoustic physics", {"c.yaml": FORWARD.replace("count: 16}", "count: 16}, das: {gauge_length: 10}")}, FWD, 2,
      "geometry.receivers.das: {'gauge_length': 10} needs physics: elastic"),
    C("components with acoustic physics", {"c.yaml": FORWARD.replace("count: 16}", "count: 16}, components: [vx]")}, FWD, 2,
      "geometry.receivers.components: ['vx'] needs physics: elastic"),
    C("moment tensor with acoustic physics", {"c.yaml": FORWARD + "source: {type: moment, components: [1, 1, 0]}\n"}, FWD, 2,
      "source: {'type': 'moment'", "needs physics: elastic", "drop the source section"),
    C("force source with acoustic physics", {"c.yaml": FORWARD + "source: {type: force, components: [1, 0]}\n"}, PLAN, 2,
      "source: {'type': 'force'", "needs physics: elastic"),
    C("elastic moment tensor of 2 components", {"c.yaml": elastic() + "source: {type: moment, components: [1, 1]}\n"}, FWD, 2,
      "source.components: [1, 1] is not [m_xx, m_zz, m_xz] in N m/m"),
    C("elastic unknown physics", {"c.yaml": "physics: elastik\n" + FORWARD}, FWD, 2,
      "physics: 'elastik' is not one of acoustic, elastic"),
    C("DAS gauge outside the model", {"c.yaml": elastic(receivers="{line: {start: {x: 0, z: 10}, end: {x: 300, z: 10}, count: 16}, "
                                                                 "das: {gauge_length: 20}}")}, FWD, 2,
      "geometry.receivers.das (the gauges' starts", "x=-10", "outside the model"),
    C("elastic snapshots", {"c.yaml": elastic() + "output: {snapshot_interval: 0.05}\n"}, FWD, 2,
      "output.snapshot_interval: 0.05 s", "set it to 0"),
    C("elastic fwi true model with acoustic keys", {"c.yaml": elastic() + TRUE + "inversion: {bands: [null], iterations: 1}\n"},
      FWI, 2, "true_model: ", "physics elastic needs three"),
    # --- fwi: inverted quantities, parameterisation and bounds against the physics (issue 23)
    C("fwi vs with acoustic physics", {"c.yaml": fwi("{bands: [null], iterations: 1, parameters: [vs]}")}, FWI, 2,
      "inversion.parameters: vs is not a quantity here (physics acoustic has the one parameter vp)"),
    C("fwi lambda-mu-rho with acoustic physics", {"c.yaml": fwi("{bands: [null], iterations: 1, parameterization: lambda-mu-rho}")},
      FWI, 2, "inversion.parameterization: lambda-mu-rho needs physics: elastic"),
    C("fwi vp with lambda-mu-rho", {"c.yaml": elastic() + ETRUE + "inversion: {iterations: 1, parameterization: lambda-mu-rho, parameters: [vp]}\n"},
      FWI, 2, "inversion.parameters: vp is not a quantity here (parameterization lambda-mu-rho moves lambda, mu, rho)"),
    C("fwi bounds for a quantity not inverted", {"c.yaml": elastic() + ETRUE + "inversion: {iterations: 1, parameters: [vp], bounds: {vs: [900, 1400]}}\n"},
      FWI, 2, "inversion.bounds.vs: [900.0, 1400.0] bounds a quantity that is not inverted (inverted: vp)", "add vs to inversion.parameters"),
    C("fwi bounds min >= max", {"c.yaml": elastic() + ETRUE + "inversion: {iterations: 1, bounds: {vp: [2400, 1700]}}\n"}, FWI, 2,
      "inversion.bounds: vp: [2400, 1700] m/s has min >= max", "min < max"),
    C("fwi one bounds pair for elastic", {"c.yaml": elastic() + ETRUE + "inversion: {iterations: 1, bounds: [1500, 2500]}\n"}, FWI, 2,
      "inversion.bounds: [1500.0, 2500.0] is one [min, max] pair but physics elastic inverts vp, vs, rho", "{vp: [1500, 3500]"),
    C("fwi negative lambda bound", {"c.yaml": elastic() + ETRUE + "inversion: {iterations: 1, parameterization: lambda-mu-rho, "
                                                                  "bounds: {lambda: [-1e9, 9e9]}}\n"}, FWI, 2,
      "inversion.bounds.lambda: [-1e+09, 9e+09] Pa allows lambda < 0", "lower bound >= 0"),
    C("fwi elastic bounds not containing the start", {"c.yaml": elastic() + ETRUE + "inversion: {iterations: 1, bounds: {vs: [500, 900]}}\n"},
      FWI, 2, "inversion.bounds.vs: [500, 900] m/s do not contain the start model's range [1111.11, 1111.11] m/s"),
    C("fwi nn model with elastic physics", {"c.yaml": fwi(model="physics: elastic\nmodel: {kind: nn, shape: [21, 31], spacing: 10.0, v0: 2000.0, scale: 200.0}\n")},
      FWI, 2, "model.kind: nn with physics elastic: a network represents the acoustic velocity only"),
    C("fwi nn model without v0", {"c.yaml": fwi(model="model: {kind: nn, shape: [21, 31], spacing: 10.0, scale: 200.0}\n")}, FWI, 2,
      "model.v0"),
    C("fwi elastic pseudo_hessian", {"c.yaml": elastic() + ETRUE + "inversion: {iterations: 1, preconditioning: pseudo_hessian}\n"}, FWI, 2,
      "inversion.preconditioning: pseudo_hessian is acoustic only", "use none or depth"),
    C("fwi elastic observed files", {"c.yaml": elastic() + "observed: {kind: hdf5, path: obs.h5}\ninversion: {iterations: 1}\n"}, FWI, 2,
      "observed: given with physics elastic", "use true_model"),
    C("fwi elastic per-band grids", {"c.yaml": elastic() + ETRUE + "inversion: {iterations: 1, grid: per_band}\n"}, FWI, 2,
      "inversion.grid: per_band with physics elastic", "acoustic pixel models only", "use grid: fixed"),
    C("fwi nn model per-band grids", {"c.yaml": fwi("{bands: [3.0, null], iterations: 1, grid: per_band}",
                                                    model="model: {kind: nn, shape: [21, 31], spacing: 10.0, v0: 2000.0, scale: 200.0}\n")},
      FWI, 2, "inversion.grid: per_band with a network model", "use grid: fixed"),
    # --- physics acoustic_vd (issue 26): its own solver (solve/acoustic_vd.py), 2D and 3D
    C("acoustic_vd with vs", {"c.yaml": elastic().replace("physics: elastic", "physics: acoustic_vd")}, FWD, 2,
      "model.vs: {'vp_ratio': 1.8} given with physics acoustic_vd", "drop vs", "physics: elastic"),
    C("acoustic_vd one velocity model", {"c.yaml": "physics: acoustic_vd\n" + FORWARD}, FWD, 2,
      "model: ", "physics acoustic_vd needs two, {vp, rho}"),
    C("acoustic_vd density in g/cm^3", {"c.yaml": AVD.replace("rho: {gardner: true}", "rho: {kind: constant, velocity: 2.2}")}, FWD, 2,
      "model.rho: densities down to 2.2 kg/m^3", "multiply by 1000"),
    C("acoustic_vd force source", {"c.yaml": AVD + "source: {type: force, components: [1, 0]}\n"}, FWD, 2,
      "source.type: 'force' with physics acoustic_vd", "set type: explosive"),
    C("acoustic_vd snapshots", {"c.yaml": AVD + "output: {snapshot_interval: 0.05}\n"}, FWD, 2,
      "output.snapshot_interval: 0.05 s", "physics acoustic_vd"),
    C("fwi acoustic_vd inverting vs", {"c.yaml": AVD + ATRUE + "inversion: {iterations: 1, parameters: [vs]}\n"}, FWI, 2,
      "inversion.parameters: vs is not a quantity here (physics acoustic_vd is a fluid: vs stays 0)", "use any of vp, rho"),
    C("fwi acoustic_vd lambda-mu-rho", {"c.yaml": AVD + ATRUE + "inversion: {iterations: 1, parameterization: lambda-mu-rho}\n"},
      FWI, 2, "inversion.parameterization: lambda-mu-rho with physics acoustic_vd", "ip-rho"),
    C("fwi impedance with elastic physics", {"c.yaml": elastic() + ETRUE + "inversion: {iterations: 1, parameterization: ip-rho}\n"},
      FWI, 2, "inversion.parameterization: ip-rho (acoustic impedance) needs physics: acoustic_vd"),
    C("image with acoustic_vd", {"c.yaml": AVD + ATRUE}, IMAGE, 2, "physics: acoustic_vd is not available for adseismic image",
      "use physics: acoustic"),
    C("locate with acoustic_vd", {"c.yaml": ELOCATE.replace("physics: elastic", "physics: acoustic_vd")}, LOC, 2,
      "physics: acoustic_vd is not available for adseismic locate", "use physics: acoustic"),
    # --- physics vti (issue 26): 2D pseudo-acoustic VTI, forward and fwi
    C("vti epsilon below delta", {"c.yaml": VTI.replace("delta: 0.05", "delta: 0.2")}, FWD, 2,
      "model.epsilon, model.delta: epsilon < delta", "epsilon = 0.1, delta = 0.2", "use epsilon >= delta"),
    C("vti delta at -1/2", {"c.yaml": VTI.replace("delta: 0.05", "delta: -0.5")}, FWD, 2,
      "model.epsilon, model.delta: delta <= -0.5", "use delta > -0.5"),
    C("vti epsilon file of the wrong shape", {"c.yaml": VTI.replace("epsilon: 0.1", "epsilon: {kind: npy, path: eps.npy}"),
                                              "eps.npy": npy(np.full((31, 21), 0.1))}, FWD, 2,
      "model.epsilon.path: eps.npy holds a grid of shape [31, 21]", "not model.vp's (shape [21, 31]", "axes: xz"),
    C("vti epsilon with units", {"c.yaml": VTI.replace("epsilon: 0.1", "epsilon: {kind: npy, path: eps.npy, units: km/s}"),
                                 "eps.npy": npy(np.full((21, 31), 0.1))}, FWD, 2,
      "model.epsilon.units: 'km/s' is not a key of a 'npy' epsilon (it is dimensionless)"),
    C("vti epsilon as text", {"c.yaml": VTI.replace("epsilon: 0.1", "epsilon: 1e-1")}, FWD, 2,
      "model.epsilon: '1e-1' is not a number", "Thomsen's epsilon"),
    C("vti layered epsilon with a missing interface",
      {"c.yaml": VTI.replace("epsilon: 0.1", "epsilon: {kind: layered, values: [0.1, 0.2], interfaces: []}")}, FWD, 2, "model.epsilon.interfaces: [] is not a list of 1 depths"),
    C("vti without delta", {"c.yaml": VTI.replace("  delta: 0.05\n", "")}, FWD, 2, "model.delta: missing", "Thomsen"),
    C("vti one velocity model", {"c.yaml": "physics: vti\n" + FORWARD}, FWD, 2, "model: ", "physics vti needs {vp, epsilon, delta}"),
    C("vti moment source", {"c.yaml": VTI + "source: {type: moment, components: [1, 1, 0]}\n"}, FWD, 2,
      "source.type: 'moment' with physics vti", "set type: explosive"),
    C("vti parallel", {"c.yaml": VTI + "parallel: {engine: threads, devices: [cpu]}\n"}, FWD, 2,
      "parallel: given with physics vti", "drop the parallel section"),
    C("fwi vti with a parameterization", {"c.yaml": VTI + VTRUE + "inversion: {parameterization: lambda-mu-rho}\n"}, FWI, 2,
      "inversion.parameterization: lambda-mu-rho with physics vti", "vp, epsilon, delta, rho", "drop it"),
    C("fwi vti delta bound below -1/2", {"c.yaml": VTI + VTRUE + "inversion: {parameters: [delta], bounds: {delta: [-0.6, 0.2]}}\n"},
      FWI, 2, "inversion.bounds.delta: [-0.6, 0.2] allows delta <= -0.5", "delta > -1/2", "give finite bounds above -0.5"),
    C("fwi vti bounds for epsilon not inverted", {"c.yaml": VTI + VTRUE + "inversion: {bounds: {epsilon: [0, 0.3]}}\n"}, FWI, 2,
      "inversion.bounds.epsilon: [0.0, 0.3] bounds a quantity that is not inverted (inverted: vp)", "add epsilon to inversion.parameters"),
    C("fwi vti one bounds pair", {"c.yaml": VTI + VTRUE + "inversion: {bounds: [1500, 2500]}\n"}, FWI, 2,
      "inversion.bounds: [1500.0, 2500.0] is one [min, max] pair but physics vti", "epsilon: [0, 0.3]"),
    C("image with vti", {"c.yaml": VTI + "true_model: {kind: constant, shape: [21, 31], spacing: 10.0, velocity: 2100.0}\n"}, IMAGE, 2,
      "physics: vti is not available for adseismic image", "physics: acoustic"),
    C("locate with vti", {"c.yaml": ELOCATE.replace("physics: elastic", "physics: vti")}, LOC, 2,
      "physics: vti is not available for adseismic locate", "physics: acoustic"),
    # --- physics viscoacoustic (issue 26): 2D constant Q, forward and fwi
    C("viscoacoustic q 0", {"c.yaml": VQ.replace("q: 30.0", "q: 0.0")}, FWD, 2,
      "model.q: 0.0 at z = 0 m, x = 0 m", "Q must be > 0", ".inf: lossless"),
    C("viscoacoustic layered q below 0", {"c.yaml": VQ.replace("q: 30.0", "q: {kind: layered, values: [50.0, -5.0], interfaces: [100.0]}")},
      FWD, 2, "model.q: -5.0 at z = 100 m, x = 0 m (index (10, 0)", "Q must be > 0"),
    C("viscoacoustic q NaN", {"c.yaml": VQ.replace("q: 30.0", "q: .nan")}, FWD, 2,
      "model.q: nan is not a finite number", "the quality factor Q"),
    C("viscoacoustic q file NaN", {"c.yaml": VQ.replace("q: 30.0", "q: {kind: npy, path: q.npy}"),
                                   "q.npy": npy(np.where(np.arange(31) < 3, np.nan, 30.0) * np.ones((21, 1)))}, FWD, 2,
      "model.q.path: q.npy holds 63 non-finite values (the first, nan, at index (0, 0))", "(or +inf)"),
    C("viscoacoustic q file of the wrong shape", {"c.yaml": VQ.replace("q: 30.0", "q: {kind: npy, path: q.npy}"),
                                                  "q.npy": npy(np.full((31, 21), 30.0))}, FWD, 2,
      "model.q.path: q.npy holds a grid of shape [31, 21]", "not model.vp's (shape [21, 31]", "axes: xz"),
    C("viscoacoustic without q", {"c.yaml": VQ.replace("  q: 30.0\n", "")}, FWD, 2, "model.q: missing", "the quality factor"),
    C("viscoacoustic bad q_band", {"c.yaml": VQ.replace("q: 30.0", "q: 30.0\n  q_band: [30.0, 3.0]")}, FWD, 2,
      "model.q_band: [30.0, 3.0] Hz is not 0 < f_min < f_max"),
    C("viscoacoustic force source", {"c.yaml": VQ + "source: {type: force, components: [1, 0]}\n"}, FWD, 2,
      "source.type: 'force' with physics viscoacoustic", "set type: explosive"),
    C("viscoacoustic snapshots", {"c.yaml": VQ + "output: {snapshot_interval: 0.05}\n"}, FWD, 2,
      "output.snapshot_interval: 0.05 s", "visco-acoustic (constant Q) solver"),
    C("viscoacoustic parallel", {"c.yaml": VQ + "parallel: {engine: threads, devices: [cpu]}\n"}, FWD, 2,
      "parallel: given with physics viscoacoustic", "drop the parallel section"),
    C("fwi viscoacoustic inverting vs", {"c.yaml": VQ + VQTRUE + "inversion: {parameters: [vs]}\n"}, FWI, 2,
      "inversion.parameters: vs is not a quantity here (physics viscoacoustic has vp, q, rho)", "use any of vp, q, rho"),
    C("fwi viscoacoustic q bound 0", {"c.yaml": VQ + VQTRUE + "inversion: {parameters: [q], bounds: {q: [0, 100]}}\n"}, FWI, 2,
      "inversion.bounds.q: [0, 100] allows q <= 0", "Q > 0", "give finite bounds above 0"),
    C("fwi viscoacoustic lossless start with q inverted", {"c.yaml": VQ.replace("q: 30.0", "q: .inf") + VQTRUE + "inversion: {parameters: [q]}\n"},
      FWI, 2, "inversion.parameters: q is inverted but the start model's q is infinite (lossless)", "give a finite start Q"),
    C("fwi viscoacoustic true model's own q_band", {"c.yaml": VQ + VQTRUE + "  q_band: [2.0, 20.0]\n"}, FWI, 2,
      "true_model.q_band: (2.0, 20.0) differs from model.q_band (None)", "the start model's relaxation mechanisms"),
    C("fwi viscoacoustic parallel", {"c.yaml": VQ + VQTRUE + "parallel: {engine: threads, devices: [cpu]}\n"}, FWI, 2,
      "parallel: given with physics viscoacoustic", "acoustic shots only", "drop it"),
    C("fwi viscoacoustic observed files", {"c.yaml": VQ + "observed: {kind: hdf5, path: d.h5}\n"}, FWI, 2,
      "observed: given with physics viscoacoustic", "use true_model"),
    C("fwi viscoacoustic pseudo-Hessian", {"c.yaml": VQ + VQTRUE + "inversion: {preconditioning: pseudo_hessian}\n"}, FWI, 2,
      "inversion.preconditioning: pseudo_hessian is acoustic only", "use none or depth"),
    C("image with viscoacoustic", {"c.yaml": VQ + ATRUE}, IMAGE, 2,
      "physics: viscoacoustic is not available for adseismic image", "physics: acoustic"),
    C("locate with viscoacoustic", {"c.yaml": ELOCATE.replace("physics: elastic", "physics: viscoacoustic")}, LOC, 2,
      "physics: viscoacoustic is not available for adseismic locate", "physics: acoustic"),
    # --- adseismic image
    C("image lsrtm with elastic physics", {"c.yaml": elastic() + ETRUE + "image: {method: lsrtm}\n"}, IMAGE, 2,
      "image.method: lsrtm with physics: elastic", "use method: rtm"),
    C("image illumination with elastic physics", {"c.yaml": elastic() + ETRUE + "image: {illumination: true}\n"}, IMAGE, 2,
      "image.illumination: true with physics: elastic", "drop the key"),
    C("image with a network model", {"c.yaml": image("{method: rtm}").replace(MODEL, "model: {kind: nn, shape: [21, 31], spacing: 10.0, v0: 2000.0, scale: 200.0}\n")},
      IMAGE, 2, "model.kind: nn is a parameterisation for fwi"),
    C("image iterations 0", {"c.yaml": image("{method: lsrtm, iterations: 0}")}, IMAGE, 2, "image.iterations: 0 < 1", "at least 1"),
    C("image iterations with rtm", {"c.yaml": image("{iterations: 5}")}, IMAGE, 2,
      "image.iterations: 5 with method: rtm", "set method: lsrtm"),
    C("image negative smoothing", {"c.yaml": image("{smoothing: -50}")}, IMAGE, 2, "image.smoothing: -50 is negative"),
    C("image smoothing wider than the model", {"c.yaml": image("{smoothing: 5000}")}, IMAGE, 2,
      "image.smoothing: 5000 m is larger than the model"),
    C("image water below the model", {"c.yaml": image("{water_depth: 400}")}, IMAGE, 2,
      "image.water_depth: 400 m is at or below the model's bottom (200 m)"),
    C("image laplacian with lsrtm", {"c.yaml": image("{method: lsrtm, laplacian: true}")}, IMAGE, 2,
      "image.laplacian: true with method: lsrtm"),
    C("image method misspelt", {"c.yaml": image("{method: kirchhoff}")}, IMAGE, 2, "image.method: 'kirchhoff' is not one of rtm, lsrtm"),
    C("image epsilon 0", {"c.yaml": image("{epsilon: 0}")}, IMAGE, 2, "image.epsilon: 0"),
    C("image without data", {"c.yaml": image("{method: rtm}", data="")}, IMAGE, 2, "true_model/observed: give exactly one"),
    C("image with an inversion section", {"c.yaml": image("{method: rtm}") + "inversion: {iterations: 1}\n"}, IMAGE, 2,
      "inversion: unknown key", "image, true_model, observed"),
    C("image all-zero observed data", {"obs.h5": forward_data(zero=True), "c.yaml": image("{method: rtm}", data="observed: {kind: hdf5, path: obs.h5}\n")},
      IMAGE, 2, "every sample of the observed data is zero"),
    # --- locate: moment-tensor sources (physics elastic)
    C("locate moment tensor with acoustic physics", {"ev.mseed": miniseed, "c.yaml": LOCATE + ACOUSTIC_TRACES + "source: {type: moment}\n"},
      LOC, 2, "source.type: 'moment'", "needs elastic physics", "set physics: elastic"),
    C("locate mt constraint with acoustic physics", {"ev.mseed": miniseed,
                                                     "c.yaml": LOCATE + ACOUSTIC_TRACES + "source: {constraint: double_couple}\n"},
      LOC, 2, "source.constraint: 'double_couple'", "needs physics: elastic"),
    C("locate mt constraint misspelt", {"ev.mseed": two_component, "c.yaml": ELOCATE + "source: {constraint: dc}\n"}, LOC, 2,
      "source.constraint", "'dc'", "none, deviatoric, double_couple"),
    C("locate elastic pressure source", {"ev.mseed": two_component, "c.yaml": ELOCATE + "source: {type: pressure}\n"}, LOC, 2,
      "source.type: 'pressure' with physics elastic", "source.type: moment"),
    C("locate double couple with a 3D model", {"ev.mseed": two_component, "c.yaml": ELOCATE.replace("shape: [41, 61]", "shape: [41, 11, 61]").replace("origin: [0, -300]", "origin: [0, 0, -300]")
                                               + "source: {constraint: double_couple}\n"},
      LOC, 2, "model.vp: a 3D model", "forward modelling only", "give a 2D model"),
    C("locate elastic traces lacking X", {"ev.mseed": two_component, "c.yaml": ELOCATE}, LOC, 2,
      "station XX.S2.", "lacks its X component", "add the missing channel"),
    C("locate elastic one component kept", {"ev.mseed": lambda d, n: two_component(d, n, ()),
                                            "c.yaml": ELOCATE.replace("local_coordinates", "component: Z, local_coordinates")},
      LOC, 2, "traces.component: 'Z'", "physics elastic fits Z and X", "drop traces.component"),
    C("locate elastic optimiser study", {"ev.mseed": lambda d, n: two_component(d, n, ()), "c.yaml": ELOCATE},
      LOC + ["--compare-optimizers"], 2, "--compare-optimizers", "acoustic physics only", "physics is elastic"),
    # --- parallel: the threads engine (several devices in one process), forward on workers, locate refused (issue 25)
    C("threads on a device this host lacks", {"c.yaml": fwi() + "parallel: {engine: threads, devices: [cuda:7]}\n"}, FWI, 2,
      "parallel.devices[0]", "'cuda:7' is not available", "list devices of this host"),
    C("threads: more devices than shots", {"c.yaml": FORWARD + "parallel: {engine: threads, devices: [cpu, cpu, cpu]}\n"}, FWD, 2,
      "parallel.devices: 3 devices for 2 shot(s)", "list at most 2 device(s)"),
    C("threads with a scheduler", {"c.yaml": FORWARD + "parallel: {engine: threads, scheduler: local}\n"}, FWD, 2,
      "parallel.scheduler: 'local' given with engine threads", "write engine: dask"),
    C("threads with workers", {"c.yaml": fwi() + "parallel: {engine: threads, workers: 2}\n"}, FWI, 2,
      "parallel.workers: 2 given with engine threads", "devices: [cpu, cpu]"),
    C("locate with a parallel section", {"ev.mseed": miniseed, "c.yaml": LOCATE + ACOUSTIC_TRACES + "parallel: {engine: threads}\n"}, LOC, 2,
      "parallel: a location simulates one event per evaluation", "drop the section"),
]


@pytest.mark.parametrize("case", CATALOGUE, ids=[c.name for c in CATALOGUE])
def test_bad_input_catalogue(case, tmp_path, capsys, caplog):
    d = tmp_path / "in"
    d.mkdir()
    for name, content in case.files.items():
        if callable(content):
            content(d, name)
        elif isinstance(content, bytes):
            (d / name).write_bytes(content)
        else:
            (d / name).write_text(content, encoding="utf-8")
    out = tmp_path / "out"
    argv = [a.format(d=d, out=out) for a in case.argv]
    with caplog.at_level(logging.INFO, logger="adseismic"):
        status = main(argv)
    captured = capsys.readouterr()
    text = captured.out + captured.err + caplog.text
    assert "Traceback" not in text, text
    assert status == case.status, text
    for fragment in case.fragments:
        assert fragment in text, f"{fragment!r} not in:\n{text}"
    for fragment in case.absent:
        assert fragment not in text, f"{fragment!r} in:\n{text}"
    if status != 0:
        assert not out.exists() or not any(out.iterdir()), f"a refusal left {sorted(p.name for p in out.iterdir())}"
        assert len([ln for ln in captured.err.splitlines() if "error:" in ln]) == 1, captured.err


# --------------------------------------------------------------------------- the SEG-Y depth convention

def test_segy_depth_convention_auto_reads_judi_depths_with_a_warning(tmp_path, caplog):
    from adseismic.data.model import Model
    from adseismic.data.read import read_shot_gathers

    judi_segy(tmp_path, "shots.segy")
    model = Model(np.full((21, 31), 2000.0), 10.0)
    with caplog.at_level(logging.WARNING, logger="adseismic"):
        auto = read_shot_gathers(tmp_path / "shots.segy", depth_convention="auto", model=model)
    assert np.allclose(auto.sources[:, 0], 20.0) and np.allclose(auto.receivers[..., 0], 10.0)
    assert "using depth_convention 'depth'" in caplog.text and "z -20..-10 m" in caplog.text
    caplog.clear()
    elev = read_shot_gathers(tmp_path / "shots.segy", depth_convention="elevation", model=model)
    assert np.allclose(elev.sources[:, 0], -20.0)  # the SEG-Y standard: elevation up
    assert "set depth_convention: depth" in caplog.text
    depth = read_shot_gathers(tmp_path / "shots.segy", depth_convention="depth")
    assert np.allclose(depth.sources, auto.sources) and np.allclose(depth.receivers, auto.receivers)
    x = read_shot_gathers(tmp_path / "shots.segy", depth_convention="auto")  # no model: the standard
    assert np.allclose(x.sources[:, 0], -20.0)


def test_station_a_little_off_the_line_warns_with_the_distance(caplog):
    from adseismic.data.geometry import check_offline
    from adseismic.data.model import Model

    model = Model(np.full((21, 31), 2000.0), 10.0)  # 300 m long
    with caplog.at_level(logging.WARNING, logger="adseismic"):
        check_offline(np.array([0.0, 5.0, 40.0]), ["A", "B", "C"], model)
    assert "1 of 3 stations" in caplog.text and "40 m (C)" in caplog.text
