"""The ``adseismic`` command line.

    adseismic plan CONFIG                      check any config, print the plan and its workflow's costs
    adseismic forward CONFIG -o OUTDIR         plan, simulate every shot, write data.h5 + PNGs
    adseismic fwi CONFIG -o OUTDIR             full-waveform inversion (adseismic.inversion.fwi)
    adseismic locate CONFIG -o OUTDIR          locate an event from its traces (adseismic.location.run)
    adseismic image CONFIG -o OUTDIR           RTM or least-squares RTM image (adseismic.imaging.run)
    adseismic bench [--device cpu cuda:0] -o DIR   speed/memory on the standard scenes (adseismic.bench)
    adseismic bench --physics -o DIR           the physics family (issue 26) beside Deepwave

forward, fwi, locate and image share -o/--output/--outdir, --dry-run (what ``plan`` runs), --force and -q.
Exit codes: 0 success; 2 invalid input (config, model, refused plan, output directory: the message says
which key and how to fix it, no traceback); 3 the simulation blew up (PropagationError; no data.h5 is
written); 130 interrupted (one line); 1 anything unexpected (with traceback).

Each subcommand is a (register, run) pair in :data:`COMMANDS`; adding one means writing its two
functions and adding it there.
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import functools
import json
import math
import pathlib
import signal
import sys
import threading
import time

import numpy as np

from adseismic.config import ConfigError, ForwardConfig, load_config
from adseismic.data.atomic import write_text_atomic
from adseismic.data.model import ModelError
from adseismic.runs import EXIT_INPUT, EXIT_INTERRUPTED, EXIT_OK, EXIT_UNSTABLE, CommandError, RunLog, format_position, log, version

SNAPSHOT_LIMIT_BYTES = 8 * 2**30  # refuse snapshot settings that would hold more than this


# --------------------------------------------------------------------------------- helpers

def _plan(config: ForwardConfig):
    from adseismic.scene import plan_scene

    return plan_scene(config)


def _warnings_text(plan) -> list[str]:
    """Warnings that plan.describe() does not already print."""
    text = plan.describe()
    return [w for w in getattr(plan, "warnings", []) if w not in text]


def snapshot_every(config: ForwardConfig, plan) -> int:
    """Time steps between snapshots (0: none) from output.snapshot_interval (s); refuses settings
    whose snapshots would not fit in memory (ConfigError naming output.snapshot_interval)."""
    interval = config.output.snapshot_interval
    if not interval:
        return 0
    every = max(1, int(round(interval / plan.dt)))
    n_snap = (plan.nt - 1) // every + 1
    itemsize = 4 if plan.precision == "float32" else 8
    nbytes = n_snap * config.n_shots * int(np.prod(plan.shape)) * itemsize
    if nbytes > SNAPSHOT_LIMIT_BYTES:
        raise ConfigError(
            f"output.snapshot_interval: {interval:g} s gives {n_snap} snapshots x {config.n_shots} "
            f"shots x {int(np.prod(plan.shape)):,} cells = {nbytes / 2**30:.1f} GiB, above the "
            f"{SNAPSHOT_LIMIT_BYTES / 2**30:.0f} GiB limit; use an interval of at least "
            f"{interval * nbytes / SNAPSHOT_LIMIT_BYTES:.3g} s, or 0 for none")
    if abs(every * plan.dt - interval) > 0.01 * interval:
        log.info("output.snapshot_interval %g s rounded to %d steps = %.4g s", interval, every,
                 every * plan.dt)
    return every


def _config_text(config: ForwardConfig) -> str:
    if config.path is not None:
        return pathlib.Path(config.path).read_text(encoding="utf-8")
    import yaml

    return yaml.safe_dump(config.raw, sort_keys=False)


# --------------------------------------------------------------------------------- shared flags

def _register_run(p: argparse.ArgumentParser, what: str) -> None:
    """The flags every workflow shares (forward, fwi, locate): CONFIG, -o, --dry-run, --force, -q."""
    p.add_argument("config", type=pathlib.Path, help=f"YAML {what} config file")
    p.add_argument("-o", "--output", "--outdir", dest="outdir", type=pathlib.Path,
                   help="output directory (created if needed); required unless --dry-run")
    p.add_argument("--dry-run", action="store_true",
                   help="check the config and inputs, print the plan with its costs, write nothing")
    p.add_argument("--force", action="store_true",
                   help="run although the planner's memory or time estimate is above the budget")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar, log only warnings to stderr (the log file is complete)")


def _force(config, force: bool):
    """config (a workflow config) with simulation.force set when --force was given."""
    if not force:
        return config
    import dataclasses

    if hasattr(config, "forward"):
        return dataclasses.replace(config, forward=_force(config.forward, True))
    return dataclasses.replace(config, simulation=dataclasses.replace(config.simulation, force=True))


def _outdir(args) -> pathlib.Path:
    """The output directory of a run (not a dry run): refused before any work if it cannot be one."""
    outdir = args.outdir
    if outdir is None:
        raise CommandError("-o/--outdir: missing; give the output directory (or --dry-run to only check and plan)")
    if outdir.exists() and not outdir.is_dir():
        raise CommandError(f"-o: {outdir} exists and is not a directory; choose another output directory")
    return outdir


def _check_device(device: str, dry_run: bool) -> None:
    """Refuse a device this machine lacks, before any work; a dry run (plan) only warns, so that a config for
    another machine (a GPU) can be planned here."""
    from adseismic.solve.common import resolve_device

    try:
        resolve_device(device)
    except ValueError as e:
        if not dry_run:
            raise
        print(f"WARNING   {e}: the plan below is for that device; running here would be refused")


def _make_outdir(outdir: pathlib.Path, args) -> None:
    """Create the run directory; records in args.created what was there, for _clean_refused."""
    existed = outdir.is_dir()
    args.created = (outdir, existed, {p.name for p in outdir.iterdir()} if existed else set())
    try:
        outdir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CommandError(f"-o: cannot create {outdir} ({e.strerror or e}); choose a directory you can write to") from None


PREAMBLE = ("config.yaml", "forward.log", "fwi.log", "locate.log", "image.log", "observed.h5", "observed_waveforms.h5")  # written before a run's work


def _clean_refused(args) -> None:
    """After a refusal (exit 2) raised once the run directory existed: remove the files of PREAMBLE this run created
    (and the directory, if it created it and it is left empty), so that a refused run leaves what was there before.
    Work products (journals, data) are never removed."""
    state = getattr(args, "created", None)
    if state is None or not state[0].is_dir():
        return
    outdir, existed, before = state
    for name in PREAMBLE:
        if name not in before and (outdir / name).is_file():
            (outdir / name).unlink()
    if not existed and not any(outdir.iterdir()):
        outdir.rmdir()


def _written(outdir: pathlib.Path, since: float) -> list[str]:
    """Names of the files in outdir (recursively) written since ``since`` (time.time()), sorted."""
    return sorted(str(p.relative_to(outdir)) for p in outdir.rglob("*") if p.is_file() and p.stat().st_mtime >= since - 1.0)


def _wrote_line(outdir: pathlib.Path, since: float, detail: dict | None = None) -> str:
    names = [f"{n} ({detail[n]})" if detail and n in detail else n for n in _written(outdir, since)]
    return f"wrote {outdir}/ ({len(names)} files): {', '.join(names)}"


def _hms(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.3g} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


#: seconds of a misfit + gradient evaluation per shot, in forward runs of that shot: the forward, its checkpointed
#: re-run and the adjoint (measured 6.0 on 2 CPU cores for configs/fwi_demo.yaml: 1.65 s an evaluation of 6 shots
#: planned at 0.046 s a forward shot)
GRADIENT_COST = 6.0


# --------------------------------------------------------------------------------- plan

WORKFLOWS = ("forward", "fwi", "locate", "image")


def workflow_of(path: pathlib.Path) -> str:
    """Which workflow a config is for, from its top-level keys: `image` -> image, `inversion` (or `true_model`,
    `observed`) -> fwi, `traces` -> locate, otherwise forward."""
    from adseismic.config.common import _read_yaml

    raw, _ = _read_yaml(path)
    if "image" in raw:
        return "image"
    if any(k in raw for k in ("inversion", "true_model", "observed")):
        return "fwi"
    return "locate" if "traces" in raw else "forward"


def _register_plan(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=pathlib.Path, help="YAML config of any workflow (forward, fwi, locate, image)")
    p.add_argument("--workflow", choices=WORKFLOWS, help="the workflow to plan (default: read from the config's keys)")
    p.add_argument("--force", action="store_true", help="plan although the estimate is above the budget")


def cmd_plan(args) -> int:
    """`adseismic plan CONFIG` is `adseismic <workflow> CONFIG --dry-run` for the config's workflow."""
    wf = args.workflow or workflow_of(args.config)
    dry = build_parser().parse_args([wf, str(args.config), "--dry-run"] + ["--force"] * args.force)
    return dry.func(dry)


