"""Warp kernels for the 2D isotropic elastic wave equation, velocity-stress on a staggered grid.

Equations (z down, x right; b = 1/rho, lambda = rho (vp^2 - 2 vs^2), mu = rho vs^2):

    dvx/dt = b (dsxx/dx + dsxz/dz) + b f_x delta,     dsxx/dt = (lambda + 2 mu) dvx/dx + lambda dvz/dz - dMxx/dt delta,
    dvz/dt = b (dsxz/dx + dszz/dz) + b f_z delta,     dszz/dt = lambda dvx/dx + (lambda + 2 mu) dvz/dz - dMzz/dt delta,
                                                      dsxz/dt = mu (dvx/dz + dvz/dx) - dMxz/dt delta.

Staggering (Virieux 1986; Levander 1988), positions in cells from padded node (0, 0) as (z, x); the
array index (i, k) of every field stands for:

    sxx, szz, vp, vs, rho   (i,       k)           vx   (i,       k + 1/2)
    sxz                     (i + 1/2, k + 1/2)     vz   (i + 1/2, k)

lambda and mu are taken at the normal-stress nodes, mu at a shear node is the harmonic mean of its four
neighbours (0 if any is 0, so fluids carry no shear), the buoyancy at a velocity node the arithmetic
mean of 1/rho at its two neighbours; all of these are computed once per run from the padded vp, vs, rho
by the `materials` kernel, which Warp differentiates (the chain rule to vp, vs, rho). Staggered derivatives of order 2/4/8
(numerics.STAGGERED_DERIVATIVE).

Time (leapfrog): the state at level n holds v at t = (n - 1/2) dt and the stresses at t = n dt. One
step: v^{n+1/2} = v^{n-1/2} + dt b (div s^n + f(t_n) delta), then s^{n+1} = s^n + dt C : grad v^{n+1/2}
- (M(t_{n+1}) - M(t_n)) delta. A recorded sample n of vx or vz is therefore v at t = (n - 1/2) dt; of
pressure -(sxx + szz)/2 at t = n dt.

Layout. Fields are (n_shots, Lz, Lx) with x contiguous; models (Lz, Lx); every axis is padded as
[halo R][PML][physical grid][PML][halo R], R = order/2, halo cells stay zero and are never written.
CPML (Komatitsch & Martin 2007, kappa = 1): one memory variable per spatial derivative in each update
(8 in all), stored in strips along its axis (Axis.store maps a padded index to the strip index, -1
outside), with the damping profile evaluated at the derivative's own (integer or half) positions.

Free surface (stress imaging, Levander 1988; Graves 1996): the top row of normal-stress nodes (padded
row `top`, physical z = 0) is the surface, szz = 0 there and sxx follows from szz = 0
(dsxx/dt = 4 mu (lambda + mu) / (lambda + 2 mu) dvx/dx); szz and sxz above it are the antisymmetric images
of those below. Velocities are not computed above the surface: the vertical derivatives of velocity
whose full stencil would reach above it use the highest staggered order that fits (order 2 on the first
row). Lamb's problem accuracy: docs/accuracy.md.

Sources and receivers use the Kaiser-windowed sinc operator of kernels/common.py (HICKS_RADIUS,
C^1 in the position) at each field's own staggered position. Near a free surface the operator's points
above it are folded onto their mirror nodes, with a sign change for szz and sxz (odd images) and
without for vx, vz, sxx; a normal-stress node on the surface gets no szz weight.

Kernels. A step is `velocity` then `stress`, each as per-cell reference kernels (what Warp differentiates for
adjoint="warp") or as the fast path (`make_updates`, one kernel per half step and Layout): threads updating
tiles of rows x cols cells of the core (the cells with neither CPML nor free surface, its columns from and to
multiples of the vector width) on flat arrays viewed as vectors of cols values, with the z-stencil in sliding
register windows and each row's values along x loaded once per tile, and threads doing the other interior cells
(the frame) with the reference's per-cell code, in one launch or two. A kernel may write its outputs into its
inputs (every cell reads only its own old value of a field it writes), so forward steps run in place, or out of
place into a level's own arrays (under a tape, and in the hand-written adjoint sweep). Hand-written adjoints
(launched by Elastic.adjoint_update on explicit adjoint arrays: the old fields' adjoints written, the others
added to) first compute per cell the adjoint of every raw stencil sum (CPML, materials and pointwise terms
included) into scratch arrays (`*_adjoint`), then apply the transposed stencils as gathers (`*_transpose`); rows
next to a free surface, whose stencils fold or shrink, scatter with atomics instead. On a GPU (AdjointLayout,
`make_adjoints`) tiles of the cells whose gathers read core cells alone fuse the two passes, forming those
cells' raw stencil sums' adjoints in sliding windows and lines (or, AdjointLayout.split, `make_split_adjoints`: a
tile's gathers and then, apart, its pass 1 work, each with fewer live values, on vectors). The source and receiver
kernels' adjoints are Warp's generated ones, launched directly (adjoint=True).
"""


import functools
import math
from types import SimpleNamespace
from typing import Any, NamedTuple

import numpy as np
import warp as wp

from adseismic.kernels.common import (HICKS_RADIUS, Kernels, adjoint_launch, aligned, as_vectors, hicks_axis, host_operator, unique_kernel,
                                      vector_access)
from adseismic.kernels.numerics import STAGGERED_DERIVATIVE


class Layout(NamedTuple):
    """How the fast path does the core: each thread updates a tile of `rows` consecutive rows (z) x `cols` adjacent
    columns (x), `threads` per block; a tile's row is one vector of `cols` (1, 2 or 4) values per array (fewer where
    the padded row length is no multiple: Elastic.width). lean: the core reads one model array fewer per cell in each
    half step, deriving bx, bz from 1/rho at the normal-stress nodes and lambda and the shear nodes' mu from
    lambda + 2 mu and mu, with `materials`' operations (36 -> 32 and 44 -> 40 bytes per cell). merged: the
    core and the frame in one launch instead of two."""

    rows: int
    cols: int
    threads: int = 128
    lean: bool = True
    merged: bool = True


# The GPU's forward layout, chosen from LAYOUTS by benchmarks/speed_elastic.py (timings: docs/benchmarks.md, "Layout timings").
CORE_LAYOUT = Layout(1, 2, 128, lean=True, merged=True)
LAYOUTS = (
    Layout(1, 2, 128, True, True),
    Layout(1, 2, 128, False, True),
    Layout(1, 4, 128, False, True),
    Layout(2, 2, 128, False, True),
    Layout(8, 2, 128, False, True),
    Layout(8, 4, 128, False, True),
    Layout(4, 4, 128, False, True),
    Layout(4, 2, 128, False, True),
    Layout(8, 1, 128, False, True),
    Layout(16, 2, 128, False, True),
    Layout(8, 2, 256, False, True),
    Layout(8, 2, 128, False, False),
    Layout(8, 2, 128, True, True),
    Layout(8, 4, 128, True, True),
)


class AdjointLayout(NamedTuple):
    """How the hand-written adjoint's fused kernels (make_adjoints) do the adjoint box: each thread a tile of `rows`
    rows (z) x `cols` columns (x) of one shot, `threads` per block. split: each half step's two passes one after the
    other (make_split_adjoints; gathers over the adjoint box, pass 1's work inside the inner box), fewer live values
    per thread, a tile's row one vector of `cols` values per array (fewer where the padded row length is no multiple:
    Elastic.adjoint_width), the boxes' columns from and to multiples of it; merged (split only): a tile's sums in the
    gathers' launch, by the same thread, rather than in a launch of their own."""

    rows: int
    cols: int
    threads: int = 128
    split: bool = False
    merged: bool = True


# The GPU's adjoint layout by order, chosen from ADJOINT_LAYOUTS by benchmarks/speed_elastic.py --adjoint-variants
# (timings and registers per thread: docs/benchmarks.md, "Layout timings"). The CPU runs the per-cell kernels.
ADJOINT_LAYOUT = {o: AdjointLayout(1, 4, 128, split=True) for o in (2, 4, 8)}
ADJOINT_LAYOUTS = (
    AdjointLayout(1, 4, 128, split=True),
    AdjointLayout(1, 2, 128, split=True),
    AdjointLayout(3, 4, 128, split=True),
    AdjointLayout(8, 2, 128),
    AdjointLayout(4, 2, 128),
    AdjointLayout(16, 2, 128),
    AdjointLayout(8, 1, 128),
    AdjointLayout(16, 1, 128),
    AdjointLayout(4, 1, 128),
    AdjointLayout(2, 2, 128),
    AdjointLayout(8, 2, 256),
    AdjointLayout(8, 1, 256),
    AdjointLayout(4, 2, 128, split=True),
    AdjointLayout(8, 2, 128, split=True),
    AdjointLayout(16, 2, 128, split=True),
    AdjointLayout(8, 1, 128, split=True),
    AdjointLayout(16, 1, 128, split=True),
    AdjointLayout(4, 4, 128, split=True),
    AdjointLayout(8, 4, 128, split=True),
    AdjointLayout(8, 2, 256, split=True),
    AdjointLayout(8, 2, 64, split=True),
    AdjointLayout(2, 2, 128, split=True),
    AdjointLayout(2, 4, 128, split=True),
    AdjointLayout(4, 2, 128, split=True, merged=False),
    AdjointLayout(4, 4, 128, split=True, merged=False),
)
# threads per block of the hand adjoints' pass 1, a thread a cell (docs/benchmarks.md, "Layout timings")
PASS1_THREADS = 128
TRANSPOSE_ROWS, TRANSPOSE_THREADS = 16, 128  # cells per thread along z, threads per block of the hand adjoints' gathers

# CPML memory variables: name -> axis of their derivative and strip (0 = z, 1 = x). vx_x is d(sxx)/dx at
# vx nodes, vx_z d(sxz)/dz at vx nodes, s_x d(vx)/dx at normal-stress nodes, xz_z d(vx)/dz at sxz nodes...
PSI = {"vx_x": 1, "vx_z": 0, "vz_x": 1, "vz_z": 0, "s_x": 1, "s_z": 0, "xz_z": 0, "xz_x": 1}
PSI_V = ("vx_x", "vx_z", "vz_x", "vz_z")  # of the velocity update
PSI_S = ("s_x", "s_z", "xz_z", "xz_x")  # of the stress update
MATERIALS = ("bx", "bz", "l2m", "lam", "mu", "muh", "b")  # see _materials' `materials`


@functools.lru_cache(maxsize=None)
def build(order: int, dtype, free_surface: bool):
    """Kernels for one (order, dtype, free_surface) combination, compiled once per process."""
    ns = _types(order, dtype, free_surface)
    for builder in (_derivatives, _cpml, _pointwise, _indexing, _cells, _values, _velocity_adjoints, _stress_adjoints, _shots,
                    _materials, _sources, _receivers, _layouts):  # fmt: skip
        vars(ns).update(builder(ns))  # the Warp funcs and kernels it makes, for the builders after it
    return Kernels(
        Axis=ns.Axis, materials=ns.materials, velocity=ns.velocity, stress=ns.stress, updates=ns.updates,
        velocity_adjoint=ns.velocity_adjoint, velocity_transpose=ns.velocity_transpose, stress_adjoint=ns.stress_adjoint,
        stress_transpose=ns.stress_transpose, adjoints=ns.adjoints, split_adjoints=ns.split_adjoints, sum_shots=ns.sum_shots,
        inject_force=ns.inject_force, inject_moment=ns.inject_moment, inject_force_op=ns.inject_force_op,
        inject_moment_op=ns.inject_moment_op, weights=ns.weights, record=ns.record, record_adjoint=ns.record_adjoint,
        add_into=ns.add_into, pad_model=ns.pad_model, halo=ns.M, operator_points=ns.NPTS,
    )  # fmt: skip


# The builders below make build's Warp funcs and kernels, a concern each. Each takes the namespace `ns` (_types' constants
# and types, and what the builders before it made) and returns what it makes; a Warp func or kernel finds the names it
# uses among its builder's locals (unpacked from ns) and the module's globals.


def _types(order: int, dtype, free_surface: bool):
    """The constants and Warp types of one configuration: a namespace that build's builders read and add to."""
    M = order // 2
    HR = HICKS_RADIUS
    W = 2 * HR
    NPTS = W * W
    C = STAGGERED_DERIVATIVE[order]
    fs = bool(free_surface)
    arr1 = wp.array(dtype=dtype)
    arr2 = wp.array2d(dtype=dtype)
    arr3 = wp.array3d(dtype=dtype)
    arr4 = wp.array4d(dtype=dtype)
    iarr1 = wp.array(dtype=wp.int32)
    vecw = wp.types.vector(length=2 * M, dtype=dtype)

    @wp.struct
    class Axis:
        store: wp.array(dtype=wp.int32)  # strip index per padded index, -1 outside the PML strips
        a: wp.array(dtype=dtype)  # CPML a, b at integer positions
        b: wp.array(dtype=dtype)
        ah: wp.array(dtype=dtype)  # CPML a, b at half positions (index p stands for p + 1/2)
        bh: wp.array(dtype=dtype)

    return SimpleNamespace(M=M, HR=HR, W=W, NPTS=NPTS, C=C, fs=fs, dtype=dtype, arr1=arr1, arr2=arr2, arr3=arr3, arr4=arr4,
                           iarr1=iarr1, vecw=vecw, Axis=Axis)  # fmt: skip


def make_dz(ns, mr: int, half_in: bool, image: bool):
    # d/dz (times dz) with mr staggered weights of a field on half (half_in) or integer z nodes,
    # evaluated at integer (half_in) or half nodes; `image`: antisymmetric image above row `top`.
    # Returns the derivative and its transpose (adj += g d(dz)/df, with atomics).
    fs, dtype, arr3 = ns.fs, ns.dtype, ns.arr3
    c = STAGGERED_DERIVATIVE[2 * mr]
    h = 1 if half_in else 0

    @wp.func
    def read(f: arr3, s: int, z: int, x: int, top: int) -> dtype:
        if wp.static(image and fs):
            if z < top:
                return -f[s, 2 * top - wp.static(h) - z, x]
        return f[s, z, x]

    @wp.func
    def dz(f: arr3, s: int, z: int, x: int, top: int) -> dtype:
        acc = dtype(0.0)
        for m in range(wp.static(mr)):
            lo = read(f, s, z - m - wp.static(h), x, top)
            hi = read(f, s, z + m + wp.static(1 - h), x, top)
            acc += dtype(wp.static(c[m])) * (hi - lo)
        return acc

    @wp.func
    def spread(adj: arr3, s: int, z: int, x: int, top: int, g: dtype):
        zz = z
        gg = g
        if wp.static(image and fs):
            if z < top:
                zz = 2 * top - wp.static(h) - z
                gg = -g
        wp.atomic_add(adj, s, zz, x, gg)

    @wp.func
    def dz_t(adj: arr3, s: int, z: int, x: int, top: int, g: dtype):
        for m in range(wp.static(mr)):
            cg = dtype(wp.static(c[m])) * g
            spread(adj, s, z - m - wp.static(h), x, top, -cg)
            spread(adj, s, z + m + wp.static(1 - h), x, top, cg)

    return dz, dz_t


def make_dx(ns, half_in: bool):
    # d/dx (times dx) at integer (half_in) or half nodes, and its transpose
    M, C, dtype, arr3 = ns.M, ns.C, ns.dtype, ns.arr3
    h = 1 if half_in else 0

    @wp.func
    def dx(f: arr3, s: int, z: int, x: int) -> dtype:
        acc = dtype(0.0)
        for m in range(wp.static(M)):
            acc += dtype(wp.static(C[m])) * (f[s, z, x + m + wp.static(1 - h)] - f[s, z, x - m - wp.static(h)])
        return acc

    @wp.func
    def dx_t(adj: arr3, s: int, z: int, x: int, g: dtype):
        for m in range(wp.static(M)):
            cg = dtype(wp.static(C[m])) * g
            wp.atomic_add(adj, s, z, x - m - wp.static(h), -cg)
            wp.atomic_add(adj, s, z, x + m + wp.static(1 - h), cg)

    return dx, dx_t


def make_gather(ns, half_in: bool):
    # transpose of a full-order derivative as a gather: sum over the nodes whose stencil reads node i
    # (flat index; step 1 along x, lx along z) of their adjoint t
    M, C, dtype, arr1 = ns.M, ns.C, ns.dtype, ns.arr1
    h = 1 if half_in else 0

    @wp.func
    def gather(t: arr1, i: int, step: int) -> dtype:
        acc = dtype(0.0)
        for m in range(wp.static(M)):
            acc += dtype(wp.static(C[m])) * (t[i + (wp.static(h - 1) - m) * step] - t[i + (m + wp.static(h)) * step])
        return acc

    return gather


