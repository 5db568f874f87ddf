"""Optimisers whose runs can be killed and resumed to the same result.

The objective of an inversion (a wave simulation plus its gradient) costs seconds to minutes per
call, so every evaluation counts and a run must survive being killed. Everything here is built on
an evaluation **journal**:

* every call of the objective appends ``(sha256(x bytes), f, g)`` to a :class:`Journal`, which is
  saved atomically (``<path>.part`` written, fsynced, ``os.replace``-d into place) after each
  evaluation when ``journal_path`` is given;
* resuming a run is running the same deterministic optimiser again from the same ``x0`` with the
  loaded journal. While the journal has entries the objective is *not* called: the requested x must
  hash to the recorded hash (otherwise :class:`JournalMismatch` names the evaluation: the run is not
  reproducible, e.g. the config, x0, bounds or options changed) and the recorded ``(f, g)`` is
  returned. Once the journal is exhausted the objective is evaluated for real and appended.

This needs no access to an optimiser's internal state, so it works for scipy's L-BFGS-B as well as
for the loops written here, and a resumed run is bitwise identical to an uninterrupted one when the
objective is deterministic (same ``x`` -> same ``f, g`` bits). The user ``callback`` is called again
during the replay, so a resumed run rewrites the same history/log/PNG files.

Units: ``x`` is in whatever units the caller's parameterisation uses (e.g. m/s for a velocity
model, m for a source position); ``f`` in the misfit's units; ``g = df/dx`` in f-units per x-unit.
``x`` and ``g`` are float64 1-D arrays of the same length n.

Conventions shared by all methods
---------------------------------
* ``bounds`` are projected by clipping: ``x0`` is clipped into the box first, and every trial point
  is ``clip(., lower, upper)``.
* Projected gradient (as in L-BFGS-B): ``pg = clip(x - g, lower, upper) - x``; the ``grad_tol`` rule
  stops when ``max|pg| < grad_tol``.
* The ``rel_decrease`` rule stops after an accepted iteration k when
  ``|f_{k-1} - f_k| / max(|f_{k-1}|, tiny) < rel_decrease`` (for the monotone methods L-BFGS and GD
  this is the relative decrease; for Adam, which is not monotone, it is the relative change, so an
  increase does not stop the run).
* Rules are checked after every accepted iteration in the order grad_tol, rel_decrease,
  max_iterations, max_evaluations (grad_tol and the limits also at the starting point). If the
  evaluation budget runs out in the middle of an iteration (a line search), the run stops with
  ``"max_evaluations"`` at the last accepted iterate; that partial iteration's evaluations count.
* ``stop_reason`` is one of ``"grad_tol"``, ``"rel_decrease"``, ``"max_iterations"``,
  ``"max_evaluations"``, ``"line_search_failed"``, or ``"scipy: <message>"`` for any other reason
  scipy's L-BFGS-B stops.
* Evaluating the same x twice in a row costs one evaluation (the second is served from memory).
"""
from __future__ import annotations

import hashlib
import math
import os
import pathlib
import struct
import time
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from adseismic.data.atomic import atomic_path

__all__ = ["JournalMismatch", "Journal", "OptimizeResult", "minimize", "equal_cost_comparison",
           "hash_x", "projected_gradient_norm", "METHODS", "STOP_REASONS"]

METHODS = ("lbfgs", "gd", "adam")
STOP_REASONS = ("grad_tol", "rel_decrease", "max_iterations", "max_evaluations",
                "line_search_failed")

# The free L-BFGS keeps up to LBFGS_MEMORY pairs (torch.optim.LBFGS's history_size), fewer where they would pass
# LBFGS_MEMORY_BYTES, never fewer than 10 (L-BFGS-B's). With 10 pairs the FWI race ended at 0.6237 model error, with
# 20 or 100 (a band's 20 iterations all remembered) at 0.6070, in the same time (docs/benchmarks.md, 2026-12-01).
LBFGS_MEMORY = 100
LBFGS_MEMORY_BYTES = 2 * 2**30
_TINY = np.finfo(np.float64).tiny
_FORMAT = "adseismic-optimize-journal"
_TAIL_MAGIC = b"ADSJ"
_FORMAT_VERSION = 1


class JournalMismatch(RuntimeError):
    """A resumed run asked for a different x than the journal recorded: the run is not a replay of
    the journaled one (changed x0, bounds, method, options, objective or code). ``evaluation`` is
    the 0-based index of the first evaluation that differs."""

    def __init__(self, message: str, evaluation: int):
        super().__init__(message)
        self.evaluation = evaluation


class _BudgetExhausted(Exception):
    """Internal: the optimiser asked for an evaluation beyond max_evaluations."""


def hash_x(x) -> bytes:
    """sha256 digest (32 bytes) of x as a C-contiguous float64 array's bytes."""
    return hashlib.sha256(np.ascontiguousarray(x, dtype=np.float64).tobytes()).digest()


def _shuffle(raw: bytes, itemsize: int = 8) -> bytes:
    # HDF5's shuffle filter: byte k of every element, for k = 0..itemsize-1.
    return np.frombuffer(raw, np.uint8).reshape(-1, itemsize).T.tobytes()


def _unshuffle(raw: bytes, itemsize: int = 8) -> bytes:
    return np.frombuffer(raw, np.uint8).reshape(itemsize, -1).T.tobytes()