def _print_plan(title: str, plan, extra: list[str] = ()) -> None:
    print(title)
    print(plan.describe())
    for w in _warnings_text(plan):
        print(f"WARNING   {w}")
    for line in extra:
        print(line)


# --------------------------------------------------------------------------------- forward

def _register_forward(p: argparse.ArgumentParser) -> None:
    _register_run(p, "forward")
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True,
                   help="show a progress bar over time steps (default: on)")


def _elastic_traces(scene, result, store, n_receivers: int) -> dict:
    """{name: (data (n_shots, n_receivers, nt) as ``store``, units, sample times)} of what the elastic receivers record
    (scene.recording: components and DAS strain rate) from forward_elastic's (or forward_elastic3d's, with vy) result
    (store.write_forward's components)."""
    from adseismic.solve.receivers import SAMPLE_TIMES, UNITS

    recorded = {c: getattr(result, c) for c in ("vx", "vy", "vz", "pressure") if getattr(result, c, None) is not None}
    data = scene.recording.data(recorded, n_receivers)
    return {name: (a.astype(store), UNITS[name], f"t = {SAMPLE_TIMES[name]}") for name, a in data.items()}


def cmd_forward(args) -> int:
    from adseismic import plotting
    from adseismic.data import store as io
    from adseismic.scene import build_scene, run_forward
    from adseismic.solve.common import PropagationError

    # --- everything that can be refused is checked before OUTDIR is touched
    config = _force(load_config(args.config), args.force)
    plan = _plan(config)
    every = snapshot_every(config, plan)
    _check_device(plan.device, args.dry_run)
    if config.parallel is not None and not args.dry_run:  # devices present, scheduler reachable, not more workers than shots
        from adseismic.solve.pools import check_pool

        check_pool(config.parallel, plan.device, config.n_shots)
    if args.dry_run:
        _print_plan(f"forward plan for {args.config} ({config.model.ndim}D, {config.n_shots} shot(s), "
                    f"{len(config.geometry.receivers)} receivers)", plan,
                    [f"total     ~{_hms(plan.seconds_per_shot * config.n_shots)} for {config.n_shots} shot(s) on {plan.device} (estimate)"])
        return EXIT_OK
    outdir = _outdir(args)
    scene = build_scene(config, plan)
    progress = args.progress and not args.quiet

    since = time.time()
    _make_outdir(outdir, args)
    with RunLog(outdir / "forward.log", args.quiet):
        log.info("adseismic %s forward %s -> %s", version(), args.config, outdir)
        log.info("plan:\n%s", plan.describe())
        for w in plan.warnings:
            log.warning("%s", w)
        # outputs of an earlier run would no longer match config.yaml and forward.log
        stale = [outdir / "data.h5", outdir / "waveforms.h5", outdir / "model.png", outdir / "snapshots_shot0.png",
                 *outdir.glob("gather_shot*.png"), *outdir.glob("model_*.png")]
        stale = [p for p in stale if p.exists()]
        if stale:
            log.info("replacing the outputs of an earlier run in %s: %s", outdir,
                     ", ".join(p.name for p in stale))
            for p in stale:
                p.unlink()
        text = _config_text(config)
        write_text_atomic(outdir / "config.yaml", text)

        n_shots = config.n_shots
        log.info("running %d shot(s), %d steps of %.6g s on %s (%s)", n_shots, plan.nt, plan.dt,
                 plan.device, plan.precision)
        t0 = time.perf_counter()
        try:
            if config.parallel is None:
                result = run_forward(scene, snapshot_every=every, progress=progress)
            else:  # the shots over the workers, gathered in shot order
                from adseismic.solve.pools import forward_on_workers

                result = forward_on_workers(scene, config.parallel, every, progress)
        except PropagationError as e:
            log.error("%s", e)
            raise CommandError(f"simulation failed: {e}; no data.h5 was written",
                               EXIT_UNSTABLE) from None
        seconds = time.perf_counter() - t0
        rate = plan.padded_cells * plan.nt * n_shots / max(seconds, 1e-9)
        log.info("simulated in %.2f s (%.3g padded cell updates per second)", seconds, rate)

        src_world = np.asarray(config.geometry.sources, float)
        rec_world = np.asarray(config.geometry.receivers, float)
        params = {k: v for k, v in config.wavelet.params.items() if k != "samples"}
        attrs = {
            "dx": plan.dx, "order": plan.order, "precision": plan.precision,
            "device": plan.device, "free_surface": bool(plan.free_surface),
            "pml_width": plan.pml_width, "pml_reflection": plan.pml_reflection,
            "f_max": plan.f_max, "courant": plan.courant, "cfl_limit": plan.cfl_limit,
            "expected_error": plan.expected_error, "grid_origin": tuple(plan.origin),
            "n_shots": n_shots, "wavelet_kind": config.wavelet.kind,
            "wavelet_params": repr(params), "model_name": config.model.name,
            "adseismic_version": version(),
            "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "config_yaml": text, "config_path": str(pathlib.Path(args.config).resolve()),
            "plan": plan.describe(), "seconds": seconds, "physics": config.physics,
        }
        if config.physics != "acoustic":  # the mechanism (N/m or N m/m per unit of the wavelet) and the fibre
            das = config.geometry.das
            attrs.update(source_type=config.source.type, source_components=config.source.components,
                         **({"das_gauge_length": das.gauge_length, "das_direction": das.direction} if das else {}))
        ndim = config.model.ndim
        units = "units of source_wavelet" + (" x m" if ndim == 3 else "")
        store = np.float32 if plan.precision == "float32" else np.float64  # as simulated
        traces = _elastic_traces(scene, result, store, len(rec_world)) if config.physics != "acoustic" else None
        data_path = io.write_forward(
            outdir / "data.h5", receiver_data=None if traces else result.receiver_amplitudes.astype(store),
            source_wavelet=scene.wavelet, dt=result.dt, source_coordinates=src_world,
            receiver_coordinates=rec_world, velocity=scene.model.values, spacing=plan.dx,
            origin=plan.origin, attrs=attrs, snapshots=getattr(result, "snapshots", None),
            snapshot_times=getattr(result, "snapshot_times", None), units=units, components=traces)
        log.info("wrote %s", data_path)
        from adseismic.data.asdf import write_forward_asdf  # the same traces in ASDF (pyasdf optional: a warning without it)

        if traces:
            log.info("no waveforms.h5 (ASDF) for physics %s: data.h5 holds %s", config.physics, ", ".join(traces))
        else:
            write_forward_asdf(outdir / "waveforms.h5", receiver_data=result.receiver_amplitudes.astype(store), dt=result.dt,
                               source_coordinates=src_world, receiver_coordinates=rec_world, wavelet=scene.wavelet, units=units)

        pngs = [plotting.plot_model(outdir / "model.png", scene.model.values, plan.dx,
                                    plan.origin, src_world, rec_world,
                                    title=config.model.name or "velocity model")]
        if config.physics != "acoustic":  # model.png is vp; acoustic_vd has no vs (0); vti has epsilon and delta, viscoacoustic q (arrays)
            fields = {"vs": "S velocity (m/s)", "epsilon": "Thomsen epsilon", "delta": "Thomsen delta",
                      "q": "quality factor Q (blank: lossless)", "rho": "density (kg/m^3)"}
            pngs += [plotting.plot_model(outdir / f"model_{name}.png", getattr(f, "values", f), plan.dx, plan.origin,
                                         src_world, rec_world, title=f"{name} on the simulation grid", label=label)
                     for name, label in fields.items() if (f := getattr(scene.model, name, None)) is not None]
        for k in range(n_shots):
            where = ", ".join(f"{a}={v:g}" for a, v in zip("zyx" if ndim == 3 else "zx",
                                                            src_world[k]))
            for name, (data, unit, _) in (traces or {"": (result.receiver_amplitudes, None, None)}).items():
                pngs.append(plotting.plot_gather(outdir / f"gather_shot{k}{'_' + name if name else ''}.png",
                                                 data[k], result.dt, rec_world if traces else rec_world[:, -1], units=unit,
                                                 title=f"shot {k} (source {where} m){' ' + name if name else ''}"))
        if getattr(result, "snapshots", None) is not None:
            pngs.append(plotting.plot_snapshots(
                outdir / "snapshots_shot0.png", result.snapshots[:, 0], result.snapshot_times,
                plan.dx, plan.origin, src_world[:1], title="shot 0 wavefield u"))
        log.info("wrote %d figures", len(pngs))
        wrote = _wrote_line(outdir, since, {"data.h5": f"{n_shots} shots x {len(rec_world)} receivers x {plan.nt} samples"})
        log.info("%s", wrote)

    if not args.quiet:
        print(plan.describe())
    print(wrote)
    return EXIT_OK