def _derivatives(ns):
    """The staggered derivatives and their transposes (scatters with atomics, and gathers)."""
    M, C, fs, dtype, arr3, vecw = ns.M, ns.C, ns.fs, ns.dtype, ns.arr3, ns.vecw
    dx_of_int, dxt_of_int = make_dx(ns, False)
    dx_of_half, dxt_of_half = make_dx(ns, True)
    gather_int, gather_half = make_gather(ns, False), make_gather(ns, True)
    dz_szz, dzt_szz = make_dz(ns, M, False, True)  # at vz nodes
    dz_sxz, dzt_sxz = make_dz(ns, M, True, True)  # at vx nodes
    # velocity z-derivatives in the stress update: full order, and orders 2, 4, 6 (m = 1, 2, 3 weights) for
    # the rows next to a free surface
    dz_vz, dzt_vz = make_dz(ns, M, True, False)
    dz_vx, dzt_vx = make_dz(ns, M, False, False)
    (dz_vz1, dzt_vz1), (dz_vz2, dzt_vz2), (dz_vz3, dzt_vz3) = (make_dz(ns, m, True, False) for m in (1, 2, 3))
    (dz_vx1, dzt_vx1), (dz_vx2, dzt_vx2), (dz_vx3, dzt_vx3) = (make_dz(ns, m, False, False) for m in (1, 2, 3))

    @wp.func
    def dvz_normal(vz: arr3, s: int, z: int, x: int, top: int) -> dtype:
        # d(vz)/dz (times dz) at normal-stress node (z, x), order reduced next to a free surface
        k = z - top
        if wp.static(fs and M >= 2):
            if k == 1:
                return dz_vz1(vz, s, z, x, top)
        if wp.static(fs and M >= 3):
            if k == 2:
                return dz_vz2(vz, s, z, x, top)
        if wp.static(fs and M >= 4):
            if k == 3:
                return dz_vz3(vz, s, z, x, top)
        return dz_vz(vz, s, z, x, top)

    @wp.func
    def dvz_normal_t(adj: arr3, s: int, z: int, x: int, top: int, g: dtype):
        k = z - top
        done = False
        if wp.static(fs and M >= 2):
            if k == 1:
                dzt_vz1(adj, s, z, x, top, g)
                done = True
        if wp.static(fs and M >= 3):
            if k == 2:
                dzt_vz2(adj, s, z, x, top, g)
                done = True
        if wp.static(fs and M >= 4):
            if k == 3:
                dzt_vz3(adj, s, z, x, top, g)
                done = True
        if not done:
            dzt_vz(adj, s, z, x, top, g)

    @wp.func
    def dvx_shear(vx: arr3, s: int, z: int, x: int, top: int) -> dtype:
        # d(vx)/dz (times dz) at shear node (z + 1/2, x + 1/2), order reduced next to a free surface
        k = z - top
        if wp.static(fs):
            if k == 0:
                return dz_vx1(vx, s, z, x, top)
        if wp.static(fs and M >= 3):
            if k == 1:
                return dz_vx2(vx, s, z, x, top)
        if wp.static(fs and M >= 4):
            if k == 2:
                return dz_vx3(vx, s, z, x, top)
        return dz_vx(vx, s, z, x, top)

    @wp.func
    def dvx_shear_t(adj: arr3, s: int, z: int, x: int, top: int, g: dtype):
        k = z - top
        done = False
        if wp.static(fs):
            if k == 0:
                dzt_vx1(adj, s, z, x, top, g)
                done = True
        if wp.static(fs and M >= 3):
            if k == 1:
                dzt_vx2(adj, s, z, x, top, g)
                done = True
        if wp.static(fs and M >= 4):
            if k == 2:
                dzt_vx3(adj, s, z, x, top, g)
                done = True
        if not done:
            dzt_vx(adj, s, z, x, top, g)

    @wp.func
    def dwin(w: vecw) -> dtype:
        # z-derivative from a window w[j] = f[z0 + j], j < 2M, centred between w[M - 1] and w[M]
        acc = dtype(0.0)
        for m in range(wp.static(M)):
            acc += dtype(wp.static(C[m])) * (w[wp.static(M) + m] - w[wp.static(M - 1) - m])
        return acc

    return dict(
        dx_of_int=dx_of_int, dxt_of_int=dxt_of_int, dx_of_half=dx_of_half, dxt_of_half=dxt_of_half, gather_int=gather_int,
        gather_half=gather_half, dz_szz=dz_szz, dzt_szz=dzt_szz, dz_sxz=dz_sxz, dzt_sxz=dzt_sxz, dvz_normal=dvz_normal,
        dvz_normal_t=dvz_normal_t, dvx_shear=dvx_shear, dvx_shear_t=dvx_shear_t, dwin=dwin,
    )  # fmt: skip


def _cpml(ns):
    """The CPML memory variables' updates and their adjoints."""
    dtype, arr1, arr3 = ns.dtype, ns.arr1, ns.arr3

    # The per-cell kernels load everything a cell needs before they store anything: Warp's arrays may alias, so the
    # compiler keeps a load after an earlier store, and a load, store, load, ... chain waits on memory at each load.

    @wp.func
    def cpml_psi(d: dtype, j: int, p: int, a: arr1, b: arr1, old: arr3, s: int, row: int, col: int) -> dtype:
        # psi = b psi_old + a d at strip cell (row, col) (0 outside the strips)
        if j < 0:
            return dtype(0.0)
        return b[p] * old[s, row, col] + a[p] * d

    @wp.func
    def cpml(d: dtype, j: int, psi: dtype, new: arr3, s: int, row: int, col: int) -> dtype:
        # d + psi, psi stored at strip cell (row, col); d unchanged outside the strips
        if j < 0:
            return d
        new[s, row, col] = psi
        return d + psi

    @wp.func
    def cpml_value(d: dtype, j: int, new: arr3, s: int, row: int, col: int) -> dtype:
        # cpml's result recomputed from the psi it stored
        if j < 0:
            return d
        return d + new[s, row, col]

    @wp.func
    def psi_adjoint(j: int, p: int, a: arr1, b: arr1, adj: arr3, s: int, row: int, col: int):
        # (psi's adjoint, a, b) at strip cell (row, col), for cpml_t (zeros outside the strips)
        if j < 0:
            return dtype(0.0), dtype(0.0), dtype(0.0)
        return adj[s, row, col], a[p], b[p]

    @wp.func
    def cpml_t(g: dtype, j: int, q0: dtype, ap: dtype, bp: dtype, adj: arr3, s: int, row: int, col: int) -> dtype:
        # adjoint of cpml in place: g is the adjoint of its result; adj (psi's adjoint, q0 = psi_adjoint's) goes from
        # psi_new's to psi_old's (its only term); returns the adjoint of d
        if j < 0:
            return g
        q = q0 + g
        adj[s, row, col] = bp * q
        return g + ap * q

    return dict(cpml_psi=cpml_psi, cpml=cpml, cpml_value=cpml_value, psi_adjoint=psi_adjoint, cpml_t=cpml_t)


def _pointwise(ns):
    """The updates' pointwise terms, and the free surface's rows."""
    M, fs, dtype = ns.M, ns.fs, ns.dtype

    @wp.func
    def advance(f: dtype, dt: dtype, m: dtype, d: dtype) -> dtype:
        return f + dt * m * d

    @wp.func
    def normal_rates(l2m: dtype, lam: dtype, dvx: dtype, dvz: dtype):
        return l2m * dvx + lam * dvz, lam * dvx + l2m * dvz

    @wp.func
    def surface_modulus(l2m: dtype, lam: dtype, mu: dtype) -> dtype:
        # dsxx/dt = this * dvx/dx on a free surface (szz = 0)
        return dtype(4.0) * mu * (lam + mu) / l2m

    @wp.func
    def surface_row(z: int, top: int) -> bool:
        # rows whose z-stencils fold (image) or shrink: scattered by the hand adjoints
        if wp.static(fs):
            return z < top + wp.static(M)
        return False

    return dict(advance=advance, normal_rates=normal_rates, surface_modulus=surface_modulus, surface_row=surface_row)


def _indexing(ns):
    """Which cells a thread takes: the frame's (outside a box), a column's, and whether a cell lies in a box."""
    M = ns.M

    @wp.func
    def frame_cell(f: int, lz: int, lx: int, core: wp.vec4i):
        # (z, x) of the f-th interior cell outside the core rows [core[0], core[1]) x columns
        # [core[2], core[3]): first the full rows above and below the core, then the core rows' sides
        nx = lx - wp.static(2 * M)
        above = (core[0] - wp.static(M)) * nx
        below = (lz - wp.static(M) - core[1]) * nx
        z = int(0)
        x = int(0)
        if f < above:
            z = wp.static(M) + f // nx
            x = wp.static(M) + f % nx
        elif f < above + below:
            z = core[1] + (f - above) // nx
            x = wp.static(M) + (f - above) % nx
        else:
            g = f - above - below
            sides = core[2] - wp.static(M) + lx - wp.static(M) - core[3]
            z = core[0] + g // sides
            x = wp.static(M) + g % sides
            if x >= core[2]:
                x = x - core[2] + core[3]
        return z, x

    @wp.func
    def column(t: int, lz: int, lx: int, box: wp.vec4i, rows: int):
        # thread t of a 1D launch over the rows [box[0], box[1]) x columns [box[2], box[3]) of every shot,
        # `rows` cells along z each: flat field index of its first cell, flat model index, number of cells
        nx = box[3] - box[2]
        blocks = (box[1] - box[0] + rows - 1) // rows
        q = t // nx
        x = box[2] + t - q * nx
        s = q // blocks
        z = box[0] + (q - s * blocks) * rows
        n = wp.min(rows, box[1] - z)
        c = z * lx + x
        return s * lz * lx + c, c, n

    @wp.func
    def inside(z: int, x: int, b: wp.vec4i) -> bool:
        return z >= b[0] and z < b[1] and x >= b[2] and x < b[3]

    return dict(frame_cell=frame_cell, column=column, inside=inside)