class Journal:
    """The evaluations of one optimisation run, in call order: the sha256 of each requested x
    (32 bytes; x itself is not kept), f (float64) and g (float64, shape (n,)).

    On disk (``save(path)`` / ``Journal.load(path)``): one HDF5 file plus, while a run goes on, an
    append-only tail ``<path>.append``.
    HDF5 layout: ``sha256`` uint8 (N, 32); ``f`` float64 (N,); ``g`` float64 (N, n), chunked (1, c)
    with c = min(n, ``chunk_elements``), shuffle + gzip; root attrs ``format``, ``format_version``,
    ``n`` and any ``meta`` given by the caller. It is replaced atomically (``<path>.part`` written,
    fsynced, ``os.replace``-d).
    The first save of a journal to a path writes the HDF5 file; each later save of the same journal
    appends only the new evaluations to the tail, one record each (magic, length, crc32, then the
    index, hash, f and the compressed gradient chunks), fsynced: constant cost per evaluation
    instead of a rewrite of every gradient so far. A record torn by a kill fails its length or
    crc32 and is dropped by ``load`` (with every record after it), so a killed run resumes from its
    last complete evaluation. ``save(path, compact=True)`` (the end of a run) folds the tail into
    one HDF5 file again, readable by plain HDF5 tools.

    Gradients are kept *compressed in memory* and written with HDF5 direct chunk writes, so a save
    never re-compresses; ``g(i)`` decompresses one entry on demand.

    ``append(..., save_to=path)`` (the evaluator's path) compresses the gradient and appends its
    record to the tail on a background thread, in call order, and returns at once: the ~10 ms of
    zlib and fsync a 70,000-cell gradient costs overlap the next evaluation (zlib releases the
    GIL). Every other method waits for that work first and re-raises its error, so the journal
    reads the same; a kill loses at most the records still being written (re-evaluated on resume).
    """

    def __init__(self, compression_level: int = 4, chunk_elements: int = 1 << 17):
        self.compression_level = int(compression_level)
        self.chunk_elements = int(chunk_elements)
        self.meta: dict = {}
        self._hashes: list[bytes] = []
        self._f: list[float] = []
        self._g_chunks: list[list[bytes]] = []  # per entry: compressed (shuffle+deflate) chunks
        self._n: int | None = None
        self._disk: tuple | None = None  # (path, entries, tail bytes): what path and its tail hold of us
        self._writer: ThreadPoolExecutor | None = None  # append(save_to=...)'s background thread
        self._pending: list = []  # its futures not yet waited for
        self._failed = False  # a background append failed: the later ones are not written

    def flush(self) -> None:
        """Wait for the background appends (append(save_to=...)) and end their thread; re-raise the first error."""
        try:
            self._settle()
        finally:
            if self._writer is not None:
                self._writer.shutdown(wait=True)
                self._writer = None

    def _settle(self) -> None:
        """Wait for the background appends (append(save_to=...)); re-raise the first error."""
        pending, self._pending = self._pending, []
        for fut in pending:
            fut.result()

    # ---- contents --------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._hashes)

    @property
    def n(self) -> int | None:
        """Length of x and g (None while empty)."""
        return self._n

    def _chunk(self) -> int:
        return max(1, min(self._n or 1, self.chunk_elements))

    def append(self, x_hash: bytes, f: float, g, save_to=None) -> None:
        """Record one evaluation: the 32-byte sha256 of x (see :func:`hash_x`), f and g (n,). save_to:
        a path to ``save`` to afterwards; the gradient's compression and that save then run on the
        background thread (see the class docstring)."""
        g = np.array(g, dtype=np.float64, copy=True).ravel()
        if len(x_hash) != 32:
            raise ValueError("x_hash: expected a 32-byte sha256 digest")
        if self._n is None:
            self._n = g.size
        elif g.size != self._n:
            raise ValueError(f"g: length {g.size} differs from the journal's n = {self._n}")
        for fut in [f_ for f_ in self._pending if f_.done()]:  # an earlier background error surfaces here
            self._pending.remove(fut)
            fut.result()
        i = len(self._hashes)
        self._hashes.append(bytes(x_hash))
        self._f.append(float(f))
        self._g_chunks.append(None)
        if save_to is None:
            self._g_chunks[i] = self._compress(g)
            return
        if self._writer is None:
            self._writer = ThreadPoolExecutor(1, thread_name_prefix="adseismic-journal")

        def work():
            if self._failed:  # as after a kill: nothing more reaches the disk once a write failed
                return
            try:
                self._g_chunks[i] = self._compress(g)
                self._save(pathlib.Path(save_to), False, i + 1)
            except BaseException:
                self._failed = True
                raise

        self._pending.append(self._writer.submit(work))

    def _compress(self, g: np.ndarray) -> list:
        c = self._chunk()
        chunks = []
        for j in range(0, max(g.size, 1), c):
            block = np.zeros(c, np.float64)  # edge chunks are stored full-size (zero padded)
            part = g[j:j + c]
            block[:part.size] = part
            chunks.append(zlib.compress(_shuffle(block.tobytes()), self.compression_level))
        return chunks

    def hash(self, i: int) -> bytes:
        """sha256 digest of the x of evaluation i."""
        return self._hashes[i]

    def f(self, i: int) -> float:
        """Objective value of evaluation i."""
        return self._f[i]

    def g(self, i: int) -> np.ndarray:
        """Gradient of evaluation i, a fresh float64 array (n,)."""
        self._settle()
        raw = b"".join(_unshuffle(zlib.decompress(c)) for c in self._g_chunks[i])
        return np.frombuffer(raw, np.float64)[:self._n].copy()

    @property
    def fs(self) -> np.ndarray:
        """All objective values, float64 (N,)."""
        return np.array(self._f, dtype=np.float64)

    def truncate(self, length: int) -> None:
        """Keep only the first ``length`` evaluations."""
        self._settle()
        del self._hashes[length:], self._f[length:], self._g_chunks[length:]
        if not self._hashes:
            self._n = None
        if self._disk is not None and self._disk[1] > length:  # the file holds more: rewrite it
            self._disk = None

    # ---- file --------------------------------------------------------------------------------
    def save(self, path, compact: bool = False) -> pathlib.Path:
        """Write the journal to ``path``: the new evaluations appended to ``<path>.append`` when
        this journal was saved to (or loaded from) ``path`` before, else (or with ``compact``) the
        whole journal as one HDF5 file, atomically."""
        self._settle()
        return self._save(pathlib.Path(path), compact)

    def _save(self, path: pathlib.Path, compact: bool, upto: int | None = None) -> pathlib.Path:
        # upto: the evaluations to write (a background save writes those before its own append's)
        upto = len(self) if upto is None else upto
        disk = self._disk
        if not compact and disk is not None and disk[0] == path.resolve():
            self._append_tail(path, disk[1], disk[2], upto)
        else:
            self._write_hdf5(path, upto)
        return path

    def has_tail(self, path) -> bool:
        """Whether part of this journal sits in the append-only tail of ``path``."""
        self._settle()
        return self._disk is not None and self._disk[0] == pathlib.Path(path).resolve() and self._disk[2] > 0

    def _append_tail(self, path: pathlib.Path, saved: int, tail_bytes: int, upto: int) -> None:
        tail = _tail_path(path)
        records = b"".join(self._record(i) for i in range(saved, upto))
        with open(tail, "r+b" if tail.exists() else "wb") as fh:
            fh.truncate(tail_bytes)  # drop a record torn by an earlier kill
            fh.seek(tail_bytes)
            fh.write(records)
            fh.flush()
            os.fsync(fh.fileno())
        self._disk = (path.resolve(), upto, tail_bytes + len(records))

    def _record(self, i: int) -> bytes:
        chunks = self._g_chunks[i]
        payload = b"".join([struct.pack("<Q32sdI", i, self._hashes[i], self._f[i], len(chunks)),
                            *(struct.pack("<I", len(c)) + c for c in chunks)])
        return _TAIL_MAGIC + struct.pack("<II", len(payload), zlib.crc32(payload)) + payload

    def _write_hdf5(self, path: pathlib.Path, upto: int) -> None:
        import h5py

        path.parent.mkdir(parents=True, exist_ok=True)
        part = atomic_path(path)
        N, n = upto, (self._n or 0)
        try:
            with h5py.File(part, "w") as h:
                h.attrs["format"] = _FORMAT
                h.attrs["format_version"] = _FORMAT_VERSION
                h.attrs["n"] = n
                for k, v in self.meta.items():
                    h.attrs[k] = v
                h.create_dataset("sha256", data=np.frombuffer(b"".join(self._hashes[:N]), np.uint8)
                                 .reshape(N, 32))
                d = h.create_dataset("f", data=np.asarray(self._f[:N], np.float64).reshape(N))
                d.attrs["description"] = "objective value of each evaluation, in call order"
                if N and n:
                    c = self._chunk()
                    d = h.create_dataset("g", shape=(N, n), dtype=np.float64, chunks=(1, c),
                                         shuffle=True, compression="gzip",
                                         compression_opts=self.compression_level)
                    for i, chunks in enumerate(self._g_chunks[:N]):
                        for j, data in enumerate(chunks):
                            d.id.write_direct_chunk((i, j * c), data, 0)
                else:
                    d = h.create_dataset("g", shape=(N, n), dtype=np.float64)
                d.attrs["description"] = "gradient df/dx of each evaluation, in call order"
            with open(part, "rb+") as fh:
                os.fsync(fh.fileno())
            # the old tail goes first: a kill between the two steps leaves the old file without
            # its tail (a shorter journal, re-evaluated on resume), never a tail on the new file
            _tail_path(path).unlink(missing_ok=True)
            os.replace(part, path)
        except BaseException:
            part.unlink(missing_ok=True)
            raise
        _fsync_dir(path.parent)
        self._disk = (path.resolve(), N, 0)

    @classmethod
    def load(cls, path) -> "Journal":
        """Read a journal written by :meth:`save`."""
        import h5py

        path = pathlib.Path(path)
        with h5py.File(path, "r") as h:
            if h.attrs.get("format") != _FORMAT:
                raise ValueError(f"{path}: not an adseismic optimisation journal")
            hashes = np.asarray(h["sha256"][...], np.uint8)
            fs = np.asarray(h["f"][...], np.float64)
            dg = h["g"]
            N, n = dg.shape
            level = dg.compression_opts if dg.compression == "gzip" else 4
            j = cls(compression_level=level if isinstance(level, int) else 4)
            j.meta = {k: v for k, v in h.attrs.items()
                      if k not in ("format", "format_version", "n")}
            if len(hashes) != N or len(fs) != N or hashes.shape[1:] != (32,):
                raise ValueError(f"{path}: inconsistent journal datasets")
            direct = (N and n and dg.chunks is not None and dg.chunks[0] == 1
                      and dg.compression == "gzip" and dg.shuffle)
            if direct:
                j.chunk_elements = dg.chunks[1]
            for i in range(N):
                if direct:
                    c = dg.chunks[1]
                    chunks = []
                    for k in range(0, n, c):
                        mask, data = dg.id.read_direct_chunk((i, k))
                        if mask:  # a filter was skipped for this chunk: take the slow path
                            break
                        chunks.append(bytes(data))
                    else:
                        j._hashes.append(hashes[i].tobytes())
                        j._f.append(float(fs[i]))
                        j._g_chunks.append(chunks)
                        j._n = n
                        continue
                j.append(hashes[i].tobytes(), float(fs[i]), dg[i])
        j._n = j._n if j._n is not None or not n else n
        tail_bytes = j._read_tail(_tail_path(path))
        j._disk = (path.resolve(), len(j), tail_bytes)
        return j

    def _read_tail(self, tail: pathlib.Path) -> int:
        """Append the complete records of ``tail`` that continue this journal; returns the bytes
        they take (a torn or foreign record ends the tail)."""
        raw = tail.read_bytes() if tail.exists() else b""
        pos, head = 0, len(_TAIL_MAGIC) + 8
        while pos + head <= len(raw) and raw[pos:pos + len(_TAIL_MAGIC)] == _TAIL_MAGIC:
            size, crc = struct.unpack_from("<II", raw, pos + len(_TAIL_MAGIC))
            payload = raw[pos + head:pos + head + size]
            if len(payload) != size or zlib.crc32(payload) != crc:
                break
            i, x_hash, f, n_chunks = struct.unpack_from("<Q32sdI", payload)
            if i != len(self):
                break
            chunks, at = [], struct.calcsize("<Q32sdI")
            for _ in range(n_chunks):
                (length,) = struct.unpack_from("<I", payload, at)
                chunks.append(payload[at + 4:at + 4 + length])
                at += 4 + length
            self._hashes.append(x_hash)
            self._f.append(f)
            self._g_chunks.append(chunks)
            pos += head + size
        return pos


