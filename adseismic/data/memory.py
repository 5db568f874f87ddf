"""How much memory a run may use: the free memory of the CPU (available RAM) or of a CUDA device.

:func:`available_bytes` is what the planner (adseismic.scene) compares its estimate with, and what the model
loader (adseismic.data.models) compares a model's node count with. Warp is imported only for a CUDA device.
"""
from __future__ import annotations

import os

__all__ = ["available_bytes"]


def _cpu_available() -> int | None:
    """Available RAM in bytes: psutil if installed, else /proc/meminfo's MemAvailable, else free pages
    (os.sysconf); None when none of them answers."""
    try:
        import psutil  # noqa: PLC0415 - optional

        return int(psutil.virtual_memory().available)
    except Exception:  # noqa: BLE001 - not installed or not supported here
        pass
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def _cuda_available(device: str) -> int | None:
    """Free memory (bytes) of the CUDA device ``device`` ("cuda" or "cuda:N") through Warp; None if unknown."""
    try:
        import warp as wp  # noqa: PLC0415

        d = wp.get_device(device)
        free = getattr(d, "free_memory", None)
        return None if free is None else int(free)
    except Exception:  # noqa: BLE001 - no CUDA, no such device, an older Warp
        return None


def available_bytes(device: str = "cpu") -> int | None:
    """Bytes a run on ``device`` ("cpu", "cuda", "cuda:N") can allocate now: available RAM for the CPU, the
    device's free memory for CUDA; None when it cannot be told (then no limit is applied)."""
    device = str(device)
    if device.startswith("cuda"):
        return _cuda_available(device)
    return _cpu_available()