# --------------------------------------------------------------------------------- fwi

def _register_fwi(p: argparse.ArgumentParser) -> None:
    _register_run(p, "inversion (forward sections + inversion)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in OUTDIR from its journals (same config required)")


def _fwi_costs(config, prepared) -> list[str]:
    inv, plan = config.inversion, prepared.plan
    n_bands, shots = len(inv.bands), plan.n_shots
    its = inv.iterations if isinstance(inv.iterations, list) else [inv.iterations] * n_bands
    # an L-BFGS iteration takes ~1.2 evaluations (line search) plus one at the start of a band
    evals = sum(inv.evaluations or int(math.ceil(1.2 * i)) + 1 for i in its)
    per_eval = GRADIENT_COST * plan.seconds_per_shot * shots
    observed = "simulated from true_model first (one forward per shot)" if prepared.observed is None else "read from files"
    return [f"fwi       {n_bands} band(s) x <= {max(its)} iterations: <= {evals} evaluations x {shots} shot(s) "
            f"(misfit + gradient), observed data {observed}",
            f"          wall time up to ~{_hms(evals * per_eval)} on {plan.device} ({_hms(per_eval)} an evaluation; estimate)"]


def cmd_fwi(args) -> int:
    from adseismic.config import load_fwi_config
    from adseismic.inversion.fwi import prepare_fwi, run_fwi
    from adseismic.solve.common import PropagationError

    config = _force(load_fwi_config(args.config), args.force)
    _check_device(config.forward.simulation.device, args.dry_run)
    with RunLog(None, args.quiet or args.dry_run) as early:
        log.info("adseismic %s fwi %s -> %s%s", version(), args.config, args.outdir, " (resume)" if args.resume else "")
        prepared = prepare_fwi(config)  # plans and reads/checks observed files before OUTDIR is touched
    if args.dry_run:
        c = config.forward
        _print_plan(f"fwi plan for {args.config} ({c.model.ndim}D, {c.n_shots} shot(s), {len(c.geometry.receivers)} receivers)",
                    prepared.plan, _fwi_costs(config, prepared))
        return EXIT_OK
    outdir = _outdir(args)
    text = _config_text(config.forward)
    started = outdir.is_dir() and any(outdir.glob("journal_band*.h5"))
    if args.resume:
        if not started:
            raise CommandError(f"--resume: {outdir} holds no run to resume (no journal_band*.h5); drop --resume to start one")
        old = (outdir / "config.yaml").read_text(encoding="utf-8") if (outdir / "config.yaml").exists() else None
        if old != text:
            raise CommandError(f"--resume: the config differs from {outdir / 'config.yaml'}; a resumed run must use the same "
                               "config (start a new run directory for a changed one)")
    elif started:
        raise CommandError(f"-o: {outdir} already holds a run; add --resume to continue it or choose another directory")
    since = time.time()
    _make_outdir(outdir, args)
    with RunLog(outdir / "fwi.log", args.quiet, earlier=early.records):
        write_text_atomic(outdir / "config.yaml", text)
        try:
            res = run_fwi(config, outdir, progress=not args.quiet, prepared=prepared)
        except PropagationError as e:
            raise CommandError(f"simulation failed: {e}", EXIT_UNSTABLE) from None
        except KeyboardInterrupt:
            log.info("interrupted; continue with: adseismic fwi %s -o %s --resume", args.config, outdir)  # (the file's record)
            raise
        wrote = _wrote_line(outdir, since)
        log.info("%s (%.0f s)", wrote, res.seconds)
    for i, b in enumerate(res.bands):
        print(f"band {i} ({b['band']}): {b['iterations']} iterations, {b['evaluations']} evaluations, "
              f"misfit {b['misfit']:.4g} of its start ({b['stop_reason']})")
    if res.errors:
        e = res.errors
        change = 1 - e["final_anomaly"] / e["start_anomaly"]
        print(f"relative model error in the anomaly: {e['start_anomaly']:.4f} -> {e['final_anomaly']:.4f} "
              f"({100 * abs(change):.0f}% {'lower' if change >= 0 else 'higher'}); below the water / masks: "
              f"{e['start_below_water']:.4f} -> {e['final_below_water']:.4f}")
    print(f"{wrote} ({res.seconds:.0f} s)")
    return EXIT_OK