@dataclass
class OptimizeResult:
    """Outcome of :func:`minimize`.

    x: the last accepted iterate (float64 (n,), units of x); f: the objective there;
    iterations: accepted iterations; evaluations: objective evaluations used (replayed + real);
    stop_reason: see the module docstring; history: one dict per accepted iteration
    ``{"iteration", "f", "grad_norm" (max |projected gradient|), "step" (||x_k - x_{k-1}||_2, units
    of x), "evaluations" (cumulative)}``; replayed_evaluations: how many of ``evaluations`` came
    from the journal instead of calling the objective; real_evaluations: how many called it.
    """
    x: np.ndarray
    f: float
    iterations: int
    evaluations: int
    stop_reason: str
    history: list = field(default_factory=list)
    replayed_evaluations: int = 0
    g: np.ndarray | None = None

    @property
    def real_evaluations(self) -> int:
        return self.evaluations - self.replayed_evaluations


def projected_gradient_norm(x, g, lower, upper) -> float:
    """max |clip(x - g, lower, upper) - x|, the projected-gradient norm of L-BFGS-B."""
    if g.size == 0:
        return 0.0
    return float(np.max(np.abs(np.clip(x - g, lower, upper) - x)))


def _tail_path(path: pathlib.Path) -> pathlib.Path:
    """The append-only tail of a journal file (see :class:`Journal`)."""
    return path.with_name(path.name + ".append")


