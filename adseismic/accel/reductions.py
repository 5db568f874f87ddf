"""Device reductions (GPU block reductions, graph-capturable): the blow-up monitor's max |u| and count of
non-finite values, a model's value range, the on-device l2 misfit, and the graph clock's tick."""

import functools

import numpy as np
import warp as wp

MONITOR_BLOCK = 256


@wp.kernel
def tick(clock: wp.array(dtype=wp.int32), steps: int):
    """clock[0] += steps (the time index of a replayed graph)."""
    clock[0] = clock[0] + steps


@functools.lru_cache(maxsize=None)
def reduction_kernels(dtype):
    """(monitor, extrema): block-reduced GPU kernels over a flat array v read as 4-vectors v4 (its first 4 len(v4)
    values; thread 0 also reads the rest), thread t reading v4[t + k stride] for k < iters (coalesced; a vector
    load keeps 4 values in flight per thread), MONITOR_BLOCK threads per block reducing to one atomic each.
    monitor: stats[0] = max(stats[0], max |v| of the finite values), stats[1] += count of non-finite ones.
    extrema: float64 stats = [min, max] of the finite values (stats starts at [+max, -max, 0]), stats[2] += count
    of non-finite ones (float64 stats, so arrays of either dtype share one stats array)."""
    big = float(np.finfo(wp.dtype_to_numpy(dtype)).max)
    vec4 = wp.types.vector(length=4, dtype=dtype)

    @wp.func
    def take(val: dtype, lo: dtype, hi: dtype, top: dtype, bad: dtype):
        if wp.isfinite(val):
            return wp.min(lo, val), wp.max(hi, val), wp.max(top, wp.abs(val)), bad
        return lo, hi, top, bad + dtype(1.0)

    @wp.func
    def scan(v4: wp.array(dtype=vec4), v: wp.array(dtype=dtype), t: int, stride: int, iters: int):
        lo = dtype(wp.static(big))
        hi = -lo
        top = dtype(0.0)
        bad = dtype(0.0)
        for k in range(iters):
            c = t + k * stride
            if c < v4.shape[0]:
                q = v4[c]
                for j in range(4):
                    lo, hi, top, bad = take(q[j], lo, hi, top, bad)
        if t == 0:
            for c in range(4 * v4.shape[0], v.shape[0]):
                lo, hi, top, bad = take(v[c], lo, hi, top, bad)
        return lo, hi, top, bad

    @wp.kernel(module="unique")
    def monitor(v4: wp.array(dtype=vec4), v: wp.array(dtype=dtype), stats: wp.array(dtype=dtype), stride: int, iters: int):
        lo, hi, top, bad = scan(v4, v, wp.tid(), stride, iters)
        block_top = wp.tile_max(wp.tile(top))
        block_bad = wp.tile_sum(wp.tile(bad))
        if wp.tid() % wp.static(MONITOR_BLOCK) == 0:
            wp.atomic_max(stats, 0, block_top[0])
            wp.atomic_add(stats, 1, block_bad[0])

    @wp.kernel(module="unique")
    def extrema(v4: wp.array(dtype=vec4), v: wp.array(dtype=dtype), stats: wp.array(dtype=wp.float64), stride: int, iters: int):
        lo, hi, top, bad = scan(v4, v, wp.tid(), stride, iters)
        block_lo = wp.tile_min(wp.tile(lo))
        block_hi = wp.tile_max(wp.tile(hi))
        block_bad = wp.tile_sum(wp.tile(bad))
        if wp.tid() % wp.static(MONITOR_BLOCK) == 0:
            wp.atomic_min(stats, 0, wp.float64(block_lo[0]))
            wp.atomic_max(stats, 1, wp.float64(block_hi[0]))
            wp.atomic_add(stats, 2, wp.float64(block_bad[0]))

    return monitor, extrema


