"""Warp kernels for the constant-density acoustic wave equation, 2D and 3D.

Equation:  (1/v^2) d2u/dt2 - laplacian(u) = s(t) delta(x - x_s),
scheme:    u[n+1] = 2 u[n] - u[n-1] + v^2 dt^2 (L u[n] + s[n] delta_h),
with L the order-2/4/8 Laplacian whose second derivatives are stretched by a convolutional PML
(Komatitsch & Martin 2007; second-order form of Pasalic & McGarry 2010) along every absorbing axis:

    d2u/dx2  ->  d2u/dx2 + d(psi)/dx + zeta,
    psi[n]  = b psi[n-1]  + a du/dx[n],
    zeta[n] = b zeta[n-1] + a (d2u/dx2 + d(psi)/dx)[n].

Layout. Every field is (n_shots, nz, ny, nx) with x contiguous; 2D uses ny = 1. Each axis is padded
as [halo R][PML][physical grid][PML][halo R] with R = order/2; halo cells stay zero and are never
written, so stencils need no bounds checks. With a free surface the top has no PML: its first
non-halo row is the surface (u = 0) and reads above it mirror the field with a sign change
(pressure release by antisymmetric imaging). psi and zeta are stored only in strips along each axis
("strip" index j; Axis.store maps a padded index to j, Axis.pos maps back), which keeps the memory of
a taped time step close to one wavefield.

Off-grid sources and receivers use one operator for injection and recording (so the two are exact
adjoints): a Kaiser-windowed sinc of half-width HICKS_RADIUS cells per axis (Hicks 2002, shape
parameter HICKS_B for wavenumbers up to pi/2, i.e. >= 4 points per wavelength; per axis its weights sum to one
and have zero first and second moments: kernels/common.hicks_axis), mirrored with a sign change across a free
surface. The Kaiser window has its edge value (1/I0(b), ~1%) subtracted so that the weights are continuously
differentiable in the position (source-location gradients).

All kernels write fresh outputs from inputs (or add with atomics), never read-modify their own
input, so each time step can be differentiated by wp.Tape when given its own arrays; the hand-written
adjoint's kernels, never taped, may update an array in place.
"""


import functools
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from adseismic.kernels.common import (
    HICKS_RADIUS,
    Kernels,
    adjoint_launch,
    aligned,
    as_vectors,
    block_rows,
    flat_access,
    frame_map,
    hicks_axis,
    unique_kernel,
    vector_access,
)
from adseismic.kernels.numerics import FIRST_DERIVATIVE, SECOND_DERIVATIVE

# GPU core steps: rows (along z) x adjacent columns per thread (one vector), 2D and 3D, threads per block
# (docs/benchmarks.md, "Layout timings")
GPU_CORE_ROWS, GPU_CORE_COLS, GPU_CORE_THREADS = 4, 2, 128
GPU_CORE3_ROWS, GPU_CORE3_COLS = 4, 2
GPU_FRAME3_ROWS, GPU_FRAME3_COLS = 4, 1  # the 3D frame's cells a thread: rows along z x adjacent columns (2D: one)
CPU_THREADS = int(os.environ.get("ADSEISMIC_CPU_THREADS", "2"))  # threads over row blocks of a CPU step
FRAME_CELL_COST = 2.0  # a CPU adjoint step: the time of a frame cell (the per-cell gather, CPML) over a tile's cell


@functools.lru_cache(maxsize=None)
def build(ndim: int, order: int, dtype, free_surface: bool):
    """Kernels for one (ndim, order, dtype, free_surface) combination, compiled once per process."""
    R = order // 2
    W = 2 * HICKS_RADIUS
    NPTS = W**ndim
    ns = _Parts(
        ndim=ndim, dtype=dtype, R=R, A=SECOND_DERIVATIVE[order], B=FIRST_DERIVATIVE[order], HR=HICKS_RADIUS, W=W, NPTS=NPTS,
        fs=bool(free_surface), three=ndim == 3, arr1=wp.array(dtype=dtype), iarr1=wp.array(dtype=wp.int32),
        arr3=wp.array3d(dtype=dtype), arr4=wp.array4d(dtype=dtype),
    )  # fmt: skip
    # each builder reads what the ones before it made (pre_step calls _points' record_point)
    for builder in (_stencils, _cpml, _reference_step, _cpu_rows, _points, _flat_cells, _gpu_step, _psi_adjoint, _adjoint_terms,
                    _adjoint_step, _flat_adjoint, _pre_adjoint, _model_ops):
        vars(ns).update(builder(ns))
    return Kernels(
        Axis=ns.Axis, step=ns.step, step_core=functools.lru_cache(maxsize=None)(functools.partial(_step_core, ns)), step_rows=ns.step_rows,
        step_core_rows=ns.step_core_rows, psi=ns.psi, psi_flat=ns.psi_flat, inject=ns.inject, adjoint_step=ns.adjoint_step,
        adjoint_core=functools.lru_cache(maxsize=None)(functools.partial(_adjoint_core, ns)), squared=ns.squared, model_gradient=ns.model_gradient,
        psi_adjoint=ns.psi_adjoint, pre_adjoint=ns.pre_adjoint, post_adjoint=ns.post_adjoint, pre_step=ns.pre_step, record=ns.record,
        weights=ns.weights, compact=ns.compact,
        inject_fixed=ns.inject_fixed, record_fixed=ns.record_fixed, record_summed=ns.record_summed, pad_model=ns.pad_model, scatter=ns.scatter,
        energy=ns.energy, halo=R, operator_points=NPTS,
    )  # fmt: skip


class _Parts:
    """What the builders of one configuration share: its constants (R = order / 2, the stencil weights A and B, the
    operator's HR, W and NPTS, the free-surface flag fs, three = 3D), its array types and, as attributes, the Warp
    structs, funcs and kernels the builders have made so far. A builder reads what it uses into locals, the names
    its Warp code resolves (closure variables), and returns what it makes. A plain object, hashed by identity: _lanes
    and _core_tile are cached per configuration."""

    def __init__(self, **kw):
        self.__dict__.update(kw)


def _stencils(ns):
    """The CPML axis struct and the stencils: field reads (free-surface image), d2 and d1 along each axis, d1's
    transpose, d2 of a window (d2w) and flat reads."""
    dtype, R, A, B, fs, arr1, arr4 = ns.dtype, ns.R, ns.A, ns.B, ns.fs, ns.arr1, ns.arr4

    @wp.struct
    class Axis:
        a: wp.array(dtype=dtype)  # CPML coefficient a per padded index (0 outside the PML)
        b: wp.array(dtype=dtype)  # CPML coefficient b per padded index
        store: wp.array(dtype=wp.int32)  # strip index per padded index, -1 outside the strip
        pos: wp.array(dtype=wp.int32)  # padded index per strip index

    @wp.func
    def at(u: arr4, s: int, z: int, y: int, x: int, top: int) -> dtype:
        # Field value; above a free surface (row `top`) the antisymmetric image.
        if wp.static(fs):
            if z < top:
                return -u[s, 2 * top - z, y, x]
        return u[s, z, y, x]

    def shift(axis: int):
        # read of the field at offset m along `axis` from (i, j, k); along z the free-surface image
        @wp.func
        def read(u: arr4, s: int, i: int, j: int, k: int, m: int, top: int) -> dtype:
            if wp.static(axis == 0):
                return at(u, s, i + m, j, k, top)
            elif wp.static(axis == 1):
                return u[s, i, j + m, k]
            else:
                return u[s, i, j, k + m]

        return read

    def make_d2(axis: int):
        read = shift(axis)

        @wp.func
        def d2(u: arr4, s: int, i: int, j: int, k: int, top: int) -> dtype:
            # second derivative along `axis` (times dx^2)
            acc = dtype(wp.static(A[0])) * u[s, i, j, k]
            for m in range(wp.static(R)):
                acc += dtype(wp.static(A[m + 1])) * (read(u, s, i, j, k, m + 1, top) + read(u, s, i, j, k, -m - 1, top))
            return acc

        return d2

    def make_d1(axis: int):
        # central first derivative along `axis` (times dx) of a field or a psi strip (no image:
        # psi and zeta never reach above a free surface)
        @wp.func
        def d1(a: arr4, s: int, i: int, j: int, k: int) -> dtype:
            acc = dtype(0.0)
            for m in range(wp.static(R)):
                if wp.static(axis == 0):
                    acc += dtype(wp.static(B[m])) * (a[s, i + m + 1, j, k] - a[s, i - m - 1, j, k])
                elif wp.static(axis == 1):
                    acc += dtype(wp.static(B[m])) * (a[s, i, j + m + 1, k] - a[s, i, j - m - 1, k])
                else:
                    acc += dtype(wp.static(B[m])) * (a[s, i, j, k + m + 1] - a[s, i, j, k - m - 1])
            return acc

        return d1

    def make_d1_transpose(axis: int):
        # adjoint of d1: adj[(i, j, k) +- m along axis] +-= B_m g
        @wp.func
        def d1t(adj: arr4, s: int, i: int, j: int, k: int, g: dtype):
            for m in range(wp.static(R)):
                c = dtype(wp.static(B[m])) * g
                if wp.static(axis == 0):
                    wp.atomic_add(adj, s, i + m + 1, j, k, c)
                    wp.atomic_add(adj, s, i - m - 1, j, k, -c)
                elif wp.static(axis == 1):
                    wp.atomic_add(adj, s, i, j + m + 1, k, c)
                    wp.atomic_add(adj, s, i, j - m - 1, k, -c)
                else:
                    wp.atomic_add(adj, s, i, j, k + m + 1, c)
                    wp.atomic_add(adj, s, i, j, k - m - 1, -c)

        return d1t

    d2z, d2y, d2x = make_d2(0), make_d2(1), make_d2(2)
    d1 = (make_d1(0), make_d1(1), make_d1(2))
    d1t = (make_d1_transpose(0), make_d1_transpose(1), make_d1_transpose(2))
    vecw = wp.types.vector(length=2 * R + 1, dtype=dtype)

    @wp.func
    def d2w(w: vecw) -> dtype:
        # second derivative (times dx^2) from a window of the 2R+1 values centred on the cell: the sum of
        # d2z/d2x in the same order, so the line kernels reproduce the per-cell kernel bit for bit
        acc = dtype(wp.static(A[0])) * w[wp.static(R)]
        for m in range(wp.static(R)):
            acc += dtype(wp.static(A[m + 1])) * (w[wp.static(R + 1) + m] + w[wp.static(R - 1) - m])
        return acc

    @wp.func
    def d1w(w: vecw) -> dtype:
        # first derivative (times dx) from a window of 2R+1 values centred on the cell: d1's sum in d1's order
        acc = dtype(0.0)
        for m in range(wp.static(R)):
            acc += dtype(wp.static(B[m])) * (w[wp.static(R + 1) + m] - w[wp.static(R - 1) - m])
        return acc

    @wp.func
    def flat(a: arr1, base: int, k: int) -> dtype:
        # a[base + k] for base, k >= 0, written so that the compiler sees a non-negative index: Warp wraps
        # negative indices, and the select that takes keeps a loop over k from being vectorised
        return a[wp.max(base, 0) + k]

    return dict(Axis=Axis, d2z=d2z, d2y=d2y, d2x=d2x, d1=d1, d1t=d1t, vecw=vecw, d2w=d2w, d1w=d1w, flat=flat)


def _cpml(ns):
    """The CPML: psi per cell and its kernels (per cell and CPU rows) along each axis, and the stretch terms of d2."""
    dtype, R, B, arr1, arr4, Axis, d1, flat = ns.dtype, ns.R, ns.B, ns.arr1, ns.arr4, ns.Axis, ns.d1, ns.flat

    def make_psi_cell(axis: int):
        # psi along one axis (0: z, 1: y, 2: x) at one cell (s, i, j, k) of that axis' strip
        deriv = d1[axis]

        @wp.func
        def psi_cell(u: arr4, psi_old: arr4, psi_new: arr4, ax: Axis, inv_dx: dtype, s: int, i: int, j: int, k: int):
            if wp.static(axis == 0):
                p = ax.pos[i]
            elif wp.static(axis == 1):
                p = ax.pos[j]
            else:
                p = ax.pos[k]
            a = ax.a[p]
            val = dtype(0.0)
            if a != dtype(0.0):
                if wp.static(axis == 0):
                    du = deriv(u, s, p, j, k)
                elif wp.static(axis == 1):
                    du = deriv(u, s, i, p, k)
                else:
                    du = deriv(u, s, i, j, p)
                val = ax.b[p] * psi_old[s, i, j, k] + a * du * inv_dx
            psi_new[s, i, j, k] = val

        return psi_cell

    psi_cells = [make_psi_cell(a) for a in range(3)]

    def make_psi(axis: int):
        # one thread per strip cell (Warp's generated adjoint, and a GPU step without a core; the GPU step's own is
        # _gpu_step's psi_flat)
        cell = psi_cells[axis]

        @unique_kernel(grid_stride=False)
        def psi_kernel(u: arr4, psi_old: arr4, psi_new: arr4, ax: Axis, inv_dx: dtype):
            s, i, j, k = wp.tid()
            cell(u, psi_old, psi_new, ax, inv_dx, s, i, j, k)

        # CPU: one thread per strip line (s, first + i, j), looping over its last axis on the flat arrays (as
        # psi_cell; strip: the strip's shape (Z, Y, X), grid: the padded one), vectorised but along x
        @unique_kernel
        def psi_rows(u: arr1, psi_old: arr1, psi_new: arr1, ax: Axis, inv_dx: dtype, strip: wp.vec3i, grid: wp.vec3i, first: int):
            s, i, j = wp.tid()
            i += first
            q = ((s * strip[0] + i) * strip[1] + j) * strip[2]
            c = ((s * grid[0] + i) * grid[1] + j) * grid[2]  # u at (s, i, j, 0)
            if wp.static(axis < 2):
                d = grid[2]  # the neighbours' offset along the axis
                if wp.static(axis == 0):
                    p = ax.pos[i]
                    c += (p - i) * grid[1] * grid[2]
                    d *= grid[1]
                else:
                    p = ax.pos[j]
                    c += (p - j) * grid[2]
                a = ax.a[p]
                b = ax.b[p]
                k = int(0)
                while k < strip[2]:
                    val = dtype(0.0)
                    if a != dtype(0.0):
                        du = dtype(0.0)
                        for m in range(wp.static(R)):
                            du += dtype(wp.static(B[m])) * (flat(u, c + (m + 1) * d, k) - flat(u, c - (m + 1) * d, k))
                        val = b * flat(psi_old, q, k) + a * du * inv_dx
                    psi_new[wp.max(q, 0) + k] = val
                    k += 1
            else:
                k = int(0)
                while k < strip[2]:
                    p = ax.pos[k]
                    a = ax.a[p]
                    val = dtype(0.0)
                    if a != dtype(0.0):
                        du = dtype(0.0)
                        for m in range(wp.static(R)):
                            du += dtype(wp.static(B[m])) * (u[c + p + m + 1] - u[c + p - m - 1])
                        val = ax.b[p] * psi_old[q + k] + a * du * inv_dx
                    psi_new[q + k] = val
                    k += 1

        return psi_kernel, psi_rows

    psi = [make_psi(a) for a in range(3)]

    pair = wp.types.vector(length=2, dtype=dtype)

    @wp.func
    def cpml_term(t: dtype, dpsi: dtype, zeta: dtype, a: dtype, b: dtype, inv_dx: dtype) -> pair:
        # (d(psi)/dx + zeta_new, zeta_new) from t = d2u/dx2, dpsi = d1 of psi (times dx), the old zeta and the cell's a, b
        d = dpsi * inv_dx
        zn = b * zeta + a * (t + d)
        return pair(d + zn, zn)

    def make_stretch(axis: int):
        # CPML term of the second derivative along `axis`, from t = d2u/dx2 at (s, z, y, x) and the cell's strip
        # index j = ca.store[p] (p: its index along `axis`): stretch gives (d(psi)/dx + zeta_new, zeta_new) in the
        # strip, else (0, 0), loading only; keep stores zeta_new there (a kernel's stores come after its loads:
        # Warp's arrays may alias, so a load after a store waits for it)
        dpsi = d1[axis]

        @wp.func
        def at_strip(j: int, z: int, y: int, x: int) -> wp.vec3i:
            if wp.static(axis == 0):
                return wp.vec3i(j, y, x)
            elif wp.static(axis == 1):
                return wp.vec3i(z, j, x)
            return wp.vec3i(z, y, j)

        @wp.func
        def stretch(t: dtype, j: int, p: int, s: int, z: int, y: int, x: int, psi: arr4, zeta: arr4, ca: Axis, inv_dx: dtype) -> pair:
            if j >= 0:
                c = at_strip(j, z, y, x)
                return cpml_term(t, dpsi(psi, s, c[0], c[1], c[2]), zeta[s, c[0], c[1], c[2]], ca.a[p], ca.b[p], inv_dx)
            return pair(dtype(0.0), dtype(0.0))

        @wp.func
        def keep(zn: dtype, j: int, s: int, z: int, y: int, x: int, zeta_new: arr4):
            if j >= 0:
                c = at_strip(j, z, y, x)
                zeta_new[s, c[0], c[1], c[2]] = zn

        return stretch, keep

    (stretch_z, keep_z), (stretch_y, keep_y), (stretch_x, keep_x) = make_stretch(0), make_stretch(1), make_stretch(2)
    return dict(psi=psi, pair=pair, cpml_term=cpml_term, stretch_z=stretch_z, stretch_y=stretch_y, stretch_x=stretch_x, keep_z=keep_z,
                keep_y=keep_y, keep_x=keep_x)