# --------------------------------------------------------------------------------- bench

def _register_bench(p: argparse.ArgumentParser) -> None:
    from adseismic.bench import register

    register(p)


def cmd_bench(args) -> int:
    from adseismic.bench import cmd_bench as run

    return run(args)


# --------------------------------------------------------------------------------- locate

def _register_locate(p: argparse.ArgumentParser) -> None:
    _register_run(p, "location (model, traces, preprocess, source, search)")
    p.add_argument("--compare-optimizers", action="store_true",
                   help="also run the optimiser study (GD, Adam, L-BFGS-B, Gauss-Newton; scaled and raw units) on this event")
    p.add_argument("--study-evaluations", type=int, default=30, metavar="N",
                   help="evaluations per optimiser in --compare-optimizers (default 30)")
    p.add_argument("--misfit-map", type=int, default=None, metavar="N",
                   help="positions per axis of the misfit map around the event (one batched simulation; default 11, "
                        "physics elastic 7)")


def _locate_costs(config, prep, args) -> list[str]:
    plan, search = prep.plan, config.search
    starts = len(prep.starts)
    evals = starts * int(math.ceil(1.2 * search["iterations"]))
    per_eval = GRADIENT_COST * plan.seconds_per_shot  # one event
    n_map = args.misfit_map ** plan.ndim
    lines = [f"locate    1 event, {len(prep.stations)} stations, {starts} start(s) x <= {search['iterations']} iterations: "
             f"<= {evals} evaluations (misfit + gradient)",
             f"          misfit map {args.misfit_map}^{plan.ndim} = {n_map} positions (forward only, batched)",
             f"          wall time up to ~{_hms(evals * per_eval + n_map * plan.seconds_per_shot)} on {plan.device} "
             f"({_hms(per_eval)} an evaluation; estimate)"]
    if args.compare_optimizers:
        lines.append(f"          + optimiser study: 8 runs x <= {args.study_evaluations} evaluations "
                     f"(~{_hms(8 * args.study_evaluations * per_eval)})")
    return lines