def _cells(ns):
    """The per-cell updates (reference kernels and the frame)."""
    M, fs, dtype, arr2, arr3, Axis = ns.M, ns.fs, ns.dtype, ns.arr2, ns.arr3, ns.Axis
    dx_of_int, dx_of_half, dz_sxz, dz_szz, dvz_normal, dvx_shear = (ns.dx_of_int, ns.dx_of_half, ns.dz_sxz, ns.dz_szz, ns.dvz_normal,
                                                                    ns.dvx_shear)  # fmt: skip
    cpml_psi, cpml, advance, normal_rates, surface_modulus = ns.cpml_psi, ns.cpml, ns.advance, ns.normal_rates, ns.surface_modulus

    @wp.func
    def velocity_cell(
        vx: arr3, vz: arr3, sxx: arr3, szz: arr3, sxz: arr3, bx: arr2, bz: arr2,
        p_vx_x: arr3, p_vx_z: arr3, p_vz_x: arr3, p_vz_z: arr3,
        n_vx_x: arr3, n_vx_z: arr3, n_vz_x: arr3, n_vz_z: arr3,
        vx_new: arr3, vz_new: arr3, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int, s: int, z: int, x: int,
    ):  # fmt: skip
        jz = az.store[z]
        jx = ax.store[x]
        r1 = dx_of_int(sxx, s, z, x) * inv_dx  # vx at (z, x + 1/2)
        r2 = dz_sxz(sxz, s, z, x, top) * inv_dx
        r3 = dx_of_half(sxz, s, z, x) * inv_dx  # vz at (z + 1/2, x)
        r4 = dz_szz(szz, s, z, x, top) * inv_dx
        p1 = cpml_psi(r1, jx, x, ax.ah, ax.bh, p_vx_x, s, z, jx)
        p2 = cpml_psi(r2, jz, z, az.a, az.b, p_vx_z, s, jz, x)
        p3 = cpml_psi(r3, jx, x, ax.a, ax.b, p_vz_x, s, z, jx)
        p4 = cpml_psi(r4, jz, z, az.ah, az.bh, p_vz_z, s, jz, x)
        ux = vx[s, z, x]
        uz = vz[s, z, x]
        mx = bx[z, x]
        mz = bz[z, x]
        d1 = cpml(r1, jx, p1, n_vx_x, s, z, jx)
        d2 = cpml(r2, jz, p2, n_vx_z, s, jz, x)
        d3 = cpml(r3, jx, p3, n_vz_x, s, z, jx)
        d4 = cpml(r4, jz, p4, n_vz_z, s, jz, x)
        vx_new[s, z, x] = advance(ux, dt, mx, d1 + d2)
        vz_new[s, z, x] = advance(uz, dt, mz, d3 + d4)

    @wp.func
    def stress_cell(
        vx: arr3, vz: arr3, sxx: arr3, szz: arr3, sxz: arr3, l2m: arr2, lam: arr2, mu: arr2, muh: arr2,
        p_s_x: arr3, p_s_z: arr3, p_xz_z: arr3, p_xz_x: arr3,
        n_s_x: arr3, n_s_z: arr3, n_xz_z: arr3, n_xz_x: arr3,
        sxx_new: arr3, szz_new: arr3, sxz_new: arr3, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int,
        s: int, z: int, x: int,
    ):  # fmt: skip
        jz = az.store[z]
        jx = ax.store[x]
        r1 = dx_of_half(vx, s, z, x) * inv_dx  # normal stresses at (z, x)
        r2 = dvz_normal(vz, s, z, x, top) * inv_dx
        r3 = dvx_shear(vx, s, z, x, top) * inv_dx  # shear stress at (z + 1/2, x + 1/2)
        r4 = dx_of_int(vz, s, z, x) * inv_dx
        p1 = cpml_psi(r1, jx, x, ax.a, ax.b, p_s_x, s, z, jx)
        p2 = cpml_psi(r2, jz, z, az.a, az.b, p_s_z, s, jz, x)
        p3 = cpml_psi(r3, jz, z, az.ah, az.bh, p_xz_z, s, jz, x)
        p4 = cpml_psi(r4, jx, x, ax.ah, ax.bh, p_xz_x, s, z, jx)
        c1 = l2m[z, x]
        c2 = lam[z, x]
        fxx = sxx[s, z, x]
        fzz = szz[s, z, x]
        fxz = sxz[s, z, x]
        c4 = muh[z, x]
        surface = False
        if wp.static(fs):
            surface = z == top
        q = dtype(0.0)
        if surface:
            q = surface_modulus(c1, c2, mu[z, x])
        dvx = cpml(r1, jx, p1, n_s_x, s, z, jx)
        dvz = cpml(r2, jz, p2, n_s_z, s, jz, x)
        e1 = cpml(r3, jz, p3, n_xz_z, s, jz, x)
        e2 = cpml(r4, jx, p4, n_xz_x, s, z, jx)
        sxx_rate, szz_rate = normal_rates(c1, c2, dvx, dvz)
        if surface:
            sxx_new[s, z, x] = fxx + dt * (q * dvx)
            szz_new[s, z, x] = dtype(0.0)
        else:
            sxx_new[s, z, x] = fxx + dt * sxx_rate
            szz_new[s, z, x] = fzz + dt * szz_rate
        sxz_new[s, z, x] = advance(fxz, dt, c4, e1 + e2)

    @unique_kernel
    def velocity(
        vx: arr3, vz: arr3, sxx: arr3, szz: arr3, sxz: arr3, bx: arr2, bz: arr2,
        p_vx_x: arr3, p_vx_z: arr3, p_vz_x: arr3, p_vz_z: arr3,
        n_vx_x: arr3, n_vx_z: arr3, n_vz_x: arr3, n_vz_z: arr3,
        vx_new: arr3, vz_new: arr3, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        s, zi, xi = wp.tid()
        velocity_cell(vx, vz, sxx, szz, sxz, bx, bz, p_vx_x, p_vx_z, p_vz_x, p_vz_z, n_vx_x, n_vx_z, n_vz_x, n_vz_z,
                      vx_new, vz_new, az, ax, dt, inv_dx, top, s, zi + wp.static(M), xi + wp.static(M))  # fmt: skip

    @unique_kernel
    def stress(
        vx: arr3, vz: arr3, sxx: arr3, szz: arr3, sxz: arr3, l2m: arr2, lam: arr2, mu: arr2, muh: arr2,
        p_s_x: arr3, p_s_z: arr3, p_xz_z: arr3, p_xz_x: arr3,
        n_s_x: arr3, n_s_z: arr3, n_xz_z: arr3, n_xz_x: arr3,
        sxx_new: arr3, szz_new: arr3, sxz_new: arr3, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        s, zi, xi = wp.tid()
        stress_cell(vx, vz, sxx, szz, sxz, l2m, lam, mu, muh, p_s_x, p_s_z, p_xz_z, p_xz_x, n_s_x, n_s_z, n_xz_z, n_xz_x,
                    sxx_new, szz_new, sxz_new, az, ax, dt, inv_dx, top, s, zi + wp.static(M), xi + wp.static(M))  # fmt: skip

    return dict(velocity_cell=velocity_cell, stress_cell=stress_cell, velocity=velocity, stress=stress)


# Sources of the tiles' windows and lines (`value`): a field (flat array), or what pass 1 of the hand-written
# adjoints stores as t_k at a core cell (no CPML, no surface), the adjoint of a raw stencil sum: Scaled, dt m g / dx
# for an update f += dt m (sum) / dx, g the adjoint of f; Normal, (p dt gx + q dt gz) / dx for the normal stresses'
# sums (normal_rates with materials p, q; gx, gz the adjoints of sxx, szz). base: flat index of the shot's first cell.
def make_products(ns, arr):
    # Scaled and Normal on flat arrays (arr1) or on arrays of vectors (base then in vectors), and their constructors
    dtype = ns.dtype

    @wp.struct
    class Scaled:
        g: arr
        m: arr
        base: int
        dt: dtype
        inv_dx: dtype

    @wp.struct
    class Normal:
        gx: arr
        gz: arr
        p: arr
        q: arr
        base: int
        dt: dtype
        inv_dx: dtype

    @wp.func
    def scaled(g: arr, m: arr, base: int, dt: dtype, inv_dx: dtype) -> Scaled:
        a = Scaled()
        a.g = g
        a.m = m
        a.base = base
        a.dt = dt
        a.inv_dx = inv_dx
        return a

    @wp.func
    def normal(gx: arr, gz: arr, p: arr, q: arr, base: int, dt: dtype, inv_dx: dtype) -> Normal:
        a = Normal()
        a.gx = gx
        a.gz = gz
        a.p = p
        a.q = q
        a.base = base
        a.dt = dt
        a.inv_dx = inv_dx
        return a

    return Scaled, Normal, scaled, normal


def _values(ns):
    """`value` of a flat array, Scaled or Normal at a flat index (the fused adjoint tiles' sources), and the constructors of
    Scaled and Normal."""
    dtype, arr1, normal_rates = ns.dtype, ns.arr1, ns.normal_rates
    Scaled, Normal, scaled, normal = make_products(ns, arr1)

    @wp.func
    def value(f: arr1, i: int) -> dtype:
        return f[i]

    @wp.func
    def value(a: Scaled, i: int) -> dtype:  # noqa: F811 (a Warp overload)
        return a.dt * a.m[i - a.base] * a.g[i] * a.inv_dx

    @wp.func
    def value(a: Normal, i: int) -> dtype:  # noqa: F811
        c = i - a.base
        r, _ = normal_rates(a.p[c], a.q[c], a.dt * a.gx[i], a.dt * a.gz[i])
        return r * a.inv_dx

    return dict(scaled=scaled, normal=normal, value=value)


def make_tiling(ns, rows: int, cols: int, width: int):
    # What tiles of rows x cols cells share (make_updates, make_adjoints): the place of tile t, and sliding z-windows
    # w[j, m] (column j, row m) and x-lines r[p] of a source f with their derivative. The loaders read f in blocks of
    # `width` adjacent cells (get), their indices in blocks: a vector of an array of vectors (arrv; the forward's and
    # the split adjoint's fields and models), of ScaledV or NormalV (the split adjoint's t_k), or with width 1 any
    # `value` (flat indices; the fused adjoint's). width divides cols.
    M, C, dtype, value, normal_rates = ns.M, ns.C, ns.dtype, ns.value, ns.normal_rates
    win = wp.types.matrix(shape=(cols, 2 * M), dtype=dtype)
    line = wp.types.vector(length=cols + 2 * M - 1, dtype=dtype)
    vec = wp.types.vector(length=width, dtype=dtype)
    arrv = wp.array(dtype=vec)
    alone = -1  # load_line's window row when no window holds the line's values
    lo, hi = -M // width, (cols + M - 1) // width  # the blocks a line reaches, relative to the tile's first
    load, put = vector_access(width, dtype)

    @wp.func
    def get(f: arrv, i: int) -> vec:
        return load(f, i)

    @wp.func
    def get(f: Any, i: int) -> vec:  # noqa: F811 (a Warp overload)
        r = vec()
        for j in range(wp.static(width)):
            r[j] = value(f, i * wp.static(width) + j)
        return r

    # Scaled and Normal on arrays of vectors (base in vectors): their `value`s a block at a time
    ScaledV, NormalV, scaled_v, normal_v = make_products(ns, arrv)

    @wp.func
    def get(a: ScaledV, i: int) -> vec:  # noqa: F811
        g = load(a.g, i)
        m = load(a.m, i - a.base)
        r = vec()
        for j in range(wp.static(width)):
            r[j] = a.dt * m[j] * g[j] * a.inv_dx
        return r

    @wp.func
    def get(a: NormalV, i: int) -> vec:  # noqa: F811
        gx = load(a.gx, i)
        gz = load(a.gz, i)
        p = load(a.p, i - a.base)
        q = load(a.q, i - a.base)
        r = vec()
        for j in range(wp.static(width)):
            u, _ = normal_rates(p[j], q[j], a.dt * gx[j], a.dt * gz[j])
            r[j] = u * a.inv_dx
        return r

    @wp.func
    def dline(r: line, j: int) -> dtype:
        # x-derivative (times dx) at column j of a tile from a line centred between r[j + M - 1] and r[j + M]
        acc = dtype(0.0)
        for m in range(wp.static(M)):
            acc += dtype(wp.static(C[m])) * (r[j + wp.static(M) + m] - r[j + wp.static(M - 1) - m])
        return acc

    @wp.func
    def tile(t: int, lz: int, lx: int, core: wp.vec4i):
        # tile t of the core (x fastest, then rows, then shots): flat field and model indices of its first cell,
        # its first row and its number of columns (< cols at the core's right edge)
        nxc = (core[3] - core[2] + wp.static(cols - 1)) // wp.static(cols)
        blocks = (core[1] - core[0] + wp.static(rows - 1)) // wp.static(rows)
        q = t // nxc
        x = core[2] + (t - q * nxc) * wp.static(cols)
        s = q // blocks
        z = core[0] + (q - s * blocks) * wp.static(rows)
        c = z * lx + x
        return s * lz * lx + c, c, z, wp.min(wp.static(cols), core[3] - x)

    @wp.func
    def place(t: int, lz: int, lx: int, core: wp.vec4i):
        # tile t's field and model vector indices, first row, and vectors per row (cols = width, core's columns
        # from and to multiples of it)
        i, c, z, _ = tile(t, lz, lx, core)
        return i // wp.static(width), c // wp.static(width), z, lx // wp.static(width)

    @wp.func
    def load_window(f: Any, i: int, n: int, first: int) -> win:
        # f at rows first .. first + 2M - 1 (relative to block i, n blocks per row) of the tile's columns
        w = win()
        for m in range(wp.static(2 * M)):
            for b in range(wp.static(cols // width)):
                a = get(f, i + b + (first + m) * n)
                for j in range(wp.static(width)):
                    w[wp.static(b * width) + j, m] = a[j]
        return w

    @wp.func
    def slide(w: win, f: Any, i: int, n: int, newest: int) -> win:
        # the window one row further down: f at row `newest` (relative to i) enters
        for j in range(wp.static(cols)):
            for m in range(wp.static(2 * M - 1)):
                w[j, m] = w[j, m + 1]
        for b in range(wp.static(cols // width)):
            a = get(f, i + b + newest * n)
            for j in range(wp.static(width)):
                w[wp.static(b * width) + j, wp.static(2 * M - 1)] = a[j]
        return w

    @wp.func
    def load_line(f: Any, i: int, first: int, w: win, m: int) -> line:
        # f at columns first .. first + cols + 2M - 2 (relative to the tile's first, block i), read from the blocks
        # that hold them (the neighbours' too); the tile's own columns r[j - first] are taken from the window's
        # row m (m = alone: from f)
        r = line()
        for q in range(wp.static(hi - lo + 1)):
            b = q + wp.static(lo)
            o = b * wp.static(width)  # the block's first column
            if o + wp.static(width) > first and o < first + wp.static(cols + 2 * M - 1):
                if m == wp.static(alone) or o < 0 or o >= wp.static(cols):
                    a = get(f, i + b)
                    for j in range(wp.static(width)):
                        p = o + j - first
                        if p >= 0 and p < wp.static(cols + 2 * M - 1):
                            r[p] = a[j]
                else:
                    for j in range(wp.static(width)):
                        r[o + j - first] = w[o + j, m]
        return r

    return vec, arrv, alone, get, put, dline, tile, place, load_window, slide, load_line, scaled_v, normal_v


def _update_tiles(ns, rows: int, cols: int, lean: bool):
    """make_updates' tiles: velocity_cell and stress_cell without CPML and surface, on a tile of rows x cols cells."""
    M, dtype, tiling, advance, dwin, normal_rates = ns.M, ns.dtype, ns.tiling, ns.advance, ns.dwin, ns.normal_rates
    vec, arrv, alone, get, put, dline, _, place, load_window, slide, load_line, _, _ = tiling(rows, cols, cols)
    nodes = wp.types.vector(length=cols + 1, dtype=dtype)  # lean: a model row at the tile's columns and the next

    @wp.func
    def load_nodes(f: arrv, c: int) -> nodes:
        a = get(f, c)
        r = nodes()
        for p in range(wp.static(cols)):
            r[p] = a[p]
        e = get(f, c + 1)
        r[wp.static(cols)] = e[0]
        return r

    @wp.func
    def reciprocals(u: nodes) -> nodes:
        r = nodes()
        for p in range(wp.static(cols + 1)):
            r[p] = dtype(1.0) / u[p]
        return r

    @wp.func
    def velocity_tile(
        vx: arrv, vz: arrv, sxx: arrv, szz: arrv, sxz: arrv, m1: arrv, m2: arrv, vx_new: arrv, vz_new: arrv,
        t: int, lz: int, lx: int, core: wp.vec4i, dt: dtype, inv_dx: dtype,
    ):  # fmt: skip
        # velocity_cell without CPML and surface; m1, m2 = bx, bz, or (lean) m1 = 1/rho and bx, bz its means
        i, c, z, n = place(t, lz, lx, core)
        wa = load_window(sxz, i, n, wp.static(-M))  # sxz at rows z - M .. z + M - 1 (for vx)
        wb = load_window(szz, i, n, wp.static(1 - M))  # szz at rows z - M + 1 .. z + M (for vz)
        b0 = nodes()  # lean: 1/rho at row z and z + 1, columns x .. x + cols
        b1 = nodes()
        if wp.static(lean):
            b1 = load_nodes(m1, c)
        for k in range(wp.static(rows)):
            if z + k < core[1]:
                ra = load_line(sxx, i, wp.static(1 - M), wa, wp.static(alone))  # sxx at x - M + 1 ..
                rb = load_line(sxz, i, wp.static(-M), wa, wp.static(M))  # sxz at x - M ..
                ux = get(vx, i)
                uz = get(vz, i)
                if wp.static(lean):
                    b0 = b1
                    b1 = load_nodes(m1, c + n)
                else:
                    bx = get(m1, c)
                    bz = get(m2, c)
                ox = vec()
                oz = vec()
                for j in range(wp.static(cols)):
                    if wp.static(lean):
                        mx = dtype(0.5) * (b0[j] + b0[j + 1])
                        mz = dtype(0.5) * (b0[j] + b1[j])
                    else:
                        mx = bx[j]
                        mz = bz[j]
                    ox[j] = advance(ux[j], dt, mx, dline(ra, j) * inv_dx + dwin(wa[j]) * inv_dx)
                    oz[j] = advance(uz[j], dt, mz, dline(rb, j) * inv_dx + dwin(wb[j]) * inv_dx)
                put(vx_new, i, ox)
                put(vz_new, i, oz)
                if wp.static(k + 1 < rows):
                    wa = slide(wa, sxz, i, n, wp.static(M))
                    wb = slide(wb, szz, i, n, wp.static(M + 1))
                i += n
                c += n

    @wp.func
    def stress_tile(
        vx: arrv, vz: arrv, sxx: arrv, szz: arrv, sxz: arrv, m1: arrv, m2: arrv, m3: arrv,
        sxx_new: arrv, szz_new: arrv, sxz_new: arrv, t: int, lz: int, lx: int, core: wp.vec4i, dt: dtype, inv_dx: dtype,
    ):  # fmt: skip
        # stress_cell without CPML and surface; m1, m2, m3 = l2m, lam, muh, or (lean) m1 = l2m, m2 = mu with
        # lam = l2m - 2 mu and muh the harmonic mean of mu at the shear node's four neighbours (0 if one is 0)
        i, c, z, n = place(t, lz, lx, core)
        wa = load_window(vz, i, n, wp.static(-M))  # vz at rows z - M .. z + M - 1 (normal stresses)
        wb = load_window(vx, i, n, wp.static(1 - M))  # vx at rows z - M + 1 .. z + M (sxz)
        u0 = nodes()  # lean: mu and 1/mu at rows z and z + 1, columns x .. x + cols
        u1 = nodes()
        q0 = nodes()
        q1 = nodes()
        if wp.static(lean):
            u1 = load_nodes(m2, c)
            q1 = reciprocals(u1)
        for k in range(wp.static(rows)):
            if z + k < core[1]:
                ra = load_line(vx, i, wp.static(-M), wb, wp.static(M - 1))  # vx at x - M ..
                rb = load_line(vz, i, wp.static(1 - M), wa, wp.static(M))  # vz at x - M + 1 ..
                axx = get(sxx, i)
                azz = get(szz, i)
                axz = get(sxz, i)
                l2m = get(m1, c)
                if wp.static(lean):
                    u0 = u1
                    q0 = q1
                    u1 = load_nodes(m2, c + n)
                    q1 = reciprocals(u1)
                else:
                    lam = get(m2, c)
                    muh = get(m3, c)
                oxx = vec()
                ozz = vec()
                oxz = vec()
                for j in range(wp.static(cols)):
                    c1 = l2m[j]
                    if wp.static(lean):
                        c2 = c1 - dtype(2.0) * u0[j]
                        h = dtype(0.0)
                        if u0[j] > dtype(0.0) and u1[j] > dtype(0.0) and u0[j + 1] > dtype(0.0) and u1[j + 1] > dtype(0.0):
                            h = dtype(4.0) / (q0[j] + q1[j] + q0[j + 1] + q1[j + 1])
                    else:
                        c2 = lam[j]
                        h = muh[j]
                    sxx_rate, szz_rate = normal_rates(c1, c2, dline(ra, j) * inv_dx, dwin(wa[j]) * inv_dx)
                    oxx[j] = axx[j] + dt * sxx_rate
                    ozz[j] = azz[j] + dt * szz_rate
                    oxz[j] = advance(axz[j], dt, h, dwin(wb[j]) * inv_dx + dline(rb, j) * inv_dx)
                put(sxx_new, i, oxx)
                put(szz_new, i, ozz)
                put(sxz_new, i, oxz)
                if wp.static(k + 1 < rows):
                    wa = slide(wa, vz, i, n, wp.static(M))
                    wb = slide(wb, vx, i, n, wp.static(M + 1))
                i += n
                c += n

    return velocity_tile, stress_tile


def make_updates(ns, rows: int, cols: int, lean: bool):
    # The fast path's (velocity, stress) kernels for core tiles of rows x cols cells (see Layout). One 1D launch
    # (unravelling a multi-dimensional thread index costs 64-bit divisions) covers threads offset + tid: those
    # below `tiles` update a core tile each, on the flat arrays viewed as vectors of cols values (arrv; fields
    # S * Lz * Lx / cols, models Lz * Lx / cols; the core's columns start and end at multiples of cols), those
    # from `frame` on (a block boundary) one frame cell each with the reference's per-cell code. A tile loads and
    # stores its cells of a row as one vector per array, keeps the z-stencil's values in sliding windows w[j, m]
    # (column j, row m) and loads each value of a row along x once into a line r[p], sharing it between the
    # tile's columns; the loop over rows is unrolled. Every sum is formed in the reference's order, so a tile
    # reproduces the per-cell kernels bit for bit where the compiler contracts no multiply-adds (the CPU).
    dtype, arr2, arr3, Axis = ns.dtype, ns.arr2, ns.arr3, ns.Axis
    frame_cell, velocity_cell, stress_cell = ns.frame_cell, ns.velocity_cell, ns.stress_cell
    arrv = ns.tiling(rows, cols, cols)[1]
    velocity_tile, stress_tile = _update_tiles(ns, rows, cols, lean)

    @unique_kernel(grid_stride=False, enable_backward=False)
    def velocity_update(
        vx: arr3, vz: arr3, sxx: arr3, szz: arr3, sxz: arr3, bx: arr2, bz: arr2,
        p_vx_x: arr3, p_vx_z: arr3, p_vz_x: arr3, p_vz_z: arr3,
        n_vx_x: arr3, n_vx_z: arr3, n_vz_x: arr3, n_vz_z: arr3,
        vx_new: arr3, vz_new: arr3, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int, core: wp.vec4i,
        f_vx: arrv, f_vz: arrv, f_sxx: arrv, f_szz: arrv, f_sxz: arrv, m1: arrv, m2: arrv, f_vx_new: arrv, f_vz_new: arrv,
        tiles: int, frame: int, frame_cells: int, offset: int,
    ):  # fmt: skip
        # f_*: the fields as vectors; m1, m2: the core's model arrays (see velocity_tile)
        t = wp.tid() + offset
        lz = vx.shape[1]
        lx = vx.shape[2]
        if t < tiles:
            velocity_tile(f_vx, f_vz, f_sxx, f_szz, f_sxz, m1, m2, f_vx_new, f_vz_new, t, lz, lx, core, dt, inv_dx)
        elif t >= frame:
            s = (t - frame) // frame_cells
            z, x = frame_cell(t - frame - s * frame_cells, lz, lx, core)
            velocity_cell(vx, vz, sxx, szz, sxz, bx, bz, p_vx_x, p_vx_z, p_vz_x, p_vz_z, n_vx_x, n_vx_z, n_vz_x, n_vz_z,
                          vx_new, vz_new, az, ax, dt, inv_dx, top, s, z, x)  # fmt: skip

    @unique_kernel(grid_stride=False, enable_backward=False)
    def stress_update(
        vx: arr3, vz: arr3, sxx: arr3, szz: arr3, sxz: arr3, l2m: arr2, lam: arr2, mu: arr2, muh: arr2,
        p_s_x: arr3, p_s_z: arr3, p_xz_z: arr3, p_xz_x: arr3,
        n_s_x: arr3, n_s_z: arr3, n_xz_z: arr3, n_xz_x: arr3,
        sxx_new: arr3, szz_new: arr3, sxz_new: arr3, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int, core: wp.vec4i,
        f_vx: arrv, f_vz: arrv, f_sxx: arrv, f_szz: arrv, f_sxz: arrv, m1: arrv, m2: arrv, m3: arrv,
        f_sxx_new: arrv, f_szz_new: arrv, f_sxz_new: arrv, tiles: int, frame: int, frame_cells: int, offset: int,
    ):  # fmt: skip
        t = wp.tid() + offset
        lz = vx.shape[1]
        lx = vx.shape[2]
        if t < tiles:
            stress_tile(f_vx, f_vz, f_sxx, f_szz, f_sxz, m1, m2, m3, f_sxx_new, f_szz_new, f_sxz_new, t, lz, lx, core, dt, inv_dx)
        elif t >= frame:
            s = (t - frame) // frame_cells
            z, x = frame_cell(t - frame - s * frame_cells, lz, lx, core)
            stress_cell(vx, vz, sxx, szz, sxz, l2m, lam, mu, muh, p_s_x, p_s_z, p_xz_z, p_xz_x, n_s_x, n_s_z, n_xz_z, n_xz_x,
                        sxx_new, szz_new, sxz_new, az, ax, dt, inv_dx, top, s, z, x)  # fmt: skip

    return velocity_update, stress_update


# --- hand-written adjoints ------------------------------------------------------------------------
# In place: one adjoint State goes from level n + 1's to level n's (adj(old field) = adj(new field) + the gathers' terms;
# each thread reads an adjoint field's cell before writing it and writes no other thread's). Pass 1 (`*_adjoint`,
# thread per interior cell outside `hole` (frame_cell), all shots): the materials' adjoints (added), the CPML memory
# variables' (in place), and t_k = adjoint of the k-th raw stencil sum into the scratch arrays (0 on surface rows,
# which scatter theirs). Pass 2 (`*_gather`, launched by `*_transpose` or make_adjoints' kernels, which fuse it with
# pass 1 inside the hole): adj(inputs) += transposed stencils of t_k, gathered.
def _velocity_adjoints(ns):
    """The velocity half step's hand-written adjoint: pass 1 and pass 2."""
    dtype, arr1, arr2, arr3, Axis = ns.dtype, ns.arr1, ns.arr2, ns.arr3, ns.Axis
    frame_cell, column, surface_row, cpml_value, psi_adjoint, cpml_t = (ns.frame_cell, ns.column, ns.surface_row, ns.cpml_value,
                                                                        ns.psi_adjoint, ns.cpml_t)  # fmt: skip
    dx_of_int, dx_of_half, dz_sxz, dz_szz = ns.dx_of_int, ns.dx_of_half, ns.dz_sxz, ns.dz_szz
    dxt_of_int, dxt_of_half, dzt_sxz, dzt_szz, gather_int, gather_half = (ns.dxt_of_int, ns.dxt_of_half, ns.dzt_sxz, ns.dzt_szz,
                                                                          ns.gather_int, ns.gather_half)  # fmt: skip


    @unique_kernel(grid_stride=False, enable_backward=False)
    def velocity_adjoint(
        sxx: arr3, szz: arr3, sxz: arr3, bx: arr2, bz: arr2, n_vx_x: arr3, n_vx_z: arr3, n_vz_x: arr3, n_vz_z: arr3,
        g_vx: arr3, g_vz: arr3, g_sxx: arr3, g_szz: arr3, g_sxz: arr3, g_bx: arr2, g_bz: arr2, gp_vx_x: arr3, gp_vx_z: arr3,
        gp_vz_x: arr3, gp_vz_z: arr3, t1: arr3, t2: arr3, t3: arr3, t4: arr3, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int,
        hole: wp.vec4i,
    ):  # fmt: skip
        z, x = frame_cell(wp.tid(), sxx.shape[1], sxx.shape[2], hole)
        jz = az.store[z]
        jx = ax.store[x]
        b1 = bx[z, x]
        b2 = bz[z, x]
        g1 = g_bx[z, x]
        g2 = g_bz[z, x]
        acc1 = dtype(0.0)
        acc2 = dtype(0.0)
        scatter = surface_row(z, top)
        for s in range(sxx.shape[0]):  # (loads first: see cpml_psi)
            ga = g_vx[s, z, x]
            gb = g_vz[s, z, x]
            d1 = cpml_value(dx_of_int(sxx, s, z, x) * inv_dx, jx, n_vx_x, s, z, jx)
            d2 = cpml_value(dz_sxz(sxz, s, z, x, top) * inv_dx, jz, n_vx_z, s, jz, x)
            d3 = cpml_value(dx_of_half(sxz, s, z, x) * inv_dx, jx, n_vz_x, s, z, jx)
            d4 = cpml_value(dz_szz(szz, s, z, x, top) * inv_dx, jz, n_vz_z, s, jz, x)
            q1, pa1, pb1 = psi_adjoint(jx, x, ax.ah, ax.bh, gp_vx_x, s, z, jx)
            q2, pa2, pb2 = psi_adjoint(jz, z, az.a, az.b, gp_vx_z, s, jz, x)
            q3, pa3, pb3 = psi_adjoint(jx, x, ax.a, ax.b, gp_vz_x, s, z, jx)
            q4, pa4, pb4 = psi_adjoint(jz, z, az.ah, az.bh, gp_vz_z, s, jz, x)
            acc1 += dt * ga * (d1 + d2)
            acc2 += dt * gb * (d3 + d4)
            ha = dt * b1 * ga
            hb = dt * b2 * gb
            a1 = cpml_t(ha, jx, q1, pa1, pb1, gp_vx_x, s, z, jx) * inv_dx
            a2 = cpml_t(ha, jz, q2, pa2, pb2, gp_vx_z, s, jz, x) * inv_dx
            a3 = cpml_t(hb, jx, q3, pa3, pb3, gp_vz_x, s, z, jx) * inv_dx
            a4 = cpml_t(hb, jz, q4, pa4, pb4, gp_vz_z, s, jz, x) * inv_dx
            if scatter:
                dxt_of_int(g_sxx, s, z, x, a1)
                dzt_sxz(g_sxz, s, z, x, top, a2)
                dxt_of_half(g_sxz, s, z, x, a3)
                dzt_szz(g_szz, s, z, x, top, a4)
                a1 = dtype(0.0)
                a2 = dtype(0.0)
                a3 = dtype(0.0)
                a4 = dtype(0.0)
            t1[s, z, x] = a1
            t2[s, z, x] = a2
            t3[s, z, x] = a3
            t4[s, z, x] = a4
        g_bx[z, x] = g1 + acc1
        g_bz[z, x] = g2 + acc2

    @wp.func
    def velocity_gather(t1: arr1, t2: arr1, t3: arr1, t4: arr1, g_sxx: arr1, g_szz: arr1, g_sxz: arr1, i: int, lx: int):
        # pass 2 at flat index i: t1 = adj of dx_of_int(sxx), t2 of dz_sxz (half nodes in), t3 of dx_of_half(sxz), t4 of dz_szz
        g_sxx[i] = g_sxx[i] + gather_int(t1, i, 1)
        g_sxz[i] = g_sxz[i] + gather_half(t2, i, lx) + gather_half(t3, i, 1)
        g_szz[i] = g_szz[i] + gather_int(t4, i, lx)

    @unique_kernel(grid_stride=False, enable_backward=False)
    def velocity_transpose(t1: arr1, t2: arr1, t3: arr1, t4: arr1, g_sxx: arr1, g_szz: arr1, g_sxz: arr1,
                           lz: int, lx: int, box: wp.vec4i, rows: int):  # fmt: skip
        i, c, n = column(wp.tid(), lz, lx, box, rows)
        for k in range(n):
            velocity_gather(t1, t2, t3, t4, g_sxx, g_szz, g_sxz, i, lx)
            i += lx

    return dict(velocity_adjoint=velocity_adjoint, velocity_gather=velocity_gather, velocity_transpose=velocity_transpose)


def _stress_adjoints(ns):
    """The stress half step's hand-written adjoint: pass 1 and pass 2."""
    fs, dtype, arr1, arr2, arr3, Axis = ns.fs, ns.dtype, ns.arr1, ns.arr2, ns.arr3, ns.Axis
    frame_cell, column, surface_row, cpml_value, psi_adjoint, cpml_t = (ns.frame_cell, ns.column, ns.surface_row, ns.cpml_value,
                                                                        ns.psi_adjoint, ns.cpml_t)  # fmt: skip
    surface_modulus, normal_rates = ns.surface_modulus, ns.normal_rates
    dx_of_int, dx_of_half, dvz_normal, dvx_shear = ns.dx_of_int, ns.dx_of_half, ns.dvz_normal, ns.dvx_shear
    dxt_of_int, dxt_of_half, dvz_normal_t, dvx_shear_t, gather_int, gather_half = (
        ns.dxt_of_int, ns.dxt_of_half, ns.dvz_normal_t, ns.dvx_shear_t, ns.gather_int, ns.gather_half)  # fmt: skip

    @unique_kernel(grid_stride=False, enable_backward=False)
    def stress_adjoint(
        vx: arr3, vz: arr3, l2m: arr2, lam: arr2, mu: arr2, muh: arr2, n_s_x: arr3, n_s_z: arr3, n_xz_z: arr3, n_xz_x: arr3,
        g_sxx: arr3, g_szz: arr3, g_sxz: arr3, g_vx: arr3, g_vz: arr3, g_l2m: arr2, g_lam: arr2, g_mu: arr2, g_muh: arr2,
        gp_s_x: arr3, gp_s_z: arr3, gp_xz_z: arr3, gp_xz_x: arr3, t1: arr3, t2: arr3, t3: arr3, t4: arr3, az: Axis, ax: Axis, dt: dtype,
        inv_dx: dtype, top: int, hole: wp.vec4i,
    ):  # fmt: skip
        z, x = frame_cell(wp.tid(), vx.shape[1], vx.shape[2], hole)
        jz = az.store[z]
        jx = ax.store[x]
        c1 = l2m[z, x]
        c2 = lam[z, x]
        c3 = mu[z, x]
        c4 = muh[z, x]
        g1 = g_l2m[z, x]
        g2 = g_lam[z, x]
        g3 = g_mu[z, x]
        g4 = g_muh[z, x]
        acc_l2m = dtype(0.0)
        acc_lam = dtype(0.0)
        acc_mu = dtype(0.0)
        acc_muh = dtype(0.0)
        scatter = surface_row(z, top)
        surface = False
        if wp.static(fs):
            surface = z == top
        for s in range(vx.shape[0]):  # (loads first: see cpml_psi)
            gxx = g_sxx[s, z, x]
            gzz = g_szz[s, z, x]
            gxz = g_sxz[s, z, x]
            dvx = cpml_value(dx_of_half(vx, s, z, x) * inv_dx, jx, n_s_x, s, z, jx)
            dvz = cpml_value(dvz_normal(vz, s, z, x, top) * inv_dx, jz, n_s_z, s, jz, x)
            e1 = cpml_value(dvx_shear(vx, s, z, x, top) * inv_dx, jz, n_xz_z, s, jz, x)
            e2 = cpml_value(dx_of_int(vz, s, z, x) * inv_dx, jx, n_xz_x, s, z, jx)
            q1, pa1, pb1 = psi_adjoint(jx, x, ax.a, ax.b, gp_s_x, s, z, jx)
            q2, pa2, pb2 = psi_adjoint(jz, z, az.a, az.b, gp_s_z, s, jz, x)
            q3, pa3, pb3 = psi_adjoint(jz, z, az.ah, az.bh, gp_xz_z, s, jz, x)
            q4, pa4, pb4 = psi_adjoint(jx, x, ax.ah, ax.bh, gp_xz_x, s, z, jx)
            hxx = dt * gxx
            hzz = dt * gzz
            if surface:  # sxx += dt q dvx with q = 4 mu (lam + mu) / l2m; szz = 0
                q = surface_modulus(c1, c2, c3)
                gq = hxx * dvx
                acc_mu += gq * dtype(4.0) * (c2 + dtype(2.0) * c3) / c1
                acc_lam += gq * dtype(4.0) * c3 / c1
                acc_l2m -= gq * q / c1
                gdvx = q * hxx
                gdvz = dtype(0.0)
            else:
                acc_l2m += hxx * dvx + hzz * dvz
                acc_lam += hxx * dvz + hzz * dvx
                gdvx, gdvz = normal_rates(c1, c2, hxx, hzz)
            acc_muh += dt * gxz * (e1 + e2)
            he = dt * c4 * gxz
            a1 = cpml_t(gdvx, jx, q1, pa1, pb1, gp_s_x, s, z, jx) * inv_dx
            a2 = cpml_t(gdvz, jz, q2, pa2, pb2, gp_s_z, s, jz, x) * inv_dx
            a3 = cpml_t(he, jz, q3, pa3, pb3, gp_xz_z, s, jz, x) * inv_dx
            a4 = cpml_t(he, jx, q4, pa4, pb4, gp_xz_x, s, z, jx) * inv_dx
            if surface:
                g_szz[s, z, x] = dtype(0.0)
            if scatter:
                dxt_of_half(g_vx, s, z, x, a1)
                dvz_normal_t(g_vz, s, z, x, top, a2)
                dvx_shear_t(g_vx, s, z, x, top, a3)
                dxt_of_int(g_vz, s, z, x, a4)
                a1 = dtype(0.0)
                a2 = dtype(0.0)
                a3 = dtype(0.0)
                a4 = dtype(0.0)
            t1[s, z, x] = a1
            t2[s, z, x] = a2
            t3[s, z, x] = a3
            t4[s, z, x] = a4
        g_l2m[z, x] = g1 + acc_l2m
        g_lam[z, x] = g2 + acc_lam
        g_mu[z, x] = g3 + acc_mu
        g_muh[z, x] = g4 + acc_muh

    @wp.func
    def stress_gather(t1: arr1, t2: arr1, t3: arr1, t4: arr1, g_vx: arr1, g_vz: arr1, i: int, lx: int):
        # pass 2 at flat index i: t1 = adj of dx_of_half(vx), t2 of dz_vz (half nodes in), t3 of dz_vx, t4 of dx_of_int(vz)
        g_vx[i] = g_vx[i] + gather_half(t1, i, 1) + gather_int(t3, i, lx)
        g_vz[i] = g_vz[i] + gather_half(t2, i, lx) + gather_int(t4, i, 1)

    @unique_kernel(grid_stride=False, enable_backward=False)
    def stress_transpose(t1: arr1, t2: arr1, t3: arr1, t4: arr1, g_vx: arr1, g_vz: arr1,
                         lz: int, lx: int, box: wp.vec4i, rows: int):  # fmt: skip
        i, c, n = column(wp.tid(), lz, lx, box, rows)
        for k in range(n):
            stress_gather(t1, t2, t3, t4, g_vx, g_vz, i, lx)
            i += lx

    return dict(stress_adjoint=stress_adjoint, stress_gather=stress_gather, stress_transpose=stress_transpose)


def _shots(ns):
    """The materials' adjoints of the tiles with several shots: a shot's term (add_shot), and their sum (sum_shots)."""
    dtype, arr1 = ns.dtype, ns.arr1

    @wp.func
    def add_shot(g: Any, t: Any, c: int, i: int, term: Any, shots: int):
        # one shot's term of a material's adjoint at model index c: added, as pass 1 adds 0 + term, or with several shots
        # kept in the scratch t at the shot's flat index i for sum_shots (values, or vectors at vector indices)
        if shots == 1:
            g[c] = g[c] + term
        else:
            t[i] = term

    @wp.func
    def shot_sum(t: arr1, g: arr1, c: int, cells: int, shots: int):
        acc = dtype(0.0)
        for s in range(shots):
            acc += t[s * cells + c]
        g[c] = g[c] + acc

    @unique_kernel(grid_stride=False, enable_backward=False)
    def sum_shots(t1: arr1, t2: arr1, t3: arr1, g1: arr1, g2: arr1, g3: arr1, count: int, shots: int, lz: int, lx: int, inner: wp.vec4i):
        # g_k += the sum over the shots of t_k, k < count (2 or 3), at the cells of `inner`, in pass 1's order
        q = wp.tid()
        nx = inner[3] - inner[2]
        r = q // nx
        c = (inner[0] + r) * lx + inner[2] + q - r * nx
        shot_sum(t1, g1, c, lz * lx, shots)
        shot_sum(t2, g2, c, lz * lx, shots)
        if count == 3:
            shot_sum(t3, g3, c, lz * lx, shots)

    return dict(add_shot=add_shot, sum_shots=sum_shots)


def make_adjoints(ns, rows: int, cols: int):
    # The (velocity, stress) kernels of pass 2 fused with pass 1 inside the hole (Elastic.adjoint_update), one 1D
    # launch each, laid out as make_updates': threads below `tiles` take a tile of rows x cols cells of `box` (the
    # cells whose gathers read t_k of core cells alone) of one shot; those from `frame` (a block boundary) gather one
    # cell outside `box` (frame_cells per shot) from the scratch. A tile gathers t_k of core cells from sliding
    # windows and lines of their raw products (Scaled, Normal) and, inside `inner` (the hole of pass 1, which wrote
    # t_k of the ring box - inner that the frame's gathers read), does pass 1's work too (add_shot). Every sum in the
    # per-cell kernels' order (a transposed stencil is its derivative negated, exactly): bit for bit on the CPU.
    M, dtype, arr1, tiling, dwin, scaled, normal = ns.M, ns.dtype, ns.arr1, ns.tiling, ns.dwin, ns.scaled, ns.normal
    frame_cell, inside, add_shot, velocity_gather, stress_gather = (ns.frame_cell, ns.inside, ns.add_shot, ns.velocity_gather,
                                                                    ns.stress_gather)  # fmt: skip
    _, _, alone, _, _, dline, tile, _, load_window, slide, load_line, _, _ = tiling(rows, cols, 1)

    @wp.func
    def velocity_tile(
        sxx: arr1, szz: arr1, sxz: arr1, bx: arr1, bz: arr1, g_vx: arr1, g_vz: arr1, g_sxx: arr1, g_szz: arr1, g_sxz: arr1,
        g_bx: arr1, g_bz: arr1, t1: arr1, t2: arr1, t: int, shots: int, lz: int, lx: int, box: wp.vec4i, inner: wp.vec4i, dt: dtype, inv_dx: dtype,
    ):  # fmt: skip
        i, c, z, ncol = tile(t, lz, lx, box)
        x = c - z * lx
        ta = scaled(g_vx, bx, i - c, dt, inv_dx)  # t1 = t2 of velocity_adjoint
        tb = scaled(g_vz, bz, i - c, dt, inv_dx)  # t3 = t4
        wa = load_window(sxz, i, lx, wp.static(-M))  # sxz at rows z - M .. z + M - 1 (d2)
        wb = load_window(szz, i, lx, wp.static(1 - M))  # szz at rows z - M + 1 .. z + M (d4)
        w2 = load_window(ta, i, lx, wp.static(1 - M))  # t2 at rows z - M + 1 .. z + M
        w4 = load_window(tb, i, lx, wp.static(-M))  # t4 at rows z - M .. z + M - 1
        for k in range(wp.static(rows)):
            if z + k < box[1]:
                ra = load_line(sxx, i, wp.static(1 - M), wa, wp.static(alone))  # sxx at x - M + 1 .. (d1)
                rb = load_line(sxz, i, wp.static(-M), wa, wp.static(M))  # sxz at x - M .. (d3)
                r1 = load_line(ta, i, wp.static(-M), w2, wp.static(M - 1))  # t1 at x - M ..
                r3 = load_line(tb, i, wp.static(1 - M), w4, wp.static(M))  # t3 at x - M + 1 ..
                for j in range(wp.static(cols)):
                    if j < ncol:
                        g_sxx[i + j] = g_sxx[i + j] - dline(r1, j)
                        g_sxz[i + j] = g_sxz[i + j] - dwin(w2[j]) - dline(r3, j)
                        g_szz[i + j] = g_szz[i + j] - dwin(w4[j])
                        if inside(z + k, x + j, inner):
                            ga = g_vx[i + j]
                            gb = g_vz[i + j]
                            add_shot(g_bx, t1, c + j, i + j, dt * ga * (dline(ra, j) * inv_dx + dwin(wa[j]) * inv_dx), shots)
                            add_shot(g_bz, t2, c + j, i + j, dt * gb * (dline(rb, j) * inv_dx + dwin(wb[j]) * inv_dx), shots)
                if wp.static(k + 1 < rows):
                    wa = slide(wa, sxz, i, lx, wp.static(M))
                    wb = slide(wb, szz, i, lx, wp.static(M + 1))
                    w2 = slide(w2, ta, i, lx, wp.static(M + 1))
                    w4 = slide(w4, tb, i, lx, wp.static(M))
                i += lx
                c += lx

    @wp.func
    def stress_tile(
        vx: arr1, vz: arr1, l2m: arr1, lam: arr1, muh: arr1, g_sxx: arr1, g_szz: arr1, g_sxz: arr1, g_vx: arr1, g_vz: arr1,
        g_l2m: arr1, g_lam: arr1, g_muh: arr1, t1: arr1, t2: arr1, t3: arr1, t: int, shots: int, lz: int, lx: int, box: wp.vec4i,
        inner: wp.vec4i, dt: dtype, inv_dx: dtype,
    ):  # fmt: skip
        i, c, z, ncol = tile(t, lz, lx, box)
        x = c - z * lx
        tx = normal(g_sxx, g_szz, l2m, lam, i - c, dt, inv_dx)  # t1 of stress_adjoint
        tz = normal(g_sxx, g_szz, lam, l2m, i - c, dt, inv_dx)  # t2
        ts = scaled(g_sxz, muh, i - c, dt, inv_dx)  # t3 = t4
        wa = load_window(vz, i, lx, wp.static(-M))  # vz at rows z - M .. z + M - 1 (dvz)
        wb = load_window(vx, i, lx, wp.static(1 - M))  # vx at rows z - M + 1 .. z + M (e1)
        w2 = load_window(tz, i, lx, wp.static(1 - M))  # t2 at rows z - M + 1 .. z + M
        w3 = load_window(ts, i, lx, wp.static(-M))  # t3 at rows z - M .. z + M - 1
        for k in range(wp.static(rows)):
            if z + k < box[1]:
                ra = load_line(vx, i, wp.static(-M), wb, wp.static(M - 1))  # vx at x - M .. (dvx)
                rb = load_line(vz, i, wp.static(1 - M), wa, wp.static(M))  # vz at x - M + 1 .. (e2)
                r1 = load_line(tx, i, wp.static(1 - M), w2, wp.static(alone))  # t1 at x - M + 1 ..
                r4 = load_line(ts, i, wp.static(-M), w3, wp.static(M))  # t4 at x - M ..
                for j in range(wp.static(cols)):
                    if j < ncol:
                        g_vx[i + j] = g_vx[i + j] - dline(r1, j) - dwin(w3[j])
                        g_vz[i + j] = g_vz[i + j] - dwin(w2[j]) - dline(r4, j)
                        if inside(z + k, x + j, inner):
                            gxx = g_sxx[i + j]
                            gzz = g_szz[i + j]
                            gxz = g_sxz[i + j]
                            dvx = dline(ra, j) * inv_dx
                            dvz = dwin(wa[j]) * inv_dx
                            hxx = dt * gxx
                            hzz = dt * gzz
                            add_shot(g_l2m, t1, c + j, i + j, hxx * dvx + hzz * dvz, shots)
                            add_shot(g_lam, t2, c + j, i + j, hxx * dvz + hzz * dvx, shots)
                            add_shot(g_muh, t3, c + j, i + j, dt * gxz * (dwin(wb[j]) * inv_dx + dline(rb, j) * inv_dx), shots)
                if wp.static(k + 1 < rows):
                    wa = slide(wa, vz, i, lx, wp.static(M))
                    wb = slide(wb, vx, i, lx, wp.static(M + 1))
                    w2 = slide(w2, tz, i, lx, wp.static(M + 1))
                    w3 = slide(w3, ts, i, lx, wp.static(M))
                i += lx
                c += lx

    @unique_kernel(grid_stride=False, enable_backward=False)
    def velocity_fused(
        sxx: arr1, szz: arr1, sxz: arr1, bx: arr1, bz: arr1, g_vx: arr1, g_vz: arr1, g_sxx: arr1, g_szz: arr1, g_sxz: arr1,
        g_bx: arr1, g_bz: arr1, t1: arr1, t2: arr1, t3: arr1, t4: arr1,
        lz: int, lx: int, shots: int, box: wp.vec4i, inner: wp.vec4i, dt: dtype, inv_dx: dtype, tiles: int, frame: int,
        frame_cells: int,
    ):  # fmt: skip
        t = wp.tid()
        if t < tiles:
            velocity_tile(sxx, szz, sxz, bx, bz, g_vx, g_vz, g_sxx, g_szz, g_sxz, g_bx, g_bz, t1, t2, t, shots, lz, lx, box, inner,
                          dt, inv_dx)  # fmt: skip
        elif t >= frame:
            s = (t - frame) // frame_cells
            z, x = frame_cell(t - frame - s * frame_cells, lz, lx, box)
            velocity_gather(t1, t2, t3, t4, g_sxx, g_szz, g_sxz, (s * lz + z) * lx + x, lx)

    @unique_kernel(grid_stride=False, enable_backward=False)
    def stress_fused(
        vx: arr1, vz: arr1, l2m: arr1, lam: arr1, muh: arr1, g_sxx: arr1, g_szz: arr1, g_sxz: arr1, g_vx: arr1, g_vz: arr1,
        g_l2m: arr1, g_lam: arr1, g_muh: arr1, t1: arr1, t2: arr1, t3: arr1, t4: arr1, lz: int, lx: int, shots: int, box: wp.vec4i,
        inner: wp.vec4i, dt: dtype, inv_dx: dtype, tiles: int, frame: int, frame_cells: int,
    ):  # fmt: skip
        t = wp.tid()
        if t < tiles:
            stress_tile(vx, vz, l2m, lam, muh, g_sxx, g_szz, g_sxz, g_vx, g_vz, g_l2m, g_lam, g_muh, t1, t2, t3, t, shots, lz, lx, box,
                        inner, dt, inv_dx)  # fmt: skip
        elif t >= frame:
            s = (t - frame) // frame_cells
            z, x = frame_cell(t - frame - s * frame_cells, lz, lx, box)
            stress_gather(t1, t2, t3, t4, g_vx, g_vz, (s * lz + z) * lx + x, lx)

    return velocity_fused, stress_fused


def _split_gathers(ns, rows: int, width: int):
    """make_split_adjoints' gathers: make_adjoints' tiles' gathers on vectors."""
    M, dtype, tiling, dwin = ns.M, ns.dtype, ns.tiling, ns.dwin
    vec, arrv, alone, get, put, dline, _, place, load_window, slide, load_line, scaled_v, normal_v = tiling(rows, width, width)

    @wp.func
    def velocity_gathers_tile(
        bx: arrv, bz: arrv, g_vx: arrv, g_vz: arrv, g_sxx: arrv, g_szz: arrv, g_sxz: arrv,
        t: int, lz: int, lx: int, box: wp.vec4i, dt: dtype, inv_dx: dtype,
    ):  # fmt: skip
        i, c, z, n = place(t, lz, lx, box)
        ta = scaled_v(g_vx, bx, i - c, dt, inv_dx)  # t1 = t2 of velocity_adjoint
        tb = scaled_v(g_vz, bz, i - c, dt, inv_dx)  # t3 = t4
        w2 = load_window(ta, i, n, wp.static(1 - M))  # t2 at rows z - M + 1 .. z + M
        w4 = load_window(tb, i, n, wp.static(-M))  # t4 at rows z - M .. z + M - 1
        for k in range(wp.static(rows)):
            if z + k < box[1]:
                r1 = load_line(ta, i, wp.static(-M), w2, wp.static(M - 1))  # t1 at x - M ..
                r3 = load_line(tb, i, wp.static(1 - M), w4, wp.static(M))  # t3 at x - M + 1 ..
                a = get(g_sxx, i)
                b = get(g_sxz, i)
                d = get(g_szz, i)
                oa = vec()
                ob = vec()
                od = vec()
                for j in range(wp.static(width)):
                    oa[j] = a[j] - dline(r1, j)
                    ob[j] = b[j] - dwin(w2[j]) - dline(r3, j)
                    od[j] = d[j] - dwin(w4[j])
                put(g_sxx, i, oa)
                put(g_sxz, i, ob)
                put(g_szz, i, od)
                if wp.static(k + 1 < rows):
                    w2 = slide(w2, ta, i, n, wp.static(M + 1))
                    w4 = slide(w4, tb, i, n, wp.static(M))
                i += n

    @wp.func
    def stress_gathers_tile(
        l2m: arrv, lam: arrv, muh: arrv, g_sxx: arrv, g_szz: arrv, g_sxz: arrv, g_vx: arrv, g_vz: arrv,
        t: int, lz: int, lx: int, box: wp.vec4i, dt: dtype, inv_dx: dtype,
    ):  # fmt: skip
        i, c, z, n = place(t, lz, lx, box)
        tx = normal_v(g_sxx, g_szz, l2m, lam, i - c, dt, inv_dx)  # t1 of stress_adjoint
        tz = normal_v(g_sxx, g_szz, lam, l2m, i - c, dt, inv_dx)  # t2
        ts = scaled_v(g_sxz, muh, i - c, dt, inv_dx)  # t3 = t4
        w2 = load_window(tz, i, n, wp.static(1 - M))  # t2 at rows z - M + 1 .. z + M
        w3 = load_window(ts, i, n, wp.static(-M))  # t3 at rows z - M .. z + M - 1
        for k in range(wp.static(rows)):
            if z + k < box[1]:
                r1 = load_line(tx, i, wp.static(1 - M), w2, wp.static(alone))  # t1 at x - M + 1 ..
                r4 = load_line(ts, i, wp.static(-M), w3, wp.static(M))  # t4 at x - M ..
                a = get(g_vx, i)
                b = get(g_vz, i)
                oa = vec()
                ob = vec()
                for j in range(wp.static(width)):
                    oa[j] = a[j] - dline(r1, j) - dwin(w3[j])
                    ob[j] = b[j] - dwin(w2[j]) - dline(r4, j)
                put(g_vx, i, oa)
                put(g_vz, i, ob)
                if wp.static(k + 1 < rows):
                    w2 = slide(w2, tz, i, n, wp.static(M + 1))
                    w3 = slide(w3, ts, i, n, wp.static(M))
                i += n

    return velocity_gathers_tile, stress_gathers_tile


def _split_sums(ns, rows: int, width: int):
    """make_split_adjoints' sums: make_adjoints' tiles' pass 1 work on vectors, at their cells inside `inner`."""
    M, dtype, tiling, dwin = ns.M, ns.dtype, ns.tiling, ns.dwin
    vec, arrv, alone, get, put, dline, _, place, load_window, slide, load_line, _, _ = tiling(rows, width, width)

    @wp.func
    def shot_old(g: arrv, c: int, shots: int) -> vec:
        # what add_shot_v adds to: g's vector at c with one shot
        if shots == 1:
            return get(g, c)
        return vec()

    @wp.func
    def add_shot_v(g: arrv, t: arrv, c: int, i: int, old: vec, term: vec, shots: int):
        # add_shot on vectors (one access each), g's old value loaded beforehand (shot_old: loads before stores)
        if shots == 1:
            put(g, c, old + term)
        else:
            put(t, i, term)

    @wp.func
    def within(c: int, z: int, lx: int, inner: wp.vec4i) -> bool:
        # whether the columns of the tile at model vector index c, row z lie in inner
        x = c * wp.static(width) - z * lx
        return x >= inner[2] and x < inner[3]

    @wp.func
    def velocity_sums_tile(
        sxx: arrv, szz: arrv, sxz: arrv, g_vx: arrv, g_vz: arrv, g_bx: arrv, g_bz: arrv, t1: arrv, t2: arrv, t: int, shots: int, lz: int,
        lx: int, box: wp.vec4i, inner: wp.vec4i, dt: dtype, inv_dx: dtype,
    ):  # fmt: skip
        i, c, z, n = place(t, lz, lx, box)
        if within(c, z, lx, inner):
            wa = load_window(sxz, i, n, wp.static(-M))  # sxz at rows z - M .. z + M - 1 (d2)
            wb = load_window(szz, i, n, wp.static(1 - M))  # szz at rows z - M + 1 .. z + M (d4)
            for k in range(wp.static(rows)):
                if z + k < inner[1]:
                    if z + k >= inner[0]:
                        ra = load_line(sxx, i, wp.static(1 - M), wa, wp.static(alone))  # sxx at x - M + 1 .. (d1)
                        rb = load_line(sxz, i, wp.static(-M), wa, wp.static(M))  # sxz at x - M .. (d3)
                        ga = get(g_vx, i)
                        gb = get(g_vz, i)
                        oa = shot_old(g_bx, c, shots)
                        ob = shot_old(g_bz, c, shots)
                        ea = vec()
                        eb = vec()
                        for j in range(wp.static(width)):
                            ea[j] = dt * ga[j] * (dline(ra, j) * inv_dx + dwin(wa[j]) * inv_dx)
                            eb[j] = dt * gb[j] * (dline(rb, j) * inv_dx + dwin(wb[j]) * inv_dx)
                        add_shot_v(g_bx, t1, c, i, oa, ea, shots)
                        add_shot_v(g_bz, t2, c, i, ob, eb, shots)
                    if wp.static(k + 1 < rows):
                        wa = slide(wa, sxz, i, n, wp.static(M))
                        wb = slide(wb, szz, i, n, wp.static(M + 1))
                    i += n
                    c += n

    @wp.func
    def stress_sums_tile(
        vx: arrv, vz: arrv, g_sxx: arrv, g_szz: arrv, g_sxz: arrv, g_l2m: arrv, g_lam: arrv, g_muh: arrv, t1: arrv, t2: arrv,
        t3: arrv, t: int, shots: int, lz: int, lx: int, box: wp.vec4i, inner: wp.vec4i, dt: dtype, inv_dx: dtype,
    ):  # fmt: skip
        i, c, z, n = place(t, lz, lx, box)
        if within(c, z, lx, inner):
            wa = load_window(vz, i, n, wp.static(-M))  # vz at rows z - M .. z + M - 1 (dvz)
            wb = load_window(vx, i, n, wp.static(1 - M))  # vx at rows z - M + 1 .. z + M (e1)
            for k in range(wp.static(rows)):
                if z + k < inner[1]:
                    if z + k >= inner[0]:
                        ra = load_line(vx, i, wp.static(-M), wb, wp.static(M - 1))  # vx at x - M .. (dvx)
                        rb = load_line(vz, i, wp.static(1 - M), wa, wp.static(M))  # vz at x - M + 1 .. (e2)
                        gxx = get(g_sxx, i)
                        gzz = get(g_szz, i)
                        gxz = get(g_sxz, i)
                        o1 = shot_old(g_l2m, c, shots)
                        o2 = shot_old(g_lam, c, shots)
                        o3 = shot_old(g_muh, c, shots)
                        e1 = vec()
                        e2 = vec()
                        e3 = vec()
                        for j in range(wp.static(width)):
                            dvx = dline(ra, j) * inv_dx
                            dvz = dwin(wa[j]) * inv_dx
                            hxx = dt * gxx[j]
                            hzz = dt * gzz[j]
                            e1[j] = hxx * dvx + hzz * dvz
                            e2[j] = hxx * dvz + hzz * dvx
                            e3[j] = dt * gxz[j] * (dwin(wb[j]) * inv_dx + dline(rb, j) * inv_dx)
                        add_shot_v(g_l2m, t1, c, i, o1, e1, shots)
                        add_shot_v(g_lam, t2, c, i, o2, e2, shots)
                        add_shot_v(g_muh, t3, c, i, o3, e3, shots)
                    if wp.static(k + 1 < rows):
                        wa = slide(wa, vz, i, n, wp.static(M))
                        wb = slide(wb, vx, i, n, wp.static(M + 1))
                    i += n
                    c += n

    return velocity_sums_tile, stress_sums_tile


def make_split_adjoints(ns, rows: int, width: int):
    # The adjoint box's two passes with fewer live values than make_adjoints' (AdjointLayout.split), on the flat arrays
    # viewed as vectors of `width` values (arrv), each tile row one vector (the boxes' columns from and to multiples of
    # it): `*_gathers_tile` do make_adjoints' tiles' gathers (box: their `box`), `*_sums_tile` the tiles' pass 1 work
    # at their cells inside `inner`, one after the other (no value passes between them), a thread a tile of `box`. The
    # same sums as make_adjoints', in the same order.
    dtype, arr1, frame_cell, velocity_gather, stress_gather = ns.dtype, ns.arr1, ns.frame_cell, ns.velocity_gather, ns.stress_gather
    arrv = ns.tiling(rows, width, width)[1]
    velocity_gathers_tile, stress_gathers_tile = _split_gathers(ns, rows, width)
    velocity_sums_tile, stress_sums_tile = _split_sums(ns, rows, width)

    # what: 1 the gathers (tiles t < tiles, and the frame's threads t >= frame), 2 the sums' tiles, 3 both. The two read
    # the same adjoint fields at a tile's cells and write different arrays; together they read them once from memory.
    @unique_kernel(grid_stride=False, enable_backward=False)
    def velocity_split(
        bx: arrv, bz: arrv, g_vx: arrv, g_vz: arrv, g_sxx: arrv, g_szz: arrv, g_sxz: arrv, sxx: arrv, szz: arrv, sxz: arrv,
        g_bx: arrv, g_bz: arrv, s1: arrv, s2: arrv, t1: arr1, t2: arr1, t3: arr1, t4: arr1, f_sxx: arr1, f_szz: arr1, f_sxz: arr1,
        shots: int, lz: int, lx: int, box: wp.vec4i, inner: wp.vec4i, dt: dtype, inv_dx: dtype, tiles: int, frame: int, frame_cells: int,
        what: int,
    ):  # fmt: skip
        # s1, s2: the scratch t1, t2 as vectors (the sums' terms with several shots); f_*: g_sxx, g_szz, g_sxz as flat arrays
        t = wp.tid()
        if t < tiles:  # (the sums first: their last loads then wait on no store of the gathers')
            if what != 1:
                velocity_sums_tile(sxx, szz, sxz, g_vx, g_vz, g_bx, g_bz, s1, s2, t, shots, lz, lx, box, inner, dt, inv_dx)
            if what != 2:
                velocity_gathers_tile(bx, bz, g_vx, g_vz, g_sxx, g_szz, g_sxz, t, lz, lx, box, dt, inv_dx)
        elif t >= frame:
            s = (t - frame) // frame_cells
            z, x = frame_cell(t - frame - s * frame_cells, lz, lx, box)
            velocity_gather(t1, t2, t3, t4, f_sxx, f_szz, f_sxz, (s * lz + z) * lx + x, lx)

    @unique_kernel(grid_stride=False, enable_backward=False)
    def stress_split(
        l2m: arrv, lam: arrv, muh: arrv, g_sxx: arrv, g_szz: arrv, g_sxz: arrv, g_vx: arrv, g_vz: arrv, vx: arrv, vz: arrv,
        g_l2m: arrv, g_lam: arrv, g_muh: arrv, s1: arrv, s2: arrv, s3: arrv, t1: arr1, t2: arr1, t3: arr1, t4: arr1, f_vx: arr1,
        f_vz: arr1, shots: int, lz: int, lx: int, box: wp.vec4i, inner: wp.vec4i, dt: dtype, inv_dx: dtype, tiles: int, frame: int,
        frame_cells: int, what: int,
    ):  # fmt: skip
        t = wp.tid()
        if t < tiles:
            if what != 1:
                stress_sums_tile(vx, vz, g_sxx, g_szz, g_sxz, g_l2m, g_lam, g_muh, s1, s2, s3, t, shots, lz, lx, box, inner, dt, inv_dx)
            if what != 2:
                stress_gathers_tile(l2m, lam, muh, g_sxx, g_szz, g_sxz, g_vx, g_vz, t, lz, lx, box, dt, inv_dx)
        elif t >= frame:
            s = (t - frame) // frame_cells
            z, x = frame_cell(t - frame - s * frame_cells, lz, lx, box)
            stress_gather(t1, t2, t3, t4, f_vx, f_vz, (s * lz + z) * lx + x, lx)

    return velocity_split, stress_split


def _layouts(ns):
    """The tiled kernels' builders, by layout (each built on its first use): tiling, and Kernels' updates, adjoints and
    split_adjoints."""

    def cached(make):
        return functools.lru_cache(maxsize=None)(functools.partial(make, ns))

    return dict(tiling=cached(make_tiling), updates=cached(make_updates), adjoints=cached(make_adjoints),
                split_adjoints=cached(make_split_adjoints))  # fmt: skip


def _materials(ns):
    """The models' kernels: MATERIALS from the padded vp, vs, rho (materials), padding (pad_model), adding (add_into)."""
    M, dtype, arr2 = ns.M, ns.dtype, ns.arr2

    @unique_kernel
    def materials(vp: arr2, vs: arr2, rho: arr2, bx: arr2, bz: arr2, l2m: arr2, lam: arr2, mu: arr2, muh: arr2, b: arr2):
        # MATERIALS at the interior nodes: buoyancy at vx and vz nodes, lambda + 2 mu, lambda, mu at the
        # normal-stress nodes, the harmonic mean of the 4 neighbouring mu at the shear nodes, and 1/rho at the
        # normal-stress nodes (for the lean core, which forms bx, bz from it as here)
        zi, xi = wp.tid()
        z = zi + wp.static(M)
        x = xi + wp.static(M)
        r = rho[z, x]
        b[z, x] = dtype(1.0) / r
        bx[z, x] = dtype(0.5) * (dtype(1.0) / r + dtype(1.0) / rho[z, x + 1])
        bz[z, x] = dtype(0.5) * (dtype(1.0) / r + dtype(1.0) / rho[z + 1, x])
        m1 = r * vs[z, x] * vs[z, x]
        m2 = rho[z + 1, x] * vs[z + 1, x] * vs[z + 1, x]
        m3 = rho[z, x + 1] * vs[z, x + 1] * vs[z, x + 1]
        m4 = rho[z + 1, x + 1] * vs[z + 1, x + 1] * vs[z + 1, x + 1]
        c = r * vp[z, x] * vp[z, x]
        l2m[z, x] = c
        lam[z, x] = c - dtype(2.0) * m1
        mu[z, x] = m1
        h = dtype(0.0)
        if m1 > dtype(0.0) and m2 > dtype(0.0) and m3 > dtype(0.0) and m4 > dtype(0.0):
            h = dtype(4.0) / (dtype(1.0) / m1 + dtype(1.0) / m2 + dtype(1.0) / m3 + dtype(1.0) / m4)
        muh[z, x] = h

    @unique_kernel(enable_backward=False)
    def add_into(g: arr2, b: arr2):
        # g += b (a model-shaped adjoint kept apart, added at the end)
        z, x = wp.tid()
        g[z, x] = g[z, x] + b[z, x]

    @unique_kernel
    def pad_model(v: arr2, vpad: arr2, origin: wp.vec2i):
        # padded model from the physical one, extended by edge replication into PML and halo
        z, x = wp.tid()
        vpad[z, x] = v[wp.clamp(z - origin[0], 0, v.shape[0] - 1), wp.clamp(x - origin[1], 0, v.shape[1] - 1)]

    return dict(materials=materials, add_into=add_into, pad_model=pad_model)


def make_point(ns, hicks, oz: float, ox: float, odd: bool):
    # q-th operator node of a field whose index (i, k) sits at (i + oz, k + ox): padded index, weight
    HR, W, fs, dtype, arr3 = ns.HR, ns.W, ns.fs, ns.dtype, ns.arr3
    fold = 1 if oz > 0.0 else 0

    @wp.func
    def point(loc: arr3, s: int, n: int, q: int, origin: wp.vec2i, inv_dx: dtype, top: int):
        zc = loc[s, n, 0] * inv_dx + dtype(origin[0]) - dtype(wp.static(oz))
        xc = loc[s, n, 1] * inv_dx + dtype(origin[1]) - dtype(wp.static(ox))
        iz = int(wp.floor(zc)) - wp.static(HR - 1) + q // wp.static(W)
        ix = int(wp.floor(xc)) - wp.static(HR - 1) + q % wp.static(W)
        w = hicks(dtype(iz) - zc, zc) * hicks(dtype(ix) - xc, xc)
        if wp.static(fs):
            if wp.static(odd and fold == 0):
                if iz == top:
                    w = dtype(0.0)
            if iz + wp.static(fold) <= top - wp.static(1 - fold):
                iz = 2 * top - wp.static(fold) - iz
                if wp.static(odd):
                    w = -w
        return wp.vec2i(iz, ix), w

    return point


def _sources(ns):
    """The sources' injection, at their locations or through fixed operators, and the fixed operators (weights)."""
    dtype, arr2, arr3, arr4, iarr1 = ns.dtype, ns.arr2, ns.arr3, ns.arr4, ns.iarr1
    hicks = hicks_axis(dtype)
    pt_vx = make_point(ns, hicks, 0.0, 0.5, False)
    pt_vz = make_point(ns, hicks, 0.5, 0.0, False)
    pt_sxx = make_point(ns, hicks, 0.0, 0.0, False)
    pt_szz = make_point(ns, hicks, 0.0, 0.0, True)
    pt_sxz = make_point(ns, hicks, 0.5, 0.5, True)

    @wp.func
    def add_force(vx: arr3, vz: arr3, bx: arr2, bz: arr2, a: dtype, fz: dtype, fx: dtype, s: int, i: wp.vec2i, w: dtype, j: wp.vec2i,
                  u: dtype):  # fmt: skip
        # one operator point of a line force: vx += a bx w fx at node i, vz += a bz u fz at node j (points of weight 0 skipped)
        if w != dtype(0.0):
            wp.atomic_add(vx, s, i[0], i[1], a * bx[i[0], i[1]] * w * fx)
        if u != dtype(0.0):
            wp.atomic_add(vz, s, j[0], j[1], a * bz[j[0], j[1]] * u * fz)

    @wp.func
    def add_moment(f: arr3, s: int, i: wp.vec2i, w: dtype, a: dtype, m: dtype):
        if w != dtype(0.0):
            wp.atomic_add(f, s, i[0], i[1], a * w * m)

    @unique_kernel
    def inject_force(
        vx: arr3, vz: arr3, bx: arr2, bz: arr2, amp: arr3, comp: arr3, loc: arr3, n: int, clock: iarr1,
        origin: wp.vec2i, scale: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        # v += dt b f(t_n) w / dx^2 (scale = dt / dx^2); comp (S, n_src, 2) = (f_z, f_x) direction weights.
        # Here and in the other source/receiver kernels the sample is n + clock[0] (a device counter, for
        # graph replays).
        s, src, q = wp.tid()
        a = scale * amp[s, src, n + clock[0]]
        i, w = pt_vx(loc, s, src, q, origin, inv_dx, top)
        j, u = pt_vz(loc, s, src, q, origin, inv_dx, top)
        add_force(vx, vz, bx, bz, a, comp[s, src, 0], comp[s, src, 1], s, i, w, j, u)

    @unique_kernel
    def inject_force_op(
        vx: arr3, vz: arr3, bx: arr2, bz: arr2, amp: arr3, comp: arr3, idx: wp.array4d(dtype=wp.vec2i), wts: arr4, n: int, clock: iarr1,
        scale: dtype,
    ):  # fmt: skip
        # inject_force through the fixed operator (idx, wts) of Elastic.operator (sources whose locations are not differentiated)
        s, src, q = wp.tid()
        a = scale * amp[s, src, n + clock[0]]
        add_force(vx, vz, bx, bz, a, comp[s, src, 0], comp[s, src, 1], s, idx[0, s, src, q], wts[0, s, src, q], idx[1, s, src, q],
                  wts[1, s, src, q])  # fmt: skip

    @unique_kernel
    def inject_moment(
        sxx: arr3, szz: arr3, sxz: arr3, amp: arr3, comp: arr3, loc: arr3, n: int, clock: iarr1,
        origin: wp.vec2i, scale: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        # s_ij -= (M(t_{n+1}) - M(t_n)) m_ij w / dx^2 (scale = 1 / dx^2); comp (S, n_src, 3) = (Mxx, Mzz, Mxz)
        s, src, q = wp.tid()
        a = -scale * (amp[s, src, n + clock[0] + 1] - amp[s, src, n + clock[0]])
        i, w = pt_sxx(loc, s, src, q, origin, inv_dx, top)
        add_moment(sxx, s, i, w, a, comp[s, src, 0])
        i, w = pt_szz(loc, s, src, q, origin, inv_dx, top)
        add_moment(szz, s, i, w, a, comp[s, src, 1])
        i, w = pt_sxz(loc, s, src, q, origin, inv_dx, top)
        add_moment(sxz, s, i, w, a, comp[s, src, 2])

    @unique_kernel
    def inject_moment_op(
        sxx: arr3, szz: arr3, sxz: arr3, amp: arr3, comp: arr3, idx: wp.array4d(dtype=wp.vec2i), wts: arr4, n: int, clock: iarr1,
        scale: dtype,
    ):  # fmt: skip
        s, src, q = wp.tid()
        a = -scale * (amp[s, src, n + clock[0] + 1] - amp[s, src, n + clock[0]])
        add_moment(sxx, s, idx[2, s, src, q], wts[2, s, src, q], a, comp[s, src, 0])
        add_moment(szz, s, idx[3, s, src, q], wts[3, s, src, q], a, comp[s, src, 1])
        add_moment(sxz, s, idx[4, s, src, q], wts[4, s, src, q], a, comp[s, src, 2])

    @unique_kernel(enable_backward=False)  # computed once per run, never differentiated (locations are fixed)
    def weights(loc: arr3, origin: wp.vec2i, inv_dx: dtype, top: int, idx: wp.array4d(dtype=wp.vec2i), w: arr4):
        # fixed operators, computed once per run: node and weight of point q of location r for vx, vz, sxx, szz, sxz
        # (first index)
        s, r, q = wp.tid()
        i, wq = pt_vx(loc, s, r, q, origin, inv_dx, top)
        idx[0, s, r, q] = i
        w[0, s, r, q] = wq
        i, wq = pt_vz(loc, s, r, q, origin, inv_dx, top)
        idx[1, s, r, q] = i
        w[1, s, r, q] = wq
        i, wq = pt_sxx(loc, s, r, q, origin, inv_dx, top)
        idx[2, s, r, q] = i
        w[2, s, r, q] = wq
        i, wq = pt_szz(loc, s, r, q, origin, inv_dx, top)
        idx[3, s, r, q] = i
        w[3, s, r, q] = wq
        i, wq = pt_sxz(loc, s, r, q, origin, inv_dx, top)
        idx[4, s, r, q] = i
        w[4, s, r, q] = wq

    return dict(inject_force=inject_force, inject_force_op=inject_force_op, inject_moment=inject_moment,
                inject_moment_op=inject_moment_op, weights=weights)  # fmt: skip


def _receivers(ns):
    """Recording through the receivers' fixed operator (record), and its adjoint (record_adjoint)."""
    dtype, arr3, arr4, iarr1 = ns.dtype, ns.arr3, ns.arr4, ns.iarr1

    @unique_kernel
    def record(
        vx: arr3, vz: arr3, sxx: arr3, szz: arr3, d_vx: arr3, d_vz: arr3, d_p: arr3,
        idx: wp.array4d(dtype=wp.vec2i), w: arr4, n: int, clock: iarr1,
    ):  # fmt: skip
        s, r, q = wp.tid()
        t = n + clock[0]
        wq = w[0, s, r, q]
        if wq != dtype(0.0):
            i = idx[0, s, r, q]
            wp.atomic_add(d_vx, s, r, t, wq * vx[s, i[0], i[1]])
        wq = w[1, s, r, q]
        if wq != dtype(0.0):
            i = idx[1, s, r, q]
            wp.atomic_add(d_vz, s, r, t, wq * vz[s, i[0], i[1]])
        wq = w[2, s, r, q]
        if wq != dtype(0.0):
            i = idx[2, s, r, q]
            wp.atomic_add(d_p, s, r, t, dtype(-0.5) * wq * sxx[s, i[0], i[1]])
        wq = w[3, s, r, q]
        if wq != dtype(0.0):
            i = idx[3, s, r, q]
            wp.atomic_add(d_p, s, r, t, dtype(-0.5) * wq * szz[s, i[0], i[1]])

    @unique_kernel(enable_backward=False)
    def record_adjoint(
        g_vx: arr3, g_vz: arr3, g_sxx: arr3, g_szz: arr3, r_vx: arr3, r_vz: arr3, r_p: arr3,
        idx: wp.array4d(dtype=wp.vec2i), w: arr4, n: int, clock: iarr1,
    ):  # fmt: skip
        # record's adjoint: the fields' adjoints += the operator's transpose applied to sample n of the residuals; a zero
        # sample adds nothing and is skipped (a misfit of vz alone: one atomic a point, not four)
        s, r, q = wp.tid()
        t = n + clock[0]
        a = r_vx[s, r, t]
        if a != dtype(0.0):
            wq = w[0, s, r, q]
            i = idx[0, s, r, q]
            wp.atomic_add(g_vx, s, i[0], i[1], wq * a)
        a = r_vz[s, r, t]
        if a != dtype(0.0):
            wq = w[1, s, r, q]
            i = idx[1, s, r, q]
            wp.atomic_add(g_vz, s, i[0], i[1], wq * a)
        a = r_p[s, r, t]
        if a != dtype(0.0):
            wq = w[2, s, r, q]
            i = idx[2, s, r, q]
            wp.atomic_add(g_sxx, s, i[0], i[1], dtype(-0.5) * wq * a)
            wq = w[3, s, r, q]
            i = idx[3, s, r, q]
            wp.atomic_add(g_szz, s, i[0], i[1], dtype(-0.5) * wq * a)

    return dict(record=record, record_adjoint=record_adjoint)


@functools.lru_cache(maxsize=None)
def shear_ratio(dtype):
    """Kernel r = vs / vp on flat arrays (the on-device check of vs <= vp / sqrt(2))."""

    @unique_kernel(enable_backward=False)
    def ratio(vp: wp.array(dtype=dtype), vs: wp.array(dtype=dtype), r: wp.array(dtype=dtype)):
        i = wp.tid()
        r[i] = vs[i] / vp[i]

    return ratio


def cpml_axis(n_lo: int, n_hi: int, length: int, halo: int, dx: float, dt: float, vmax: float,
              reflection: float, frequency: float):  # fmt: skip
    """CPML of one axis at integer and half positions: (store, width, a, b, ah, bh).

    Profiles as kernels/acoustic.cpml_profile (d = d0 (x/L)^2, d0 = 3 vmax ln(1/R) / (2 L),
    alpha = pi f (1 - x/L)), x the depth into the layer of the position p (a, b) or p + 1/2 (ah, bh).
    store[p] = strip index for p in [0, halo + n_lo) and [length - halo - n_hi - 1, length), else -1.
    """
    pos = np.arange(length, dtype=float)
    first, last = halo + n_lo, length - halo - n_hi - 1  # first and last physical node

    def profile(shift):
        a, b = np.zeros(length), np.ones(length)
        for n, depth in ((n_lo, first - (pos + shift)), (n_hi, pos + shift - last)):
            if n == 0:
                continue
            frac = np.clip(depth / n, 0.0, 1.0)
            inside = depth > 0
            d = 3.0 * vmax * np.log(1.0 / reflection) / (2.0 * n * dx) * frac**2
            alpha = np.pi * frequency * (1.0 - frac)
            bb = np.exp(-(d + alpha) * dt)
            aa = np.where(d + alpha > 0, d * (bb - 1.0) / np.maximum(d + alpha, 1e-300), 0.0)
            a, b = np.where(inside, aa, a), np.where(inside, bb, b)
        return a, b

    store = -np.ones(length, dtype=np.int32)
    cells = ([*range(0, first)] if n_lo else []) + ([*range(last, length)] if n_hi else [])
    store[cells] = np.arange(len(cells), dtype=np.int32)
    return (store, max(len(cells), 1), *profile(0.0), *profile(0.5))


@functools.lru_cache(maxsize=32)
def cpml_axes(Axis, lo, n_hi: int, padded, halo: int, dx: float, dt: float, vmax: float, reflection: float, frequency: float,
              dtype, device):  # fmt: skip
    """The CPML of each axis of a staggered grid: ((Axis() with store, a, b, ah, bh as Warp arrays per axis), (strip
    width per axis)) from cpml_axis; lo: the layer's cells at each axis's low end (a tuple), n_hi: at its high end.
    Kept per argument set (the kernels only read the arrays): a repeated setup (an inversion's every evaluation, a
    benchmark's every call) neither recomputes nor uploads them (0.7-1.2 ms a VD1000 forward on an H200), and a kept
    time loop finds its own arrays (solve/loop.py: no copy)."""
    host = [cpml_axis(lo[a], n_hi, padded[a], halo, dx, dt, vmax, reflection, frequency) for a in range(len(padded))]
    # two uploads (a host-to-device copy each waits for the device), every axis's arrays views of them
    stores = wp.array(np.concatenate([h[0] for h in host]), dtype=wp.int32, device=device)
    profiles = wp.array(np.concatenate([p for h in host for p in h[2:]]), dtype=dtype, device=device)
    axes, widths = [], []
    for a, (_, width, *_) in enumerate(host):
        n, first = padded[a], sum(padded[:a])
        axis = Axis()
        axis.store = stores[first : first + n]
        for i, name in enumerate(("a", "b", "ah", "bh")):
            setattr(axis, name, profiles[4 * first + i * n : 4 * first + (i + 1) * n])
        axes.append(axis)
        widths.append(width)
    return tuple(axes), tuple(widths)


class State:
    """Fields at one time level n: vx, vz at t = (n - 1/2) dt, sxx, szz, sxz at t = n dt, and the CPML
    memory variables psi (dict, see PSI)."""

    def __init__(self, vx, vz, sxx, szz, sxz, psi):
        self.vx, self.vz, self.sxx, self.szz, self.sxz, self.psi = vx, vz, sxx, szz, sxz, psi

    def arrays(self):
        return [self.vx, self.vz, self.sxx, self.szz, self.sxz, *(self.psi[k] for k in PSI)]


class Elastic:
    """Launch helper: padded grid, CPML coefficients and one time step of the 2D elastic scheme.

    shape: physical grid (nz, nx) cells; dx (m), dt (s); pml_width cells on every absorbing side
    (all four, or three with free_surface); vmax: CPML reference speed (m/s). Positions passed to the
    source and receiver kernels are metres (z, x) from the physical grid's node 0.
    """

    def __init__(self, shape, dx, dt, order, n_shots, pml_width, pml_reflection, pml_frequency, vmax,
                 free_surface=False, dtype=wp.float32, device="cpu"):  # fmt: skip
        self.ndim = 2
        self.shape = tuple(int(n) for n in shape)
        self.dx, self.dt, self.order, self.n_shots = float(dx), float(dt), int(order), int(n_shots)
        self.dtype, self.device, self.free_surface = dtype, device, bool(free_surface)
        self.k = build(self.order, dtype, self.free_surface)
        R = self.k.halo
        nb = int(pml_width)
        lo = (0 if free_surface else nb, nb)
        self.padded = tuple(self.shape[a] + lo[a] + nb + 2 * R for a in range(2))
        self.origin = wp.vec2i(R + lo[0], R + lo[1])
        self.top = R
        self.axes, self.strip_width = cpml_axes(self.k.Axis, lo, nb, self.padded, R, dx, dt, vmax, pml_reflection, pml_frequency, dtype, device)
        Lz, Lx = self.padded
        # the cells that need neither CPML (cpml_axis's strips) nor the free surface's folded or shortened stencils
        # (rows top .. top + R - 1); the core (padded rows core[0]:core[1], columns core[2]:core[3]), their columns from
        # and to multiples of `lanes`, which the vector width of the core tiles divides (Elastic.width)
        z0 = 2 * R if free_surface else R + nb
        plain = (z0, Lz - R - nb - 1, R + nb, Lx - R - nb - 1)
        self.lanes = next(V for V in (4, 2, 1) if Lx % V == 0)
        self.core = aligned(*plain, self.lanes)
        core_cells = max(self.core[1] - self.core[0], 0) * max(self.core[3] - self.core[2], 0)
        self.frame_cells = (Lz - 2 * R) * (Lx - 2 * R) - core_cells
        fits = self.n_shots * Lz * Lx < 2**31  # int32 flat indices
        self.has_core = core_cells > 0 and fits
        self.box = wp.vec4i(R, Lz - R, R, Lx - R)  # the interior
        self.rows, self.block = TRANSPOSE_ROWS, TRANSPOSE_THREADS  # of the hand adjoints' gathers (_flat_launch)
        self.layout = CORE_LAYOUT
        self.interior = (self.n_shots, Lz - 2 * R, Lx - 2 * R)
        self.inv_dx = dtype(1.0 / dx)
        self.dt_device = dtype(dt)
        self.cuda = wp.get_device(device).is_cuda
        # The hand-written adjoint's fused tiles (make_adjoints; scalar, not aligned) take the adjoint box, the plain cells
        # less R on each side: a cell's gathers read t_k of the cells up to R away along z or x, which are plain cells' raw
        # products there. Pass 1 leaves them the inner box (the adjoint box less R more on each side), the cells no gather
        # outside the adjoint box reads, and writes t_k of the ring between the two. no_hole: pass 1 everywhere (the
        # per-cell path).
        self.adjoint_box = wp.vec4i(plain[0] + R, plain[1] - R, plain[2] + R, plain[3] - R)
        self.adjoint_inner = wp.vec4i(plain[0] + 2 * R, plain[1] - 2 * R, plain[2] + 2 * R, plain[3] - 2 * R)
        self.no_hole = wp.vec4i(R, R, R, R)
        self.has_adjoint_box = fits and min(plain[1] - plain[0], plain[3] - plain[2]) > 4 * R
        self.adjoint_layout = ADJOINT_LAYOUT[self.order] if self.cuda and self.has_adjoint_box else None  # None: the per-cell kernels
        self.clock = wp.zeros(1, dtype=wp.int32, device=device)  # stays 0: plain launches pass n itself

    def psi_shape(self, name):
        axis = PSI[name]
        shape = [self.n_shots, *self.padded]
        shape[axis + 1] = self.strip_width[axis]
        return tuple(shape)

    def new_state(self, requires_grad=False) -> State:
        def zeros(shape):
            return wp.zeros(shape, dtype=self.dtype, device=self.device, requires_grad=requires_grad)

        full = (self.n_shots, *self.padded)
        return State(*(zeros(full) for _ in range(5)), {k: zeros(self.psi_shape(k)) for k in PSI})

    def pad_model(self, m, requires_grad=False):
        """Padded model (Lz, Lx) from a physical one (wp.array2d (nz, nx))."""
        out = wp.zeros(self.padded, dtype=self.dtype, device=self.device, requires_grad=requires_grad)
        wp.launch(self.k.pad_model, dim=self.padded, inputs=[m, out, self.origin], device=self.device)
        return out

    def materials(self, vp, vs, rho, requires_grad=False, out=None):
        """MATERIALS (padded (Lz, Lx) arrays, interior nodes set) from the padded vp, vs, rho; into out (an earlier
        call's) if given."""
        if out is None:
            out = tuple(wp.zeros(self.padded, dtype=self.dtype, device=self.device, requires_grad=requires_grad) for _ in MATERIALS)
        wp.launch(self.k.materials, dim=self.interior[1:], inputs=[vp, vs, rho, *out], device=self.device)
        return out

    def _threads(self, box):
        return self.n_shots * -(-(box[1] - box[0]) // self.rows) * (box[3] - box[2])

    def _flat_launch(self, kernel, box, arrays, *extra):
        wp.launch(kernel, dim=self._threads(box), inputs=[*(a.flatten() for a in arrays), *self.padded, box, self.rows, *extra],
                  block_dim=self.block, device=self.device, record_tape=False)  # fmt: skip

    @property
    def width(self):
        """The core tiles' columns, a vector of each array: self.layout's, or fewer where the row length is no multiple."""
        return min(self.layout.cols, self.lanes)

    def update_kernels(self):
        """The fast path's (velocity, stress) kernels of self.layout."""
        return self.k.updates(self.layout.rows, self.width, self.layout.lean)

    def update(self, kind: int, st: State, out: State, mat, generated=False, part=None):
        """Half step `kind`: 0 = out's velocities from st's velocities and stresses, 1 = out's stresses from st's
        stresses and out's velocities (in place where out is st). The per-cell reference kernel when `generated`
        (recorded on the active tape) or without a core, else the core tiles and the frame (self.layout; part
        "core" or "frame": only that part, for timing)."""
        bx, bz, l2m, lam, mu, muh, b = mat
        P, Q = st.psi, out.psi
        common = [*self.axes, self.dt_device, self.inv_dx, self.top]
        if kind == 0:
            reference = self.k.velocity
            args = [st.vx, st.vz, st.sxx, st.szz, st.sxz, bx, bz, *(P[k] for k in PSI_V), *(Q[k] for k in PSI_V), out.vx, out.vz, *common]
            flat = [st.vx, st.vz, st.sxx, st.szz, st.sxz, *((b, b) if self.layout.lean else (bx, bz)), out.vx, out.vz]
        else:
            reference = self.k.stress
            args = [out.vx, out.vz, st.sxx, st.szz, st.sxz, l2m, lam, mu, muh, *(P[k] for k in PSI_S), *(Q[k] for k in PSI_S),
                    out.sxx, out.szz, out.sxz, *common]  # fmt: skip
            flat = [out.vx, out.vz, st.sxx, st.szz, st.sxz, *((l2m, mu, mu) if self.layout.lean else (l2m, lam, muh)), out.sxx, out.szz, out.sxz]
        if generated or not self.has_core:
            wp.launch(reference, dim=self.interior, inputs=args, device=self.device, record_tape=generated)
            return
        lay, c = self.layout, self.core
        tiles = self.n_shots * -(-(c[1] - c[0]) // lay.rows) * ((c[3] - c[2]) // self.width)
        frame = -(-tiles // lay.threads) * lay.threads  # the frame's first thread, on a block boundary
        cells = self.n_shots * self.frame_cells
        inputs = [*args, c, *(as_vectors(a, self.width) for a in flat), tiles, frame, self.frame_cells]
        launches = {"core": (tiles, 0), "frame": (cells, frame)}
        if part is not None:
            launches = {part: launches[part]}
        elif lay.merged:
            launches = {"all": (frame + cells, 0)}
        for dim, offset in launches.values():
            wp.launch(self.update_kernels()[kind], dim=dim, inputs=[*inputs, offset], block_dim=lay.threads, device=self.device,
                      record_tape=False)  # fmt: skip

    def _source_launch(self, out: State, mat, sources, n: int, clock):
        """(kernel, dim, inputs) injecting sample n (+ clock[0]) of sources into out: a force into its velocities,
        a moment into its stresses; at their locations, or through their fixed operator (Elastic.operator) in their place."""
        kind, amp, comp, loc = sources
        if isinstance(loc, tuple):
            fields = [out.vx, out.vz, mat[0], mat[1]] if kind == "force" else [out.sxx, out.szz, out.sxz]
            scale = self.dt / self.dx**2 if kind == "force" else 1.0 / self.dx**2
            kernel = self.k.inject_force_op if kind == "force" else self.k.inject_moment_op
            return kernel, loc[1].shape[1:], [*fields, amp, comp, *loc, n, clock, self.dtype(scale)]
        dim = (self.n_shots, loc.shape[1], self.k.operator_points)
        if kind == "force":
            return self.k.inject_force, dim, [out.vx, out.vz, mat[0], mat[1], amp, comp, loc, n, clock, self.origin,
                                              self.dtype(self.dt / self.dx**2), self.inv_dx, self.top]  # fmt: skip
        return self.k.inject_moment, dim, [out.sxx, out.szz, out.sxz, amp, comp, loc, n, clock, self.origin, self.dtype(1.0 / self.dx**2),
                                           self.inv_dx, self.top]  # fmt: skip

    def step(self, st: State, mat, sources, n: int, out: State | None = None, clock=None) -> State:
        """Advance st (level n) to level n + 1 with source sample n (+ clock[0], an int32 device array
        (1,), for graph replays). mat: MATERIALS (Elastic.materials); sources: (kind, amplitudes
        (S, n_src, nt), components, locations (S, n_src, 2) m or their Elastic.operator) with kind "force" or "moment",
        or None.
        With out=None the step is done in place (forward only); with `out` (other arrays: a kept level, or
        fresh ones under a tape) st is left unchanged and out is returned. Under an active wp.Tape the
        per-cell reference kernels are launched and recorded (Warp's generated adjoints)."""
        out = st if out is None else out
        clock = self.clock if clock is None else clock
        generated = wp._src.context.runtime.tape is not None

        def inject(kind):
            if sources is not None and sources[0] == kind:
                kernel, dim, inputs = self._source_launch(out, mat, sources, n, clock)
                wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)

        self.update(0, st, out, mat, generated)
        inject("force")
        self.update(1, st, out, mat, generated)
        inject("moment")
        return out

    def _outside(self, box):
        """Interior cells per shot outside box."""
        return math.prod(self.interior[1:]) - (box[1] - box[0]) * (box[3] - box[2])

    def _fused(self):
        return self.adjoint_layout is not None and self.has_adjoint_box

    @property
    def adjoint_width(self):
        """The split adjoint tiles' columns, a vector of each array: self.adjoint_layout's, or fewer where the row length is
        no multiple."""
        return min(self.adjoint_layout.cols, self.lanes)

    def adjoint_boxes(self):
        """(box, inner) of self.adjoint_layout: the adjoint box and the inner box, split their columns from and to
        multiples of adjoint_width (inner still R inside box along x, so that the frame's gathers read pass 1's t_k)."""
        if not self.adjoint_layout.split:
            return self.adjoint_box, self.adjoint_inner
        R, V = self.k.halo, self.adjoint_width
        b = aligned(*self.adjoint_box, V)
        inner = aligned(b[0] + R, b[1] - R, b[2] + R, b[3] - R, V)
        return (*(wp.vec4i(c[0], c[1], c[2], max(c[3], c[2])) for c in (b, inner)),)

    def _tiles(self, box, rows, cols):
        """Tiles of rows x cols cells covering box in every shot."""
        return self.n_shots * -(-(box[1] - box[0]) // rows) * -(-(box[3] - box[2]) // cols)

    def adjoint_kernels(self):
        """The kernels adjoint_update launches: pass 1 (velocity, stress), pass 2 (velocity, stress; with
        self.adjoint_layout the fused or split tiles and the frame's gathers) and, so with several shots, sum_shots."""
        k, lay = self.k, self.adjoint_layout
        if not self._fused():
            return k.velocity_adjoint, k.stress_adjoint, k.velocity_transpose, k.stress_transpose
        tiles = k.split_adjoints(lay.rows, self.adjoint_width) if lay.split else k.adjoints(lay.rows, lay.cols)
        return (k.velocity_adjoint, k.stress_adjoint, *tiles, *((k.sum_shots,) if self.n_shots > 1 else ()))

    def adjoint_update(self, kind: int, st: State, out: State, mat, adj: State, adj_mat, scratch, part=None):
        """Adjoint of update(kind, st, out, mat) out of place (st and out as it left them), in place in the adjoint State
        adj (out's on entry, st's on return), adj_mat as in adjoint_step. Kind 1 takes its update's memory variables'
        adjoints back a level and adds to adj's velocities and the moduli's adjoints; kind 0 takes its memory variables'
        back and adds to adj's stresses and the buoyancies' adjoints. Pass 1 (per cell, outside the inner box
        with self.adjoint_layout), then pass 2 (the gathers, or with self.adjoint_layout the fused tiles and the frame's
        gathers; split: the tiles' gathers and sums, in one launch where merged, and the frame's gathers); part "pass1" or
        "pass2" launches that alone, "tiles" pass 2's tiles alone (split: their gathers), "sums" the split tiles' sums
        alone (for timing)."""
        bx, bz, l2m, lam, mu, muh, _ = mat
        g_bx, g_bz, g_l2m, g_lam, g_mu, g_muh = adj_mat
        Q, G = out.psi, adj.psi
        if kind == 0:
            args = [st.sxx, st.szz, st.sxz, bx, bz, *(Q[k] for k in PSI_V), adj.vx, adj.vz, adj.sxx, adj.szz, adj.sxz, g_bx, g_bz,
                    *(G[k] for k in PSI_V)]  # fmt: skip
            flat = [st.sxx, st.szz, st.sxz, bx, bz, adj.vx, adj.vz, adj.sxx, adj.szz, adj.sxz, g_bx, g_bz]
            gathered = [adj.sxx, adj.szz, adj.sxz]
            summed = [g_bx, g_bz, g_bz]  # sum_shots' g1, g2 (and an unused g3)
            split = [bx, bz, adj.vx, adj.vz, *gathered, st.sxx, st.szz, st.sxz, g_bx, g_bz]  # the split kernels' vector arrays
        else:
            args = [out.vx, out.vz, l2m, lam, mu, muh, *(Q[k] for k in PSI_S), adj.sxx, adj.szz, adj.sxz, adj.vx, adj.vz, g_l2m, g_lam, g_mu,
                    g_muh, *(G[k] for k in PSI_S)]  # fmt: skip
            flat = [out.vx, out.vz, l2m, lam, muh, adj.sxx, adj.szz, adj.sxz, adj.vx, adj.vz, g_l2m, g_lam, g_muh]
            gathered = [adj.vx, adj.vz]
            summed = [g_l2m, g_lam, g_muh]
            split = [l2m, lam, muh, adj.sxx, adj.szz, adj.sxz, *gathered, out.vx, out.vz, g_l2m, g_lam, g_muh]
        kernels = self.adjoint_kernels()
        fused = self._fused()
        box, inner = self.adjoint_boxes() if fused else (self.box, self.no_hole)
        if part in (None, "pass1"):
            wp.launch(kernels[kind], dim=self._outside(inner), inputs=[*args, *scratch, *self.axes, self.dt_device, self.inv_dx, self.top, inner],
                      block_dim=PASS1_THREADS, device=self.device, record_tape=False)  # fmt: skip
        if part == "pass1":
            return
        if not fused:
            self._flat_launch(kernels[2 + kind], self.box, [*scratch, *gathered])
            return
        lay = self.adjoint_layout
        t = [a.flatten() for a in scratch]
        cells = self._outside(box)
        if lay.split:
            V = self.adjoint_width
            tiles = self._tiles(box, lay.rows, V)
            frame = -(-tiles // lay.threads) * lay.threads  # the frame's first thread, on a block boundary
            inputs = [*(as_vectors(a, V) for a in split + scratch[: 2 + kind]), *t, *(a.flatten() for a in gathered), self.n_shots,
                      *self.padded, box, inner, self.dt_device, self.inv_dx, tiles, frame, cells]  # fmt: skip
            whole = frame + self.n_shots * cells
            launches = {"sums": [(tiles, 2)], "tiles": [(tiles, 1)], None: [(whole, 3)] if lay.merged else [(tiles, 2), (whole, 1)]}
            for dim, what in launches[part if part in launches else None]:
                wp.launch(kernels[2 + kind], dim=dim, inputs=[*inputs, what], block_dim=lay.threads, device=self.device, record_tape=False)
        else:
            tiles = self._tiles(box, lay.rows, lay.cols)
            frame = -(-tiles // lay.threads) * lay.threads
            inputs = [*(a.flatten() for a in flat), *t, *self.padded, self.n_shots, box, inner]
            wp.launch(kernels[2 + kind], dim=tiles if part == "tiles" else frame + self.n_shots * cells,
                      inputs=[*inputs, self.dt_device, self.inv_dx, tiles, frame, cells], block_dim=lay.threads, device=self.device,
                      record_tape=False)  # fmt: skip
        if self.n_shots > 1 and part in (None, "pass2"):  # the materials' adjoints the tiles left in the scratch
            wp.launch(kernels[-1], dim=(inner[1] - inner[0]) * (inner[3] - inner[2]),
                      inputs=[*t[:3], *(a.flatten() for a in summed), 2 + kind, self.n_shots, *self.padded, inner], device=self.device,
                      record_tape=False)  # fmt: skip

    def adjoint_step(self, st: State, out: State, mat, adj: State, adj_mat, sources, adj_sources, scratch, n: int, clock=None, side=None):
        """Adjoint of step(st, mat, sources, n, out) (out-of-place, st and out as it left them): the hand-written
        adjoints of the half steps (adjoint_update) and Warp's generated ones of the source injection. adj: the adjoint
        State, level n + 1's on entry and level n's on return (in place; its halo cells are never read); adj_mat: the
        adjoints of MATERIALS but b (6 arrays (Lz, Lx)); adj_sources: of the sources' (amplitudes, components,
        locations; given a fixed operator, the locations' is left alone); both added to. scratch: four fields (S, Lz, Lx)
        whose halo is zero. side: None, or (stream, (g_bx, g_bz)) with a graphs.SideStream: a force's adjoint then runs
        on that stream beside the velocity half step's (E2000: 3.9 us a step), adding its buoyancies' adjoints to g_bx,
        g_bz (the caller adds those to adj_mat's at the end), not to adj_mat's, which the half step updates."""
        clock = self.clock if clock is None else clock

        def source_adjoint(kind, first, extra=()):  # adjoints of the injection's inputs, in launch order from `first` (the fields)
            if sources is not None and sources[0] == kind:
                kernel, dim, inputs = self._source_launch(out, mat, sources, n, clock)
                wrt = adj_sources[:2] if isinstance(sources[3], tuple) else adj_sources
                adjoint_launch(kernel, dim, inputs, dict(enumerate([*first, *extra, *wrt])), self.device)

        source_adjoint("moment", [adj.sxx, adj.szz, adj.sxz])
        self.adjoint_update(1, st, out, mat, adj, adj_mat, scratch)
        if side is None:
            source_adjoint("force", [adj.vx, adj.vz], adj_mat[:2])
            self.adjoint_update(0, st, out, mat, adj, adj_mat, scratch)
            return
        stream, buoyancy = side
        with stream():  # reads adj's velocities, which the velocity half step's adjoint only reads
            source_adjoint("force", [adj.vx, adj.vz], buoyancy)
        self.adjoint_update(0, st, out, mat, adj, adj_mat, scratch)
        stream.join()

    def operator(self, locations):
        """The fixed operator of points at locations (S, n, 2) m (receivers; sources whose locations are not differentiated):
        node indices and weights (5, S, n, points) at the vx, vz, sxx, szz and sxz nodes."""
        shape = (5, self.n_shots, locations.shape[1], self.k.operator_points)
        return host_operator(self.k.weights, locations, [self.origin, self.inv_dx, self.top], shape, wp.vec2i, self.dtype, self.device)

    def record(self, st: State, data, op, n: int, clock=None):
        """data = (vx, vz, pressure) arrays (S, n_rec, nt): add sample n (+ clock[0]) through the receiver
        operator op (Elastic.operator)."""
        clock = self.clock if clock is None else clock
        wp.launch(self.k.record, dim=op[1].shape[1:], inputs=[st.vx, st.vz, st.sxx, st.szz, *data, *op, n, clock], device=self.device)

    def record_adjoint(self, adj: State, residual, op, n: int, clock=None):
        """Adjoint of record: adj's vx, vz, sxx, szz += the receiver operator's transpose applied to sample n
        (+ clock[0]) of residual = (vx, vz, pressure) arrays (S, n_rec, levels)."""
        clock = self.clock if clock is None else clock
        wp.launch(self.k.record_adjoint, dim=op[1].shape[1:], inputs=[adj.vx, adj.vz, adj.sxx, adj.szz, *residual, *op, n, clock],
                  device=self.device, record_tape=False)  # fmt: skip

    def physical(self, a):
        """View of the physical grid (nz, nx) of a padded model-shaped array."""
        o = self.origin
        return a[o[0] : o[0] + self.shape[0], o[1] : o[1] + self.shape[1]]
