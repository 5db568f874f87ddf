"""A small mutation check: targeted mutations of the library, each applied to a scratch copy of the repository, and the
pytest selection that must catch it (issue 29).

    python tests/mutations.py [--only NAME ...] [--jobs N] [--write]

For each mutation: the tracked files (git ls-files) are copied into a fresh tempfile.mkdtemp(), with the installed
layout made there (adseismic/kernels -> ../kernels, adseismic/data_synthetic -> ../data_synthetic, as pyproject.toml
maps them), the mutation applied (its original text must occur exactly once in its file: a code change that moves
or rewrites the text is refused, so that a stale mutation is noticed, not silently skipped), and
`python -m pytest -q -x -p no:cacheprovider -m "" <selection>` (slow tests included) run in the scratch root with PYTHONPATH at the scratch root
and a fresh empty WARP_CACHE_PATH (no kernel built from the unmutated code is loaded). Result: caught (pytest exit
code 1: a test failed), missed (exit 0: every selected test passed on the mutant), error (any other exit code: no
test collected, a usage or import error, an interruption). Before the mutations run, a scratch copy is checked to
import its own adseismic (not the editable install of the working tree).

Mutations marked gpu_only are caught only by tests that run on a GPU (ADSEISMIC_TEST_DEVICE=cuda:0); on the CPU
they are reported as "GPU only" and not run.

--write writes docs/testing.md (how to run it and the table of the last run). pytest does not collect this file
(its name does not start with test_).
"""

from __future__ import annotations

import argparse
import datetime
import os
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LINKS = {"adseismic/kernels": "../kernels", "adseismic/data_synthetic": "../data_synthetic"}
DEVICE = os.environ.get("ADSEISMIC_TEST_DEVICE", "cpu")


@dataclass(frozen=True)
class Mutation:
    name: str
    file: str  # relative to the repository root
    original: str  # must occur exactly once in file
    replacement: str
    selection: tuple[str, ...]  # pytest arguments: file paths and -k expressions
    models: str  # the fault it stands for
    gpu_only: bool = False