def cmd_locate(args) -> int:
    from adseismic.config import load_locate_config
    from adseismic.location.locate import compare_optimizers, optimizer_table
    from adseismic.location.run import event_misfit_map, locate_event, prepare_locate, simulation_options, write_outputs
    from adseismic.solve.common import PropagationError

    if args.study_evaluations < 1:
        raise CommandError(f"--study-evaluations: {args.study_evaluations} < 1; give at least 1")
    if args.misfit_map is not None and args.misfit_map < 3:
        raise CommandError(f"--misfit-map: {args.misfit_map} < 3; give at least 3 positions per axis")
    config = _force(load_locate_config(args.config), args.force)
    if args.misfit_map is None:  # an elastic shot costs ~4 acoustic ones
        args.misfit_map = 7 if config.physics == "elastic" else 11
    if args.compare_optimizers and config.physics != "acoustic":
        raise CommandError(f"--compare-optimizers: the optimiser study runs acoustic physics only, but physics is {config.physics}; "
                           f"drop --compare-optimizers (or locate with physics: acoustic)")
    _check_device(config.simulation.device, args.dry_run)
    if not args.dry_run:
        outdir = _outdir(args)
        if (outdir / "summary.json").exists():
            raise CommandError(f"-o: {outdir} already holds a location (summary.json); choose another directory")
    with RunLog(None, args.quiet or args.dry_run) as early:
        log.info("adseismic %s locate %s -> %s", version(), args.config, args.outdir)
        prep = prepare_locate(config)  # reads and checks every input before OUTDIR is touched
    if args.dry_run:
        _print_plan(f"locate plan for {args.config} ({prep.model.ndim}D, 1 event, {len(prep.stations)} stations)",
                    prep.plan, _locate_costs(config, prep, args))
        return EXIT_OK
    since = time.time()
    _make_outdir(outdir, args)
    with RunLog(outdir / "locate.log", args.quiet, earlier=early.records):
        write_text_atomic(outdir / "config.yaml", _config_text(config))
        t0 = time.perf_counter()

        def progress(iteration, evaluations, position, origin_time):
            log.info("iteration %d (%d evaluations): %s, origin time %.5f s", iteration, evaluations,
                     format_position(position), prep.t_shift + origin_time)  # fmt: skip

        try:
            res = locate_event(prep, callback=progress)
            mmap = event_misfit_map(prep, res, n=args.misfit_map)
            study = None
            if args.compare_optimizers:
                log.info("optimiser study: 8 runs of at most %d evaluations each", args.study_evaluations)
                study = compare_optimizers(prep.model, prep.stations, prep.observed, prep.plan.dt, prep.noise_std, res.start,
                                           {"position": res.position, "origin_time": res.origin_time}, peak_frequency=prep.f0,
                                           max_evaluations=args.study_evaluations, bounds=prep.bounds,
                                           progress=lambda r: log.info("study: %s", r), **simulation_options(prep))  # fmt: skip
        except PropagationError as e:
            raise CommandError(f"simulation failed: {e}", EXIT_UNSTABLE) from None
        write_outputs(outdir, prep, res, mmap, study)
        log.info("located in %.0f s", time.perf_counter() - t0)
        wrote = _wrote_line(outdir, since)
        log.info("%s", wrote)
    s = json.loads((outdir / "summary.json").read_text())
    axes = list(s["position_m"])
    pos = ", ".join(f"{k} = {v:.1f} +- {s['position_error_m_1sigma'][k]:.1f} m" for k, v in s["position_m"].items())
    print(f"event at {pos} (1 sigma; axes {', '.join(axes)}); origin time {s['origin_time_utc']} +- "
          f"{s['origin_time_error_s_1sigma']:.4f} s")
    if "latitude" in s:
        print(f"latitude {s['latitude']:.5f}, longitude {s['longitude']:.5f}, depth {s['depth_m']:.0f} m")
    if "truth_position_error_m" in s:
        print(f"distance to the true position: {s['truth_position_error_m']:.2f} m")
    if "moment_tensor" in s:
        mt = s["moment_tensor"]
        comp = ", ".join(f"{k} {v:.3g}" for k, v in mt["local_xyz"].items() if v is not None)
        planes = "; ".join(f"{p['strike']:.0f}/{p['dip']:.0f}/{p['rake']:.0f}" for p in mt["nodal_planes"])
        print(f"moment tensor ({mt['constraint']}, {mt['units']}): {comp}; unresolved in 2D: {', '.join(mt['unresolved'])}; "
              f"scalar moment {mt['scalar_moment']:.3g}; nodal planes (strike/dip/rake) {planes}")
    if study is not None:
        print(optimizer_table(study))
    print(wrote)
    return EXIT_OK


