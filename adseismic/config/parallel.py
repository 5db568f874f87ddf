"""The optional ``parallel:`` section (fwi, forward): the shots of each evaluation (or of a forward run) spread over
workers: Dask worker processes, or threads of this process, one per device.

    parallel:
      engine: dask                       # dask (worker processes, here or on a cluster) or threads (this process)
      scheduler: local                   # dask: local (a LocalCluster on this host) or a scheduler address, tcp://host:8786
      devices: [cpu, cpu]                # one worker per entry; or all (every GPU, else CPU workers); cpu, cuda, cuda:N
      workers: 2                         # dask, optional: the number of workers (default: one per device)

engine threads: one Python thread and one Warp stream per entry of devices, in this process, without Dask
(adseismic.solve.devices.DevicePool); it takes no scheduler and no workers (list the devices instead).
No section: one process, one device. What this module checks needs nothing but the text and the shot count
(keys, types, device spelling, more devices or workers than shots); whether the scheduler answers and the devices
exist is checked before any work by adseismic.solve.pools.check_pool (ValueError naming the key).
Imports no workflow and nothing of Dask.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from adseismic.config.common import ConfigError, _check_keys, _choice, _integer, _mapping, _short

__all__ = ["PARALLEL_KEYS", "ParallelConfig", "parse_parallel"]

PARALLEL_KEYS = ("engine", "scheduler", "devices", "workers")
ENGINES = ("dask", "threads")
DEVICE_RE = re.compile(r"^(cpu|cuda|cuda:\d+)$")
ADDRESS_RE = re.compile(r"^([a-z]+://)?[^\s:/]+:\d+$")


@dataclass
class ParallelConfig:
    """engine: "dask" or "threads"; scheduler (dask): "local" or an address (tcp://host:port); devices: a list of
    device names (one worker per entry, worker i on devices[i % len(devices)] when workers is larger), "all" (every
    GPU, else CPU workers: one per core, at most one per shot) or None (all for a CUDA simulation.device, CPU workers
    for cpu); workers (dask): int or None."""

    engine: str = "dask"
    scheduler: str = "local"
    devices: list | str | None = None
    workers: int | None = None


def parse_parallel(raw, n_shots: int, key: str = "parallel") -> ParallelConfig | None:
    """The parallel section (None when absent or null: one process)."""
    if raw is None:
        return None
    sec = _mapping(raw, key, "engine: dask | threads, scheduler: local | tcp://host:port, devices: [cpu, cpu] | all")
    _check_keys(sec, key, PARALLEL_KEYS)
    out = ParallelConfig()
    if sec.get("engine") is not None:
        out.engine = _choice(sec["engine"], f"{key}.engine", ENGINES)
    if sec.get("scheduler") is not None:
        s = sec["scheduler"]
        if not isinstance(s, str) or not (s == "local" or ADDRESS_RE.match(s.strip())):
            raise ConfigError(f"{key}.scheduler: {_short(s)} is neither local nor a scheduler address; write local (a cluster "
                              f"on this host) or the address the Dask scheduler prints, e.g. tcp://10.0.0.5:8786")
        out.scheduler = s.strip()
    devices = sec.get("devices")
    if devices is not None:
        if devices == "all":
            out.devices = "all"
        elif isinstance(devices, list) and devices:
            for i, d in enumerate(devices):
                if not isinstance(d, str) or not DEVICE_RE.match(d):
                    raise ConfigError(f"{key}.devices[{i}]: {_short(d)} is not a device; write cpu, cuda or cuda:N (N = 0, 1, ...)")
            if len(devices) > n_shots:
                raise ConfigError(f"{key}.devices: {len(devices)} devices for {n_shots} shot(s); a worker needs at least one shot: "
                                  f"list at most {n_shots} device(s)")
            out.devices = list(devices)
        else:
            raise ConfigError(f"{key}.devices: {_short(devices)} is not a list of devices or all; write e.g. [cuda:0, cuda:1], "
                              f"[cpu, cpu] or all")
    if sec.get("workers") is not None:
        n = _integer(sec["workers"], f"{key}.workers")
        if n < 1:
            raise ConfigError(f"{key}.workers: {n} < 1; give at least 1 worker (or drop the parallel section for one process)")
        if n > n_shots:
            raise ConfigError(f"{key}.workers: {n} workers for {n_shots} shot(s); a worker needs at least one shot: "
                              f"give at most {n_shots}")
        if isinstance(out.devices, list) and n < len(out.devices):
            raise ConfigError(f"{key}.workers: {n} is fewer than the {len(out.devices)} devices listed in {key}.devices; "
                              f"give at least {len(out.devices)} workers or list fewer devices")
        out.workers = n
    if out.engine == "threads":
        for k, fix in (("scheduler", "drop it, or write engine: dask to run on a Dask scheduler"),
                       ("workers", "list one device per thread instead, e.g. devices: [cpu, cpu]")):
            if sec.get(k) is not None:
                raise ConfigError(f"{key}.{k}: {_short(sec[k])} given with engine threads, which runs one thread per device "
                                  f"in this process; {fix}")
    return out
