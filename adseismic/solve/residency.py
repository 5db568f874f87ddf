"""Shot data kept on a device across evaluations (issue 25), the one mechanism of both parallel engines (a
DevicePool's threads, solve.devices; a Dask worker process, solve.distributed): a per-process cache of each batch's
observed data and weights as Warp arrays, keyed by (batch key, device)."""

from __future__ import annotations

import collections

import numpy as np
import warp as wp

from adseismic.solve.common import resolve_device

RESIDENT: dict[tuple[str, str], tuple] = {}  # (batch key, device) -> (observed, weights) on that device, in this process
UPLOADS: collections.Counter = collections.Counter()  # (batch key, device) -> uploads of those arrays, until evicted


def resident(data: dict, device: str, misfit: str) -> dict:
    """The batch's data as batch_gradient runs them on `device` (the one mechanism of both pools: a DevicePool's
    threads and a Dask worker process). With the "l2" misfit (formed on the device) its observed data and weights
    (n_shots, n_receivers, nt) as float64 Warp arrays on the device, uploaded by the first call in this process for
    the batch's key (data["key"], unique per pool, band and batch) and device, reused by the later calls until
    `evict`; with any other misfit (formed on the host) the data as they are."""
    if misfit != "l2":
        return data
    at = (data["key"], resolve_device(device))
    arrays = RESIDENT.get(at)
    if arrays is None:
        arrays = RESIDENT[at] = tuple(None if data.get(n) is None else
                                      wp.array(np.ascontiguousarray(data[n], dtype=float), dtype=wp.float64, device=device)
                                      for n in ("observed", "weights"))  # fmt: skip
        UPLOADS[at] += 1
    return dict(data, observed=arrays[0], weights=arrays[1])


def evict(token: str) -> None:
    """Free this process's resident arrays of the pool `token` (its batch keys start with it), and forget their
    upload counts: at each keep (a new band) and at close."""
    for cache in (RESIDENT, UPLOADS):
        for at in [at for at in cache if at[0].startswith(f"{token}-")]:
            del cache[at]