# --------------------------------------------------------------------------------- image

def _register_image(p: argparse.ArgumentParser) -> None:
    _register_run(p, "imaging (forward sections + image + true_model or observed)")


def _image_costs(config, prep) -> list[str]:
    im, plan = config.image, prep.plan
    # a gradient (background forward, its checkpointed re-run, the adjoint) ~ GRADIENT_COST forward runs; a Born
    # run two (background and scattered wavefields) and the observed data one
    runs = GRADIENT_COST + (im.iterations * (GRADIENT_COST + 2) if im.method == "lsrtm" else 0)
    runs += 1 if prep.observed is None else 0
    what = "RTM: one migration" if im.method == "rtm" else f"LSRTM: {im.iterations} CG iterations (one Born + one migration each)"
    source = "simulated from true_model" if prep.observed is None else "read from files"
    return [f"image     {what} of {plan.n_shots} shot(s); observed data {source}",
            f"          wall time ~{_hms(runs * plan.seconds_per_shot * plan.n_shots)} on {plan.device} (estimate)"]


def cmd_image(args) -> int:
    from adseismic.config.image import load_image_config
    from adseismic.imaging.run import prepare_image, run_image
    from adseismic.solve.common import PropagationError

    config = _force(load_image_config(args.config), args.force)
    _check_device(config.forward.simulation.device, args.dry_run)
    with RunLog(None, args.quiet or args.dry_run) as early:
        log.info("adseismic %s image %s -> %s", version(), args.config, args.outdir)
        prep = prepare_image(config)  # plans, makes the background and reads observed files before OUTDIR is touched
    c = config.forward
    if args.dry_run:
        _print_plan(f"image plan for {args.config} ({c.model.ndim}D, {c.n_shots} shot(s), {len(c.geometry.receivers)} receivers)",
                    prep.plan, _image_costs(config, prep))
        return EXIT_OK
    outdir = _outdir(args)
    since = time.time()
    _make_outdir(outdir, args)
    with RunLog(outdir / "image.log", args.quiet, earlier=early.records):
        write_text_atomic(outdir / "config.yaml", _config_text(c))
        try:
            res = run_image(config, outdir, progress=not args.quiet, prepared=prep)
        except PropagationError as e:
            raise CommandError(f"simulation failed: {e}; no image.h5 was written", EXIT_UNSTABLE) from None
        wrote = _wrote_line(outdir, since)
        log.info("%s", wrote)
    n = res.residual_norms
    if len(n) > 1:
        print(f"lsrtm: data residual {n[-1] / n[0]:.4g} of the reflection data's norm after {len(n) - 1} iterations")
    print(wrote)
    return EXIT_OK