MUTATIONS = [
    Mutation(
        "acoustic_o4_weight", "kernels/numerics.py",
        "    4: (-5.0 / 2.0, 4.0 / 3.0, -1.0 / 12.0),",
        "    4: (-5.0 / 2.0, 1.01 * 4.0 / 3.0, -1.0 / 12.0),",
        ("tests/test_propagate.py", "-k", "spatial_convergence and 4-4.0"),
        "acoustic order-4 second-derivative weight a1 = 4/3 1% off",
    ),
    Mutation(
        "staggered_o4_weight", "kernels/numerics.py",
        "    4: (9.0 / 8.0, -1.0 / 24.0),",
        "    4: (1.01 * 9.0 / 8.0, -1.0 / 24.0),",
        ("tests/test_elastic.py", "-k", "full_space_point_force_against_analytic"),
        "staggered order-4 first-derivative weight 9/8 1% off",
    ),
    Mutation(
        "cpml_d0", "kernels/acoustic/propagator.py",
        "        d0 = 3.0 * vmax * np.log(1.0 / reflection) / (2.0 * thick)",
        "        d0 = 0.9 * 3.0 * vmax * np.log(1.0 / reflection) / (2.0 * thick)",
        ("tests/test_propagate.py", "-k", "cpml_reflection"),
        "acoustic CPML damping profile d0 10% low",
    ),
    Mutation(
        "acoustic_src_scale", "kernels/acoustic/propagator.py",
        "        self.src_scale = dtype(dt * dt / dx**self.ndim)",
        "        self.src_scale = dtype(1.01 * dt * dt / dx**self.ndim)",
        ("tests/test_propagate.py", "-k", "off_grid_source_and_receivers_2d_absolute_amplitude"),
        "acoustic source scale (dt^2 / dx^ndim) 1% off",
    ),
    Mutation(
        "hicks_b", "kernels/common.py",
        "HICKS_B = 6.31",
        "HICKS_B = 5.0",
        ("tests/test_propagate.py", "-k", "operator_response_is_flat_in_band"),
        "Hicks operator's Kaiser window parameter b 6.31 -> 5.0",
    ),
    Mutation(
        "hicks_moments", "kernels/common.py",
        "        return hicks(d) / h0 + taper(d) * (a0 + (a1 + a2 * d) * d)",
        "        return hicks(d) / h0",
        ("tests/test_propagate.py", "-k", "off_grid_source_and_receivers_2d_absolute_amplitude"),
        "Hicks operator's weights normalised only (first and second moments not zeroed)",
    ),
    Mutation(
        "device_l2_sign", "adseismic/accel/reductions.py",
        "            res[s, r, t] = dtype(d * dt)",
        "            res[s, r, t] = dtype(-d * dt)",
        ("tests/test_elastic.py", "-k", "default_l2_on_device"),
        "elastic on-device l2 residual with its sign flipped",
    ),
    Mutation(
        "elastic_moment_amp", "kernels/elastic/propagator.py",
        "            wp.atomic_add(f, s, i[0], i[1], a * w * m)",
        "            wp.atomic_add(f, s, i[0], i[1], a * w * m * dtype(1.01))",
        ("tests/test_elastic.py", "-k", "fluid_matches_acoustic_pressure"),
        "elastic moment (explosive) source amplitude 1% high (add_moment)",
    ),
    Mutation(
        "elastic_force_amp", "kernels/elastic/propagator.py",
        "        # one operator point of a line force: vx += a bx w fx at node i, vz += a bz u fz at node j (points of weight 0 skipped)\n",
        "        # one operator point of a line force: vx += a bx w fx at node i, vz += a bz u fz at node j (points of weight 0 skipped)\n"
        "        a = a * dtype(1.01)\n",
        ("tests/test_elastic.py", "-k", "full_space_point_force_against_analytic"),
        "elastic force source amplitude 1% high (add_force)",
    ),
    Mutation(
        "correlation_no_obs_norm", "adseismic/solve/misfits.py",
        "    c = np.sum(d * o, axis=-1, keepdims=True) / (nd * no)",
        "    c = np.sum(d * o, axis=-1, keepdims=True) / nd",
        ("tests/test_misfits.py",),
        "correlation misfit without the observed trace's norm",
    ),
    Mutation(
        "host_l2_no_dt", "adseismic/solve/misfits.py",
        "    loss = 0.5 * float(flat @ flat) * dt",
        "    loss = 0.5 * float(flat @ flat)",
        ("tests/test_misfits.py",),
        "host l2 misfit value without the factor dt",
    ),
    Mutation(
        "sweep_zero_restart", "adseismic/solve/sweep.py",
        "                    _copy(start, self.checkpoints[k - 1])",
        "                    [a.zero_() for a in start]",
        ("tests/test_adjoint.py", "-k", "checkpoint and acoustic-2d"),
        "checkpointed sweep: a segment recomputed from a zero state instead of its checkpoint",
    ),
    Mutation(
        "taped_carry_dropped", "adseismic/solve/sweep.py",
        "            seeds.update(zip(st.arrays(), carry))",
        "            pass",
        ("tests/test_adjoint.py", "-k", "checkpoint and acoustic-2d"),
        "taped (Warp-generated) sweep: the adjoint state carried between segments dropped",
    ),
    Mutation(
        "acoustic_grad_factor", "kernels/acoustic/propagator.py",
        "        grad[z, y, x] = grad[z, y, x] + dtype(2.0) * v[z, y, x] * dt2 * acc",
        "        grad[z, y, x] = grad[z, y, x] + dtype(2.02) * v[z, y, x] * dt2 * acc",
        ("tests/test_adjoint.py", "-k", "taylor and acoustic-2d"),
        "acoustic model gradient factor 2 v dt^2 1% off",
    ),
    Mutation(
        "kept_loop_not_refilled", "adseismic/solve/loop.py",
        "    su.fill_model(mine.model)\n",
        "    pass  # mutation: the kept loop keeps the previous call's model\n",
        ("tests/test_propagate.py", "tests/test_elastic.py", "-k", "kept_time_loop_is_refilled"),
        "kept (CUDA-graph) time loop not refilled with the new model",
        gpu_only=True,
    ),
    Mutation(
        "kept_sweep_not_refilled", "adseismic/solve/elastic.py",
        "zip(self.su.inputs(self.sources), su.inputs(su.sources_of(self.amplitudes, fixed=True))), *zip(self.mat, mat)]:",
        "zip(self.su.inputs(self.sources), su.inputs(su.sources_of(self.amplitudes, fixed=True)))]:",
        ("tests/test_elastic.py", "-k", "kept_sweep_is_refilled"),
        "kept elastic sweep (Levels.refill) not refilled with the new model",
    ),
]