def _fsync_dir(directory: pathlib.Path) -> None:
    """Make a rename in ``directory`` durable (where the system allows)."""
    try:
        dfd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass


class _Evaluator:
    """The objective wrapped with the journal, the evaluation budget and a one-entry memo."""

    def __init__(self, fun, journal: Journal, path, max_evaluations, on_evaluation=None):
        self.fun = fun
        self.journal = journal
        self.path = path
        self.max_evaluations = max_evaluations
        self.on_evaluation = on_evaluation
        self.count = 0       # evaluations so far (replayed + real)
        self.replayed = 0
        self._last = None    # (hash, f, g)

    def lookup(self, x):
        h = hash_x(x)
        if self._last is not None and self._last[0] == h:
            return self._last[1], self._last[2].copy()
        return None

    def __call__(self, x):
        x = np.array(x, dtype=np.float64, copy=True).ravel()
        h = hash_x(x)
        if self._last is not None and self._last[0] == h:
            return self._last[1], self._last[2].copy()
        if self.max_evaluations is not None and self.count >= self.max_evaluations:
            raise _BudgetExhausted
        i = self.count
        if i < len(self.journal):
            if self.journal.hash(i) != h:
                raise JournalMismatch(
                    f"evaluation {i}: the requested x (sha256 {h.hex()[:16]}...) differs from the "
                    f"journal's (sha256 {self.journal.hash(i).hex()[:16]}...); this run is not a "
                    f"replay of the journaled one (changed x0, bounds, method, options or "
                    f"objective?)", i)
            f, g = self.journal.f(i), self.journal.g(i)
            self.replayed += 1
        else:
            t0 = time.perf_counter()
            f, g = self.fun(x.copy())
            t1 = time.perf_counter()
            f = float(f)
            g = np.array(g, dtype=np.float64, copy=True).ravel()
            if g.shape != x.shape:
                raise ValueError(f"fun returned g of length {g.size} for x of length {x.size}")
            self.journal.append(h, f, g, save_to=self.path)
            if self.on_evaluation is not None:
                self.on_evaluation(i, {"objective": t1 - t0, "journal": time.perf_counter() - t1})
        self.count += 1
        self._last = (h, f, g)
        return f, g.copy()


