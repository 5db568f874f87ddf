"""What every command's run shares: exit codes, CommandError, logging to the run's log file, the package
version. The CLI (adseismic.cli) and the benchmark (adseismic.bench) import it; it imports neither."""

from __future__ import annotations

import logging
import pathlib
import sys

log = logging.getLogger("adseismic")

EXIT_OK, EXIT_ERROR, EXIT_INPUT, EXIT_UNSTABLE = 0, 1, 2, 3


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


class RunLog:
    """Context: 'adseismic' logger to ``logfile`` (INFO) and stderr (INFO, or WARNING if quiet)."""

    def __init__(self, logfile: pathlib.Path | None, quiet: bool):
        self.logfile, self.quiet, self.handlers = logfile, quiet, []

    def __enter__(self):
        fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
        err = logging.StreamHandler(sys.stderr)
        err.setLevel(logging.WARNING if self.quiet else logging.INFO)
        err.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
        self.handlers.append(err)
        if self.logfile is not None:
            fh = logging.FileHandler(self.logfile, mode="w", encoding="utf-8")
            fh.setLevel(logging.INFO)
            fh.setFormatter(fmt)
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
