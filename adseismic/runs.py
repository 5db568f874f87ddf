"""What every command's run shares: exit codes, CommandError, logging to the run's log file, the package
version, and how bands and positions are written for people (format_band, format_position: logs, figures,
summaries). The CLI (adseismic.cli), the benchmark (adseismic.bench), the workflows and adseismic.plotting import
it; it imports nothing of the package."""

from __future__ import annotations

import logging
import os
import pathlib
import sys
import time

log = logging.getLogger("adseismic")

EXIT_OK, EXIT_ERROR, EXIT_INPUT, EXIT_UNSTABLE, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


class CommandError(Exception):
    """Raised by a subcommand to exit with ``code`` and ``message`` (no traceback)."""

    def __init__(self, message: str, code: int = EXIT_INPUT):
        super().__init__(message)
        self.code = code


def version() -> str:
    try:
        from importlib.metadata import version as _v

        return _v("adseismic")
    except Exception:  # not installed (running from a source tree)
        return "unknown"


class _Keep(logging.Handler):
    def __init__(self):
        super().__init__(logging.INFO)
        self.records = []

    def emit(self, record):
        self.records.append(record)


class RunLog:
    """Context: 'adseismic' logger to ``logfile`` (INFO) and stderr (INFO, or WARNING if quiet).

    ``earlier``: records of a RunLog without a file (the checks made before the run directory may be
    created) written first into ``logfile`` only (the terminal has shown them); ``records`` keeps every
    record of this context for such a later replay."""

    def __init__(self, logfile: pathlib.Path | None, quiet: bool, earlier=()):
        self.logfile, self.quiet, self.earlier, self.handlers = logfile, quiet, list(earlier), []
        self.records = []

    def __enter__(self):
        fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
        err = logging.StreamHandler(sys.stderr)
        err.setLevel(logging.WARNING if self.quiet else logging.INFO)
        err.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
        keep = _Keep()
        self.records = keep.records
        self.handlers += [err, keep]
        if self.logfile is not None:
            fh = logging.FileHandler(self.logfile, mode="w", encoding="utf-8")
            fh.setLevel(logging.INFO)
            fh.setFormatter(fmt)
            for r in self.earlier:
                fh.handle(r)
            self.handlers.append(fh)
        self.level = log.level
        log.setLevel(logging.INFO)
        for h in self.handlers:
            log.addHandler(h)
        return self

    def __exit__(self, *exc):
        for h in self.handlers:
            log.removeHandler(h)
            h.close()
        log.setLevel(self.level)
        return False


class _LogProgress:
    """The stand-in for a progress bar where stderr is no terminal (a log file, a pipe, CI): one INFO line
    at every ``step`` fraction of ``total`` and at the end, instead of a bar redrawn with carriage returns."""

    def __init__(self, iterable, total, desc, unit, step):
        self.iterable, self.desc, self.unit, self.step = iterable, desc, unit, step
        self.total = total if total is not None else (len(iterable) if hasattr(iterable, "__len__") else None)
        self.n, self.next, self.t0, self.postfix = 0, step, time.perf_counter(), ""

    def __iter__(self):
        for x in self.iterable:
            yield x
            self.update()

    def update(self, n=1):
        self.n += n
        if self.total and self.n >= self.next * self.total and self.n < self.total:
            log.info("%s: %d/%d %s (%.0f%%, %.1f s)%s", self.desc, self.n, self.total, self.unit, 100 * self.n / self.total,
                     time.perf_counter() - self.t0, self.postfix)
            while self.next * self.total <= self.n:
                self.next += self.step

    def set_postfix_str(self, text):
        self.postfix = f" {text}" if text else ""

    def close(self):
        if self.n and self.total:
            log.info("%s: %d/%d %s done in %.1f s%s", self.desc, self.n, self.total, self.unit, time.perf_counter() - self.t0, self.postfix)


def progress_bar(iterable=None, *, total=None, desc="", unit="it", enabled=True, leave=False, step=0.25):
    """A tqdm bar on a terminal; where stderr is not a terminal, one log line per ``step`` of the total
    (no carriage-return floods in log files). ``enabled=False``: silent. Same update/close API as tqdm."""
    if not enabled:
        from tqdm.auto import tqdm

        return tqdm(iterable, total=total, disable=True)
    if sys.stderr.isatty() and os.environ.get("TERM") != "dumb":
        from tqdm.auto import tqdm

        return tqdm(iterable, total=total, desc=desc, unit=unit, leave=leave)
    return _LogProgress(iterable, total, desc, unit, step)


def format_band(lo: float | None, hi: float | None) -> str:
    """A frequency band (f_low or None, f_high or None) in Hz for people: "<= 4 Hz" (a low-pass),
    ">= 2 Hz" (a high-pass), "2-4 Hz" (a band-pass) or "full band" (no filter)."""
    if lo is None and hi is None:
        return "full band"
    if lo is None:
        return f"<= {hi:g} Hz"
    if hi is None:
        return f">= {lo:g} Hz"
    return f"{lo:g}-{hi:g} Hz"


def format_position(values, axes: str | None = None, digits: int = 1, errors=None) -> str:
    """A position in world metres for people, each value named by its axis: "z = 698.7 m, x = 1612.0 m"
    (axes default "zx" in 2D, "zyx" in 3D: the package's axis order). With ``errors`` (one per axis, m):
    "z = 698.70 +- 0.11 m, x = ..."."""
    vals = [float(v) for v in values]
    axes = axes or ("zx" if len(vals) == 2 else "zyx" if len(vals) == 3 else "x" if len(vals) == 1 else None)
    if axes is None or len(axes) != len(vals):
        raise ValueError(f"format_position: {len(vals)} values for axes {axes!r}; give one value per axis")
    if errors is None:
        return ", ".join(f"{a} = {v:.{digits}f} m" for a, v in zip(axes, vals))
    return ", ".join(f"{a} = {v:.{digits}f} +- {float(e):.{digits}f} m" for a, v, e in zip(axes, vals, errors))
