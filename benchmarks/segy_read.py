"""SEG-Y read rate and memory (issue 27): the streaming reader (``engine="stream"``: numpy memmap window by window)
against today's ObsPy reader (``engine="obspy"``), on a generated SEG-Y file.

    python benchmarks/segy_read.py                # 2 GB file, both readers, each in a fresh process
    python benchmarks/segy_read.py --gb 0.2       # smaller file
    python benchmarks/segy_read.py --gb 2 --skip-obspy

The file (big-endian, IEEE float samples, or IBM with --ibm; n_rec receivers per shot, nt samples) is written to a
temporary directory and deleted afterwards. Each reader runs in its own subprocess so that its peak RSS
(resource.getrusage ru_maxrss) is its own; MB/s counts the file's bytes over the wall time of read_shot_gathers.
Results: docs/benchmarks.md, "SEG-Y read (issue 27)".
"""
from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

FIELDS = {  # name -> (0-based byte offset, type), SEG-Y rev 1 (as adseismic.data.read.TRACE_FIELDS)
    "trace_sequence_number_within_line": (0, "i4"),
    "original_field_record_number": (8, "i4"),
    "trace_number_within_the_original_field_record": (12, "i4"),
    "receiver_group_elevation": (40, "i4"),
    "surface_elevation_at_source": (44, "i4"),
    "scalar_to_be_applied_to_all_elevations_and_depths": (68, "i2"),
    "scalar_to_be_applied_to_all_coordinates": (70, "i2"),
    "source_coordinate_x": (72, "i4"),
    "group_coordinate_x": (80, "i4"),
    "coordinate_units": (88, "i2"),
    "number_of_samples_in_this_trace": (114, "u2"),
    "sample_interval_in_ms_for_this_trace": (116, "u2"),
}


def float_to_ibm(x):
    """float32 array -> IBM single-precision words (uint32), truncating the fraction (as most writers do)."""
    x = np.asarray(x, dtype=np.float64)
    sign = (x < 0).astype(np.uint32) << 31
    a = np.abs(x)
    nz = a > 0
    e = np.zeros(a.shape, dtype=np.int64)
    e[nz] = np.floor(np.log2(a[nz]) / 4).astype(np.int64) + 1  # 16^(e-1) <= a < 16^e
    frac = np.zeros(a.shape)
    frac[nz] = a[nz] / 16.0 ** e[nz]
    big = frac >= 1.0
    e[big] += 1
    frac[big] /= 16
    mant = np.floor(frac * 2 ** 24).astype(np.uint32)
    return np.where(nz, sign | ((e + 64).astype(np.uint32) << 24) | mant, np.uint32(0)).astype(np.uint32)


