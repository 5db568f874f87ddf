"""What a new user meets first (issue 28): every shipped config plans, --dry-run writes nothing, one data
place inside the clone, the same output flags on every command, interrupts and unwritable output
directories end in one line (not a traceback), progress in log files as lines, not redrawn bars."""

import logging
import re
from pathlib import Path

import pytest
import yaml

from adseismic import cli
from adseismic.runs import log, progress_bar

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))
TINY_FORWARD = {"model": {"kind": "constant", "shape": [21, 31], "spacing": 20.0, "velocity": 2000.0},
                "geometry": {"sources": {"points": [{"x": 300, "z": 20}]}, "receivers": {"line": {"start": {"x": 0, "z": 10}, "end": {"x": 600, "z": 10}, "count": 7}}},
                "wavelet": {"kind": "ricker", "peak_frequency": 8.0},
                "simulation": {"order": 4, "pml_width": 6, "duration": 0.3}}  # fmt: skip


def write(tmp_path, raw, name="run.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize("path", CONFIGS, ids=[p.stem for p in CONFIGS])
def test_plan_accepts_every_shipped_config(path, capsys):
    assert cli.main(["plan", str(path)]) == 0
    out = capsys.readouterr().out
    wf = cli.workflow_of(path)
    assert out.startswith(f"{wf} plan for ") or f"\n{wf} plan for " in out
    assert "cost " in out and "wall time" in out or wf == "forward" and "total " in out


def test_workflow_of_reads_the_keys(tmp_path):
    assert cli.workflow_of(ROOT / "configs" / "fwi_demo.yaml") == "fwi"
    assert cli.workflow_of(ROOT / "configs" / "locate_demo.yaml") == "locate"
    assert cli.workflow_of(ROOT / "configs" / "example_2d.yaml") == "forward"


@pytest.mark.parametrize("workflow, path", [("forward", "example_2d"), ("fwi", "fwi_demo"), ("locate", "locate_demo")])
def test_dry_run_of_every_workflow_writes_nothing(workflow, path, tmp_path, capsys):
    out = tmp_path / "out"
    assert cli.main([workflow, str(ROOT / "configs" / f"{path}.yaml"), "-o", str(out), "--dry-run"]) == 0
    assert not out.exists()
    assert f"{workflow} plan for" in capsys.readouterr().out


def test_every_command_takes_the_same_output_flags():
    parser = cli.build_parser()
    for name in ("forward", "fwi", "locate", "bench"):
        sub = parser._subparsers._group_actions[0].choices[name]
        flags = {s for a in sub._actions for s in a.option_strings if a.dest == "outdir"}
        assert flags == {"-o", "--output", "--outdir"}, (name, flags)


def test_shipped_configs_read_their_files_inside_the_clone():
    for path in CONFIGS:
        text = path.read_text()
        assert "shared/data" not in text, path
        for section in yaml.safe_load(text).values():
            if isinstance(section, dict) and "path" in section:
                target = (path.parent / section["path"]).resolve()
                assert target.is_file() and ROOT in target.parents, (path.name, target)


def test_no_test_looks_outside_the_clone_for_data():
    for path in (ROOT / "tests").glob("*.py"):
        text = path.read_text()
        assert not re.search(r"shared[\"' /]+data|/tmp/", text.replace("test_first_hour", "")) or path.name == "test_first_hour.py", path


def test_missing_output_directory_is_refused(tmp_path, capsys):
    assert cli.main(["forward", str(write(tmp_path, TINY_FORWARD))]) == 2
    assert "-o/--outdir: missing" in capsys.readouterr().err


def test_output_directory_that_cannot_be_created_is_refused(tmp_path, capsys):
    (tmp_path / "a_file").write_text("x")
    assert cli.main(["forward", str(write(tmp_path, TINY_FORWARD)), "-o", str(tmp_path / "a_file" / "out"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "-o: cannot create" in err and "Traceback" not in err


def test_interrupt_exits_130_with_one_line(tmp_path, capsys, monkeypatch):
    import adseismic.scene

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(adseismic.scene, "run_forward", interrupted)
    out = tmp_path / "out"
    assert cli.main(["forward", str(write(tmp_path, TINY_FORWARD)), "-o", str(out), "-q"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "interrupted" in err[0]
    assert not (out / "data.h5").exists() and not list(out.glob("*.part"))


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_signal_landing_in_a_finaliser_still_interrupts(sig, capsys):
    """CI saw SIGTERM land in a Warp array's __del__: Python ignores exceptions raised there, and the FWI ran on to
    exit 0. The interrupt must come out of the code that dropped the object, and no traceback is printed."""
    import gc
    import signal
    import time

    class Finalised:
        def __del__(self):
            signal.raise_signal(getattr(signal, sig))
            sum(range(100))  # bytecodes, so the handler runs here, inside __del__

    with pytest.raises(KeyboardInterrupt, match=sig), cli._interruptible():
        Finalised()
        gc.collect()
        t0 = time.monotonic()
        while time.monotonic() - t0 < 2:  # the interrupt comes 1 ms later, from SIGALRM
            pass
    assert "Exception ignored" not in capsys.readouterr().err


def test_an_interrupt_in_a_threaded_cpu_step_leaves_no_worker_waiting():
    """A SIGTERM landed in the main thread's share of a threaded CPU step before its barrier: the worker waited there
    for ever and the interpreter's exit, which joins it, hung (a locate run stopped by `timeout` never exited). The
    step breaks the barrier on whatever stops the main thread, so the worker fails at once and is free again."""
    import threading

    import warp as wp

    from adseismic.kernels.acoustic import propagator
    from adseismic.solve.common import init_warp

    init_warp()
    prop = propagator.Acoustic((16, 16), 1.0, 0.1, 4, 1, 0, 1e-3, 10.0, 1.0, dtype=wp.float32, device="cpu")
    prop.threads = 2
    at_barrier = threading.Event()

    def job(i, barrier):
        if i == 0:
            at_barrier.wait(5)
            raise KeyboardInterrupt  # as the handler of a signal would, in the main thread, before the barrier
        at_barrier.set()
        barrier.wait()

    with pytest.raises(KeyboardInterrupt):
        prop._split(job)
    assert prop._pool.submit(lambda: "free").result(timeout=5) == "free"  # the worker left the broken barrier


def test_progress_in_a_log_is_lines_not_a_bar(caplog, capsys):
    with caplog.at_level(logging.INFO, logger=log.name):
        bar = progress_bar(total=100, desc="time steps", unit="steps")
        for _ in range(100):
            bar.update()
        bar.close()
    lines = [r.getMessage() for r in caplog.records]
    assert 3 <= len(lines) <= 5 and lines[-1].startswith("time steps: 100/100 steps done")  # 25%, 50%, 75%, done
    assert "\r" not in capsys.readouterr().err


def test_a_refusal_inside_a_run_leaves_nothing_behind(tmp_path, capsys, monkeypatch):
    import adseismic.scene

    def refuse(*a, **k):
        raise ValueError("simulation.example: refused inside the run")

    monkeypatch.setattr(adseismic.scene, "run_forward", refuse)
    out = tmp_path / "out"
    assert cli.main(["forward", str(write(tmp_path, TINY_FORWARD)), "-o", str(out), "-q"]) == 2
    assert not out.exists()  # config.yaml and forward.log were written, then removed with the directory it made
    (tmp_path / "kept").mkdir()
    (tmp_path / "kept" / "notes.txt").write_text("mine")
    assert cli.main(["forward", str(write(tmp_path, TINY_FORWARD)), "-o", str(tmp_path / "kept"), "-q"]) == 2
    assert [p.name for p in (tmp_path / "kept").iterdir()] == ["notes.txt"]


@pytest.mark.slow
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_signal_during_fwi_exits_130_and_the_run_resumes(sig, tmp_path):
    """Also where the process starts with SIGINT ignored (a background job of a script), which Python keeps:
    the interrupt used to be swallowed and the run ended with exit status 0."""
    import json
    import os
    import signal
    import subprocess
    import sys
    import time

    from .test_fwi import TINY

    cfg = write(tmp_path, {**TINY, "inversion": {**TINY["inversion"], "iterations": 6}}, "fwi.yaml")
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "adseismic.cli", "fwi", str(cfg), "-o", str(out), "-q"]
    p = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    while not (out / "journal_band0.h5").exists() and p.poll() is None:
        time.sleep(0.05)
    time.sleep(0.3)
    os.kill(p.pid, getattr(signal, sig))
    err = p.communicate(timeout=120)[1]
    assert p.returncode == 130, err
    lines = [line for line in err.splitlines() if not line.startswith(("Warp", "WARNING: band 0"))]  # (TINY's band grid refused)
    assert len(lines) == 1 and f"interrupted by {sig}" in lines[0] and "--resume" in lines[0], lines
    assert not list(out.glob("*.part")) and not (out / "summary.json").exists()
    r = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert [b["iterations"] for b in json.loads((out / "summary.json").read_text())["bands"]] == [6, 6]