def _bounds(bounds, n):
    if bounds is None:
        return np.full(n, -np.inf), np.full(n, np.inf)
    lo, hi = bounds

    def vec(b, default):
        b = np.asarray(default if b is None else b, np.float64)
        if b.size == n and b.ndim > 1:  # e.g. a model-shaped array for a raveled model x
            b = b.ravel()
        return np.broadcast_to(b, (n,)).copy()

    lo, hi = vec(lo, -np.inf), vec(hi, np.inf)
    if np.any(lo > hi):
        raise ValueError("bounds: some lower bound exceeds its upper bound")
    return lo, hi


class _Run:
    """Iteration bookkeeping and stopping rules shared by the methods."""

    def __init__(self, ev, lo, hi, max_iterations, max_evaluations, rel_decrease, grad_tol,
                 callback):
        self.ev, self.lo, self.hi = ev, lo, hi
        self.max_iterations, self.max_evaluations = max_iterations, max_evaluations
        self.rel_decrease, self.grad_tol, self.callback = rel_decrease, grad_tol, callback
        self.history: list[dict] = []
        self.iteration = 0
        self.x = self.f = self.g = None

    def start(self, x, f, g):
        """The starting point; returns a stop reason or None."""
        self.x, self.f, self.g = x.copy(), f, g.copy()
        if self.grad_tol and projected_gradient_norm(x, g, self.lo, self.hi) < self.grad_tol:
            return "grad_tol"
        return self._limits()

    def _limits(self):
        if self.max_iterations is not None and self.iteration >= self.max_iterations:
            return "max_iterations"
        if self.max_evaluations is not None and self.ev.count >= self.max_evaluations:
            return "max_evaluations"
        return None

    def accept(self, x, f, g):
        """Record an accepted iteration, call the callback; returns a stop reason or None."""
        f_prev = self.f
        step = float(np.linalg.norm(x - self.x))
        self.iteration += 1
        pgn = projected_gradient_norm(x, g, self.lo, self.hi)
        self.history.append({"iteration": self.iteration, "f": float(f), "grad_norm": pgn,
                             "step": step, "evaluations": self.ev.count})
        self.x, self.f, self.g = x.copy(), float(f), g.copy()
        if self.callback is not None:
            self.callback(self.iteration, x.copy(), float(f), g.copy())
        if self.grad_tol and pgn < self.grad_tol:
            return "grad_tol"
        if self.rel_decrease and abs(f_prev - f) / max(abs(f_prev), _TINY) < self.rel_decrease:
            return "rel_decrease"
        return self._limits()

    def result(self, reason):
        return OptimizeResult(x=self.x.copy(), f=float(self.f), iterations=self.iteration,
                              evaluations=self.ev.count, stop_reason=reason,
                              history=self.history, replayed_evaluations=self.ev.replayed,
                              g=self.g.copy())


def _check_options(options, allowed, method):
    unknown = set(options) - set(allowed)
    if unknown:
        raise ValueError(f"method {method!r}: unknown options {sorted(unknown)}; "
                         f"allowed: {sorted(allowed)}")


