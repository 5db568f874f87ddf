"""Shot batching, one for every physics: the shots of a survey run in batches (each one simulation over its
shots), the batches' misfits and gradients summed in a fixed order so the result does not depend on the batch
size beyond float round-off."""

from __future__ import annotations


def shot_slices(n_shots: int, per_batch: int | None = None) -> list[slice]:
    """Consecutive slices of at most per_batch shots covering range(n_shots) in order (one slice of all shots where
    per_batch is None or 0)."""
    if per_batch is not None and int(per_batch) < 0:
        raise ValueError(f"shots per batch: {per_batch} is negative; give a positive count, or 0 for all shots at once")
    step = int(per_batch) if per_batch else max(int(n_shots), 1)
    return [slice(s0, min(s0 + step, n_shots)) for s0 in range(0, n_shots, step)]