def _reduce(kernel, v: wp.array, stats: wp.array):
    flat = v.flatten()
    n4 = flat.shape[0] // 4
    v4 = flat[: 4 * n4].reshape((n4, 4)).view(wp.types.vector(length=4, dtype=v.dtype))
    threads = MONITOR_BLOCK * max(1, min(-(-n4 // MONITOR_BLOCK), 8 * wp.get_device(v.device).sm_count))
    wp.launch(kernel, dim=threads, inputs=[v4, flat, stats, threads, -(-n4 // threads)], block_dim=MONITOR_BLOCK, device=v.device)


def field_stats(fields, stats: wp.array):
    """stats (2,) <- [max |u| over the fields' finite values, count of non-finite values] (blow-up checks):
    on a GPU by launches only (graph-capturable), on the CPU by NumPy on zero-copy views (vectorised)."""
    if not stats.device.is_cuda:
        top, bad = 0.0, 0
        for u in fields:
            a = u.numpy()
            t = max(a.max(), -a.min())  # NaN if any value is
            if not np.isfinite(t):
                ok = np.isfinite(a)
                t, bad = np.abs(a[ok]).max(initial=0.0), bad + a.size - np.count_nonzero(ok)
            top = max(top, float(t))
        stats.assign(np.array([top, bad], dtype=wp.dtype_to_numpy(stats.dtype)))
        return
    stats.zero_()
    for u in fields:
        _reduce(reduction_kernels(u.dtype)[0], u, stats)


def value_ranges(arrays) -> list:
    """[(min, max, number of non-finite values)] of float32/float64 Warp arrays (either dtype) on one device, min and
    max over the finite values (+max, -max of the first array's dtype where none is): on a GPU by block reductions
    into one float64 stats array read back once (one synchronisation for all), on the CPU by NumPy on zero-copy
    views."""
    v0 = arrays[0]
    big = float(np.finfo(wp.dtype_to_numpy(v0.dtype)).max)
    if not v0.device.is_cuda:
        out = []
        for v in arrays:
            a = v.numpy()
            ok = np.isfinite(a)
            fin = a if ok.all() else a[ok]
            out.append((float(fin.min(initial=big)), float(fin.max(initial=-big)), int(a.size - np.count_nonzero(ok))))
        return out
    stats = wp.array([[big, -big, 0.0]] * len(arrays), dtype=wp.float64, device=v0.device)
    for k, v in enumerate(arrays):
        _reduce(reduction_kernels(v.dtype)[1], v, stats[k])
    return [(float(lo), float(hi), int(bad)) for lo, hi, bad in stats.numpy()]


def value_range(v: wp.array):
    """(min, max, number of non-finite values) of a float32/float64 Warp array (value_ranges)."""
    return value_ranges([v])[0]


@functools.lru_cache(maxsize=None)
def l2_residual_kernel(dtype):
    """Kernel of the "l2" misfit on the device, a thread per trace (s, r) of synthetic data (S, n_rec, >= nt samples):
    residual[s, r, t] = (synthetic - observed) dt for t < nt, formed in float64 and rounded to dtype, as the host's
    misfits._l2 forms it; total[0] += sum over t of (synthetic - observed)^2 (float64)."""
    arr3 = wp.array3d(dtype=dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def l2_residual(syn: arr3, obs: wp.array3d(dtype=wp.float64), nt: int, dt: wp.float64, res: arr3, total: wp.array(dtype=wp.float64)):
        s, r = wp.tid()
        acc = wp.float64(0.0)
        for t in range(nt):
            d = wp.float64(syn[s, r, t]) - obs[s, r, t]
            acc += d * d
            res[s, r, t] = dtype(d * dt)
        wp.atomic_add(total, 0, acc)

    return l2_residual


@functools.lru_cache(maxsize=None)
def weighted_l2_residual_kernel(dtype):
    """Kernel of the weighted "l2" misfit on the device (misfits.weighted_l2's, see there), a thread per trace (s, r)
    of synthetic data (S, n_rec, >= nt samples) against observed and weights (S, n_rec, nt) float64:
    e = w (synthetic - observed) in float64, residual[s, r, t] = (e dt) w rounded to dtype for t < nt;
    total[0] += sum over t of e^2 (float64)."""
    arr3 = wp.array3d(dtype=dtype)
    f64 = wp.array3d(dtype=wp.float64)

    @wp.kernel(module="unique", enable_backward=False)
    def weighted_l2_residual(syn: arr3, obs: f64, w: f64, nt: int, dt: wp.float64, res: arr3, total: wp.array(dtype=wp.float64)):
        s, r = wp.tid()
        acc = wp.float64(0.0)
        for t in range(nt):
            ws = w[s, r, t]
            e = ws * (wp.float64(syn[s, r, t]) - obs[s, r, t])
            acc += e * e
            res[s, r, t] = dtype((e * dt) * ws)
        wp.atomic_add(total, 0, acc)

    return weighted_l2_residual