def minimize(fun: Callable, x0, *, method: str = "lbfgs", bounds=None, max_iterations=20,
             max_evaluations=None, rel_decrease=1e-5, grad_tol=1e-8, journal_path=None,
             callback=None, options=None, on_evaluation=None) -> OptimizeResult:
    """Minimise ``fun`` from ``x0``, journaling every evaluation so the run can be resumed.

    Parameters
    ----------
    fun : ``fun(x) -> (f, g)``, x and g float64 arrays (n,), f a float; g = df/dx.
    x0 : (n,) start, units of x (clipped into ``bounds``).
    method : ``"lbfgs"`` (L-BFGS; with bounds scipy's L-BFGS-B, ``jac=True``; ``options``: ``maxcor``, ``maxls``),
        ``"gd"`` (projected steepest descent with a strong-Wolfe line search; ``options``: ``step``
        = first trial step, ``max_line_search`` = evaluations per line search (20)),
        ``"adam"`` (``options``: ``lr`` (1e-2), ``beta1`` (0.9), ``beta2`` (0.999), ``eps`` (1e-8)).
    bounds : ``(lower, upper)``, each an array of n values (any shape, raveled in C order), a scalar
        or None (unbounded); or None.
    max_iterations : accepted iterations at most (None: no limit).
    max_evaluations : objective evaluations at most, replayed + real, for every method (None: no
        limit); at least 1.
    rel_decrease : stop when the relative change of f over one iteration is below this
        (0/None: off).
    grad_tol : stop when max|projected gradient| < grad_tol (0/None: off).
    journal_path : HDF5 journal; when the file exists it is loaded and replayed (resume), and it is
        saved after every real evaluation.
    callback : ``callback(iteration, x, f, g)`` after each accepted iteration (1-based), also during
        replay, so a resumed run reproduces the same side effects.
    on_evaluation : ``on_evaluation(index, seconds)`` after each real (not replayed) evaluation and
        its journal save; index is 0-based in the journal (as in :class:`JournalMismatch`), seconds
        ``{"objective": time in fun, "journal": time handing the evaluation to the journal's background
        writer}`` (s,
        perf_counter).

    Method details
    --------------
    * **lbfgs** without bounds (every bound infinite, or bounds None): L-BFGS, the two-loop recursion and gd's
      strong-Wolfe line search below (``options``: ``maxcor``, default LBFGS_MEMORY pairs within
      LBFGS_MEMORY_BYTES; ``maxls``), O(n maxcor) work an iteration.
    * **lbfgs** with bounds: scipy's L-BFGS-B with ``maxiter``/``pgtol`` mapped from ``max_iterations``/
      ``grad_tol`` and scipy's own ``ftol`` test switched off (``rel_decrease`` is applied in an
      ``intermediate_result`` callback that raises ``StopIteration``); ``max_evaluations`` is
      enforced exactly by the wrapped objective (scipy's ``maxfun`` is only checked between
      iterations).
    * **gd**: direction d = -g with components that would leave the box at an active bound zeroed.
      The line search parameter t is a step *length in units of x* (max-norm): the trial points are
      ``clip(x + t d/max|d|, lower, upper)``, the first trial of every line search is
      ``t = options["step"]`` (default 1.0) and then t doubles until a bracket is found, followed by
      a safeguarded cubic zoom (Nocedal & Wright, alg. 3.5/3.6). A step is accepted only if it
      satisfies the strong Wolfe conditions (c1 = 1e-4, c2 = 0.9) for phi(t) = f(clip(x + t u)),
      phi' taken along the clipped path (clipped components do not move); unbounded, this is the
      usual ``f(x+p) <= f + c1 g.p`` and ``|g(x+p).p| <= c2 |g.p|``. Because the step is in units of
      x and the direction is the raw gradient, plain GD is sensitive to the scaling of x (an
      ill-conditioned problem needs many iterations, and a poor ``step`` costs extra line-search
      evaluations). If no acceptable step is found within ``max_line_search`` evaluations the run
      stops with ``"line_search_failed"`` at the last accepted iterate.
    * **adam**: ``m = b1 m + (1-b1) g``, ``v = b2 v + (1-b2) g^2``, ``x <- clip(x - lr m_hat /
      (sqrt(v_hat) + eps))``: each component moves by at most about ``lr`` (units of x) per
      iteration. One evaluation per iteration; the returned x is the last iterate (not the best).
    """
    method = method.lower()
    if method not in METHODS:
        raise ValueError(f"method: {method!r} is not one of {METHODS}")
    options = dict(options or {})
    x0 = np.array(x0, dtype=np.float64, copy=True).ravel()
    lo, hi = _bounds(bounds, x0.size)
    if max_evaluations is not None:
        max_evaluations = int(max_evaluations)
        if max_evaluations < 1:
            raise ValueError("max_evaluations: must be at least 1")
    if max_iterations is not None:
        max_iterations = int(max_iterations)
        if max_iterations < 0:
            raise ValueError("max_iterations: must be >= 0")

    path = None if journal_path is None else pathlib.Path(journal_path)
    journal = Journal.load(path) if path is not None and path.is_file() else Journal()
    if path is not None and not journal.meta:
        journal.meta = {"method": method}  # informational; replay checks hashes only
    ev = _Evaluator(fun, journal, path, max_evaluations, on_evaluation)
    run = _Run(ev, lo, hi, max_iterations, max_evaluations, rel_decrease, grad_tol, callback)

    x = np.clip(x0, lo, hi)
    try:
        f, g = ev(x)
        reason = run.start(x, f, g)
        if reason is None:
            reason = _iterate(method, run, ev, x, lo, hi, options)
    finally:
        journal.flush()  # the background appends on disk, however the run ends
    if path is not None and journal.has_tail(path):  # a finished run leaves one plain HDF5 journal
        journal.save(path, compact=True)
    return run.result(reason)


def _iterate(method, run, ev, x, lo, hi, options):
    if method == "lbfgs":
        _check_options(options, ("maxcor", "maxls"), method)
        if np.all(np.isinf(lo)) and np.all(np.isinf(hi)):
            return _lbfgs_free(run, ev, options)
        return _lbfgs(run, ev, x, lo, hi, options)
    if method == "gd":
        _check_options(options, ("step", "max_line_search"), method)
        return _gd(run, ev, options)
    _check_options(options, ("lr", "beta1", "beta2", "eps"), method)
    return _adam(run, ev, options)


# ---- L-BFGS-B ------------------------------------------------------------------------------------

