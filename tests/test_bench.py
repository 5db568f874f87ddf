"""``adseismic bench``: reports written atomically, rates, CUDA/CPU ratios, refusals; the
speed/accuracy sweep. Small CPU-only scenes (--steps) so the whole file takes well under a minute."""
import json

import numpy as np
import pytest

from adseismic import bench, cli
from adseismic.bench import SCENES, BenchRow, speed_accuracy


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory):
    """S600 (8 steps) and E2000 (elastic), each in its own worker process."""
    out = tmp_path_factory.mktemp("bench") / "out"
    code = cli.main(["bench", "--scenes", "S600", "E2000", "--steps", "8", "--no-deepwave", "-o", str(out), "-q"])
    return code, out


@pytest.mark.slow
def test_bench_writes_json_markdown_png(bench_run):
    code, out = bench_run
    assert code == 0
    names = {p.name for p in out.iterdir()}
    assert {"bench.json", "bench.md", "bench.png", "bench.log"} <= names
    assert not [n for n in names if n.endswith(".part")]
    assert (out / "bench.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    doc = json.loads((out / "bench.json").read_text())
    assert doc["machine"]["cpu_count"] >= 1 and doc["machine"]["warp"] and doc["machine"]["devices"] == {"cpu": "CPU"}
    rows = [bench.row_from_dict(r) for r in doc["rows"]]
    s600 = [r for r in rows if r.scene == "S600"]
    assert [r.mode for r in s600] == ["forward", "gradient"]
    for r in s600:
        assert r.ok and r.nt == 8 and r.nt_reference == 1000 and r.memory_scope == "scene (own process)"
        assert r.rate > 0 and r.rate_per_core > 0 and r.peak_host_rss_bytes > 50e6
        assert r.rate == pytest.approx(644**2 * 8 / r.seconds)
    assert s600[1].peak_estimate_bytes > 0 and "x" in s600[1].segments
    e = [r for r in rows if r.scene == "E2000"]
    assert len(e) == 2 and all(r.ok for r in e)
    md = (out / "bench.md").read_text()
    assert "| S600 | cpu | forward | 8 (of 1000) |" in md
    assert "2.08 (reference.md, 2-core CPU)" in md and "0.2 (reference.md, 2-core CPU)" in md
    assert "CUDA / CPU" in md


def test_in_process_forward_only(tmp_path):
    out = tmp_path / "o"
    assert cli.main(["bench", "--scenes", "S600", "--modes", "forward", "--steps", "4", "--repeat", "2", "--in-process",
                     "--no-deepwave", "-o", str(out), "-q"]) == 0  # fmt: skip
    (row,) = json.loads((out / "bench.json").read_text())["rows"]
    assert row["mode"] == "forward" and len(row["times"]) == 2 and row["seconds"] == min(row["times"])
    assert "process-wide" in row["memory_scope"]


def _row(device, rate, scene="S600", mode="forward", order=4, nt=1000):
    return BenchRow(scene=scene, kind="acoustic", engine="adseismic", device=device, device_name=device, mode=mode, order=order,
                    shape=(600, 600), shots=1, nt=nt, nt_reference=1000, padded_cells=644**2, seconds=1.0, rate=rate)  # fmt: skip


def test_cuda_cpu_ratio_and_markdown_column():
    rows = [_row("cpu", 2e7), _row("cuda:0", 3e10), _row("cpu", 5e6, mode="gradient"), _row("cuda:0", 1e10, mode="gradient"),
            _row("cuda:0", 1e11, scene="S4000"), _row("cuda:0", 2e10, order=8)]  # fmt: skip
    ratios = bench.cuda_cpu_ratios(rows)
    assert ratios == {("S600", "forward", "adseismic", 4): pytest.approx(1500.0),
                      ("S600", "gradient", "adseismic", 4): pytest.approx(2000.0)}  # fmt: skip
    machine = {"date_utc": "d", "adseismic": "v", "warp": "1.19", "devices": {"cpu": "CPU", "cuda:0": "H200"},
               "cpu_model": "x", "cpu_count": 2, "deepwave": None}  # fmt: skip
    md = bench.markdown(rows, machine)
    line = next(ln for ln in md.splitlines() if ln.startswith("| S600 | cuda:0 | forward | 1000 |"))
    assert line.rstrip().endswith("| 1,500 |")
    assert "29.7 (reference.md, H200)" in line and "| 1.01 |" in line  # ours / Deepwave = 30 / 29.7


def test_scene_definitions_match_reference():
    assert bench.padded_cells(SCENES["S600"], 4) == 644**2
    assert bench.padded_cells(SCENES["S3D400"], 4) == 444**3
    a = bench.build_arrays(SCENES["S600x4"], nt=50)
    v = a.model["velocity"]
    assert v.shape == (600, 600) and v.min() == 1500 and v.max() == 2000
    assert a.sources.shape == (4, 1, 2) and a.receivers.shape == (4, 300, 2) and a.amplitudes.shape == (4, 1, 50)
    e = bench.build_arrays(SCENES["E600x16"], nt=10)
    assert e.model["vs"][0, 0] == pytest.approx(2000 / 1.8) and e.model["rho"][0, 0] == 2200 and e.sources.shape == (16, 1, 2)
    d3 = bench.build_arrays(SCENES["S3D400"], nt=10)
    assert d3.sources.shape == (1, 1, 3) and d3.receivers.shape[-1] == 3
    assert bench.anchor_for("S4000", 8, "cuda").forward == 104.3e9 and bench.anchor_for("S4000", 4, "cpu") is None


@pytest.mark.parametrize("argv, message", [
    (["--scenes", "S9"], "--scenes: unknown scene 'S9'; choose from S600"),
    (["--device", "cuda:7"], "--device: device 'cuda:7' is not available"),
    (["--device", "tpu"], "--device: device 'tpu' is not available"),
    (["--steps", "1"], "--steps: 1 is invalid; use 2 or more"),
    (["--scenes", "S4000"], "--scenes: S4000 on cpu would take ~"),
    (["--suite", "speed-accuracy", "--sweep-ppw", "2"], "--sweep-ppw: 2 points per wavelength"),
])  # fmt: skip
def test_bad_input_exits_2_before_writing(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    assert cli.main(["bench", *argv, "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not out.exists()


def test_cpu_refusal_names_the_fix(tmp_path, capsys):
    assert cli.main(["bench", "--scenes", "S4000", "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "add --cpu-steps" in err and "--max-minutes" in err


def test_pareto_front():
    pts = [speed_accuracy.SweepPoint("cpu", 4, "float32", 4, 0.9, 10, 1e-3, 10, 100, error=e, seconds=9.0, cpu_seconds=s)
           for e, s in ((0.1, 1.0), (0.2, 2.0), (0.05, 3.0), (0.01, 10.0), (0.02, 12.0))]  # fmt: skip
    assert [(p.cost, p.error) for p in speed_accuracy.pareto_front(pts)] == [(1.0, 0.1), (3.0, 0.05), (10.0, 0.01)]


def test_speed_accuracy_sweep_small(tmp_path):
    out = tmp_path / "sa"
    code = cli.main(["bench", "--suite", "speed-accuracy", "--sweep-orders", "4", "--sweep-ppw", "4", "8", "--sweep-cfl", "0.4",
                     "--sweep-precisions", "float32", "--repeat", "1", "-o", str(out), "-q"])  # fmt: skip
    assert code == 0
    assert (out / "speed_accuracy_cpu.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (out / "bench.json").exists()  # the scenes suite did not run
    pts = json.loads((out / "speed_accuracy.json").read_text())["points"]
    sweep = [p for p in pts if not p["planner"]]
    assert [p["ppw"] for p in sweep] == pytest.approx([4, 8]) and all(p["status"] == "ok" for p in pts)
    assert sweep[1]["error"] < sweep[0]["error"] / 4  # finer grid, much smaller error (measured 0.085 -> 0.0056)
    (planner,) = [p for p in pts if p["planner"]]
    assert planner["order"] == 4 and planner["precision"] == "float32" and planner["error"] < 0.05
    assert np.isfinite(planner["seconds"]) and "planner default" in (out / "speed_accuracy.md").read_text()


@pytest.mark.parametrize("error", [MemoryError(), RuntimeError("CUDA out of memory. Tried to allocate 178.00 GiB | GPU 0")])
def test_a_failing_reference_is_reported_and_exits_0(tmp_path, monkeypatch, error):
    def deepwave_fails(*args, **kwargs):
        raise error

    monkeypatch.setattr(bench, "deepwave_available", lambda: True)
    monkeypatch.setattr(bench, "run_deepwave", deepwave_fails)
    out = tmp_path / "o"
    assert cli.main(["bench", "--scenes", "S600", "--modes", "forward", "--steps", "4", "--in-process", "-o", str(out), "-q"]) == 0
    rows = [bench.row_from_dict(r) for r in json.loads((out / "bench.json").read_text())["rows"]]
    ours, ref = rows
    assert ours.engine == "adseismic" and ours.ok and ref.engine == "deepwave" and not ref.ok
    why = f"reference failed: {type(error).__name__}" + (": CUDA out of memory. Tried to allocate 178.00 GiB" if str(error) else "")
    assert ref.status.startswith(why)
    md = (out / "bench.md").read_text()
    line = next(ln for ln in md.splitlines() if ln.startswith("| S600 | cpu | forward | 4 (of 1000) |"))
    assert why in line and "recorded 2.08 (reference.md, 2-core CPU)" in line  # the reason, then the recorded anchor
    assert why in next(ln for ln in md.splitlines() if ln.startswith("| S600 | cpu | forward |  |"))  # the live Deepwave table
    assert "not our failure" in (out / "bench.log").read_text()


def test_our_failure_still_exits_1_beside_a_failing_reference(tmp_path, monkeypatch):
    def fails(*args, **kwargs):
        raise RuntimeError("CUDA out of memory")

    monkeypatch.setattr(bench, "deepwave_available", lambda: True)
    monkeypatch.setattr(bench, "run_deepwave", fails)
    monkeypatch.setattr(bench, "run_acoustic", fails)
    out = tmp_path / "o"
    assert cli.main(["bench", "--scenes", "S600", "--modes", "forward", "--steps", "4", "--in-process", "-o", str(out), "-q"]) == 1
    statuses = [r["status"] for r in json.loads((out / "bench.json").read_text())["rows"]]
    assert statuses == ["failed: RuntimeError: CUDA out of memory", "reference failed: RuntimeError: CUDA out of memory"]


def test_a_worker_killed_in_deepwave_keeps_our_rows(monkeypatch):
    # the worker printed our rows, then died inside Deepwave (e.g. killed for memory)
    import subprocess
    from dataclasses import asdict

    ours = _row("cpu", 2e7, nt=8)
    printed = bench.WORKER_MARK + json.dumps([asdict(ours)])
    monkeypatch.setattr(subprocess, "run", lambda *a, **k: subprocess.CompletedProcess(a, -9, stdout=printed + "\n", stderr=""))
    job = bench.BenchJob("S600", "cpu", ("forward",), 4, 8, 1, None, True, "scene (own process)")
    rows = bench.run_job_in_subprocess(job)
    assert [r.engine for r in rows] == ["adseismic", "deepwave"] and rows[0].ok and rows[0].rate == 2e7
    assert rows[1].status.startswith("reference failed: worker killed") and not bench.is_our_failure(rows[1])