# --------------------------------------------------------------------------------- main

#: name -> (help, register(parser), run(args) -> exit code)
# --------------------------------------------------------------------------------- schema, init

def _register_schema(p: argparse.ArgumentParser) -> None:
    p.add_argument("workflow", choices=WORKFLOWS, help="the workflow whose config schema to write")
    p.add_argument("-o", "--output", type=pathlib.Path, help="write the JSON Schema to this file (default: print it)")


def cmd_schema(args) -> int:
    """The JSON Schema of a workflow's config, for YAML editors: put `# yaml-language-server: $schema=FILE` in a config."""
    from adseismic.config.schema import json_schema

    text = json.dumps(json_schema(args.workflow), indent=2) + "\n"
    if args.output is None:
        sys.stdout.write(text)
    else:
        write_text_atomic(args.output, text)
        print(f"wrote {args.output}")
    return EXIT_OK


def _register_init(p: argparse.ArgumentParser) -> None:
    p.add_argument("workflow", choices=WORKFLOWS, help="the workflow of the config")
    p.add_argument("-o", "--output", type=pathlib.Path, required=True, help="the YAML file to write (not overwritten)")


def cmd_init(args) -> int:
    """A commented config template that runs as written (locate: the shipped demo event, paths relative to the file)."""
    import os

    from adseismic.config.schema import template

    out = args.output
    if out.exists():
        raise CommandError(f"-o: {out} exists; give a new file name (init never overwrites a config)")
    demo = pathlib.Path(__file__).resolve().parents[2] / "configs" / "data" / "location_demo"
    demo_dir = None
    if args.workflow == "locate" and demo.is_dir():
        demo_dir = pathlib.Path(os.path.relpath(demo, out.resolve().parent)).as_posix()
    write_text_atomic(out, template(args.workflow, demo_dir, out.name))
    print(f"wrote {out}; check it with: adseismic plan {out}")
    return EXIT_OK