def _lbfgs(run: _Run, ev: _Evaluator, x, lo, hi, options):
    import scipy.optimize

    state = {"reason": None}

    def cb(intermediate_result):
        xi = np.array(intermediate_result.x, dtype=np.float64, copy=True)
        got = ev.lookup(xi)
        if got is None:  # L-BFGS-B accepts its last evaluated point; anything else is a bug
            raise RuntimeError("L-BFGS-B accepted an iterate that was not its last evaluation")
        reason = run.accept(xi, got[0], got[1])
        if reason is not None:
            state["reason"] = reason
            raise StopIteration

    unbounded = np.all(np.isinf(lo)) and np.all(np.isinf(hi))
    sp_opts = {"maxiter": run.max_iterations if run.max_iterations is not None else 10**9,
               "maxfun": 10**9, "ftol": 0.0, "gtol": float(run.grad_tol or 0.0)}
    sp_opts.update(options)
    try:
        res = scipy.optimize.minimize(ev, x, method="L-BFGS-B", jac=True,
                                      bounds=None if unbounded else scipy.optimize.Bounds(lo, hi),
                                      callback=cb, options=sp_opts)
    except _BudgetExhausted:
        return "max_evaluations"
    if state["reason"] is not None:
        return state["reason"]
    msg = str(res.message)
    if "PROJECTED GRADIENT" in msg or "PGTOL" in msg:
        return "grad_tol"
    if "RELATIVE REDUCTION" in msg:
        return "rel_decrease"
    if "ITERATIONS" in msg:
        return "max_iterations"
    if "EVALUATIONS" in msg:
        return "max_evaluations"
    if msg.startswith("ABNORMAL"):
        return "line_search_failed"
    return "scipy: " + msg


def _two_loop(g, pairs):
    """-H g for the L-BFGS inverse Hessian of the (s, y) pairs, oldest first (Nocedal & Wright alg. 7.4; H0 =
    s.y / y.y of the newest pair)."""
    q, alphas = g.copy(), []
    for s, y, rho in reversed(pairs):
        a = rho * float(s @ q)
        q -= a * y
        alphas.append(a)
    if pairs:
        s, y, rho = pairs[-1]
        q *= 1.0 / (rho * float(y @ y))
    for (s, y, rho), a in zip(pairs, reversed(alphas)):
        q += (a - rho * float(y @ q)) * s
    return -q


