"""Atomic file writes: a file is written under ``<name>.part`` in the same directory and renamed
into place with ``os.replace`` only when complete; on any error the part file is removed, so the
file appears complete or not at all (:func:`atomic_write`, :func:`write_text_atomic`,
:func:`write_h5_atomic`; :func:`atomic_path` names the part file for writers that rename it
themselves).
"""
from __future__ import annotations

import contextlib
import os
import pathlib

__all__ = ["atomic_path", "atomic_write", "write_text_atomic", "write_h5_atomic"]


def atomic_path(path) -> pathlib.Path:
    """The temporary name a file is written under before it is renamed to ``path``."""
    path = pathlib.Path(path)
    return path.with_name(path.name + ".part")  # data.h5 -> data.h5.part (= with_suffix(".h5.part"))


@contextlib.contextmanager
def atomic_write(path):
    """Context yielding the .part path to write ``path`` under: renamed into place when the block
    completes, removed on any error, so ``path`` appears complete or not at all."""
    path = pathlib.Path(path)
    part = atomic_path(path)
    try:
        yield part
        os.replace(part, path)
    except BaseException:
        part.unlink(missing_ok=True)
        raise


def write_text_atomic(path, text: str) -> None:
    """Write ``text`` to ``path`` via its .part name; nothing is left behind on error."""
    with atomic_write(path) as part:
        part.write_text(text, encoding="utf-8")


def write_h5_atomic(path, fill) -> None:
    """Create an HDF5 file at ``path`` with ``fill(h5py.File)`` via its .part name (atomic)."""
    import h5py

    with atomic_write(path) as part, h5py.File(part, "w") as f:
        fill(f)