@dataclass
class Result:
    mutation: Mutation
    result: str
    seconds: float = 0.0
    tail: str = field(default="", repr=False)

    @property
    def reason(self) -> str:
        """The first assertion or error line of the failure (pytest's "E " lines), or ""."""
        for line in self.tail.splitlines():
            if line.startswith("E "):
                return line[1:].strip()
        return ""

    @property
    def failed(self) -> str:
        """The test that failed first (pytest's FAILED line), or ""."""
        for line in self.tail.splitlines():
            if line.startswith("FAILED "):
                return line.split()[1].split("::", 1)[-1]
        return ""


def tracked_files() -> list[str]:
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, check=True, capture_output=True).stdout.decode()
    return [p for p in out.split("\0") if p]


def scratch_copy(files: list[str]) -> Path:
    """A fresh copy of the tracked files in the installed layout (adseismic.kernels, adseismic.data_synthetic)."""
    dst = Path(tempfile.mkdtemp(prefix="adseismic-mutant-"))
    for rel in files:
        src = ROOT / rel
        if not src.is_file():  # (tracked but deleted in the working tree)
            continue
        target = dst / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, target)
    for link, to in LINKS.items():
        p = dst / link
        if p.exists() or p.is_symlink():
            p.unlink()
        p.symlink_to(to, target_is_directory=True)
    return dst