def write_segy(path, n_shots, n_rec, nt, *, dt_us=2000, ibm=False, seed=0, chunk_traces=2048):
    """Write a SEG-Y rev 1 file of n_shots x n_rec fixed-length traces (big-endian; samples IEEE float32, or IBM float
    with ``ibm``): shot s at x = 100 s m, receivers at x = 10 r m, elevation 0, coordinates in mm (scalar -1000).
    Written chunk by chunk (memory bounded). Returns (path, samples of shot 0 as float32 (n_rec, nt))."""
    path = pathlib.Path(path)
    dtype = np.dtype({"names": list(FIELDS) + ["samples"],
                      "formats": [">" + t for _, t in FIELDS.values()] + [(">u4" if ibm else ">f4", (nt,))],
                      "offsets": [o for o, _ in FIELDS.values()] + [240], "itemsize": 240 + 4 * nt})
    binary = np.zeros(400, dtype=np.uint8)
    for off, val in ((3216, dt_us), (3220, nt), (3224, 1 if ibm else 5), (3228, n_rec), (3254, 1), (3500, 0x0100)):
        binary[off - 3200:off - 3198] = np.frombuffer(np.array(val, ">i2").tobytes(), np.uint8)
    rng = np.random.default_rng(seed)
    n = n_shots * n_rec
    shot0 = None
    with open(path, "wb") as f:
        f.write(b"C 1 adseismic benchmarks/segy_read.py synthetic SEG-Y".ljust(3200))
        f.write(binary.tobytes())
        for a in range(0, n, chunk_traces):
            b = min(a + chunk_traces, n)
            k = np.arange(a, b)
            buf = np.zeros(b - a, dtype=dtype)
            buf["trace_sequence_number_within_line"] = k + 1
            buf["original_field_record_number"] = k // n_rec + 1
            buf["trace_number_within_the_original_field_record"] = k % n_rec + 1
            buf["scalar_to_be_applied_to_all_elevations_and_depths"] = -1000
            buf["scalar_to_be_applied_to_all_coordinates"] = -1000
            buf["source_coordinate_x"] = (k // n_rec) * 100_000
            buf["group_coordinate_x"] = (k % n_rec) * 10_000
            buf["coordinate_units"] = 1
            buf["number_of_samples_in_this_trace"] = nt
            buf["sample_interval_in_ms_for_this_trace"] = dt_us
            x = rng.standard_normal((b - a, nt), dtype=np.float32)
            if ibm:
                x = x.astype(np.float16).astype(np.float32)  # exactly representable in IBM single precision
                buf["samples"] = float_to_ibm(x)
            else:
                buf["samples"] = x
            if a == 0:
                shot0 = x[:n_rec].copy()
            buf.tofile(f)
    return path, shot0


def _child(path, engine, shots, limit_gb):
    """Run one reader in this (fresh) process and print JSON: seconds, peak RSS, shape."""
    import resource

    if limit_gb > 0:  # today's reader holds several times the file in memory: stop it before it starves the machine
        resource.setrlimit(resource.RLIMIT_AS, (int(limit_gb * 2 ** 30), resource.RLIM_INFINITY))

    from adseismic.data.read import read_shot_gathers

    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t = time.perf_counter()
    g = read_shot_gathers(path, engine=engine, shots=None if shots is None else list(range(shots)))
    sec = time.perf_counter() - t
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    print(json.dumps({"engine": engine, "seconds": sec, "peak_rss_mib": rss / 1024, "rss_before_mib": rss0 / 1024,
                      "shape": list(g.data.shape), "data_mib": g.data.nbytes / 2 ** 20}))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gb", type=float, default=2.0, help="file size, GB (1e9 bytes); default 2")
    ap.add_argument("--nt", type=int, default=1000, help="samples per trace (default 1000)")
    ap.add_argument("--n-rec", type=int, default=500, help="receivers per shot (default 500)")
    ap.add_argument("--ibm", action="store_true", help="IBM float samples (format 1) instead of IEEE (format 5)")
    ap.add_argument("--skip-obspy", action="store_true", help="time the streaming reader only")
    ap.add_argument("--repeat", type=int, default=3, help="runs of the streaming reader (fresh process each; best kept)")
    ap.add_argument("--obspy-limit-gb", type=float, default=16.0,
                    help="address-space limit of the ObsPy reader's process, GiB (0: none; default 16)")
    ap.add_argument("--child", nargs=4, metavar=("PATH", "ENGINE", "SHOTS", "LIMIT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        path, engine, shots, limit = args.child
        return _child(path, engine, None if shots == "all" else int(shots), float(limit))
    trace_bytes = 240 + 4 * args.nt
    n_shots = max(1, round(args.gb * 1e9 / (trace_bytes * args.n_rec)))
    with tempfile.TemporaryDirectory(prefix="segy_read_") as tmp:
        path = pathlib.Path(tmp) / "survey.segy"
        t = time.perf_counter()
        write_segy(path, n_shots, args.n_rec, args.nt, ibm=args.ibm)
        size = path.stat().st_size
        print(f"wrote {path.name}: {size / 1e9:.3f} GB, {n_shots} shots x {args.n_rec} receivers x {args.nt} samples "
              f"({'IBM' if args.ibm else 'IEEE'} float) in {time.perf_counter() - t:.1f} s", flush=True)
        runs = [("stream", "all")] * args.repeat + [("stream", "1")] + ([] if args.skip_obspy else [("obspy", "all")])
        results = []
        for engine, shots in runs:
            limit = args.obspy_limit_gb if engine == "obspy" else 0
            out = subprocess.run([sys.executable, __file__, "--child", str(path), engine, shots, str(limit)],
                                 capture_output=True, text=True, check=False)
            if out.returncode:
                print(f"{engine} ({shots} shots) failed (exit {out.returncode}):\n{out.stderr[-2000:]}")
                results.append(None)
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            r["mb_per_s"] = size / 1e6 / r["seconds"]
            r["shots"] = shots
            results.append(r)
            print(f"{engine:6s} shots={shots:3s}: {r['seconds']:7.2f} s, {r['mb_per_s']:7.1f} MB/s, peak RSS "
                  f"{r['peak_rss_mib']:7.0f} MiB (process start {r['rss_before_mib']:.0f} MiB; data returned "
                  f"{r['data_mib']:.0f} MiB, shape {tuple(r['shape'])})", flush=True)
        best = min((r for r in results[:args.repeat] if r), key=lambda r: r["seconds"], default=None)
        if best:
            print(f"stream (all traces), best of {args.repeat}: {best['mb_per_s']:.1f} MB/s, peak RSS "
                  f"{best['peak_rss_mib']:.0f} MiB")
        if not args.skip_obspy and best and results[-1]:
            print(f"ratio stream / obspy (all traces): {results[-1]['seconds'] / best['seconds']:.1f}x faster")
    print("file deleted")


if __name__ == "__main__":
    sys.exit(main())