def _lbfgs_free(run: _Run, ev: _Evaluator, options):
    """L-BFGS without bounds (Nocedal & Wright alg. 7.5): the two-loop direction from the last ``maxcor`` pairs
    (default LBFGS_MEMORY, capped at LBFGS_MEMORY_BYTES of pairs, at least 10), gd's strong-Wolfe line search (first
    trial step 1, on the first iteration 1 / |g| as L-BFGS-B), ``maxls`` (20) evaluations per line search; a pair with
    s.y <= 1e-10 y.y is skipped. O(n maxcor) NumPy work an iteration, where scipy's L-BFGS-B spends ~0.1 s an
    iteration on n = 70,000 unknowns (docs/benchmarks.md)."""
    memory = max(10, min(LBFGS_MEMORY, LBFGS_MEMORY_BYTES // (16 * run.x.size)))
    m, max_ls = int(options.get("maxcor", memory)), int(options.get("maxls", 20))
    pairs = []
    while True:
        x, f0, g = run.x, run.f, run.g
        d = _two_loop(g, pairs)
        dphi0 = float(g @ d)
        if not dphi0 < 0:  # not a descent direction (round-off in the memory): restart from steepest descent
            pairs, d = [], -g
            dphi0 = float(g @ d)
            if dphi0 == 0:
                return "grad_tol"
        try:
            xt, ft, gt = _wolfe_search(_line(ev, x, d, max_ls), f0, dphi0, 1.0 if pairs else 1.0 / math.sqrt(-dphi0))
        except _LineSearchFailed:
            return "line_search_failed"
        except _BudgetExhausted:
            return "max_evaluations"
        s, y = xt - x, gt - g
        sy = float(s @ y)
        if sy > 1e-10 * float(y @ y):
            pairs = [*pairs, (s, y, 1.0 / sy)][-m:]
        reason = run.accept(xt, ft, gt)
        if reason is not None:
            return reason


# ---- projected gradient descent with a strong-Wolfe line search ----------------------------------

C1, C2 = 1e-4, 0.9


def _cubic_min(a, fa, da, b, fb, db):
    """Minimiser of the cubic interpolating (a, fa, da), (b, fb, db); None when not defined."""
    if a == b:
        return None
    d1 = da + db - 3.0 * (fa - fb) / (a - b)
    disc = d1 * d1 - da * db
    if not np.isfinite(disc) or disc < 0:
        return None
    d2 = math.copysign(math.sqrt(disc), b - a)
    den = db - da + 2.0 * d2
    if den == 0 or not np.isfinite(den):
        return None
    t = b - (b - a) * (db + d2 - d1) / den
    return t if np.isfinite(t) else None


def _gd(run: _Run, ev: _Evaluator, options):
    step0 = float(options.get("step", 1.0))
    max_ls = int(options.get("max_line_search", 20))
    if not step0 > 0:
        raise ValueError("options['step']: must be > 0")
    lo, hi = run.lo, run.hi
    while True:
        x, f0, g = run.x, run.f, run.g
        d = -g
        d[((x <= lo) & (d < 0)) | ((x >= hi) & (d > 0))] = 0.0
        scale = float(np.max(np.abs(d))) if d.size else 0.0
        if scale == 0.0:
            return "grad_tol"  # the projected gradient vanishes
        u = d / scale
        dphi0 = float(g @ u)
        try:
            found = _wolfe_search(_line(ev, x, u, max_ls, lo, hi), f0, dphi0, step0)
        except _LineSearchFailed:
            return "line_search_failed"
        except _BudgetExhausted:
            return "max_evaluations"
        xt, ft, gt = found
        reason = run.accept(xt, ft, gt)
        if reason is not None:
            return reason


class _LineSearchFailed(Exception):
    pass


def _line(ev, x, u, max_ls, lo=None, hi=None):
    """phi(t) -> (x_t, f, g, phi'(t)) along x + t u for _wolfe_search, raising _LineSearchFailed after max_ls
    evaluations; with bounds lo, hi the points are clipped into the box and phi' is taken along the clipped path
    (clipped components do not move)."""
    n_eval = [0]

    def phi(t):
        if n_eval[0] >= max_ls:
            raise _LineSearchFailed
        n_eval[0] += 1
        raw = x + t * u
        if lo is None:
            ft, gt = ev(raw)
            return raw, ft, gt, float(gt @ u)
        xt = np.clip(raw, lo, hi)
        ft, gt = ev(xt)
        free = (raw > lo) & (raw < hi)
        return xt, ft, gt, float(gt @ np.where(free, u, 0.0))

    return phi


def _wolfe_search(phi, f0, dphi0, t1):
    """Nocedal & Wright alg. 3.5: bracket, then zoom. Returns (x, f, g) of the accepted point."""
    t_prev, f_prev, d_prev = 0.0, f0, dphi0
    t = t1
    first = True
    while True:
        xt, ft, gt, dt = phi(t)
        if ft > f0 + C1 * t * dphi0 or (not first and ft >= f_prev) or not np.isfinite(ft):
            return _zoom(phi, f0, dphi0, t_prev, f_prev, d_prev, t, ft, dt)
        if abs(dt) <= -C2 * dphi0:
            return xt, ft, gt
        if dt >= 0:
            return _zoom(phi, f0, dphi0, t, ft, dt, t_prev, f_prev, d_prev)
        t_prev, f_prev, d_prev = t, ft, dt
        t = 2.0 * t
        first = False


def _zoom(phi, f0, dphi0, t_lo, f_lo, d_lo, t_hi, f_hi, d_hi):
    """Nocedal & Wright alg. 3.6 with safeguarded cubic interpolation (bisection fallback)."""
    while True:
        width = t_hi - t_lo
        t = None
        if np.isfinite(f_hi) and np.isfinite(d_hi):
            t = _cubic_min(t_lo, f_lo, d_lo, t_hi, f_hi, d_hi)
        a, b = min(t_lo, t_hi), max(t_lo, t_hi)
        margin = 0.1 * abs(width)
        if t is None or not (a + margin <= t <= b - margin):
            t = 0.5 * (t_lo + t_hi)
        if t == t_lo or t == t_hi:
            raise _LineSearchFailed  # the bracket has collapsed to rounding
        xt, ft, gt, dt = phi(t)
        if ft > f0 + C1 * t * dphi0 or ft >= f_lo or not np.isfinite(ft):
            t_hi, f_hi, d_hi = t, ft, dt
        else:
            if abs(dt) <= -C2 * dphi0:
                return xt, ft, gt
            if dt * (t_hi - t_lo) >= 0:
                t_hi, f_hi, d_hi = t_lo, f_lo, d_lo
            t_lo, f_lo, d_lo = t, ft, dt


# ---- Adam ----------------------------------------------------------------------------------------

def _adam(run: _Run, ev: _Evaluator, options):
    lr = float(options.get("lr", 1e-2))
    b1 = float(options.get("beta1", 0.9))
    b2 = float(options.get("beta2", 0.999))
    eps = float(options.get("eps", 1e-8))
    m = np.zeros_like(run.x)
    v = np.zeros_like(run.x)
    k = 0
    while True:
        k += 1
        g = run.g
        m = b1 * m + (1.0 - b1) * g
        v = b2 * v + (1.0 - b2) * (g * g)
        m_hat = m / (1.0 - b1 ** k)
        v_hat = v / (1.0 - b2 ** k)
        x = np.clip(run.x - lr * m_hat / (np.sqrt(v_hat) + eps), run.lo, run.hi)
        try:
            f, g_new = ev(x)
        except _BudgetExhausted:
            return "max_evaluations"
        reason = run.accept(x, f, g_new)
        if reason is not None:
            return reason


# ---- comparison at equal cost --------------------------------------------------------------------

def equal_cost_comparison(fun, x0, methods, evaluations, bounds=None, options_per_method=None, *,
                          rel_decrease=0.0, grad_tol=0.0, journal_dir=None,
                          callback=None) -> dict:
    """Run each method in ``methods`` from the same ``x0`` with the same budget of ``evaluations``
    objective evaluations (no iteration limit; ``rel_decrease`` off by default so that no method
    stops early on a stall) and return ``{method: OptimizeResult}`` in the given order.

    ``options_per_method``: ``{method: options dict}``. ``journal_dir``: when given, each method
    journals to ``<journal_dir>/<method>.journal.h5``, so an interrupted comparison resumes.
    ``callback(method, iteration, x, f, g)`` when given.
    """
    options_per_method = options_per_method or {}
    out = {}
    for method in methods:
        jp = None
        if journal_dir is not None:
            jp = pathlib.Path(journal_dir) / f"{method}.journal.h5"
        cb = None
        if callback is not None:
            cb = (lambda m: lambda it, x, f, g: callback(m, it, x, f, g))(method)
        out[method] = minimize(fun, x0, method=method, bounds=bounds, max_iterations=None,
                               max_evaluations=evaluations, rel_decrease=rel_decrease,
                               grad_tol=grad_tol, journal_path=jp, callback=cb,
                               options=options_per_method.get(method))
    return out