def _reference_step(ns):
    """The per-cell update and the reference step (one thread per interior cell)."""
    dtype, R, fs, three, arr3, arr4, Axis, d2z = ns.dtype, ns.R, ns.fs, ns.three, ns.arr3, ns.arr4, ns.Axis, ns.d2z
    d2y, d2x, stretch_z, stretch_y, stretch_x = ns.d2y, ns.d2x, ns.stretch_z, ns.stretch_y, ns.stretch_x
    keep_z, keep_y, keep_x, pair = ns.keep_z, ns.keep_y, ns.keep_x, ns.pair

    @wp.func
    def advance(uc: dtype, up: dtype, vv: dtype, dt2: dtype, lap: dtype) -> dtype:
        # u[n+1] from u[n] = uc, u[n-1] = up, the velocity vv and the (stretched) Laplacian lap
        return dtype(2.0) * uc - up + vv * vv * dt2 * lap

    @wp.func
    def stretched(uc: dtype, up: dtype, vv: dtype, dt2: dtype, inv_dx2: dtype, dzz: dtype, dxx: dtype, dyy: dtype, ty: dtype, tz: dtype,
                  tx: dtype) -> dtype:  # fmt: skip
        # u_next from the plain d2u along each axis (times dx^2) and the CPML terms (0 outside the strips): the plain
        # Laplacian comes first and the CPML terms are added to it, so that outside the strips it rounds as in
        # step_core, whatever multiply-adds the compiler fuses
        if wp.static(three):
            lap = (dzz + dxx + dyy) * inv_dx2 + ty
        else:
            lap = (dzz + dxx) * inv_dx2
        return advance(uc, up, vv, dt2, lap + tz + tx)

    @wp.func
    def update(
        u: arr4, u_prev: arr4, u_next: arr4, v: arr3,
        psi_z: arr4, psi_y: arr4, psi_x: arr4,
        zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        zeta_z_new: arr4, zeta_y_new: arr4, zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int,
        s: int, z: int, y: int, x: int, dzz: dtype, dxx: dtype, uc: dtype,
    ):  # fmt: skip
        # u_next at one cell from uc = u there and its d2u along z and x (times dx^2). Every load comes before the
        # first store.
        inv_dx2 = inv_dx * inv_dx
        jz = az.store[z]
        jx = ax.store[x]
        jy = int(-1)
        dyy = dtype(0.0)
        ty = pair()
        if wp.static(three):
            jy = ay.store[y]
            dyy = d2y(u, s, z, y, x, top)
            ty = stretch_y(dyy * inv_dx2, jy, y, s, z, y, x, psi_y, zeta_y, ay, inv_dx)
        tz = stretch_z(dzz * inv_dx2, jz, z, s, z, y, x, psi_z, zeta_z, az, inv_dx)
        tx = stretch_x(dxx * inv_dx2, jx, x, s, z, y, x, psi_x, zeta_x, ax, inv_dx)
        un = stretched(uc, u_prev[s, z, y, x], v[z, y, x], dt2, inv_dx2, dzz, dxx, dyy, ty[0], tz[0], tx[0])
        if wp.static(three):
            keep_y(ty[1], jy, s, z, y, x, zeta_y_new)
        keep_z(tz[1], jz, s, z, y, x, zeta_z_new)
        keep_x(tx[1], jx, s, z, y, x, zeta_x_new)
        u_next[s, z, y, x] = un

    @wp.func
    def cell(
        u: arr4, u_prev: arr4, u_next: arr4, v: arr3,
        psi_z: arr4, psi_y: arr4, psi_x: arr4,
        zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        zeta_z_new: arr4, zeta_y_new: arr4, zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int,
        s: int, z: int, y: int, x: int,
    ):  # fmt: skip
        # u_next at interior cell (s, z, y, x), read straight from the arrays (0 on a free surface)
        if wp.static(fs):
            if z == top:
                u_next[s, z, y, x] = dtype(0.0)
                return
        update(u, u_prev, u_next, v, psi_z, psi_y, psi_x, zeta_z, zeta_y, zeta_x, zeta_z_new, zeta_y_new, zeta_x_new,
               az, ay, ax, dt2, inv_dx, top, s, z, y, x, d2z(u, s, z, y, x, top), d2x(u, s, z, y, x, top), u[s, z, y, x])  # fmt: skip

    @unique_kernel(grid_stride=False)
    def step(
        u: arr4, u_prev: arr4, u_next: arr4, v: arr3,
        psi_z: arr4, psi_y: arr4, psi_x: arr4,
        zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        zeta_z_new: arr4, zeta_y_new: arr4, zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis,
        dt2: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        # Reference step: one thread per interior cell (what Warp differentiates for adjoint="warp").
        s, zi, yi, xi = wp.tid()
        z = zi + wp.static(R)
        x = xi + wp.static(R)
        y = yi
        if wp.static(three):
            y = yi + wp.static(R)
        cell(u, u_prev, u_next, v, psi_z, psi_y, psi_x, zeta_z, zeta_y, zeta_x, zeta_z_new, zeta_y_new, zeta_x_new,
             az, ay, ax, dt2, inv_dx, top, s, z, y, x)  # fmt: skip

    return dict(advance=advance, stretched=stretched, update=update, cell=cell, step=step)


def _cpu_rows(ns):
    """The CPU step's row kernels: step_rows (all but the core) and step_core_rows (the 2D core)."""
    dtype, R, A, fs, three, arr1, arr3, arr4 = ns.dtype, ns.R, ns.A, ns.fs, ns.three, ns.arr1, ns.arr3, ns.arr4
    Axis, vecw, d2z, d2w, flat, advance, update = ns.Axis, ns.vecw, ns.d2z, ns.d2w, ns.flat, ns.advance, ns.update

    @wp.func
    def row_cells(
        u: arr4, u_prev: arr4, u_next: arr4, v: arr3,
        psi_z: arr4, psi_y: arr4, psi_x: arr4,
        zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        zeta_z_new: arr4, zeta_y_new: arr4, zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int,
        s: int, z: int, y: int, x0: int, x1: int,
    ):  # fmt: skip
        # interior cells x0 <= x < x1 of row (s, z, y), with the stencil's values along x in a sliding window
        surface = False
        if wp.static(fs):
            surface = z == top
        w = vecw()
        for m in range(wp.static(2 * R + 1)):
            w[m] = u[s, z, y, x0 - wp.static(R) + m]
        for x in range(x0, x1):
            if surface:
                u_next[s, z, y, x] = dtype(0.0)
            else:
                update(u, u_prev, u_next, v, psi_z, psi_y, psi_x, zeta_z, zeta_y, zeta_x, zeta_z_new, zeta_y_new, zeta_x_new,
                       az, ay, ax, dt2, inv_dx, top, s, z, y, x, d2z(u, s, z, y, x, top), d2w(w), w[wp.static(R)])  # fmt: skip
            if x + 1 < x1:
                for m in range(wp.static(2 * R)):
                    w[m] = w[m + 1]
                w[wp.static(2 * R)] = u[s, z, y, x + wp.static(R + 1)]

    @unique_kernel(grid_stride=False)
    def step_rows(
        u: arr4, u_prev: arr4, u_next: arr4, v: arr3,
        psi_z: arr4, psi_y: arr4, psi_x: arr4,
        zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        zeta_z_new: arr4, zeta_y_new: arr4, zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis,
        dt2: dtype, inv_dx: dtype, top: int, first: int, core: wp.vec4i,
    ):  # fmt: skip
        # Forward-only step on the CPU: one thread per interior row (row `first` + zi), but for the core
        # columns [core[2], core[3]) of the core rows [core[0], core[1]) (padded indices), which
        # step_core_rows does (core[1] = core[0]: none).
        s, zi, yi = wp.tid()
        y = yi
        if wp.static(three):
            y = yi + wp.static(R)
        z = first + zi
        end = u.shape[3] - wp.static(R)
        x1 = end
        x2 = end
        if z >= core[0] and z < core[1]:
            x1 = core[2]
            x2 = core[3]
        row_cells(u, u_prev, u_next, v, psi_z, psi_y, psi_x, zeta_z, zeta_y, zeta_x, zeta_z_new, zeta_y_new, zeta_x_new,
                  az, ay, ax, dt2, inv_dx, top, s, z, y, wp.static(R), x1)  # fmt: skip
        row_cells(u, u_prev, u_next, v, psi_z, psi_y, psi_x, zeta_z, zeta_y, zeta_x, zeta_z_new, zeta_y_new, zeta_x_new,
                  az, ay, ax, dt2, inv_dx, top, s, z, y, x2, end)  # fmt: skip

    @wp.func
    def core_row(u: arr1, u_prev: arr1, u_next: arr1, v: arr1, i: int, c: int, n: int, lx: int, dt2: dtype, inv_dx2: dtype):
        # n core cells of a row from flat index i (c in v), in a loop that the compiler vectorises (a while
        # loop: Warp's range loops keep their step in a register pair that hides the induction variable)
        k = int(0)
        while k < n:
            uc = flat(u, i, k)
            dzz = dtype(wp.static(A[0])) * uc
            for m in range(wp.static(R)):
                dzz += dtype(wp.static(A[m + 1])) * (flat(u, i + (m + 1) * lx, k) + flat(u, i - (m + 1) * lx, k))
            dxx = dtype(wp.static(A[0])) * uc
            for m in range(wp.static(R)):
                dxx += dtype(wp.static(A[m + 1])) * (flat(u, i + m + 1, k) + flat(u, i - m - 1, k))
            u_next[wp.max(i, 0) + k] = advance(uc, flat(u_prev, i, k), flat(v, c, k), dt2, (dzz + dxx) * inv_dx2)
            k += 1

    @unique_kernel(grid_stride=False)
    def step_core_rows(u: arr1, u_prev: arr1, u_next: arr1, v: arr1, lz: int, lx: int, core: wp.vec4i, first: int, rows: int,
                       in_place: int, dt2: dtype, inv_dx: dtype):  # fmt: skip
        # 2D CPU step of the core columns [core[2], core[3]) of rows first..first + rows - 1 (padded, core rows)
        # of every shot, on flat arrays as step_core, one thread per row; same arithmetic as the reference
        # step. in_place: u_prev is u_next, read through u_next so that the compiler sees it (or else its
        # overlap check sends every row down the scalar path).
        t = wp.tid()
        s = t // rows
        c = (first + t - s * rows) * lx + core[2]
        i = s * lz * lx + c
        if in_place:
            core_row(u, u_next, u_next, v, i, c, core[3] - core[2], lx, dt2, inv_dx * inv_dx)
        else:
            core_row(u, u_prev, u_next, v, i, c, core[3] - core[2], lx, dt2, inv_dx * inv_dx)

    return dict(step_rows=step_rows, step_core_rows=step_core_rows)


def _flat_cells(ns):
    """The GPU step's cells addressed by flat offsets (flat_access; neighbours by strides): psi at a strip cell
    (psi_flat, and its 3D kernels) and the frame's cell (flat_cell), with the reference step's arithmetic."""
    dtype, R, fs, three, arr3, arr4, Axis, vecw = ns.dtype, ns.R, ns.fs, ns.three, ns.arr3, ns.arr4, ns.Axis, ns.vecw
    d2w, d1w, pair, cpml_term, stretched = ns.d2w, ns.d1w, ns.pair, ns.cpml_term, ns.stretched
    load3, load4, store4, _ = flat_access(dtype)

    @wp.func
    def line(a: arr4, o: int, d: int) -> vecw:
        # the 2R + 1 values of a centred on flat offset o along the axis of stride d
        w = vecw()
        for m in range(wp.static(2 * R + 1)):
            w[m] = load4(a, o + wp.static(m - R) * d)
        return w

    @wp.func
    def zline(u: arr4, o: int, n: int, z: int, top: int) -> vecw:
        # line along z (stride n) of the cell at offset o in row z; above a free surface (row top) the image, as `at`
        w = vecw()
        for m in range(wp.static(2 * R + 1)):
            if wp.static(fs):
                zm = z + wp.static(m - R)
                above = zm < top
                w[m] = wp.where(above, dtype(-1.0), dtype(1.0)) * load4(u, o + (wp.where(above, 2 * top - zm, zm) - z) * n)
            else:
                w[m] = load4(u, o + wp.static(m - R) * n)
        return w

    def make_psi_flat(axis: int):
        # psi along `axis` at flat cell q of its strip (S, Wz, Ly, Lx), (S, Lz, Wy, Lx) or (S, Lz, Ly, Wx), as psi_cell
        @wp.func
        def psi_flat(u: arr4, psi_old: arr4, psi_new: arr4, ax: Axis, inv_dx: dtype, q: int):
            ly, lx = u.shape[2], u.shape[3]
            if wp.static(axis == 0):
                n = ly * lx
                sj = q // n
                s = sj // psi_new.shape[1]
                p = ax.pos[sj - s * psi_new.shape[1]]
                o = (s * u.shape[1] + p) * n + q - sj * n
                d = n
            elif wp.static(axis == 1):
                r = q // lx
                sz = r // psi_new.shape[2]
                p = ax.pos[r - sz * psi_new.shape[2]]
                o = (sz * ly + p) * lx + q - r * lx
                d = lx
            else:
                r = q // psi_new.shape[3]
                p = ax.pos[q - r * psi_new.shape[3]]
                o = r * lx + p
                d = 1
            a = ax.a[p]
            val = dtype(0.0)
            if a != dtype(0.0):
                val = ax.b[p] * load4(psi_old, q) + a * d1w(line(u, o, d)) * inv_dx
            store4(psi_new, q, val)

        @unique_kernel(grid_stride=False, enable_backward=False)
        def psi_kernel(u: arr4, psi_old: arr4, psi_new: arr4, ax: Axis, inv_dx: dtype):
            psi_flat(u, psi_old, psi_new, ax, inv_dx, wp.tid())

        return psi_flat, psi_kernel

    (psi_flat_z, psi_z), (psi_flat_y, psi_y), (psi_flat_x, psi_x) = make_psi_flat(0), make_psi_flat(1), make_psi_flat(2)

    @wp.func
    def strip_term(t: dtype, j: int, p: int, psi: arr4, zeta: arr4, q: int, d: int, ca: Axis, inv_dx: dtype) -> pair:
        # stretch's CPML term at strip index j (flat offset q in psi and zeta, d: the axis' stride there), else 0
        if j >= 0:
            return cpml_term(t, d1w(line(psi, q, d)), load4(zeta, q), ca.a[p], ca.b[p], inv_dx)
        return pair(dtype(0.0), dtype(0.0))

    @wp.func
    def flat_cell(
        u: arr4, u_prev: arr4, u_next: arr4, v: arr3,
        psi_z: arr4, psi_y: arr4, psi_x: arr4,
        zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        zeta_z_new: arr4, zeta_y_new: arr4, zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int,
        s: int, z: int, y: int, x: int,
    ):  # fmt: skip
        # cell (the reference step's cell) with flat offsets: o of (s, z, y, x) in the fields, c in the model, qz, qy,
        # qx in the strips; every load before the first store
        lz, ly, lx = u.shape[1], u.shape[2], u.shape[3]
        n = ly * lx
        c = (z * ly + y) * lx + x
        o = s * lz * n + c
        if wp.static(fs):
            if z == top:
                store4(u_next, o, dtype(0.0))
                return
        inv_dx2 = inv_dx * inv_dx
        jz = az.store[z]
        jx = ax.store[x]
        wz = zline(u, o, n, z, top)
        dzz = d2w(wz)
        dxx = d2w(line(u, o, 1))
        qz = ((s * psi_z.shape[1] + jz) * ly + y) * lx + x
        qx = ((s * lz + z) * ly + y) * psi_x.shape[3] + jx
        jy = int(-1)
        qy = int(0)
        dyy = dtype(0.0)
        ty = pair()
        if wp.static(three):
            jy = ay.store[y]
            dyy = d2w(line(u, o, lx))
            qy = ((s * lz + z) * psi_y.shape[2] + jy) * lx + x
            ty = strip_term(dyy * inv_dx2, jy, y, psi_y, zeta_y, qy, lx, ay, inv_dx)
        tz = strip_term(dzz * inv_dx2, jz, z, psi_z, zeta_z, qz, n, az, inv_dx)
        tx = strip_term(dxx * inv_dx2, jx, x, psi_x, zeta_x, qx, 1, ax, inv_dx)
        un = stretched(wz[wp.static(R)], load4(u_prev, o), load3(v, c), dt2, inv_dx2, dzz, dxx, dyy, ty[0], tz[0], tx[0])
        if jy >= 0:
            store4(zeta_y_new, qy, ty[1])
        if jz >= 0:
            store4(zeta_z_new, qz, tz[1])
        if jx >= 0:
            store4(zeta_x_new, qx, tx[1])
        store4(u_next, o, un)

    return dict(psi_flat=(psi_z, psi_y, psi_x), psi_flat_z=psi_flat_z, psi_flat_x=psi_flat_x, flat_cell=flat_cell, line=line, zline=zline)


def _gpu_step(ns):
    """The GPU step's cell maps (frame_cell: the 2D frame's, strip_cell) and the 2D pre_step; its core and frame are
    _step_core's."""
    dtype, R, arr3, arr4, iarr1, Axis, record_point = ns.dtype, ns.R, ns.arr3, ns.arr4, ns.iarr1, ns.Axis, ns.record_point
    psi_flat_z, psi_flat_x = ns.psi_flat_z, ns.psi_flat_x

    frame_cell = frame_map(R)

    @wp.func
    def strip_cell(t: int, a: arr4) -> wp.vec3i:
        # (s, i, k) of the t-th cell of a 2D strip array a (S, I, 1, K)
        n = a.shape[1] * a.shape[3]
        s = t // n
        r = t - s * n
        i = r // a.shape[3]
        return wp.vec3i(s, i, r - i * a.shape[3])

    @unique_kernel(grid_stride=False, enable_backward=False)
    def pre_step(
        u: arr4, psi_z: arr4, psi_z_new: arr4, psi_x: arr4, psi_x_new: arr4, az: Axis, ax: Axis, inv_dx: dtype,
        z_cells: int, x_cells: int, data: arr3, idx: wp.array3d(dtype=wp.vec3i), w: arr3, n: int, clock: iarr1,
    ):  # fmt: skip
        # What a 2D GPU step does before step_core, in one launch: psi along z (the first z_cells threads) and x
        # (the next x_cells), then record_fixed's receiver points of u (idx: (S, n_rec, points))
        t = wp.tid()
        if t < z_cells:
            psi_flat_z(u, psi_z, psi_z_new, az, inv_dx, t)
        elif t < z_cells + x_cells:
            psi_flat_x(u, psi_x, psi_x_new, ax, inv_dx, t - z_cells)
        else:
            q = t - z_cells - x_cells
            per = idx.shape[1] * idx.shape[2]
            s = q // per
            rec = (q - s * per) // idx.shape[2]
            record_point(u, data, idx, w, n, clock, s, rec, q - s * per - rec * idx.shape[2])

    return dict(frame_cell=frame_cell, strip_cell=strip_cell, pre_step=pre_step)


def _tile(rows: int, cols: int, three: bool):
    """The tile of each thread of a core-layout launch (_core_tile, _adjoint_core), `rows` x `cols` cells."""
    @wp.func
    def tile(t: int, box: wp.vec4i, ybox: wp.vec2i, lz: int, ly: int, lx: int) -> wp.vec4i:
        # thread t's tile of `rows` rows x `cols` columns of the box rows [box[0], box[1]) x columns
        # [box[2], box[3]) (3D: of each y in [ybox[0], ybox[1]); 2D: ybox and ly unused) of every shot (a grid
        # (lz, [ly,] lx)): first row z, its number of columns, and the flat indices of its first cell in a
        # model (2D: z lx + x, 3D: (z ly + y) lx + x) and in the fields (shot s). Threads run along x, then y
        # (3D), then z.
        nxc = (box[3] - box[2] + wp.static(cols - 1)) // wp.static(cols)
        blocks = (box[1] - box[0] + wp.static(rows - 1)) // wp.static(rows)
        q = t // nxc
        x = box[2] + (t - q * nxc) * wp.static(cols)
        if wp.static(three):
            ny = ybox[1] - ybox[0]
            r = q // ny
            y = ybox[0] + q - r * ny
            s = r // blocks
            z = box[0] + (r - s * blocks) * wp.static(rows)
            c = (z * ly + y) * lx + x
            return wp.vec4i(z, wp.min(wp.static(cols), box[3] - x), c, s * lz * ly * lx + c)
        s = q // blocks
        z = box[0] + (q - s * blocks) * wp.static(rows)
        c = z * lx + x
        return wp.vec4i(z, wp.min(wp.static(cols), box[3] - x), c, s * lz * lx + c)

    return tile


@functools.lru_cache(maxsize=None)
def _lanes(ns, V: int):
    # Types and row reads of tiles of V adjacent columns held as V-vectors: the flat arrays are viewed as
    # arrays of vector(V) (the box's columns and the row length are multiples of V), so that a thread loads
    # and stores V cells at once. Returns (vector, its array, window (V, 2R + 1), line (V + 2R), sides, row, and
    # vector_access's load, put).
    dtype, R = ns.dtype, ns.R
    NB = -(-R // V)  # vectors each side that hold a row's R neighbours
    vec = wp.types.vector(length=V, dtype=dtype)
    arrv = wp.array(dtype=vec)
    win = wp.types.matrix(shape=(V, 2 * R + 1), dtype=dtype)
    line = wp.types.vector(length=V + 2 * R, dtype=dtype)
    load, put = vector_access(V, dtype)

    @wp.func
    def sides(a: arrv, i: int) -> line:
        # the R values left and right of vector i along its row, at r[0:R] and r[R + V:] (r[R:R + V] = 0)
        r = line()
        for b in range(wp.static(NB)):
            lo = load(a, i - wp.static(NB) + b)
            hi = load(a, i + 1 + b)
            for j in range(wp.static(V)):
                if wp.static((b - NB) * V + j + R >= 0):
                    r[wp.static((b - NB) * V + j + R)] = lo[j]
                if wp.static((b + 1) * V + j + R < V + 2 * R):
                    r[wp.static((b + 1) * V + j + R)] = hi[j]
        return r

    @wp.func
    def row(r: line, w: win) -> line:
        # r with its centre r[R:R + V] taken from the window's centre (the tile's own cells)
        out = line()
        for p in range(wp.static(V + 2 * R)):
            if wp.static(p >= R and p < R + V):
                out[p] = w[wp.static(p - R), wp.static(R)]
            else:
                out[p] = r[p]
        return out

    return vec, arrv, win, line, sides, row, load, put


@functools.lru_cache(maxsize=None)
def _core_tile(ns, rows: int, V: int):
    # GPU step of one tile of the core: rows [core[0], core[1]) x columns [core[2], core[3]) (3D: x ys
    # [ycore[0], ycore[1])) (padded indices), where there is neither CPML nor a free surface, on the flat arrays
    # viewed as V-vectors (_lanes; u: S * Lz * [Ly *] Lx / V, v: Lz * [Ly *] Lx / V). Thread t updates `rows`
    # consecutive rows of V adjacent columns, with the stencil's values along z in sliding windows, one load per
    # vector of a row along x and (3D) per neighbour along y; the loop over rows is unrolled.
    dtype, R, A, three, advance, d2w = ns.dtype, ns.R, ns.A, ns.three, ns.advance, ns.d2w
    vec, arrv, win, line, sides, row, load, put = _lanes(ns, V)
    tile = _tile(rows, V, three)

    @wp.func
    def core_tile(
        t: int, u: arrv, u_prev: arrv, u_next: arrv, v: arrv, lz: int, ly: int, lx: int, core: wp.vec4i, ycore: wp.vec2i, dt2: dtype,
        inv_dx: dtype,
    ):  # fmt: skip
        tl = tile(t, core, ycore, lz, ly, lx)
        z = tl[0]
        c = tl[2] // wp.static(V)
        i = tl[3] // wp.static(V)
        ny = lx // wp.static(V)  # y's stride (3D)
        n = ny
        if wp.static(three):
            n = ly * ny
        w = win()
        for m in range(wp.static(2 * R + 1)):
            a = load(u, i + (m - wp.static(R)) * n)
            for j in range(wp.static(V)):
                w[j, m] = a[j]
        inv_dx2 = inv_dx * inv_dx
        for k in range(wp.static(rows)):
            if z + k < core[1]:
                r = row(sides(u, i), w)
                up = load(u_prev, i)
                vv = load(v, c)
                out = vec()
                if wp.static(three):
                    # d2y as d2y does it, neighbour pair by pair
                    dyy = vec()
                    for j in range(wp.static(V)):
                        dyy[j] = dtype(wp.static(A[0])) * w[j, wp.static(R)]
                    for m in range(wp.static(R)):
                        hi = load(u, i + wp.static(m + 1) * ny)
                        lo = load(u, i - wp.static(m + 1) * ny)
                        for j in range(wp.static(V)):
                            dyy[j] += dtype(wp.static(A[m + 1])) * (hi[j] + lo[j])
                for j in range(wp.static(V)):
                    dxx = dtype(wp.static(A[0])) * w[j, wp.static(R)]
                    for m in range(wp.static(R)):
                        dxx += dtype(wp.static(A[m + 1])) * (r[j + wp.static(R + 1) + m] + r[j + wp.static(R - 1) - m])
                    lap = d2w(w[j]) + dxx
                    if wp.static(three):
                        lap = lap + dyy[j]
                    out[j] = advance(w[j, wp.static(R)], up[j], vv[j], dt2, lap * inv_dx2)
                put(u_next, i, out)
                if wp.static(k + 1 < rows):
                    a = load(u, i + wp.static(R + 1) * n)
                    for j in range(wp.static(V)):
                        for m in range(wp.static(2 * R)):
                            w[j, m] = w[j, m + 1]
                        w[j, wp.static(2 * R)] = a[j]
                i += n
                c += n

    return core_tile, arrv


@functools.lru_cache(maxsize=None)
def _frame_tile(ns, rows: int, cols: int):
    # GPU step of a tile of a 3D frame box (Acoustic._frame_boxes: interior cells outside the core), `rows` rows x up
    # to `cols` adjacent columns a thread in _tile's layout, each cell by flat_cell: a thread's index arithmetic (the
    # divisions of _tile) is shared by its cells
    dtype, arr3, arr4, Axis, flat_cell = ns.dtype, ns.arr3, ns.arr4, ns.Axis, ns.flat_cell
    tile = _tile(rows, cols, True)

    @wp.func
    def frame_tile(
        t: int, u: arr4, u_prev: arr4, u_next: arr4, v: arr3,
        psi_z: arr4, psi_y: arr4, psi_x: arr4,
        zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        zeta_z_new: arr4, zeta_y_new: arr4, zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int, box: wp.vec4i, ybox: wp.vec2i,
    ):  # fmt: skip
        lz, ly, lx = u.shape[1], u.shape[2], u.shape[3]
        tl = tile(t, box, ybox, lz, ly, lx)
        q = tl[2] // lx
        x0 = tl[2] - q * lx
        y = q - (q // ly) * ly
        s = tl[3] // (lz * ly * lx)
        for k in range(wp.static(rows)):
            z = tl[0] + k
            if z < box[1]:
                for j in range(wp.static(cols)):
                    if j < tl[1]:
                        flat_cell(u, u_prev, u_next, v, psi_z, psi_y, psi_x, zeta_z, zeta_y, zeta_x, zeta_z_new, zeta_y_new, zeta_x_new,
                                  az, ay, ax, dt2, inv_dx, top, s, z, y, x0 + j)  # fmt: skip

    return frame_tile


def _step_core(ns, rows: int, V: int, frame_rows: int, frame_cols: int):
    # The GPU step but psi in one 1D launch (unravelling a multi-dimensional thread index costs 64-bit
    # divisions): thread t + offset below `tiles` does a core tile (_core_tile; uf..vf: the flat arrays
    # as V-vectors), from `frame` (a block boundary, so that no warp mixes the two) the frame (the CPML strips
    # and the free-surface rows) by flat_cell: in 2D one interior cell outside the core (frame_cell), `cells` per
    # shot; in 3D a tile (_frame_tile) of the boxes `frames` (z0, z1, x0, x1) with frame_ys (y0, y1, the box's
    # first thread).
    dtype, three, arr3, arr4, Axis, flat_cell, frame_cell = ns.dtype, ns.three, ns.arr3, ns.arr4, ns.Axis, ns.flat_cell, ns.frame_cell
    core_tile, arrv = _core_tile(ns, rows, V)
    frame_tile = _frame_tile(ns, frame_rows, frame_cols)

    @unique_kernel(grid_stride=False, enable_backward=False)
    def step_core(
        u: arr4, u_prev: arr4, u_next: arr4, v: arr3,
        psi_z: arr4, psi_y: arr4, psi_x: arr4,
        zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        zeta_z_new: arr4, zeta_y_new: arr4, zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int,
        core: wp.vec4i, ycore: wp.vec2i, cells: int, frames: wp.array(dtype=wp.vec4i), frame_ys: wp.array(dtype=wp.vec3i),
        uf: arrv, uf_prev: arrv, uf_next: arrv, vf: arrv, tiles: int, frame: int, offset: int,
    ):  # fmt: skip
        t = wp.tid() + offset
        if t < frame:
            if t < tiles:
                core_tile(t, uf, uf_prev, uf_next, vf, u.shape[1], u.shape[2], u.shape[3], core, ycore, dt2, inv_dx)
        elif wp.static(three):
            f = t - frame
            b = int(0)
            for q in range(1, frames.shape[0]):
                if f >= frame_ys[q][2]:
                    b = q
            y = frame_ys[b]
            frame_tile(f - y[2], u, u_prev, u_next, v, psi_z, psi_y, psi_x, zeta_z, zeta_y, zeta_x, zeta_z_new, zeta_y_new, zeta_x_new,
                       az, ay, ax, dt2, inv_dx, top, frames[b], wp.vec2i(y[0], y[1]))  # fmt: skip
        else:
            s = (t - frame) // cells
            zx = frame_cell(t - frame - s * cells, u.shape[1], u.shape[3], core)
            flat_cell(u, u_prev, u_next, v, psi_z, psi_y, psi_x, zeta_z, zeta_y, zeta_x, zeta_z_new, zeta_y_new, zeta_x_new,
                      az, ay, ax, dt2, inv_dx, top, s, zx[0], 0, zx[1])  # fmt: skip

    return step_core


# --- Hand-written adjoints of psi_kernel and step, run by adseismic.gradient's backward sweep; they
# match Warp's generated adjoints (tests/test_gradient.py). The step's adjoint gathers: the Laplacian
# is symmetric, so the adjoint at a cell sums the weights of the cells whose stencils read it. Going
# back in time, the adjoint of u[n] = 2 lam[n+1] + (gathered terms) - adjoint of u[n+2] is written over
# the latter, an in-place time step like the forward one.
def _psi_adjoint(ns):
    """The adjoints of the psi kernels along each axis, and post_adjoint (a 2D adjoint step's last launch)."""
    dtype, arr3, arr4, iarr1, Axis, d1t = ns.dtype, ns.arr3, ns.arr4, ns.iarr1, ns.Axis, ns.d1t

    def make_psi_adjoint(axis: int):
        deriv_t = d1t[axis]

        @wp.func
        def psi_adjoint_cell(adj_u: arr4, adj_psi_old: arr4, adj_psi_new: arr4, adj_zeta_new: arr4, ax: Axis, inv_dx: dtype,
                             s: int, i: int, j: int, k: int):  # fmt: skip
            # consumes (and zeroes) the adjoints of psi[n+1] and zeta[n+1] at this strip cell: adds to those of
            # psi[n] and u[n]
            lam = adj_psi_new[s, i, j, k]
            adj_psi_new[s, i, j, k] = dtype(0.0)
            adj_zeta_new[s, i, j, k] = dtype(0.0)
            if wp.static(axis == 0):
                p = ax.pos[i]
            elif wp.static(axis == 1):
                p = ax.pos[j]
            else:
                p = ax.pos[k]
            a = ax.a[p]
            if a == dtype(0.0) or lam == dtype(0.0):
                return
            wp.atomic_add(adj_psi_old, s, i, j, k, ax.b[p] * lam)
            f = a * lam * inv_dx
            if wp.static(axis == 0):
                deriv_t(adj_u, s, p, j, k, f)
            elif wp.static(axis == 1):
                deriv_t(adj_u, s, i, p, k, f)
            else:
                deriv_t(adj_u, s, i, j, p, f)

        @unique_kernel(grid_stride=False)
        def psi_adjoint(adj_u: arr4, adj_psi_old: arr4, adj_psi_new: arr4, adj_zeta_new: arr4, ax: Axis, inv_dx: dtype):
            s, i, j, k = wp.tid()
            psi_adjoint_cell(adj_u, adj_psi_old, adj_psi_new, adj_zeta_new, ax, inv_dx, s, i, j, k)

        return psi_adjoint_cell, psi_adjoint

    psi_adjoints = [make_psi_adjoint(a) for a in range(3)]

    @unique_kernel(grid_stride=False, enable_backward=False)
    def post_adjoint(adj: arr4, residual: arr3, idx: wp.array3d(dtype=wp.vec3i), w: arr3, n: int, clock: iarr1):
        # What a 2D adjoint step does after adjoint_core: the adjoint of record_fixed, adj += the receiver points'
        # weights times residual[:, :, n + clock[0]] (a thread a point)
        q = wp.tid()
        per = idx.shape[1] * idx.shape[2]
        s = q // per
        rec = (q - s * per) // idx.shape[2]
        q = q - s * per - rec * idx.shape[2]
        wq = w[s, rec, q]
        if wq != dtype(0.0):
            i = idx[s, rec, q]
            wp.atomic_add(adj, s, i[0], i[1], i[2], wq * residual[s, rec, n + clock[0]])

    return dict(psi_adjoint=tuple(k for _, k in psi_adjoints), post_adjoint=post_adjoint)


def _adjoint_terms(ns):
    """The adjoint step's terms along each axis: the gathered stencil weights and the strips' adjoints."""
    dtype, R, A, fs, arr3, arr4, Axis, d1, d1t = ns.dtype, ns.R, ns.A, ns.fs, ns.arr3, ns.arr4, ns.Axis, ns.d1, ns.d1t

    @wp.func
    def weighted(q: dtype, a: dtype, adj_zn: dtype) -> dtype:
        # the weight of q = v^2 dt^2 lam of an updated cell in a strip (stretched = (1 + a) g + b zeta there)
        return q + a * (q + adj_zn)

    @wp.func
    def strip_total(g: dtype, zeta: dtype, a: dtype, b: dtype) -> dtype:
        # the stretched d2u/dx2 in a strip from g = d2u/dx2 + d(psi)/dx
        return g + b * zeta + a * g

    def make_gather(axis: int):
        @wp.func
        def weight(lam: arr4, v: arr3, adj_zn: arr4, ca: Axis, dt2: dtype, s: int, z: int, y: int, x: int) -> dtype:
            # adjoint of the stretched d2u/dx2 along `axis` at an updated cell, q = v^2 dt^2 lam (q + a (q +
            # adj zeta_new) in the strip, since stretched = (1 + a) g + b zeta there)
            vv = v[z, y, x]
            q = vv * vv * dt2 * lam[s, z, y, x]
            p = z
            if wp.static(axis == 1):
                p = y
            elif wp.static(axis == 2):
                p = x
            j = ca.store[p]
            if j >= 0:
                iz = z
                iy = y
                ix = x
                if wp.static(axis == 0):
                    iz = j
                elif wp.static(axis == 1):
                    iy = j
                else:
                    ix = j
                return weighted(q, ca.a[p], adj_zn[s, iz, iy, ix])
            return q

        @wp.func
        def gather(lam: arr4, v: arr3, adj_zn: arr4, ca: Axis, dt2: dtype, s: int, z: int, y: int, x: int, lo: int, hi: int, top: int) -> dtype:
            # sum of A_|d| weight(c - d) over the updated cells c - d (lo <= index < hi along `axis`) whose
            # stencil reads the cell c directly; along z with a free surface also the mirrored reads
            # (row 2 top - z + k reads the cell at offset -k when that lies above the surface, sign -)
            acc = dtype(0.0)
            for m in range(wp.static(2 * R + 1)):
                d = m - wp.static(R)
                iz = z
                iy = y
                ix = x
                if wp.static(axis == 0):
                    iz = z - d
                    p = iz
                elif wp.static(axis == 1):
                    iy = y - d
                    p = iy
                else:
                    ix = x - d
                    p = ix
                if p >= lo and p < hi:
                    acc += dtype(wp.static(A[abs(m - R)])) * weight(lam, v, adj_zn, ca, dt2, s, iz, iy, ix)
            if wp.static(fs and axis == 0):
                for k in range(1, wp.static(R + 1)):
                    zp = 2 * top - z + k
                    if z > top and k > z - top and zp < hi:
                        acc -= dtype(wp.static(A[k])) * weight(lam, v, adj_zn, ca, dt2, s, zp, y, x)
            return acc

        return gather

    gather_z, gather_y, gather_x = make_gather(0), make_gather(1), make_gather(2)

    def make_strip_adjoint(axis: int):
        # At an updated cell: the stretched d2u/dx2 along `axis` (recomputed, for the model gradient) and,
        # in the strip, the adjoints of zeta and psi (scattered: the strips are thin).
        dpsi = d1[axis]
        dpsi_t = d1t[axis]

        @wp.func
        def strip_adjoint(t: dtype, q: dtype, s: int, z: int, y: int, x: int, psi: arr4, zeta: arr4, adj_psi: arr4,
                          adj_zeta: arr4, adj_zeta_new: arr4, ca: Axis, inv_dx: dtype) -> dtype:  # fmt: skip
            p = z
            if wp.static(axis == 1):
                p = y
            elif wp.static(axis == 2):
                p = x
            j = ca.store[p]
            if j >= 0:
                iz = z
                iy = y
                ix = x
                if wp.static(axis == 0):
                    iz = j
                elif wp.static(axis == 1):
                    iy = j
                else:
                    ix = j
                g = t + dpsi(psi, s, iz, iy, ix) * inv_dx
                adj_zn = q + adj_zeta_new[s, iz, iy, ix]
                wp.atomic_add(adj_zeta, s, iz, iy, ix, ca.b[p] * adj_zn)
                dpsi_t(adj_psi, s, iz, iy, ix, (q + ca.a[p] * adj_zn) * inv_dx)
                return strip_total(g, zeta[s, iz, iy, ix], ca.a[p], ca.b[p])
            return t

        return strip_adjoint

    sadj_z, sadj_y, sadj_x = make_strip_adjoint(0), make_strip_adjoint(1), make_strip_adjoint(2)

    return dict(gather_z=gather_z, gather_y=gather_y, gather_x=gather_x, sadj_z=sadj_z, sadj_y=sadj_y, sadj_x=sadj_x, weighted=weighted,
                strip_total=strip_total)


def _adjoint_step(ns):
    """The adjoint step per cell (adjoint_cell) and its kernel over the interior (adjoint_step)."""
    dtype, R, fs, three, arr3, arr4, Axis, d2z = ns.dtype, ns.R, ns.fs, ns.three, ns.arr3, ns.arr4, ns.Axis, ns.d2z
    d2y, d2x, gather_z, gather_y, gather_x, sadj_z = ns.d2y, ns.d2x, ns.gather_z, ns.gather_y, ns.gather_x, ns.sadj_z
    sadj_y, sadj_x = ns.sadj_y, ns.sadj_x

    @wp.func
    def adjoint_cell(
        u: arr4, v: arr3, psi_z: arr4, psi_y: arr4, psi_x: arr4, zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        lam: arr4, adj: arr4, g: arr4, adj_out: arr4, g_out: arr4,
        adj_psi_z: arr4, adj_psi_y: arr4, adj_psi_x: arr4,
        adj_zeta_z: arr4, adj_zeta_y: arr4, adj_zeta_x: arr4,
        adj_zeta_z_new: arr4, adj_zeta_y_new: arr4, adj_zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int, s: int, z: int, y: int, x: int,
    ):  # fmt: skip
        # Adjoint of step n at interior cell (s, z, y, x). u: u[n]; psi: psi[n+1]; zeta: zeta[n];
        # lam: the adjoint of u[n+1]; adj: that of u[n+2]; adj_out gets that of u[n] (all but the psi and
        # receiver terms, which are added after); g_out = g + lam times the stretched Laplacian of u[n] (the
        # model gradient is 2 v dt^2 sum_n of it; not written on a free surface's row); the CPML variables'
        # adjoints are scattered (atomics: the strips are thin). adj_out and g_out may be adj and g (in place),
        # but separate arrays are faster on a GPU (a read and a write of one address cost more than two).
        lo_z = wp.static(R)
        if wp.static(fs):
            lo_z = top + 1  # the surface row is set to 0, not updated
        inv_dx2 = inv_dx * inv_dx
        acc = gather_z(lam, v, adj_zeta_z_new, az, dt2, s, z, y, x, lo_z, u.shape[1] - wp.static(R), top)
        acc += gather_x(lam, v, adj_zeta_x_new, ax, dt2, s, z, y, x, wp.static(R), u.shape[3] - wp.static(R), top)
        if wp.static(three):
            acc += gather_y(lam, v, adj_zeta_y_new, ay, dt2, s, z, y, x, wp.static(R), u.shape[2] - wp.static(R), top)
        acc = acc * inv_dx2
        if z >= lo_z:
            lc = lam[s, z, y, x]
            vv = v[z, y, x]
            q = vv * vv * dt2 * lc
            acc += dtype(2.0) * lc
            acc -= adj[s, z, y, x]
            total = sadj_z(d2z(u, s, z, y, x, top) * inv_dx2, q, s, z, y, x, psi_z, zeta_z, adj_psi_z, adj_zeta_z, adj_zeta_z_new, az, inv_dx)
            total += sadj_x(d2x(u, s, z, y, x, top) * inv_dx2, q, s, z, y, x, psi_x, zeta_x, adj_psi_x, adj_zeta_x, adj_zeta_x_new, ax, inv_dx)
            if wp.static(three):
                total += sadj_y(d2y(u, s, z, y, x, top) * inv_dx2, q, s, z, y, x, psi_y, zeta_y, adj_psi_y, adj_zeta_y, adj_zeta_y_new, ay, inv_dx)
            g_out[s, z, y, x] = g[s, z, y, x] + lc * total
        adj_out[s, z, y, x] = acc

    @unique_kernel(grid_stride=False)
    def adjoint_step(
        u: arr4, v: arr3, psi_z: arr4, psi_y: arr4, psi_x: arr4, zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        lam: arr4, adj: arr4, g: arr4, adj_out: arr4, g_out: arr4,
        adj_psi_z: arr4, adj_psi_y: arr4, adj_psi_x: arr4,
        adj_zeta_z: arr4, adj_zeta_y: arr4, adj_zeta_x: arr4,
        adj_zeta_z_new: arr4, adj_zeta_y_new: arr4, adj_zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        # adjoint_cell at every interior cell (3D, or 2D without a core; one thread per cell)
        s, zi, yi, xi = wp.tid()
        y = yi
        if wp.static(three):
            y = yi + wp.static(R)
        adjoint_cell(u, v, psi_z, psi_y, psi_x, zeta_z, zeta_y, zeta_x, lam, adj, g, adj_out, g_out, adj_psi_z, adj_psi_y, adj_psi_x,
                     adj_zeta_z, adj_zeta_y, adj_zeta_x, adj_zeta_z_new, adj_zeta_y_new, adj_zeta_x_new,
                     az, ay, ax, dt2, inv_dx, top, s, zi + wp.static(R), y, xi + wp.static(R))  # fmt: skip

    return dict(adjoint_cell=adjoint_cell, adjoint_step=adjoint_step)


def _flat_adjoint(ns):
    """adjoint_cell by flat offsets (flat_access): the 2D adjoint step's frame cells (_adjoint_core, CPU and GPU). Same terms in
    the same order as adjoint_cell (gather, weight, strip_adjoint), but the CPML strips' adjoints: gathered from
    _pre_adjoint's output where adjoint_cell scatters them with atomics."""
    dtype, R, A, fs, arr3, arr4, Axis = ns.dtype, ns.R, ns.A, ns.fs, ns.arr3, ns.arr4, ns.Axis
    d2w, d1w, line, zline, weighted, strip_total = ns.d2w, ns.d1w, ns.line, ns.zline, ns.weighted, ns.strip_total
    load3, load4, store4, _ = flat_access(dtype)

    @wp.func
    def weight(lam: arr4, v: arr3, adj_zn: arr4, ca: Axis, dt2: dtype, o: int, c: int, p: int, qb: int, qd: int) -> dtype:
        # weight of the updated cell at field offset o, model offset c, index p along the axis, strip offset qb + j qd
        vv = load3(v, c)
        q = vv * vv * dt2 * load4(lam, o)
        j = ca.store[p]
        if j >= 0:
            return weighted(q, ca.a[p], load4(adj_zn, qb + j * qd))
        return q

    def make_gather(axis: int):
        @wp.func
        def gather(lam: arr4, v: arr3, adj_zn: arr4, ca: Axis, dt2: dtype, o: int, c: int, p: int, d: int, qb: int, qd: int, lo: int, hi: int,
                   top: int) -> dtype:  # fmt: skip
            # gather along the axis of stride d (fields and model) from the cell at index p
            acc = dtype(0.0)
            for m in range(wp.static(2 * R + 1)):
                e = wp.static(m - R)
                if p - e >= lo and p - e < hi:
                    acc += dtype(wp.static(A[abs(m - R)])) * weight(lam, v, adj_zn, ca, dt2, o - e * d, c - e * d, p - e, qb, qd)
            if wp.static(fs and axis == 0):
                for k in range(1, wp.static(R + 1)):
                    zp = 2 * top - p + k
                    if p > top and k > p - top and zp < hi:
                        acc -= dtype(wp.static(A[k])) * weight(lam, v, adj_zn, ca, dt2, o + (zp - p) * d, c + (zp - p) * d, zp, qb, qd)
            return acc

        return gather

    gather_z, gather_x = make_gather(0), make_gather(2)

    @wp.func
    def strip_adjoint(t: dtype, p: int, psi: arr4, zeta: arr4, ca: Axis, inv_dx: dtype, qb: int, qd: int) -> dtype:
        # the stretched d2u/dx2 at index p along the axis from t = d2u/dx2 (the strips' adjoints are pre_adjoint's)
        j = ca.store[p]
        if j >= 0:
            k = qb + j * qd
            g = t + d1w(line(psi, k, qd)) * inv_dx
            return strip_total(g, load4(zeta, k), ca.a[p], ca.b[p])
        return t

    @wp.func
    def psi_term(f: arr4, ca: Axis, p: int, qb: int, qd: int) -> dtype:
        # the psi recursion's adjoint at index p along the axis: the transpose of d1 applied to f = a lam_psi / dx
        # (pre_adjoint's), gathered from the strip; 0 outside it (f is 0 but in the PML, which a strip holds with
        # R cells on either side)
        j = ca.store[p]
        if j >= 0:
            return -d1w(line(f, qb + j * qd, qd))
        return dtype(0.0)

    @wp.func
    def flat_adjoint_cell(
        u: arr4, v: arr3, psi_z: arr4, psi_y: arr4, psi_x: arr4, zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        lam: arr4, adj: arr4, g: arr4, adj_out: arr4, g_out: arr4,
        adj_psi_z: arr4, adj_psi_y: arr4, adj_psi_x: arr4,
        adj_zeta_z: arr4, adj_zeta_y: arr4, adj_zeta_x: arr4,
        adj_zeta_z_new: arr4, adj_zeta_y_new: arr4, adj_zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int, s: int, z: int, y: int, x: int,
    ):  # fmt: skip
        lz, ly, lx = u.shape[1], u.shape[2], u.shape[3]
        n = ly * lx
        c = (z * ly + y) * lx + x
        o = s * lz * n + c
        bz = (s * psi_z.shape[1] * ly + y) * lx + x  # strip offsets: base + j stride
        bx = ((s * lz + z) * ly + y) * psi_x.shape[3]
        lo_z = wp.static(R)
        if wp.static(fs):
            lo_z = top + 1
        inv_dx2 = inv_dx * inv_dx
        acc = gather_z(lam, v, adj_zeta_z_new, az, dt2, o, c, z, n, bz, n, lo_z, lz - wp.static(R), top)
        acc += gather_x(lam, v, adj_zeta_x_new, ax, dt2, o, c, x, 1, bx, 1, wp.static(R), lx - wp.static(R), top)
        acc = acc * inv_dx2
        acc += psi_term(adj_psi_z, az, z, bz, n) + psi_term(adj_psi_x, ax, x, bx, 1)
        if z >= lo_z:
            lc = load4(lam, o)
            acc += dtype(2.0) * lc
            acc -= load4(adj, o)
            total = strip_adjoint(d2w(zline(u, o, n, z, top)) * inv_dx2, z, psi_z, zeta_z, az, inv_dx, bz, n)
            total += strip_adjoint(d2w(line(u, o, 1)) * inv_dx2, x, psi_x, zeta_x, ax, inv_dx, bx, 1)
            store4(g_out, o, load4(g, o) + lc * total)
        store4(adj_out, o, acc)

    return dict(flat_adjoint_cell=flat_adjoint_cell, flat_weight=weight)


def _pre_adjoint(ns):
    """pre_adjoint, a 2D adjoint step's first launch (CPU and GPU): the CPML strips' adjoints, each strip cell gathering
    what adjoint_cell's strip terms scatter with atomics. Gathering them took the 2D GPU adjoint step from 119 to 103 us
    on S600x16 (docs/benchmarks.md) and leaves only the receivers' atomics."""
    dtype, R, B, fs, arr3, arr4, Axis = ns.dtype, ns.R, ns.B, ns.fs, ns.arr3, ns.arr4, ns.Axis
    strip_cell, weight = ns.strip_cell, ns.flat_weight
    load3, load4, store4, _ = flat_access(dtype)

    @wp.func
    def strip_cell_adjoint(lam: arr4, v: arr3, adj_psi_new: arr4, adj_psi: arr4, adj_zeta_new: arr4, adj_zeta: arr4, ca: Axis, dt2: dtype,
                           inv_dx: dtype, o: int, c: int, p: int, d: int, k: int, qd: int, lo: int, hi: int, inside: bool):  # fmt: skip
        # pre_adjoint at strip cell k: index p along the axis of stride d in the fields and the model and qd in the
        # strip, the field cell at o, the model's at c; `inside`: its other index is interior. It gathers what
        # adjoint_cell's strip terms scattered: the adjoint of psi[n+1],
        #   lam_psi = adj_psi_new (the b lam_psi of the step after) + sum_m B_m (gp(k - m - 1) - gp(k + m + 1)),
        # gp = (q + a adj_zn) / dx of an updated cell (lo <= index < hi), q = v^2 dt^2 lam, adj_zn = q + adj_zeta_new;
        # then stores adj_psi = b lam_psi (that of psi[n]), adj_psi_new = f = a lam_psi / dx (psi_term's input) and
        # adj_zeta = b adj_zn (that of zeta[n]), each 0 where it is (outside the PML, or not updated)
        a = ca.a[p]
        lp = load4(adj_psi_new, k)
        qb = k - ca.store[p] * qd  # the strip's base offset: a strip cell's neighbours in the PML are strip cells
        if a != dtype(0.0) and inside:
            for m in range(wp.static(R)):
                e = wp.static(m + 1)
                if p - e >= lo and p - e < hi:
                    lp += dtype(wp.static(B[m])) * (weight(lam, v, adj_zeta_new, ca, dt2, o - e * d, c - e * d, p - e, qb, qd) * inv_dx)
                if p + e >= lo and p + e < hi:
                    lp -= dtype(wp.static(B[m])) * (weight(lam, v, adj_zeta_new, ca, dt2, o + e * d, c + e * d, p + e, qb, qd) * inv_dx)
        zn = dtype(0.0)
        if inside and p >= lo and p < hi and ca.store[p] >= 0:
            vv = load3(v, c)
            zn = ca.b[p] * (vv * vv * dt2 * load4(lam, o) + load4(adj_zeta_new, k))
        if a == dtype(0.0):
            lp = dtype(0.0)
        store4(adj_psi, k, ca.b[p] * lp)
        store4(adj_psi_new, k, a * lp * inv_dx)
        store4(adj_zeta, k, zn)

    @unique_kernel(grid_stride=False, enable_backward=False)
    def pre_adjoint(
        lam: arr4, v: arr3, adj_psi_z_new: arr4, adj_psi_z: arr4, adj_zeta_z_new: arr4, adj_zeta_z: arr4,
        adj_psi_x_new: arr4, adj_psi_x: arr4, adj_zeta_x_new: arr4, adj_zeta_x: arr4,
        az: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int, z_cells: int, x_cells: int,
    ):  # fmt: skip
        # What a 2D adjoint step does before adjoint_core, in one launch: strip_cell_adjoint along z (the first
        # z_cells threads) and x (the next x_cells). Gathers, no atomics: each strip cell is written by its own thread,
        # adj_psi_*_new after that thread read it (never taped: the hand-written adjoint is not differentiated)
        t = wp.tid()
        lz, lx = lam.shape[1], lam.shape[3]
        lo_z = wp.static(R)
        if wp.static(fs):
            lo_z = top + 1
        if t < z_cells:
            sc = strip_cell(t, adj_psi_z)
            p = az.pos[sc[1]]
            c = p * lx + sc[2]
            inside = sc[2] >= wp.static(R) and sc[2] < lx - wp.static(R)
            strip_cell_adjoint(lam, v, adj_psi_z_new, adj_psi_z, adj_zeta_z_new, adj_zeta_z, az, dt2, inv_dx, sc[0] * lz * lx + c, c, p,
                               lx, t, lx, lo_z, lz - wp.static(R), inside)  # fmt: skip
        elif t < z_cells + x_cells:
            sc = strip_cell(t - z_cells, adj_psi_x)
            p = ax.pos[sc[2]]
            c = sc[1] * lx + p
            inside = sc[1] >= lo_z and sc[1] < lz - wp.static(R)
            strip_cell_adjoint(lam, v, adj_psi_x_new, adj_psi_x, adj_zeta_x_new, adj_zeta_x, ax, dt2, inv_dx, sc[0] * lz * lx + c, c, p, 1,
                               t - z_cells, 1, wp.static(R), lx - wp.static(R), inside)  # fmt: skip

    return dict(pre_adjoint=pre_adjoint)


def _adjoint_core(ns, rows: int, V: int):
    # The 2D adjoint step in one 1D launch, laid out as step_core: thread t + offset below `tiles` does a
    # tile of adjoint_cell on the flat arrays as V-vectors (_lanes; u, lam, adj, g: S * Lz * Lx / V; w =
    # v^2 dt^2: Lz * Lx / V) inside `box`, the cells whose stencil neighbours all lie in step_core's core (no
    # CPML, no surface image), with windows of q = w lam (gathered) and of u (the model gradient's
    # Laplacian); from `frame` (a block boundary) one interior cell outside `box` (frame_cell), `cells` per
    # shot, by flat_adjoint_cell.
    dtype, R, A, arr3, arr4, Axis, d2w = ns.dtype, ns.R, ns.A, ns.arr3, ns.arr4, ns.Axis, ns.d2w
    frame_cell, flat_adjoint_cell = ns.frame_cell, ns.flat_adjoint_cell
    vec, arrv, win, line, sides, row, load, put = _lanes(ns, V)
    tile = _tile(rows, V, False)

    @wp.func
    def adjoint_tile(t: int, u: arrv, lam: arrv, adj: arrv, g: arrv, adj_out: arrv, g_out: arrv, w: arrv, lz: int, lx: int, box: wp.vec4i, inv_dx: dtype):
        tl = tile(t, box, wp.vec2i(0, 1), lz, 1, lx)
        z = tl[0]
        c = tl[2] // wp.static(V)
        i = tl[3] // wp.static(V)
        n = lx // wp.static(V)
        wq = win()
        wu = win()
        for m in range(wp.static(2 * R + 1)):
            o = (m - wp.static(R)) * n
            a = wp.cw_mul(load(w, c + o), load(lam, i + o))
            b = load(u, i + o)
            for j in range(wp.static(V)):
                wq[j, m] = a[j]
                wu[j, m] = b[j]
        inv_dx2 = inv_dx * inv_dx
        for k in range(wp.static(rows)):
            if z + k < box[1]:
                rq = row(wp.cw_mul(sides(w, c), sides(lam, i)), wq)
                ru = row(sides(u, i), wu)
                lc = load(lam, i)
                ad = load(adj, i)
                gi = load(g, i)
                ao = vec()
                go = vec()
                for j in range(wp.static(V)):
                    # the order of gather_z + gather_x (from the far neighbour to the near one)
                    acz = dtype(0.0)
                    acx = dtype(0.0)
                    for m in range(wp.static(2 * R + 1)):
                        acz += dtype(wp.static(A[abs(m - R)])) * wq[j, wp.static(2 * R) - m]
                    for m in range(wp.static(2 * R + 1)):
                        acx += dtype(wp.static(A[abs(m - R)])) * rq[j + wp.static(2 * R) - m]
                    acc = (acz + acx) * inv_dx2
                    acc += dtype(2.0) * lc[j]
                    acc -= ad[j]
                    ao[j] = acc
                    dxx = dtype(wp.static(A[0])) * ru[j + wp.static(R)]
                    for m in range(wp.static(R)):
                        dxx += dtype(wp.static(A[m + 1])) * (ru[j + wp.static(R + 1) + m] + ru[j + wp.static(R - 1) - m])
                    go[j] = gi[j] + lc[j] * (d2w(wu[j]) * inv_dx2 + dxx * inv_dx2)
                put(adj_out, i, ao)
                put(g_out, i, go)
                if wp.static(k + 1 < rows):
                    o = wp.static(R + 1) * n
                    a = wp.cw_mul(load(w, c + o), load(lam, i + o))
                    b = load(u, i + o)
                    for j in range(wp.static(V)):
                        for m in range(wp.static(2 * R)):
                            wq[j, m] = wq[j, m + 1]
                            wu[j, m] = wu[j, m + 1]
                        wq[j, wp.static(2 * R)] = a[j]
                        wu[j, wp.static(2 * R)] = b[j]
                i += n
                c += n

    @unique_kernel(grid_stride=False, enable_backward=False)
    def adjoint_core(
        u: arr4, v: arr3, psi_z: arr4, psi_y: arr4, psi_x: arr4, zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        lam: arr4, adj: arr4, g: arr4, adj_out: arr4, g_out: arr4,
        adj_psi_z: arr4, adj_psi_y: arr4, adj_psi_x: arr4,
        adj_zeta_z: arr4, adj_zeta_y: arr4, adj_zeta_x: arr4,
        adj_zeta_z_new: arr4, adj_zeta_y_new: arr4, adj_zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int, box: wp.vec4i, cells: int,
        uf: arrv, lamf: arrv, adjf: arrv, gf: arrv, adjf_out: arrv, gf_out: arrv, wf: arrv, tiles: int, frame: int, offset: int,
    ):  # fmt: skip
        t = wp.tid() + offset
        if t < frame:
            if t < tiles:
                adjoint_tile(t, uf, lamf, adjf, gf, adjf_out, gf_out, wf, u.shape[1], u.shape[3], box, inv_dx)
        else:
            s = (t - frame) // cells
            zx = frame_cell(t - frame - s * cells, u.shape[1], u.shape[3], box)
            flat_adjoint_cell(u, v, psi_z, psi_y, psi_x, zeta_z, zeta_y, zeta_x, lam, adj, g, adj_out, g_out, adj_psi_z, adj_psi_y, adj_psi_x,
                              adj_zeta_z, adj_zeta_y, adj_zeta_x, adj_zeta_z_new, adj_zeta_y_new, adj_zeta_x_new,
                              az, ay, ax, dt2, inv_dx, top, s, zx[0], 0, zx[1])  # fmt: skip

    return adjoint_core


def _points(ns):
    """Sources and receivers: the operator's points (Hicks), inject and record at locations or at precomputed
    points (weights, compact), and record_point (a receiver point of pre_step)."""
    dtype, ndim, HR, W, NPTS, fs, three, arr3 = ns.dtype, ns.ndim, ns.HR, ns.W, ns.NPTS, ns.fs, ns.three, ns.arr3
    arr4, iarr1 = ns.arr4, ns.iarr1

    @wp.func
    def record_point(u: arr4, data: arr3, idx: wp.array3d(dtype=wp.vec3i), w: arr3, n: int, clock: iarr1, s: int, rec: int, q: int):
        wq = w[s, rec, q]
        if wq != dtype(0.0):
            i = idx[s, rec, q]
            wp.atomic_add(data, s, rec, n + clock[0], wq * u[s, i[0], i[1], i[2]])

    hicks = hicks_axis(dtype)

    @wp.func
    def point(loc: arr3, s: int, n: int, q: int, origin: wp.vec3i, inv_dx: dtype, top: int):
        # q-th stencil node of the operator at loc[s, n] (metres, (z, y, x)): padded index and weight.
        zc = loc[s, n, 0] * inv_dx + dtype(origin[0])
        xc = loc[s, n, 2] * inv_dx + dtype(origin[2])
        qz = q // wp.static(W ** (ndim - 1))
        qx = q % wp.static(W)
        iz = int(wp.floor(zc)) - wp.static(HR - 1) + qz
        ix = int(wp.floor(xc)) - wp.static(HR - 1) + qx
        w = hicks(dtype(iz) - zc, zc) * hicks(dtype(ix) - xc, xc)
        iy = int(0)
        if wp.static(three):
            yc = loc[s, n, 1] * inv_dx + dtype(origin[1])
            iy = int(wp.floor(yc)) - wp.static(HR - 1) + (q // wp.static(W)) % wp.static(W)
            w = w * hicks(dtype(iy) - yc, yc)
        if wp.static(fs):
            if iz == top:
                w = dtype(0.0)
            elif iz < top:
                iz = 2 * top - iz
                w = -w
        return wp.vec3i(iz, iy, ix), w

    @unique_kernel
    def inject(
        u_next: arr4, v: arr3, amp: arr3, loc: arr3, n: int, clock: iarr1,
        origin: wp.vec3i, scale: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        # u_next += v^2 dt^2 s[n] w / dx^ndim at the operator's nodes (scale = dt^2 / dx^ndim); here and
        # in the other source/receiver kernels the sample is n + clock[0] (a device counter, for graphs).
        # Every point adds, also one of weight 0 (at a whole distance from a location on a node): its weight's
        # derivative in the location is not 0.
        s, src, q = wp.tid()
        idx, w = point(loc, s, src, q, origin, inv_dx, top)
        vv = v[idx[0], idx[1], idx[2]]
        wp.atomic_add(u_next, s, idx[0], idx[1], idx[2], scale * vv * vv * w * amp[s, src, n + clock[0]])

    @unique_kernel
    def record(u: arr4, data: arr3, loc: arr3, n: int, clock: iarr1, origin: wp.vec3i, inv_dx: dtype, top: int):
        s, rec, q = wp.tid()
        idx, w = point(loc, s, rec, q, origin, inv_dx, top)
        wp.atomic_add(data, s, rec, n + clock[0], w * u[s, idx[0], idx[1], idx[2]])

    # Precomputed operator (positions that are not differentiated, e.g. receivers): the node index and
    # weight of every stencil point, computed once per run instead of at every time step.
    @unique_kernel
    def weights(loc: arr3, origin: wp.vec3i, inv_dx: dtype, top: int, idx: wp.array3d(dtype=wp.vec3i), w: arr3):
        s, n, q = wp.tid()
        i, wq = point(loc, s, n, q, origin, inv_dx, top)
        idx[s, n, q] = i
        w[s, n, q] = wq

    @unique_kernel(enable_backward=False)
    def compact(idx: wp.array3d(dtype=wp.vec3i), w: arr3, most: iarr1):
        # moves the points of operator (s, n) with a non-zero weight to its front, in order, zeroing the rest's
        # weights; most[0] = the largest count
        s, n = wp.tid()
        c = int(0)
        for q in range(idx.shape[2]):
            wq = w[s, n, q]
            if wq != dtype(0.0):
                idx[s, n, c] = idx[s, n, q]
                w[s, n, c] = wq
                c += 1
        for q in range(c, idx.shape[2]):
            w[s, n, q] = dtype(0.0)
        wp.atomic_max(most, 0, c)

    @unique_kernel
    def inject_fixed(u_next: arr4, v: arr3, amp: arr3, idx: wp.array3d(dtype=wp.vec3i), w: arr3, n: int, clock: iarr1, scale: dtype):
        s, src, q = wp.tid()
        wq = w[s, src, q]
        if wq != dtype(0.0):
            i = idx[s, src, q]
            vv = v[i[0], i[1], i[2]]
            wp.atomic_add(u_next, s, i[0], i[1], i[2], scale * vv * vv * wq * amp[s, src, n + clock[0]])

    def make_record_fixed(per: int):
        # thread (s, rec, g) adds the points g * per ... (g + 1) * per - 1, summed in order (unrolled, so that
        # Warp differentiates it), with one atomic: per = 1 on a GPU, all points on the CPU (record_summed:
        # one thread per receiver, threads costing more there than the sum)
        @unique_kernel
        def record_fixed(u: arr4, data: arr3, idx: wp.array3d(dtype=wp.vec3i), w: arr3, n: int, clock: iarr1):
            s, rec, g = wp.tid()
            acc = dtype(0.0)
            for k in range(wp.static(per)):
                q = g * wp.static(per) + k
                wq = w[s, rec, q]
                if wq != dtype(0.0):
                    i = idx[s, rec, q]
                    acc += wq * u[s, i[0], i[1], i[2]]
            wp.atomic_add(data, s, rec, n + clock[0], acc)

        return record_fixed

    return dict(record_point=record_point, inject=inject, record=record, weights=weights, compact=compact, inject_fixed=inject_fixed,
                record_fixed=make_record_fixed(1), record_summed=make_record_fixed(NPTS))  # fmt: skip


def _model_ops(ns):
    """Kernels on the model and the fields outside the time step: padding, Born scattering, illumination, v^2 dt^2 and
    the model gradient."""
    dtype, R, three, arr3, arr4, iarr1 = ns.dtype, ns.R, ns.three, ns.arr3, ns.arr4, ns.iarr1

    @unique_kernel
    def pad_model(v: arr3, vpad: arr3, origin: wp.vec3i):
        # Padded model from the physical one, extended by edge replication into PML and halo.
        z, y, x = wp.tid()
        iz = wp.clamp(z - origin[0], 0, v.shape[0] - 1)
        iy = wp.clamp(y - origin[1], 0, v.shape[1] - 1)
        ix = wp.clamp(x - origin[2], 0, v.shape[2] - 1)
        vpad[z, y, x] = v[iz, iy, ix]

    @unique_kernel
    def scatter(du_next: arr4, u_next: arr4, u: arr4, u_prev: arr4, v: arr3, dv: arr3):
        # Born secondary source: d(u[n+1])/dv . dv = 2 dv / v (u[n+1] - 2 u[n] + u[n-1]), since every
        # increment of the scheme (update and injection) is proportional to v^2 at its node.
        s, zi, yi, xi = wp.tid()
        z = zi + wp.static(R)
        x = xi + wp.static(R)
        y = yi
        if wp.static(three):
            y = yi + wp.static(R)
        inc = u_next[s, z, y, x] - dtype(2.0) * u[s, z, y, x] + u_prev[s, z, y, x]
        du_next[s, z, y, x] = du_next[s, z, y, x] + dtype(2.0) * dv[z, y, x] / v[z, y, x] * inc

    @unique_kernel
    def energy(u: arr4, e: arr3, n: int, clock: iarr1, levels: int):
        # e += sum over shots of u^2 (illumination, for the pseudo-Hessian preconditioner) at level
        # n + clock[0] if it is below `levels`
        s, z, y, x = wp.tid()
        if n + clock[0] < levels:
            val = u[s, z, y, x]
            wp.atomic_add(e, z, y, x, val * val)

    @unique_kernel
    def squared(v: arr3, dt2: dtype, w: arr3):
        # w = v^2 dt^2, the factor of the Laplacian in the update (read by adjoint_core)
        z, y, x = wp.tid()
        vv = v[z, y, x]
        w[z, y, x] = vv * vv * dt2

    @unique_kernel
    def model_gradient(v: arr3, g: arr4, dt2: dtype, grad: arr3):
        # grad += 2 v dt^2 sum over shots of g (g: the sums of adjoint_cell)
        z, y, x = wp.tid()
        acc = dtype(0.0)
        for s in range(g.shape[0]):
            acc += g[s, z, y, x]
        grad[z, y, x] = grad[z, y, x] + dtype(2.0) * v[z, y, x] * dt2 * acc

    return dict(pad_model=pad_model, scatter=scatter, energy=energy, squared=squared, model_gradient=model_gradient)


def _strip_layout(n_lo: int, n_hi: int, length: int, halo: int):
    """Strip storage of psi/zeta along one axis of padded length `length`.

    Each absorbing side stores [halo][PML][halo cells where d(psi)/dx is non-zero][halo zero cells],
    mirrored on the high side; the zero cells let d(psi)/dx read its neighbours without bounds checks.
    Returns (store, pos): store[p] = strip index of padded index p where the step needs psi/zeta (else
    -1); pos[j] = padded index of strip cell j.
    """
    store = -np.ones(length, dtype=np.int32)
    pos = []
    if n_lo > 0:
        region = list(range(0, 3 * halo + n_lo))
        store[: 2 * halo + n_lo] = region[: 2 * halo + n_lo]
        pos += region
    if n_hi > 0:
        region = list(range(length - 3 * halo - n_hi, length))
        base = len(pos)
        for j, p in enumerate(region):
            if j >= halo:
                store[p] = base + j
        pos += region
    return store, np.asarray(pos or [0], dtype=np.int32)


def cpml_profile(n_lo: int, n_hi: int, length: int, halo: int, dx: float, dt: float, vmax: float,
                 reflection: float, frequency: float):  # fmt: skip
    """CPML recursion coefficients (a, b) per padded index (Komatitsch & Martin 2007, kappa = 1).

    d(x) = d0 (x/L)^2 with d0 = 3 vmax ln(1/reflection) / (2 L); alpha(x) = pi f (1 - x/L); x is the
    distance into the layer of thickness L = width dx.
    """
    a = np.zeros(length)
    b = np.ones(length)
    for width, cells in ((n_lo, [(p, halo + n_lo - p) for p in range(halo, halo + n_lo)]),
                         (n_hi, [(p, p - (length - halo - n_hi) + 1) for p in range(length - halo - n_hi, length - halo)])):  # fmt: skip
        if width == 0:
            continue
        thick = width * dx
        d0 = 3.0 * vmax * np.log(1.0 / reflection) / (2.0 * thick)
        for p, depth in cells:
            frac = depth * dx / thick
            d = d0 * frac**2
            alpha = np.pi * frequency * (1.0 - frac)
            b[p] = np.exp(-(d + alpha) * dt)
            a[p] = d * (b[p] - 1.0) / (d + alpha) if d + alpha > 0 else 0.0
    return a, b


class State:
    """Wavefields at one time level n: u_prev = u[n-1], u = u[n], psi[n-1], zeta[n-1] (z, y, x)."""

    def __init__(self, u_prev, u, psi, zeta):
        self.u_prev, self.u, self.psi, self.zeta = u_prev, u, psi, zeta

    def arrays(self):
        return [a for a in (self.u_prev, self.u, *self.psi, *self.zeta) if a is not None]


class Acoustic:
    """Launch helper: padded grid, CPML coefficients and one time step of the acoustic scheme.

    shape: physical grid (nz, nx) or (nz, ny, nx) cells; dx (m) and dt (s); pml_width cells on every
    absorbing side (up to 3 more at the far end of x, where they make the padded width a multiple of 4);
    positions passed to inject/record are metres from the physical grid's node 0.
    """

    def __init__(self, shape, dx, dt, order, n_shots, pml_width, pml_reflection, pml_frequency, vmax,
                 free_surface=False, dtype=wp.float32, device="cpu"):  # fmt: skip
        self.ndim = len(shape)
        self.shape = tuple(int(n) for n in shape)
        self.dx, self.dt, self.order, self.n_shots = float(dx), float(dt), int(order), int(n_shots)
        self.dtype, self.device = dtype, device
        self.k = build(self.ndim, self.order, dtype, bool(free_surface))
        R = self.k.halo
        shape3 = (self.shape[0], self.shape[1] if self.ndim == 3 else 1, self.shape[-1])
        nb = int(pml_width)
        lo = [0 if free_surface else nb, nb if self.ndim == 3 else 0, nb]
        hi = [nb, nb if self.ndim == 3 else 0, nb]
        halo = [R, R if self.ndim == 3 else 0, R]
        if nb:  # padded x a multiple of 4, the GPU tiles' widest vectors (lanes): up to 3 more CPML cells on the far side
            hi[2] += -(shape3[2] + lo[2] + hi[2] + 2 * halo[2]) % 4
        self.padded = tuple(shape3[a] + lo[a] + hi[a] + 2 * halo[a] for a in range(3))
        self.origin = wp.vec3i(*(halo[a] + lo[a] for a in range(3)))
        self.top = R
        self.axes, self.strip_width = [], []
        for a in range(3):
            L = self.padded[a]
            store, pos = _strip_layout(lo[a], hi[a], L, halo[a])
            ca, cb = cpml_profile(lo[a], hi[a], L, halo[a], dx, dt, vmax, pml_reflection, pml_frequency)
            axis = self.k.Axis()
            axis.a = wp.array(ca, dtype=dtype, device=device)
            axis.b = wp.array(cb, dtype=dtype, device=device)
            axis.store = wp.array(store, dtype=wp.int32, device=device)
            axis.pos = wp.array(pos, dtype=wp.int32, device=device)
            self.axes.append(axis)
            self.strip_width.append(len(pos) if lo[a] + hi[a] > 0 else 0)
        # GPU step: the core (padded rows core[0]:core[1], columns core[2]:core[3], 3D: ys ycore[0]:ycore[1]) needs
        # neither CPML nor the free surface's image; the frame of interior cells around it does
        band = [[R + n if n else 0 for n in (lo[a], hi[a])] for a in range(3)]
        if free_surface:
            band[0][0] = R  # the surface row and the rows whose stencil reaches above it
        # the core's columns start and end at multiples of `lanes`, which the vector width of its tiles divides
        self.lanes = next(V for V in (4, 2, 1) if self.padded[2] % V == 0)
        self.core = aligned(R + band[0][0], self.padded[0] - R - band[0][1], R + band[2][0], self.padded[2] - R - band[2][1], self.lanes)
        self.ycore = wp.vec2i(R + band[1][0], self.padded[1] - R - band[1][1]) if self.ndim == 3 else wp.vec2i(0, 1)
        self.interior = (self.n_shots, self.padded[0] - 2 * R, self.padded[1] - 2 * halo[1], self.padded[2] - 2 * R)
        extents = (self.core[1] - self.core[0], self.ycore[1] - self.ycore[0], self.core[3] - self.core[2])
        self.frame_cells = math.prod(self.interior[1:]) - math.prod(max(e, 0) for e in extents)
        fits = min(extents) > 0 and self.n_shots * math.prod(self.padded) < 2**31  # int32 indices
        self.has_core = self.ndim == 2 and fits  # the 2D core: GPU step and adjoint, CPU rows
        # the adjoint's core: the cells whose stencil neighbours are all core cells (else an empty box)
        c = self.core
        inner = aligned(c[0] + R, c[1] - R, c[2] + R, c[3] - R, self.lanes)
        self.adjoint_box = inner if self.has_core and inner[1] > inner[0] and inner[3] > inner[2] else wp.vec4i(R, R, R, R)
        box = self.adjoint_box
        self.adjoint_frame_cells = (self.padded[0] - 2 * R) * (self.padded[2] - 2 * R) - (box[1] - box[0]) * (box[3] - box[2])
        self.core_frame = fits and wp.get_device(device).is_cuda  # the GPU step: psi, core and frame kernels
        self.inv_dx = dtype(1.0 / dx)
        self.dt2 = dtype(dt * dt)
        self.src_scale = dtype(dt * dt / dx**self.ndim)
        self.cuda = wp.get_device(device).is_cuda
        rows, cols = (GPU_CORE3_ROWS, GPU_CORE3_COLS) if self.ndim == 3 else (GPU_CORE_ROWS, GPU_CORE_COLS)
        self.core_rows, self.core_cols, self.core_threads = rows, min(cols, self.lanes), GPU_CORE_THREADS
        self.frame_rows, self.frame_cols = (GPU_FRAME3_ROWS, GPU_FRAME3_COLS) if self.ndim == 3 else (1, 1)
        # _frame_boxes per 3D frame layout, the default's made here: made at a first step inside a graph capture,
        # the arrays' upload would be captured from host buffers freed after it (replays read garbage boxes)
        self._frames = {(self.frame_rows, self.frame_cols): self._frame_boxes(self.frame_rows, self.frame_cols)}
        self.threads = 1 if self.cuda else max(1, min(CPU_THREADS, os.cpu_count() or 1, self.interior[1]))
        self._pool = None
        self._launches = {}  # recorded CPU step launches per set of arrays (_cpu_step)
        self.clock = wp.zeros(1, dtype=wp.int32, device=device)  # stays 0: plain launches pass n itself
        # (data, idx, w) standing in for a record/residual of no points in the fused launches
        self._no_points = (wp.zeros((1, 1, 1), dtype=dtype, device=device), wp.zeros((1, 1, 1), dtype=wp.vec3i, device=device),
                           wp.zeros((1, 1, 1), dtype=dtype, device=device))  # fmt: skip

    def strip_shape(self, axis: int):
        """Shape of psi/zeta along `axis`; (1, 1, 1, 1) for an axis without CPML (never read)."""
        if not self.strip_width[axis]:
            return (1, 1, 1, 1)
        shape = [self.n_shots, *self.padded]
        shape[axis + 1] = self.strip_width[axis]
        return tuple(shape)

    def new_state(self, requires_grad=False, with_prev=True) -> State:
        """Zero state; with_prev=False leaves u_prev None (a step's output shares its input's u)."""

        def zeros(shape):
            return wp.zeros(shape, dtype=self.dtype, device=self.device, requires_grad=requires_grad)

        full = (self.n_shots, *self.padded)
        return State(zeros(full) if with_prev else None, zeros(full), [zeros(self.strip_shape(a)) for a in range(3)],
                     [zeros(self.strip_shape(a)) for a in range(3)])  # fmt: skip

    def pad_model(self, v, requires_grad=False, out=None):
        """Padded model (Lz, Ly, Lx) from the physical one (wp.array3d, (nz, ny, nx), m/s), into `out` if given."""
        vpad = wp.zeros(self.padded, dtype=self.dtype, device=self.device, requires_grad=requires_grad) if out is None else out
        wp.launch(self.k.pad_model, dim=self.padded, inputs=[v, vpad, self.origin], device=self.device)
        return vpad

    def step(self, st: State, vpad, out: State | None = None, record=None) -> State:
        """Advance st (level n) to level n+1. With out=None the step is done in place (forward only);
        with `out` (fresh arrays, e.g. under a tape or kept for the adjoint) st is left unchanged and out
        is returned. record: (data, op, n, clock) to record st.u first (as `record`; on a GPU in the step's
        first launch)."""
        if out is None:
            out = State(st.u, st.u_prev, st.psi, st.zeta)  # u[n+1] overwrites u[n-1]; psi, zeta in place
            u_next = st.u_prev
        else:
            out = State(st.u, out.u, out.psi, out.zeta)
            u_next = out.u
        step_args = [st.u, st.u_prev, u_next, vpad, *out.psi, *st.zeta, *out.zeta, *self.axes, self.dt2, self.inv_dx, self.top]
        # Under a wp.Tape (Warp's generated adjoints, adjoint="warp") the per-cell reference kernels run; a
        # GPU runs the 2D step as two launches (pre_step: psi and record; step_core: core and frame), the 3D one
        # as psi along each axis, then step_core; a CPU runs rows, split among threads.
        generated = wp._src.context.runtime.tape is not None
        fused = self.core_frame and not generated
        if record is not None and not (fused and self.ndim == 2 and isinstance(record[1], tuple)):
            self.record(st.u, *record)
            record = None
        if fused and self.ndim == 2:
            self._pre_step(st, out, record)
            self.step_core(step_args, st.u, st.u_prev, u_next, vpad)
        elif fused or generated or self.cuda:
            for a in range(3):
                if self.strip_width[a]:
                    kernel, dim = (self.k.psi_flat[a], math.prod(self.strip_shape(a))) if fused else (self.k.psi[a][0], self.strip_shape(a))
                    wp.launch(kernel, dim=dim, inputs=[st.u, st.psi[a], out.psi[a], self.axes[a], self.inv_dx], device=self.device,
                              record_tape=generated)  # fmt: skip
            if fused:
                self.step_core(step_args, st.u, st.u_prev, u_next, vpad)
            else:
                wp.launch(self.k.step, dim=self.interior, inputs=step_args, device=self.device, record_tape=generated)
        else:
            self._cpu_step(st, out, u_next, vpad, step_args)
        return out

    def _strip_cells(self):
        """Cells of the z and x CPML strips (0 for an axis without)."""
        return [math.prod(self.strip_shape(a)) if self.strip_width[a] else 0 for a in (0, 2)]

    def _points(self, record):
        """(data, idx, w, n, clock, number of points) of a record/residual tuple (data, op, n, clock) or None."""
        if record is None:
            return *self._no_points, 0, self.clock, 0
        data, op, n, clock = record
        return data, *op, n, self.clock if clock is None else clock, op[1].size

    def _pre_step(self, st: State, out: State, record):
        z, x = self._strip_cells()
        data, idx, w, n, clock, points = self._points(record)
        wp.launch(self.k.pre_step, dim=z + x + points, inputs=[st.u, st.psi[0], out.psi[0], st.psi[2], out.psi[2], self.axes[0], self.axes[2],
                  self.inv_dx, z, x, data, idx, w, n, clock], device=self.device, record_tape=False)  # fmt: skip

    def adjoint_step(self, st: State, nxt: State, vpad, w, lam, adj, g, adj_psi, adj_zeta, residual=None, out=None):
        """Adjoint of the step from st (level n) to nxt (level n+1; only its psi is read): lam is the
        adjoint of u[n+1], adj that of u[n+2]; out = (adj_out, g_out), default (adj, g): adj_out gets the
        adjoint of u[n] (plus, with residual = (data, op, n, clock), that of recording u[n], as
        record_adjoint), g_out = g (S, Lz, Ly, Lx) + lam times the stretched Laplacian of u[n]; adj_psi = (of
        psi[n+1], of psi[n]), adj_zeta = (of zeta[n+1], of zeta[n]), each a list over the axes: the first ones
        are consumed (zeroed by the per-cell kernels; the 2D core's pre_adjoint overwrites the second ones and leaves
        scratch in adj_psi[0]). w = v^2 dt^2 (pad_model's shape). Separate outputs are faster on a GPU."""
        adj_out, g_out = (adj, g) if out is None else out
        args = [st.u, vpad, *nxt.psi, *st.zeta, lam, adj, g, adj_out, g_out, *adj_psi[0], *adj_zeta[1], *adj_zeta[0], *self.axes, self.dt2,
                self.inv_dx, self.top]  # fmt: skip
        if not self.has_core:
            wp.launch(self.k.adjoint_step, dim=self.interior, inputs=args, device=self.device)
            for a in range(3):
                if self.strip_width[a]:
                    wp.launch(self.k.psi_adjoint[a], dim=self.strip_shape(a), inputs=[adj_out, adj_psi[1][a], adj_psi[0][a], adj_zeta[0][a], self.axes[a],
                              self.inv_dx], device=self.device)  # fmt: skip
            if residual is not None:
                self.record_adjoint(adj_out, *residual)
            return
        z, x = self._strip_cells()
        if z + x:
            wp.launch(self.k.pre_adjoint, dim=z + x, inputs=[lam, vpad, adj_psi[0][0], adj_psi[1][0], adj_zeta[0][0], adj_zeta[1][0],
                      adj_psi[0][2], adj_psi[1][2], adj_zeta[0][2], adj_zeta[1][2], self.axes[0], self.axes[2], self.dt2, self.inv_dx,
                      self.top, z, x], device=self.device)  # fmt: skip
        self.adjoint_core(args, st.u, lam, adj, g, adj_out, g_out, w)
        data, idx, wq, n, clock, points = self._points(residual)
        if points:
            wp.launch(self.k.post_adjoint, dim=points, inputs=[adj_out, data, idx, wq, n, clock], device=self.device)

    def tiles(self, box, rows=None, cols=None, ys=1) -> int:
        """Threads of a core-layout launch over `box` and `ys` values of y (_tile; default: this helper's rows and columns)."""
        rows, cols = rows or self.core_rows, cols or self.core_cols
        return self.n_shots * -(-(box[1] - box[0]) // rows) * -(-(box[3] - box[2]) // cols) * ys

    def core_kernel(self):
        return self.k.step_core(self.core_rows, self.core_cols, self.frame_rows, self.frame_cols)

    def adjoint_kernel(self):
        return self.k.adjoint_core(self.core_rows, self.core_cols)

    def _merged(self, kernel, inputs, tiles: int, cells: int, part=None, cost=FRAME_CELL_COST):
        """Launch a core-and-frame kernel (_step_core, _adjoint_core): `tiles` core tiles, then, from a block
        boundary, `cells` frame threads (a cell or a tile each); part "core" or "frame": only that part (for
        timing). On a CPU the work is split among the step's threads: the frame in one, the tiles shared so that the
        threads' work is about equal, a frame thread counted as `cost` tile cells. Each thread writes only its own cells."""
        frame = -(-tiles // self.core_threads) * self.core_threads

        def launch(dim, offset):
            if dim > 0:
                wp.launch(kernel, dim=dim, inputs=[*inputs, tiles, frame, offset], block_dim=self.core_threads, device=self.device, record_tape=False)

        if part:
            launch(*{"core": (tiles, 0), "frame": (cells, frame)}[part])
        elif self.cuda or self.threads == 1:
            launch(frame + cells, 0)
        else:
            others = self.threads - 1
            per_tile = self.core_rows * self.core_cols
            first = round(min(max((tiles * per_tile / others - cost * cells) / (per_tile + per_tile / others), 0), tiles))

            def job(i, barrier):
                if i == 0:
                    launch(cells, frame)
                    launch(first, 0)
                else:
                    a, b = block_rows(tiles - first, i - 1, others)
                    launch(b - a, first + a)

            self._split(job)

    def step_core(self, step_args, u, u_prev, u_next, vpad, part=None):
        """The GPU step but psi (step_args: the reference step's arguments)."""
        flat = [as_vectors(a, self.core_cols) for a in (u, u_prev, u_next, vpad)]
        layout = (self.frame_rows, self.frame_cols)
        if layout not in self._frames:
            if wp.get_device(self.device).is_capturing:
                raise RuntimeError(f"3D frame layout {layout} first used inside a graph capture; run a step outside it first")
            self._frames[layout] = self._frame_boxes(*layout)
        boxes, ys, threads = self._frames[layout]
        self._merged(self.core_kernel(), [*step_args, self.core, self.ycore, self.frame_cells, boxes, ys, *flat],
                     self.tiles(self.core, ys=self.ycore[1] - self.ycore[0]), threads, part, FRAME_CELL_COST * self.frame_rows * self.frame_cols)

    def _frame_boxes(self, rows: int, cols: int):
        """The 3D frame (the interior cells outside the core) as boxes for _frame_tile: (boxes (z0, z1, x0, x1), their
        (y0, y1, first thread), threads in all): the rows above and below the core, the ys before and after it, the
        columns left and right of it, in tiles of `rows` x `cols`. In 2D: one box standing for none, and a thread a
        frame cell (frame_cell)."""
        R, (lz, ly, lx), c, yc = self.k.halo, self.padded, self.core, self.ycore
        boxes, ys, threads = [(0, 0, 0, 0)], [(0, 0, 0)], self.n_shots * self.frame_cells
        if self.ndim == 3:
            parts = [((R, c[0], R, lx - R), (R, ly - R)), ((c[1], lz - R, R, lx - R), (R, ly - R)), ((c[0], c[1], R, lx - R), (R, yc[0])),
                     ((c[0], c[1], R, lx - R), (yc[1], ly - R)), ((c[0], c[1], R, c[2]), (yc[0], yc[1])), ((c[0], c[1], c[3], lx - R), (yc[0], yc[1]))]  # fmt: skip
            boxes, ys, threads = [], [], 0
            for box, y in parts:
                if box[1] > box[0] and box[3] > box[2] and y[1] > y[0]:
                    boxes.append(box)
                    ys.append((*y, threads))
                    threads += self.tiles(box, rows, cols, y[1] - y[0])
        return wp.array(boxes, dtype=wp.vec4i, device=self.device), wp.array(ys, dtype=wp.vec3i, device=self.device), threads

    def adjoint_core(self, args, u, lam, adj, g, adj_out, g_out, w, part=None):
        """The 2D adjoint step but psi and receivers (args: adjoint_step's arguments)."""
        flat = [as_vectors(a, self.core_cols) for a in (u, lam, adj, g, adj_out, g_out, w)]
        box = self.adjoint_box
        self._merged(self.adjoint_kernel(), [*args, box, self.adjoint_frame_cells, *flat], self.tiles(box), self.n_shots * self.adjoint_frame_cells, part)

    def _cpu_step(self, st, out, u_next, vpad, step_args):
        """A CPU step, split among threads by rows: each thread does its rows of the psi strips and of the
        core, and once every thread has its psi (the frame reads the neighbours'), the frame of its rows.
        The launches are recorded once per set of arrays (an in-place run alternates two) and replayed:
        packing the arguments of a plain launch costs more than a thread's share of the work."""
        arrays = (st.u, st.u_prev, u_next, vpad, *st.psi, *out.psi, *st.zeta, *out.zeta)
        key = tuple(a.ptr for a in arrays)
        jobs = self._launches.get(key, (None,))[-1]
        if jobs is None:
            jobs = [self._cpu_launches(i, st, out, u_next, vpad, step_args) for i in range(self.threads)]
            if len(self._launches) >= 2:
                self._launches.clear()
            self._launches[key] = (arrays, jobs)  # the arrays stay alive while their pointers are keys

        def job(i, barrier):
            first, then = jobs[i]
            for cmd in first:
                cmd.launch()
            barrier.wait()
            for cmd in then:
                cmd.launch()

        self._split(job)

    def _cpu_launches(self, i, st, out, u_next, vpad, step_args):
        """Thread i's launches of a CPU step: (psi strips and core, frame) of its block of rows."""
        S, nz, ny, _ = self.interior
        R = self.k.halo
        r0, r1 = block_rows(nz, i, self.threads)
        first = []
        for a in range(3):
            shape = self.strip_shape(a)
            q0, q1 = block_rows(shape[1], i, self.threads)
            if self.strip_width[a] and q1 > q0:
                first.append(wp.launch(self.k.psi[a][1], dim=(S, q1 - q0, shape[2]), inputs=[st.u.flatten(), st.psi[a].flatten(), out.psi[a].flatten(),
                                       self.axes[a], self.inv_dx, wp.vec3i(*shape[1:]), wp.vec3i(*self.padded), q0], device=self.device, record_tape=False, record_cmd=True))  # fmt: skip
        c = self.core if self.has_core else wp.vec4i(0, 0, 0, 0)
        z0, z1 = max(c[0], R + r0), min(c[1], R + r1)
        if z1 > z0:
            first.append(wp.launch(self.k.step_core_rows, dim=S * (z1 - z0), inputs=[st.u.flatten(), st.u_prev.flatten(), u_next.flatten(), vpad.flatten(),
                                   self.padded[0], self.padded[2], c, z0, z1 - z0, int(u_next.ptr == st.u_prev.ptr), self.dt2, self.inv_dx], device=self.device, record_tape=False, record_cmd=True))  # fmt: skip
        then = [wp.launch(self.k.step_rows, dim=(S, r1 - r0, ny), inputs=[*step_args, R + r0, c], device=self.device, record_tape=False, record_cmd=True)]
        return first, then

    def _split(self, job):
        """job(i, barrier) for i < self.threads, i > 0 on worker threads (CPU launches release the GIL), with a
        threading.Barrier of them all. Whatever stops this thread (an error, or the KeyboardInterrupt of a SIGINT or
        SIGTERM, which may land anywhere in here) breaks the barrier, so no worker is left waiting at it for ever
        (and the interpreter's exit, which joins the workers, hung)."""
        barrier = threading.Barrier(self.threads)
        if self.threads == 1:
            job(0, barrier)
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix="adseismic")
        try:
            pending = [self._pool.submit(self._breaking, job, i, barrier) for i in range(1, self.threads)]
            job(0, barrier)
        except BaseException:
            barrier.abort()
            raise
        for f in pending:
            f.result()

    @staticmethod
    def _breaking(job, i, barrier):
        """A worker's job(i, barrier), breaking the barrier when it fails (the others then fail too, not wait)."""
        try:
            job(i, barrier)
        except BaseException:
            barrier.abort()
            raise

    def operator(self, locations, differentiable=False):
        """The source/receiver operator at locations (wp.array (S, n, 3), metres): the locations
        themselves when they are to be differentiated (weights recomputed every step), else the
        precomputed node indices and weights (S, n, points)."""
        if differentiable:
            return locations
        shape = (self.n_shots, locations.shape[1], self.k.operator_points)
        idx = wp.empty(shape, dtype=wp.vec3i, device=self.device)
        w = wp.empty(shape, dtype=self.dtype, device=self.device)
        wp.launch(self.k.weights, dim=shape, inputs=[locations, self.origin, self.inv_dx, self.top, idx, w], device=self.device)
        return self.compact(idx, w) if self.cuda else (idx, w)

    def compact(self, idx, w):
        """The operator (idx, w) with only as many points per location as the one with most non-zero weights has
        (a location on a node has one in 2D and 3D, not 64 or 512): each GPU thread records one point. (The CPU
        keeps every point: it sums a location's points in one thread, compiled for their number.)"""
        most = wp.zeros(1, dtype=wp.int32, device=self.device)
        wp.launch(self.k.compact, dim=idx.shape[:2], inputs=[idx, w, most], device=self.device)
        points = max(int(most.numpy()[0]), 1)
        return wp.clone(idx[:, :, :points]), wp.clone(w[:, :, :points])

    def _inject_launch(self, u, vpad, amplitudes, op, n: int, clock):
        clock = self.clock if clock is None else clock
        if isinstance(op, tuple):
            return self.k.inject_fixed, op[1].shape, [u, vpad, amplitudes, op[0], op[1], n, clock, self.src_scale]
        dim = (self.n_shots, op.shape[1], self.k.operator_points)
        return self.k.inject, dim, [u, vpad, amplitudes, op, n, clock, self.origin, self.src_scale, self.inv_dx, self.top]

    def _record_launch(self, u, data, op, n: int, clock):
        clock = self.clock if clock is None else clock
        if isinstance(op, tuple):
            kernel, per = (self.k.record_fixed, 1) if self.cuda else (self.k.record_summed, op[1].shape[2])
            return kernel, (*op[1].shape[:2], op[1].shape[2] // per), [u, data, op[0], op[1], n, clock]
        return self.k.record, (self.n_shots, op.shape[1], self.k.operator_points), [u, data, op, n, clock, self.origin, self.inv_dx, self.top]

    def inject(self, u, vpad, amplitudes, op, n: int, clock=None):
        """Add source samples n (amplitudes (S, n_src, nt)) through the operator op into u; with `clock`
        (int32 device array (1,)) the sample n + clock[0], read when the kernel runs (graph replays)."""
        kernel, dim, inputs = self._inject_launch(u, vpad, amplitudes, op, n, clock)
        wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)

    def record(self, u, data, op, n: int, clock=None):
        """data[:, :, n] += receiver samples of u through the operator op (clock as in inject)."""
        kernel, dim, inputs = self._record_launch(u, data, op, n, clock)
        wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)

    def inject_adjoint(self, adj_u, vpad, amplitudes, op, n: int, clock=None):
        """Adjoint of inject (Warp's generated one): from adj_u, the adjoint of the u it added into, add
        into the gradients (.grad) of vpad, amplitudes and, for a differentiable operator, the locations."""
        kernel, dim, inputs = self._inject_launch(adj_u, vpad, amplitudes, op, n, clock)
        adjoint_launch(kernel, dim, inputs, {0: adj_u}, self.device)

    def record_adjoint(self, adj_u, residual, op, n: int, clock=None):
        """Adjoint of record: adj_u += the receiver operator's transpose applied to residual[:, :, n]."""
        kernel, dim, inputs = self._record_launch(adj_u, residual, op, n, clock)
        adjoint_launch(kernel, dim, inputs, {0: adj_u, 1: residual}, self.device)

    def scatter(self, du_next, u_next, u, u_prev, vpad, dvpad):
        """du_next += 2 dv/v (u_next - 2 u + u_prev): the Born (tangent-linear) source term."""
        wp.launch(self.k.scatter, dim=self.interior, inputs=[du_next, u_next, u, u_prev, vpad, dvpad], device=self.device)

    def accumulate_energy(self, u, e, n: int, clock, levels: int):
        """e (padded model shape) += sum over shots of u^2 if n + clock[0] < levels; never recorded on a tape."""
        wp.launch(self.k.energy, dim=u.shape, inputs=[u, e, n, clock, levels], device=self.device, record_tape=False)

    def physical(self, a):
        """View of the physical grid (nz, ny, nx) of a padded model-shaped array."""
        o = self.origin
        ny = self.shape[1] if self.ndim == 3 else 1
        return a[o[0] : o[0] + self.shape[0], o[1] : o[1] + ny, o[2] : o[2] + self.shape[-1]]