COMMANDS = {
    "plan": ("validate a config and print the planned grid, time step and cost",
             _register_plan, cmd_plan),
    "forward": ("run the forward simulation of a config and write data.h5 and figures",
                _register_forward, cmd_forward),
    "fwi": ("full-waveform inversion: invert the start model of a config for its observed data",
            _register_fwi, cmd_fwi),
    "locate": ("locate an earthquake from its traces: position, origin time, source-time function, uncertainty",
               _register_locate, cmd_locate),
    "image": ("image the reflectors: reverse-time migration (RTM) or least-squares RTM, written as image.h5 and PNGs",
              _register_image, cmd_image),
    "bench": ("speed, memory and accuracy benchmarks on the standard scenes, beside Deepwave",
              _register_bench, cmd_bench),
    "schema": ("print (or -o: write) the JSON Schema of a workflow's config, for YAML editors' completion",
               _register_schema, cmd_schema),
    "init": ("write a commented config template that runs as written (a small synthetic CPU scene)",
             _register_init, cmd_init),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="adseismic",
        description="Differentiable seismic wave propagation (NVIDIA Warp). Units: m, s, m/s, Hz.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (help_, register, run) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        register(p)
        p.set_defaults(func=run)
    return parser


def main(argv=None) -> int:
    """Run the command line with ``argv`` (default sys.argv[1:]); returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return EXIT_INPUT
    with _interruptible():
        return _run(args)


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt(signal.Signals(signum).name)


_DEFERRED: list[str] = []  # the name of a signal whose KeyboardInterrupt a finaliser swallowed


def _redeliver_interrupt(unraisable, hook_before):
    """Python ignores an exception raised in a finaliser (a Warp array's __del__ runs often), so a signal landing
    there was lost and the run went on to exit 0. Raise it again 1 ms later from SIGALRM, outside the finaliser
    (raising it here would land in this hook, which Python ignores too)."""
    e = unraisable.exc_value
    if isinstance(e, KeyboardInterrupt) and e.args and e.args[0] in signal.Signals.__members__:
        _DEFERRED[:] = [e.args[0]]
        signal.setitimer(signal.ITIMER_REAL, 1e-3)
    else:
        hook_before(unraisable)


def _raise_deferred(signum, frame):
    if _DEFERRED:
        raise KeyboardInterrupt(_DEFERRED.pop())


@contextlib.contextmanager
def _interruptible():
    """SIGINT and SIGTERM raise KeyboardInterrupt while a command runs, also where the process was started with
    SIGINT ignored (a background job of a script: Python keeps the ignore, and Ctrl-C or `kill -INT` used to be
    swallowed, the run ending with exit status 0) or is stopped by a scheduler's SIGTERM, and where the signal lands
    in a finaliser; the handlers before are restored after. Only in the main thread (signal handlers can be set
    nowhere else)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handlers = {signal.SIGINT: _raise_interrupt, signal.SIGTERM: _raise_interrupt, signal.SIGALRM: _raise_deferred}
    before = {s: signal.signal(s, h) for s, h in handlers.items()}
    hook_before = sys.unraisablehook
    sys.unraisablehook = functools.partial(_redeliver_interrupt, hook_before=hook_before)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        _DEFERRED.clear()
        sys.unraisablehook = hook_before
        for s, h in before.items():
            signal.signal(s, h)


def _run(args) -> int:
    try:
        return args.func(args)
    except CommandError as e:
        if e.code == EXIT_INPUT:
            _clean_refused(args)
        print(f"adseismic {args.command}: error: {e}", file=sys.stderr)
        return e.code
    except (ConfigError, ModelError, ValueError) as e:
        _clean_refused(args)
        print(f"adseismic {args.command}: error: {e}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt as e:
        resume = {"fwi": f"; continue with: adseismic fwi {args.config} -o {args.outdir} --resume",
                  "forward": " (no partial outputs: files are complete or absent)",
                  "locate": " (no partial outputs: files are complete or absent)",
                  "image": " (no partial outputs: files are complete or absent)"}.get(args.command, "")
        print(f"adseismic {args.command}: interrupted{f' by {e.args[0]}' if e.args else ''}{resume}", file=sys.stderr)
        return EXIT_INTERRUPTED