def environment(root: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(root)
    env["WARP_CACHE_PATH"] = tempfile.mkdtemp(prefix="warp-cache-", dir=root)  # fresh, empty
    env.pop("PYTEST_ADDOPTS", None)
    return env


def check_isolation(files: list[str]) -> str:
    """The scratch copy imports its own adseismic (and its kernels through the links), not the working tree's."""
    root = scratch_copy(files)
    try:
        code = "import adseismic, adseismic.kernels.common as c; print(adseismic.__file__); print(c.__file__)"
        out = subprocess.run([sys.executable, "-c", code], cwd=root, env=environment(root), check=True, capture_output=True,
                             text=True).stdout.split()  # fmt: skip
        for path in out:
            if not Path(path).resolve().is_relative_to(root.resolve()):
                raise SystemExit(f"the scratch copy imports {path}, not its own adseismic under {root}")
        return out[0]
    finally:
        shutil.rmtree(root, ignore_errors=True)


def apply(root: Path, m: Mutation):
    path = root / m.file
    text = path.read_text()
    n = text.count(m.original)
    if n != 1:
        raise SystemExit(f"mutation {m.name}: its original text occurs {n} times in {m.file} (must be once): update it")
    path.write_text(text.replace(m.original, m.replacement))


def run_one(m: Mutation, files: list[str], mutate: bool = True) -> Result:
    """Run m's selection on a scratch copy with m applied (mutate=False: on the unmutated copy, the baseline)."""
    if m.gpu_only and not DEVICE.startswith("cuda"):
        return Result(m, "GPU only")
    root = scratch_copy(files)
    t0 = time.perf_counter()
    try:
        if mutate:
            apply(root, m)
        cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", "-m", "", *m.selection]  # slow tests too
        p = subprocess.run(cmd, cwd=root, env=environment(root), capture_output=True, text=True)
        result = {0: "missed", 1: "caught"}.get(p.returncode, f"error (exit {p.returncode})")
        return Result(m, result, time.perf_counter() - t0, (p.stdout + p.stderr)[-3000:])
    finally:
        shutil.rmtree(root, ignore_errors=True)


def selection_text(m: Mutation) -> str:
    return " ".join(f'"{a}"' if " " in a else a for a in m.selection)


def table(results: list[Result]) -> str:
    rows = ["| name | what it models | file | selection | failed test | result | s |", "|---|---|---|---|---|---|---|"]
    for r in results:
        m = r.mutation
        failed = f"`{r.failed}`" if r.failed else "-"
        if r.reason:
            reason = r.reason if len(r.reason) <= 80 else r.reason[:77] + "..."
            failed += ": " + reason.replace("|", "\\|")
        rows.append(f"| {m.name} | {m.models} | `{m.file}` | `{selection_text(m)}` | {failed} | {r.result} | {r.seconds:.0f} |")
    return "\n".join(rows)


def write_doc(results: list[Result], partial: bool, baseline: bool):
    today = datetime.date.today().isoformat()
    note = " (a partial run: --only)" if partial else ""
    doc = f"""# Testing

The tests run on the CPU with `pytest` (`ADSEISMIC_TEST_DEVICE=cuda:0 pytest` runs the propagator and gradient tests
on a GPU). `python -m pytest -q` (the README's command, about 5 minutes on 2 cores) leaves out the tests marked `slow`
(location studies, alternative kernel layouts, kill -9/resume, the demos' wall times); `python -m pytest -q -m slow`
runs those, and CI (`.ci/run`) runs both passes.

## Mutation check

`tests/mutations.py` applies a list of targeted mutations of the library, each to a scratch copy of the tracked
files (`git ls-files`, in the installed layout), and runs the small pytest selection that must catch it, with a
fresh empty Warp kernel cache:

    python tests/mutations.py                  # all of them, a table on stdout
    python tests/mutations.py --only cpml_d0   # some of them
    python tests/mutations.py --jobs 2 --write # two at a time; write this page

A mutation's original text must occur exactly once in its file: when the code changes, the script refuses the
mutation and names it, and the list is updated. Results: caught (pytest exit code 1), missed (exit 0: a gap in the
tests), error (any other exit code). "GPU only": caught only by tests that need a GPU (the kept CUDA-graph time
loop); run them with `ADSEISMIC_TEST_DEVICE=cuda:0 python tests/mutations.py --only kept_loop_not_refilled` on one.
Most of each run's time is building the kernels into the empty cache.

Before the mutations, each distinct selection is run on the unmutated copy and must pass (skip with
`--no-baseline`), so that "caught" means the mutation made a passing selection fail.

Last run: {today}, device {DEVICE}{note}; baseline {"run: every selection passes unmutated" if baseline else "not run"}.

{table(results)}
"""
    (ROOT / "docs" / "testing.md").write_text(doc)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="+", metavar="NAME", help="run these mutations only")
    ap.add_argument("--jobs", type=int, default=1, help="mutations run at once (default 1)")
    ap.add_argument("--write", action="store_true", help="write docs/testing.md with the table")
    ap.add_argument("--no-baseline", action="store_true", help="skip running the selections on the unmutated copy first")
    ap.add_argument("-v", "--verbose", action="store_true", help="print the pytest output of each mutation")
    args = ap.parse_args(argv)
    chosen = MUTATIONS
    if args.only:
        names = {m.name for m in MUTATIONS}
        unknown = [n for n in args.only if n not in names]
        if unknown:
            raise SystemExit(f"unknown mutations: {unknown}; known: {sorted(names)}")
        chosen = [m for m in MUTATIONS if m.name in args.only]
    files = tracked_files()
    for m in chosen:  # refuse a stale mutation before running any
        n = (ROOT / m.file).read_text().count(m.original)
        if n != 1:
            raise SystemExit(f"mutation {m.name}: its original text occurs {n} times in {m.file} (must be once): update it")
    print(f"scratch copies import {check_isolation(files)} (checked)", flush=True)

    # the baseline: each distinct selection passes on the unmutated copy (else a "caught" would mean nothing)
    firsts = {}
    for m in chosen:
        if not (m.gpu_only and not DEVICE.startswith("cuda")):
            firsts.setdefault(m.selection, m)
    baseline_ok = True
    if not args.no_baseline:
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
            for r in ex.map(lambda m: run_one(m, files, mutate=False), firsts.values()):
                ok = r.result == "missed"  # (every test passed)
                baseline_ok &= ok
                print(f"baseline {selection_text(r.mutation)}: {'passes' if ok else 'FAILS: ' + r.result} ({r.seconds:.0f} s)", flush=True)
                if not ok:
                    print(r.tail, flush=True)
        if not baseline_ok:
            raise SystemExit("a selection fails on the unmutated code: fix that first")

    def job(m):
        r = run_one(m, files)
        print(f"{m.name}: {r.result} ({r.seconds:.0f} s) {r.failed} {r.reason}", flush=True)
        if args.verbose or r.result.startswith("error"):
            print(r.tail, flush=True)
        return r

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        results = list(ex.map(job, chosen))
    print()
    print(table(results))
    if args.write:
        write_doc(results, partial=bool(args.only), baseline=not args.no_baseline)
    bad = [r for r in results if r.result not in ("caught", "GPU only")]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
