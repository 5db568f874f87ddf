"""Warp kernels for the 2D visco-acoustic wave equation: pressure-velocity on a staggered grid with L standard
linear solids (memory variables; Robertsson, Blanch & Symes 1994; Blanch, Robertsson & Symes 1995).

Equations (z down, x right; b = 1/rho; M_R, M_U the relaxed and unrelaxed moduli, g_l = M_R y_l: relaxation.py):

    dv/dt  = -b grad p,
    dp/dt  = -M_U div v - sum_l r_l + dS/dt delta(x - x_s),
    dr_l/dt = -(r_l + g_l div v) / tau_l,

so that in the frequency domain i w p = -M(w) div v, M(w) = M_R (1 + sum_l y_l i w tau_l / (1 + i w tau_l)).
S(t) is the explosive source's isotropic moment (N m per metre of line, as the elastic solver's explosive source:
a volume injection times the modulus), so p (Pa) is what acoustic_vd's pressure is for the same S; Q -> infinity
(y = 0, M_U = M_R = rho vp^2) is acoustic_vd's scheme exactly.

Staggering (as kernels/elastic): positions in cells from padded node (0, 0) as (z, x); the array index (i, k) of

    p, r_l, vp, q, rho, M_U, g_l   (i, k)        vx   (i, k + 1/2)        vz   (i + 1/2, k)

the buoyancy at a velocity node the arithmetic mean of 1/rho at its two neighbours. Staggered derivatives of
order 2/4/8 (numerics.STAGGERED_DERIVATIVE). Time (leapfrog): level n holds v at t = (n - 1/2) dt and p, r at
t = n dt; one step is v^{n+1/2} = v^{n-1/2} - dt b grad p^n, then, with D = div v^{n+1/2} and the memory
variables by the trapezoidal rule (Crank-Nicolson: stable for any dt / tau_l),

    r_l^{n+1} = c1_l r_l^n - c2_l g_l D,   c1_l = (1 - dt / (2 tau_l)) / (1 + dt / (2 tau_l)),
                                           c2_l = (dt / tau_l) / (1 + dt / (2 tau_l)),
    p^{n+1}   = p^n - dt (M_U D + sum_l (r_l^n + r_l^{n+1}) / 2) + (S(t_{n+1}) - S(t_n)) w / dx^2.

A recorded sample n of vx or vz is v at t = (n - 1/2) dt, of p at t = n dt.

Layout (as kernels/elastic): fields (n_shots, Lz, Lx), memory variables (n_shots, L, Lz, Lx), models (Lz, Lx), every
axis padded as [halo R][PML][physical grid][PML][halo R], R = order / 2, halo cells zero and never written. CPML
(Komatitsch & Martin 2007, kappa = 1; elastic.propagator.cpml_axis): one memory variable psi per spatial derivative
(PSI), stored in strips along its axis, its profile at the derivative's own (integer or half) position.

Free surface (pressure release): p = 0 on the top row of p nodes (padded row `top`, physical z = 0); above it p is
the odd image and vz the even image of the field below (p(-z) = -p(z), vz(-z) = vz(z)), so every stencil keeps its
full order. Sources and receivers use the Kaiser-windowed sinc operator of kernels/common.py at each field's
staggered position, folded across a free surface with the images' signs (elastic.propagator.make_point: odd for p
and vx, even for vz); their weights are computed once per run (`weights`).

Kernels, plain per-cell Warp kernels that Warp differentiates (Tape): `velocity` and `pressure` (a half step each,
in place or out of place: a cell reads only its own old value of a field it writes), `inject`, `record`,
`weights`, `materials` (vp, q, rho -> b_x, b_z, M_U, g_l; Warp's adjoint is the chain rule to vp, q, rho).
`velocity` and `pressure` take the arrays' flat views (State.flat, Materials.flat: same memory and .grad) and a 1D
launch over the interior cells, indexing with int32 flat offsets (Grid), not 3D arrays' 64-bit, bounds-checked ones.
A step outside a tape runs the velocity half step as `velocity_tiles[V]` instead, never differentiated: register
tiles (V adjacent cells a load, rows of p along z in a sliding window) over the core box where no CPML strip or
free-surface image is in reach (tile_plan), the per-cell arithmetic (velocity_cell) over the frame around it, in one
launch (_velocity_tiles; equal to `velocity` bit for bit on a CPU). kernels/acoustic_vd tiles its pressure half step
the same way.
"""

import functools
import math
from types import SimpleNamespace

import numpy as np
import warp as wp

from adseismic.kernels.common import (
    HICKS_RADIUS,
    Kernels,
    aligned,
    as_vectors,
    check_flat_cells,
    flat_cpml,
    frame_map,
    hicks_axis,
    host_operator,
    unique_kernel,
    vector_access,
)
from adseismic.kernels.elastic.propagator import build as elastic_build
from adseismic.kernels.elastic.propagator import cpml_axes, make_point
from adseismic.kernels.numerics import STAGGERED_DERIVATIVE
from adseismic.kernels.viscoacoustic.relaxation import SERIES_TERMS, Mechanisms

# the CPML memory variables: the axis of their derivative (and strips); vx_x: dp/dx at vx nodes, vz_z: dp/dz at vz
# nodes, p_x: dvx/dx and p_z: dvz/dz at p nodes
PSI = {"vx_x": 1, "vz_z": 0, "p_x": 1, "p_z": 0}
MATERIALS = ("bx", "bz", "mu", "g")  # buoyancy at vx and vz nodes, M_U, g_l = M_R y_l (L, Lz, Lx)

# the 2D untaped half steps' core tiles (this velocity half step, kernels/acoustic_vd's pressure one): adjacent
# columns a thread (the widest that divides the padded row), rows a thread, threads per block (docs/benchmarks.md,
# "The staggered half steps as register tiles")
TILE_LANES, TILE_ROWS, TILE_THREADS = (4, 2, 1), 2, 128

@wp.struct
class Grid:
    """The sizes a flat field kernel indexes with (int32): interior cells per shot (nz, nx), padded (lz, lx), the CPML
    strips' widths (wz, wx)."""

    nz: int
    nx: int
    lz: int
    lx: int
    wz: int
    wx: int


def _cell(ns):
    """cell(grid, t): thread t of a 1D launch over the interior cells (S nz nx) as (s, z, x, model cell z lx + x, field
    cell (s lz + z) lx + x), with int32 arithmetic."""
    M = ns.M

    @wp.func
    def cell(grid: Grid, t: int):
        r = t / grid.nx
        x = t - r * grid.nx + wp.static(M)
        s = r / grid.nz
        z = r - s * grid.nz + wp.static(M)
        m = z * grid.lx + x
        return s, z, x, m, s * grid.lz * grid.lx + m

    return cell


def _derivatives(ns):
    """build's staggered first derivatives (times dx) of p at the velocity nodes and of vx, vz at the p nodes on flat
    fields (c: the flat cell at row z, lx: the row stride), reading above a free surface the images (p odd, vz even)."""
    dtype, arr1, fs, M, C = ns.dtype, ns.arr1, ns.fs, ns.M, ns.C

    @wp.func
    def p_at(p: arr1, c: int, z: int, lx: int, top: int) -> dtype:
        # p at cell c (row z), the odd image of the row 2 top - z above a free surface
        if wp.static(fs):
            if z < top:
                return -p[c + 2 * (top - z) * lx]
        return p[c]

    @wp.func
    def vz_at(vz: arr1, c: int, z: int, lx: int, top: int) -> dtype:
        # vz at cell c (row z, at z + 1/2), the even image of the row 2 top - 1 - z above a free surface
        if wp.static(fs):
            if z < top:
                return vz[c + (2 * (top - z) - 1) * lx]
        return vz[c]

    @wp.func
    def dp_dx(p: arr1, c: int) -> dtype:
        # dp/dx times dx at (z, x + 1/2)
        acc = dtype(0.0)
        for m in range(wp.static(M)):
            acc += dtype(wp.static(C[m])) * (p[c + m + 1] - p[c - m])
        return acc

    @wp.func
    def dp_dz(p: arr1, c: int, z: int, lx: int, top: int) -> dtype:
        # dp/dz times dx at (z + 1/2, x)
        acc = dtype(0.0)
        for m in range(wp.static(M)):
            acc += dtype(wp.static(C[m])) * (p_at(p, c + (m + 1) * lx, z + m + 1, lx, top) - p_at(p, c - m * lx, z - m, lx, top))
        return acc

    @wp.func
    def dvx_dx(vx: arr1, c: int) -> dtype:
        # dvx/dx times dx at (z, x)
        acc = dtype(0.0)
        for m in range(wp.static(M)):
            acc += dtype(wp.static(C[m])) * (vx[c + m] - vx[c - m - 1])
        return acc

    @wp.func
    def dvz_dz(vz: arr1, c: int, z: int, lx: int, top: int) -> dtype:
        # dvz/dz times dx at (z, x)
        acc = dtype(0.0)
        for m in range(wp.static(M)):
            acc += dtype(wp.static(C[m])) * (vz_at(vz, c + m * lx, z + m, lx, top) - vz_at(vz, c - (m + 1) * lx, z - m - 1, lx, top))
        return acc

    return dp_dx, dp_dz, dvx_dx, dvz_dz


def _velocity(ns, record_thread):
    """The lossless velocity half step v_new = v - dt b grad p (velocity, flat arrays, a 1D launch over the interior
    cells; every load before the first store; velocity_cell: one cell's), shared with kernels/acoustic_vd, and its
    cell decoder; the tiled velocity half step records p by record_thread (_points)."""
    dtype, arr1, Axis = ns.dtype, ns.arr1, ns.Axis
    dp_dx, dp_dz = _derivatives(ns)[:2]
    cell = _cell(ns)
    cpml_psi, store_psi = flat_cpml(dtype)

    @wp.func
    def velocity_cell(
        vx: arr1, vz: arr1, p: arr1, bx: arr1, bz: arr1, o_vx_x: arr1, o_vz_z: arr1, n_vx_x: arr1, n_vz_z: arr1,
        vx_new: arr1, vz_new: arr1, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int, grid: Grid,
        s: int, z: int, x: int, m: int, c: int,
    ):  # fmt: skip
        # v_new = v - dt b grad p at the velocity nodes of cell (s, z, x) (m: its model cell, c: its field cell), for
        # untaped kernels (velocity's own is written out)
        jz = az.store[z]
        jx = ax.store[x]
        kx = (s * grid.lz + z) * grid.wx + jx
        kz = (s * grid.wz + jz) * grid.lx + x
        gx = dp_dx(p, c) * inv_dx
        gz = dp_dz(p, c, z, grid.lx, top) * inv_dx
        qx = cpml_psi(gx, jx, x, ax.ah, ax.bh, o_vx_x, kx)
        qz = cpml_psi(gz, jz, z, az.ah, az.bh, o_vz_z, kz)
        ux = vx[c]
        uz = vz[c]
        bxm = bx[m]
        bzm = bz[m]
        store_psi(jx, n_vx_x, kx, qx)
        store_psi(jz, n_vz_z, kz, qz)
        vx_new[c] = ux - dt * bxm * (gx + qx)
        vz_new[c] = uz - dt * bzm * (gz + qz)

    @unique_kernel(grid_stride=False)
    def velocity(
        vx: arr1, vz: arr1, p: arr1, bx: arr1, bz: arr1, o_vx_x: arr1, o_vz_z: arr1, n_vx_x: arr1, n_vz_z: arr1,
        vx_new: arr1, vz_new: arr1, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int, grid: Grid,
    ):  # fmt: skip
        # v_new = v - dt b grad p at every interior velocity node: velocity_cell's arithmetic written out, since Warp's
        # generated adjoint of a kernel that calls a func computes the func's forward twice (the taped VD1000 gradient
        # 15% slower; docs/benchmarks.md, "The staggered half steps as register tiles")
        s, z, x, m, c = cell(grid, wp.tid())
        jz = az.store[z]
        jx = ax.store[x]
        kx = (s * grid.lz + z) * grid.wx + jx
        kz = (s * grid.wz + jz) * grid.lx + x
        gx = dp_dx(p, c) * inv_dx
        gz = dp_dz(p, c, z, grid.lx, top) * inv_dx
        qx = cpml_psi(gx, jx, x, ax.ah, ax.bh, o_vx_x, kx)
        qz = cpml_psi(gz, jz, z, az.ah, az.bh, o_vz_z, kz)
        ux = vx[c]
        uz = vz[c]
        bxm = bx[m]
        bzm = bz[m]
        store_psi(jx, n_vx_x, kx, qx)
        store_psi(jz, n_vz_z, kz, qz)
        vx_new[c] = ux - dt * bxm * (gx + qx)
        vz_new[c] = uz - dt * bzm * (gz + qz)

    lanes = {V: _lanes(ns, V) for V in TILE_LANES}
    return velocity, velocity_cell, cell, lanes, {V: _velocity_tiles(ns, lanes[V], velocity_cell, record_thread) for V in TILE_LANES}


def _lanes(ns, V: int):
    """What a 2D core tile reads with (TILE_ROWS rows x V adjacent columns a thread, on flat fields viewed as
    V-vectors: kernels/common.as_vectors, vector_access's one load of V cells): the vector and its array types, load
    and put, row_line (a row's vectors around one), window and slide (2M rows along z, moved down a row), tile (a
    thread's first row and cells) and frame_cell (kernels/common.frame_map)."""
    M, dtype, rows = ns.M, ns.dtype, TILE_ROWS
    NB = -(-M // V)  # vectors each side that hold a row's M neighbours
    vec = wp.types.vector(length=V, dtype=dtype)
    arrv = wp.array(dtype=vec)
    line = wp.types.vector(length=(2 * NB + 1) * V, dtype=dtype)
    win = wp.types.matrix(shape=(2 * M, V), dtype=dtype)
    load, put = vector_access(V, dtype)

    @wp.func
    def row_line(a: arrv, i: int, centre: vec) -> line:
        # the NB vectors left and right of vector i along its row around `centre` (a's vector i)
        r = line()
        for b in range(wp.static(2 * NB + 1)):
            q = centre
            if wp.static(b != NB):
                q = load(a, i + wp.static(b - NB))
            for j in range(wp.static(V)):
                r[wp.static(b * V) + j] = q[j]
        return r

    @wp.func
    def window(a: arrv, i: int, n: int, first: int) -> win:
        # the 2M vectors of a at rows first .. first + 2M - 1 relative to vector i (row stride n)
        w = win()
        for k in range(wp.static(2 * M)):
            q = load(a, i + (k + first) * n)
            for j in range(wp.static(V)):
                w[k, j] = q[j]
        return w

    @wp.func
    def slide(w: win, q: vec) -> win:
        # the window one row down: its rows shifted up, q the new last row
        out = win()
        for j in range(wp.static(V)):
            for k in range(wp.static(2 * M - 1)):
                out[k, j] = w[k + 1, j]
            out[wp.static(2 * M - 1), j] = q[j]
        return out

    @wp.func
    def tile(t: int, box: wp.vec4i, lz: int, lx: int) -> wp.vec3i:
        # thread t's first row z, its first cell's flat index in a model (z lx + x) and in the fields (shot s)
        nxc = (box[3] - box[2]) // wp.static(V)
        blocks = (box[1] - box[0] + wp.static(rows - 1)) // wp.static(rows)
        q = t // nxc
        x = box[2] + (t - q * nxc) * wp.static(V)
        s = q // blocks
        z = box[0] + (q - s * blocks) * wp.static(rows)
        return wp.vec3i(z, z * lx + x, s * lz * lx + z * lx + x)

    return SimpleNamespace(V=V, NB=NB, vec=vec, arrv=arrv, load=load, put=put, row_line=row_line, window=window, slide=slide, tile=tile,
                           frame_cell=frame_map(M))  # fmt: skip


@functools.lru_cache(maxsize=32)
def tile_plan(axes, padded, halo: int, n_shots: int, free_surface: bool, top: int, margin: int = 0):
    """(V, box, tiles, frame, cells) of a 2D tiled half step (_velocity_tiles, kernels/acoustic_vd): the lanes (the
    widest of TILE_LANES that divides the padded row), the core box (rows and columns outside the CPML strips of axes
    (z, x) by `margin` cells, below a free surface's images; columns from and to a multiple of V), its tiles over the
    shots, the first frame thread (a block boundary) and the frame cells a shot. Kept per argument set, as cpml_axes'
    axes are (its two reads of the strips from the device were a tenth of a VD1000 forward's setup on an H200)."""
    R, (lz, lx) = halo, padded
    ends = []
    for a, n in zip(axes, padded):
        free = np.flatnonzero(a.store.numpy()[R:n - R] < 0) + R  # outside the CPML strips, which lie at the ends
        ends.append((int(free[0]) + margin, int(free[-1]) + 1 - margin) if free.size else (R, R))
    (z0, z1), (x0, x1) = ends
    if free_surface:
        z0 = max(z0, top + R)  # no stencil reaches the surface's images
    V = next(v for v in TILE_LANES if lx % v == 0)
    box = aligned(z0, z1, x0, x1, V)
    if box[1] <= box[0] or box[3] <= box[2]:
        box = wp.vec4i(z0, z0, x0, x0)
    h, w = box[1] - box[0], box[3] - box[2]
    tiles = n_shots * -(-h // TILE_ROWS) * (w // V)
    frame = -(-tiles // TILE_THREADS) * TILE_THREADS
    return V, box, tiles, frame, (lz - 2 * R) * (lx - 2 * R) - h * w


def tiled_recording(st, record, clock) -> tuple:
    """(a tiled half step's last arguments, its recording threads) for record = (data (vx, vz, pressure arrays (S,
    n_rec, n)), receiver_op (idx, w), k): st's fields into samples k (+ clock[0]; none past n); None: no recording."""
    if record is None:
        return [None] * 8 + [0, clock, 0], 0
    data, (idx, w), k = record
    threads = -(-math.prod(idx.shape[1:]) // TILE_THREADS) * TILE_THREADS
    return [st.vx, st.vz, st.p, *data, idx, w, k, clock, threads], threads


def _velocity_tiles(ns, L, velocity_cell, record_thread, image=False):
    """The velocity half step untaped (never differentiated), in place or out of place, as a core and a frame in one
    1D launch, after `records` threads (a multiple of TILE_THREADS, or 0) that record the receivers' p of the level
    stepped from into `sample` (+ clock[0]) (record_thread of fp, the array p is: the launch writes only velocities).
    From thread `records` on, thread t < tiles updates TILE_ROWS rows x V
    adjacent columns of the core box (tile_plan; L: _lanes), the rows of p along z in a sliding window; from `frame`
    (a block boundary, so that no warp mixes the two) one frame cell (an interior cell outside the box; `cells` a
    shot) by velocity_cell. The core's arithmetic is the cell's without its CPML and image terms: equal bit for bit on
    a CPU (docs/benchmarks.md, "The staggered half steps as register tiles"). With `image` (kernels/acoustic_vd's
    adjoint) each cell also adds f (v_new - v) into g, per velocity (f1, g1: vx's; f2, g2: vz's; flat and as vectors),
    and velocity_cell takes f1, f2, g1, g2 last; otherwise they are None."""
    M, C, dtype, arr1, arr3, Axis, rows = ns.M, ns.C, ns.dtype, ns.arr1, ns.arr3, ns.Axis, TILE_ROWS
    arr4, iarr1, idx4 = ns.arr4, ns.iarr1, ns.idx4
    V, NB, vec, arrv, load, put = L.V, L.NB, L.vec, L.arrv, L.load, L.put
    row_line, window, slide, tile, frame_cell = L.row_line, L.window, L.slide, L.tile, L.frame_cell

    @wp.func
    def velocity_tile(t: int, vx: arrv, vz: arrv, p: arrv, bx: arrv, bz: arrv, vx_new: arrv, vz_new: arrv, dt: dtype, inv_dx: dtype,
                      box: wp.vec4i, lz: int, lx: int, f1: arrv, f2: arrv, g1: arrv, g2: arrv):  # fmt: skip
        tl = tile(t, box, lz, lx)
        n = lx // wp.static(V)
        c = tl[1] // wp.static(V)
        i = tl[2] // wp.static(V)
        w = window(p, i, n, wp.static(1 - M))  # p at rows z - M + 1 .. z + M
        for r in range(wp.static(rows)):
            if tl[0] + r < box[1]:
                centre = vec()
                for j in range(wp.static(V)):
                    centre[j] = w[wp.static(M - 1), j]
                pl = row_line(p, i, centre)
                ux = load(vx, i)
                uz = load(vz, i)
                bxm = load(bx, c)
                bzm = load(bz, c)
                ox = vec()
                oz = vec()
                for j in range(wp.static(V)):
                    gx = dtype(0.0)
                    gz = dtype(0.0)
                    for m in range(wp.static(M)):
                        gx += dtype(wp.static(C[m])) * (pl[wp.static(NB * V + m + 1) + j] - pl[wp.static(NB * V - m) + j])
                        gz += dtype(wp.static(C[m])) * (w[wp.static(M + m), j] - w[wp.static(M - 1 - m), j])
                    ox[j] = ux[j] - dt * bxm[j] * (gx * inv_dx)
                    oz[j] = uz[j] - dt * bzm[j] * (gz * inv_dx)
                put(vx_new, i, ox)
                put(vz_new, i, oz)
                if wp.static(image):
                    a1 = load(f1, i)
                    a2 = load(f2, i)
                    s1 = load(g1, i)
                    s2 = load(g2, i)
                    for j in range(wp.static(V)):
                        s1[j] = s1[j] + a1[j] * (ox[j] - ux[j])
                        s2[j] = s2[j] + a2[j] * (oz[j] - uz[j])
                    put(g1, i, s1)
                    put(g2, i, s2)
                if wp.static(r + 1 < rows):
                    w = slide(w, load(p, i + wp.static(M + 1) * n))
                i += n
                c += n

    @unique_kernel(grid_stride=False, enable_backward=False)
    def velocity_tiles(
        vx: arr1, vz: arr1, p: arr1, bx: arr1, bz: arr1, o_vx_x: arr1, o_vz_z: arr1, n_vx_x: arr1, n_vz_z: arr1,
        vx_new: arr1, vz_new: arr1, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int, grid: Grid,
        vxv: arrv, vzv: arrv, pv: arrv, bxv: arrv, bzv: arrv, vx_newv: arrv, vz_newv: arrv, box: wp.vec4i, tiles: int, frame: int,
        cells: int, fvx: arr3, fvz: arr3, fp: arr3, d_vx: arr3, d_vz: arr3, d_p: arr3, idx: idx4, w: arr4, sample: int, clock: iarr1,
        records: int, f1: arr1, f2: arr1, g1: arr1, g2: arr1, f1v: arrv, f2v: arrv, g1v: arrv, g2v: arrv,
    ):  # fmt: skip
        t = wp.tid()
        if t < records:
            record_thread(t, fvx, fvz, fp, d_vx, d_vz, d_p, idx, w, sample + clock[0], 1)
            return
        t -= records
        if t < frame:
            if t < tiles:
                velocity_tile(t, vxv, vzv, pv, bxv, bzv, vx_newv, vz_newv, dt, inv_dx, box, grid.lz, grid.lx, f1v, f2v, g1v, g2v)
        else:
            s = (t - frame) // cells
            zx = frame_cell(t - frame - s * cells, grid.lz, grid.lx, box)
            m = zx[0] * grid.lx + zx[1]
            if wp.static(image):
                velocity_cell(vx, vz, p, bx, bz, o_vx_x, o_vz_z, n_vx_x, n_vz_z, vx_new, vz_new, az, ax, dt, inv_dx, top, grid, s, zx[0],
                              zx[1], m, s * grid.lz * grid.lx + m, f1, f2, g1, g2)  # fmt: skip
            else:
                velocity_cell(vx, vz, p, bx, bz, o_vx_x, o_vz_z, n_vx_x, n_vz_z, vx_new, vz_new, az, ax, dt, inv_dx, top, grid, s, zx[0],
                              zx[1], m, s * grid.lz * grid.lx + m)  # fmt: skip

    return velocity_tiles


def _points(ns):
    """The sources' and receivers' kernels of build: the fixed operator's weights at the p, vx and vz nodes (make_point,
    folded across a free surface), the explosive source's injection into p, and the recording of p, vx and vz (a
    kernel, and record_thread: a tiled launch's thread recording p or the velocities at one point)."""
    dtype, arr3, arr4, iarr1, idx4 = ns.dtype, ns.arr3, ns.arr4, ns.iarr1, ns.idx4
    hicks = hicks_axis(dtype)
    pt_p = make_point(ns, hicks, 0.0, 0.0, True)
    pt_vx = make_point(ns, hicks, 0.0, 0.5, True)
    pt_vz = make_point(ns, hicks, 0.5, 0.0, False)

    @unique_kernel(enable_backward=False)  # computed once per run, never differentiated (locations are fixed)
    def weights(loc: arr3, origin: wp.vec2i, inv_dx: dtype, top: int, idx: idx4, w: arr4):
        # the operator of location r (metres (z, x)), computed once per run: node and weight of its point q for p, vx,
        # vz (first index)
        s, r, q = wp.tid()
        i, wq = pt_p(loc, s, r, q, origin, inv_dx, top)
        idx[0, s, r, q] = i
        w[0, s, r, q] = wq
        i, wq = pt_vx(loc, s, r, q, origin, inv_dx, top)
        idx[1, s, r, q] = i
        w[1, s, r, q] = wq
        i, wq = pt_vz(loc, s, r, q, origin, inv_dx, top)
        idx[2, s, r, q] = i
        w[2, s, r, q] = wq

    @unique_kernel
    def inject(p: arr3, amp: arr3, idx: idx4, w: arr4, n: int, clock: iarr1, scale: dtype):
        # p += (S(t_{n+1}) - S(t_n)) w / dx^2 (scale = 1 / dx^2) at the p operator's points; the sample is n + clock[0]
        # (a device counter, for graph replays), here and in record
        s, src, q = wp.tid()
        t = n + clock[0]
        wq = w[0, s, src, q]
        if wq != dtype(0.0):
            i = idx[0, s, src, q]
            wp.atomic_add(p, s, i[0], i[1], scale * (amp[s, src, t + 1] - amp[s, src, t]) * wq)

    @wp.func
    def record_point(vx: arr3, vz: arr3, p: arr3, d_vx: arr3, d_vz: arr3, d_p: arr3, idx: idx4, w: arr4, s: int, r: int, q: int,
                     t: int, parts: int):  # fmt: skip
        # sample t of receiver r's p (parts bit 1) and vx, vz (bit 2): its operator's point q
        if (parts & 1) != 0:
            wq = w[0, s, r, q]
            if wq != dtype(0.0):
                i = idx[0, s, r, q]
                wp.atomic_add(d_p, s, r, t, wq * p[s, i[0], i[1]])
        if (parts & 2) != 0:
            wq = w[1, s, r, q]
            if wq != dtype(0.0):
                i = idx[1, s, r, q]
                wp.atomic_add(d_vx, s, r, t, wq * vx[s, i[0], i[1]])
            wq = w[2, s, r, q]
            if wq != dtype(0.0):
                i = idx[2, s, r, q]
                wp.atomic_add(d_vz, s, r, t, wq * vz[s, i[0], i[1]])

    @unique_kernel
    def record(vx: arr3, vz: arr3, p: arr3, d_vx: arr3, d_vz: arr3, d_p: arr3, idx: idx4, w: arr4, n: int, clock: iarr1):
        # sample n of each receiver's p, vx, vz through its operator
        s, r, q = wp.tid()
        record_point(vx, vz, p, d_vx, d_vz, d_p, idx, w, s, r, q, n + clock[0], 3)

    @wp.func
    def record_thread(t: int, vx: arr3, vz: arr3, p: arr3, d_vx: arr3, d_vz: arr3, d_p: arr3, idx: idx4, w: arr4, sample: int,
                      parts: int):  # fmt: skip
        # a tiled launch's recording thread t: record_point of point t (in (S, n_rec, points) order) where data hold the sample
        points = idx.shape[3]
        n_rec = idx.shape[2]
        if t < idx.shape[1] * n_rec * points and sample < d_p.shape[2]:
            sr = t // points
            s = sr // n_rec
            record_point(vx, vz, p, d_vx, d_vz, d_p, idx, w, s, sr - s * n_rec, t - sr * points, sample, parts)

    return weights, inject, record, record_thread


@functools.lru_cache(maxsize=None)
def build(order: int, dtype, free_surface: bool, mechanisms: int):
    """Kernels for one (order, dtype, free_surface, number of mechanisms), compiled once per process."""
    M = order // 2
    C = STAGGERED_DERIVATIVE[order]
    L = int(mechanisms)
    K = SERIES_TERMS
    fs = bool(free_surface)
    W = 2 * HICKS_RADIUS
    arr1, arr2, arr3, arr4 = wp.array(dtype=dtype), wp.array2d(dtype=dtype), wp.array3d(dtype=dtype), wp.array4d(dtype=dtype)
    iarr1 = wp.array(dtype=wp.int32)
    idx4 = wp.array4d(dtype=wp.vec2i)
    ns = SimpleNamespace(HR=HICKS_RADIUS, W=W, fs=fs, dtype=dtype, arr3=arr3, arr4=arr4, iarr1=iarr1, idx4=idx4, M=M, C=C)

    @wp.struct
    class Axis:
        store: wp.array(dtype=wp.int32)  # strip index per padded index, -1 outside the PML strips
        a: wp.array(dtype=dtype)  # CPML a, b at integer positions
        b: wp.array(dtype=dtype)
        ah: wp.array(dtype=dtype)  # at half positions (index p stands for p + 1/2)
        bh: wp.array(dtype=dtype)

    ns.Axis, ns.arr1, ns.arr2 = Axis, arr1, arr2
    dvx_dx, dvz_dz = _derivatives(ns)[2:]
    weights, inject, record, record_point = _points(ns)
    velocity, _, cell, _, velocity_tiles = _velocity(ns, record_point)
    cpml_psi, store_psi = flat_cpml(dtype)

    @unique_kernel(grid_stride=False)
    def pressure(
        vx: arr1, vz: arr1, p: arr1, r: arr1, mu: arr1, g: arr1, c1: arr1, c2: arr1, o_p_x: arr1, o_p_z: arr1,
        n_p_x: arr1, n_p_z: arr1, p_new: arr1, r_new: arr1, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int, grid: Grid,
    ):  # fmt: skip
        # p and the memory variables r_l from level n to n + 1 (module docstring); 0 on a free surface's row
        s, z, x, m, c = cell(grid, wp.tid())
        jz = az.store[z]
        jx = ax.store[x]
        kx = (s * grid.lz + z) * grid.wx + jx
        kz = (s * grid.wz + jz) * grid.lx + x
        ex = dvx_dx(vx, c) * inv_dx
        ez = dvz_dz(vz, c, z, grid.lx, top) * inv_dx
        qx = cpml_psi(ex, jx, x, ax.a, ax.b, o_p_x, kx)
        qz = cpml_psi(ez, jz, z, az.a, az.b, o_p_z, kz)
        d = (ex + qx) + (ez + qz)
        keep = dtype(1.0)
        if wp.static(fs):
            if z == top:
                keep = dtype(0.0)
        pc = p[c]
        mum = mu[m]
        area = grid.lz * grid.lx
        rsum = dtype(0.0)
        for l in range(wp.static(L)):  # r's loads wait for the previous mechanism's store (a vector of L would not)
            k = (s * wp.static(L) + l) * area + m  # r[s, l, z, x]
            old = r[k]
            new = keep * (c1[l] * old - c2[l] * g[l * area + m] * d)
            r_new[k] = new
            rsum += old + new
        store_psi(jx, n_p_x, kx, qx)
        store_psi(jz, n_p_z, kz, qz)
        p_new[c] = keep * (pc - dt * (mum * d + dtype(0.5) * rsum))

    @wp.func
    def weight(series: arr2, l: int, iq: dtype) -> dtype:
        # y_l = sum_k series[k, l] iq^(k + 1) (Horner), iq = 1 / Q
        y = dtype(0.0)
        for k in range(wp.static(K)):
            y = (y + series[wp.static(K - 1) - k, l]) * iq
        return y

    @unique_kernel
    def materials(
        vp: arr2, q: arr2, rho: arr2, series: arr2, tau: arr1, w_ref: dtype, bx: arr2, bz: arr2, mu: arr2, g: arr3,
    ):  # fmt: skip
        # MATERIALS at the interior nodes from the padded vp (m/s, phase velocity at w_ref rad/s), q and rho (kg/m^3):
        # y_l = sum_k series[k, l] q^-(k+1), m = 1 + sum_l y_l i w tau_l / (1 + i w tau_l) at w_ref = A + i B,
        # M_R = rho vp^2 Re(m^-1/2)^2 = rho vp^2 (1 + A / |m|) / (2 |m|), M_U = M_R (1 + sum y_l), g_l = M_R y_l
        zi, xi = wp.tid()
        z = zi + wp.static(M)
        x = xi + wp.static(M)
        r = rho[z, x]
        bx[z, x] = dtype(0.5) * (dtype(1.0) / r + dtype(1.0) / rho[z, x + 1])
        bz[z, x] = dtype(0.5) * (dtype(1.0) / r + dtype(1.0) / rho[z + 1, x])
        iq = dtype(1.0) / q[z, x]
        re = dtype(1.0)
        im = dtype(0.0)
        ysum = dtype(0.0)
        for l in range(wp.static(L)):
            y = weight(series, l, iq)
            wt = w_ref * tau[l]
            den = dtype(1.0) + wt * wt
            re += y * wt * wt / den
            im += y * wt / den
            ysum += y
        norm = wp.sqrt(re * re + im * im)
        relaxed = r * vp[z, x] * vp[z, x] * (dtype(1.0) + re / norm) / (dtype(2.0) * norm)
        mu[z, x] = relaxed * (dtype(1.0) + ysum)
        for l in range(wp.static(L)):
            g[l, z, x] = relaxed * weight(series, l, iq)

    return Kernels(Axis=Axis, velocity=velocity, pressure=pressure, materials=materials, weights=weights, inject=inject,
                   record=record, pad_model=elastic_build(order, dtype, fs).pad_model, halo=M, operator_points=W * W,
                   velocity_tiles=velocity_tiles)  # fmt: skip


class State:
    """Fields at one time level n: vx, vz (m/s) at t = (n - 1/2) dt, p (Pa) and the memory variables r (Pa/s,
    (n_shots, L, Lz, Lx)) at t = n dt, and the CPML memory variables psi (dict, see PSI)."""

    def __init__(self, vx, vz, p, r, psi):
        self.vx, self.vz, self.p, self.r, self.psi = vx, vz, p, r, psi
        self._flat = None
        self._vectors = {}

    def vectors(self, V: int) -> tuple:
        """vx, vz and p's flat views as vector(V) (kernels/common.as_vectors), the tiled velocity half step's inputs;
        made once per V."""
        if V not in self._vectors:
            self._vectors[V] = tuple(as_vectors(a, V) for a in (self.vx, self.vz, self.p))
        return self._vectors[V]

    def arrays(self):
        return [self.vx, self.vz, self.p, self.r, *(self.psi[k] for k in PSI)]

    def flat(self) -> "State":
        """The State of the arrays' flat (1D) views, the field kernels' inputs; made once, they share memory and .grad
        with the arrays."""
        if self._flat is None:
            self._flat = State(*(a.flatten() for a in (self.vx, self.vz, self.p, self.r)), {k: a.flatten() for k, a in self.psi.items()})
        return self._flat


class Materials(tuple):
    """A launch helper's materials (a tuple of padded arrays) with their flat (1D) views `flat`, the field kernels'
    inputs, made once (they share memory and .grad with the arrays)."""

    def __new__(cls, arrays):
        mat = super().__new__(cls, arrays)
        mat.flat = tuple(a.flatten() for a in arrays)
        mat._vectors = {}
        return mat

    def vectors(self, V: int) -> tuple:
        """The arrays' flat views as vector(V) (kernels/common.as_vectors), made once per V."""
        if V not in self._vectors:
            self._vectors[V] = tuple(as_vectors(a, V) for a in self)
        return self._vectors[V]


def field_grid(padded: tuple, halo: int, strip_width: tuple, size: int) -> Grid:
    """The Grid of a 2D launch helper; ValueError if an array of `size` cells (its largest) is past int32 flat indices."""
    check_flat_cells(size, f"n_shots x padded grid {tuple(padded)} (x mechanisms)")
    grid = Grid()
    grid.nz, grid.nx = padded[0] - 2 * halo, padded[1] - 2 * halo
    grid.lz, grid.lx = padded
    grid.wz, grid.wx = strip_width
    return grid


class Viscoacoustic:
    """Launch helper: padded grid, CPML coefficients, mechanisms and one time step of the 2D visco-acoustic scheme.

    shape: physical grid (nz, nx); dx (m), dt (s); mechanisms: relaxation.Mechanisms; f_ref: the frequency (Hz) at
    which vp is the phase velocity; pml_width cells on every absorbing side (all four, or three with free_surface);
    vmax: CPML reference speed (m/s). Locations passed to `operator` are metres (z, x) from the physical node 0."""

    def __init__(self, shape, dx, dt, order, n_shots, mechanisms: Mechanisms, f_ref, pml_width, pml_reflection,
                 pml_frequency, vmax, free_surface=False, dtype=wp.float32, device="cpu"):  # fmt: skip
        self.ndim = 2
        self.shape = tuple(int(n) for n in shape)
        self.dx, self.dt, self.order, self.n_shots = float(dx), float(dt), int(order), int(n_shots)
        self.dtype, self.device, self.free_surface = dtype, device, bool(free_surface)
        self.mechanisms, self.f_ref = mechanisms, float(f_ref)
        self.k = build(self.order, dtype, self.free_surface, mechanisms.count)
        R = self.k.halo
        nb = int(pml_width)
        lo = (0 if free_surface else nb, nb)
        self.padded = tuple(self.shape[a] + lo[a] + nb + 2 * R for a in range(2))
        self.origin = wp.vec2i(R + lo[0], R + lo[1])
        self.top = R
        self.axes, self.strip_width = cpml_axes(self.k.Axis, lo, nb, self.padded, R, dx, dt, vmax, pml_reflection, pml_frequency, dtype, device)
        half = dt / (2.0 * mechanisms.tau)
        self.c1 = wp.array((1.0 - half) / (1.0 + half), dtype=dtype, device=device)
        self.c2 = wp.array(2.0 * half / (1.0 + half), dtype=dtype, device=device)
        self.series = wp.array(mechanisms.series, dtype=dtype, device=device)
        self.tau = wp.array(mechanisms.tau, dtype=dtype, device=device)
        self.interior = (self.n_shots, self.padded[0] - 2 * R, self.padded[1] - 2 * R)
        self.grid = field_grid(self.padded, R, self.strip_width, self.n_shots * mechanisms.count * math.prod(self.padded))
        self.inv_dx = dtype(1.0 / dx)
        self.dt_device = dtype(dt)
        self.cuda = wp.get_device(device).is_cuda
        self.clock = wp.zeros(1, dtype=wp.int32, device=device)  # stays 0: plain launches pass n itself
        self.tiles = tile_plan(self.axes, self.padded, R, self.n_shots, self.free_surface, self.top)

    def psi_shape(self, name):
        axis = PSI[name]
        shape = [self.n_shots, *self.padded]
        shape[axis + 1] = self.strip_width[axis]
        return tuple(shape)

    def new_state(self, requires_grad=False) -> State:
        def zeros(shape):
            return wp.zeros(shape, dtype=self.dtype, device=self.device, requires_grad=requires_grad)

        full = (self.n_shots, *self.padded)
        return State(zeros(full), zeros(full), zeros(full), zeros((self.n_shots, self.mechanisms.count, *self.padded)),
                     {k: zeros(self.psi_shape(k)) for k in PSI})  # fmt: skip

    def pad_model(self, m, requires_grad=False):
        """Padded model (Lz, Lx) from a physical one (wp.array2d (nz, nx)), extended by edge replication."""
        out = wp.zeros(self.padded, dtype=self.dtype, device=self.device, requires_grad=requires_grad)
        wp.launch(self.k.pad_model, dim=self.padded, inputs=[m, out, self.origin], device=self.device)
        return out

    def materials(self, vp, q, rho, requires_grad=False, out=None):
        """MATERIALS (padded arrays, interior nodes set) from the padded vp (m/s), q and rho (kg/m^3); into out (an
        earlier call's Materials) if given."""

        def zeros(shape):
            return wp.zeros(shape, dtype=self.dtype, device=self.device, requires_grad=requires_grad)

        if out is None:
            out = Materials((zeros(self.padded), zeros(self.padded), zeros(self.padded), zeros((self.mechanisms.count, *self.padded))))
        w_ref = self.dtype(2.0 * np.pi * self.f_ref)
        wp.launch(self.k.materials, dim=self.interior[1:], inputs=[vp, q, rho, self.series, self.tau, w_ref, *out], device=self.device)
        return out

    def operator(self, loc: wp.array):
        """The fixed operator of locations loc (S, n, 2) metres (z, x): (idx (3, S, n, points) vec2i, weights (3, S, n,
        points)) for p, vx, vz."""
        shape = (3, *loc.shape[:2], self.k.operator_points)
        return host_operator(self.k.weights, loc, [self.origin, self.inv_dx, self.top], shape, wp.vec2i, self.dtype, self.device)

    def step(self, st: State, mat, sources, n: int, out: State | None = None, clock=None) -> State:
        """Advance st (level n) to level n + 1 with the explosive sources' samples n and n + 1 (+ clock[0]); sources:
        (amplitudes (S, n_src, >= n + 2), their operator (operator)) or None. mat: MATERIALS (materials' Materials). With
        out=None in place; else into out's arrays (st unchanged), as under a tape (each level its own arrays)."""
        out = st if out is None else out
        clock = self.clock if clock is None else clock
        f, o = st.flat(), out.flat()
        bx, bz, mu, g = mat.flat
        common = [*self.axes, self.dt_device, self.inv_dx, self.top, self.grid]
        cells = math.prod(self.interior)
        vel = [f.vx, f.vz, f.p, bx, bz, f.psi["vx_x"], f.psi["vz_z"], o.psi["vx_x"], o.psi["vz_z"], o.vx, o.vz, *common]
        if wp._src.context.runtime.tape is not None:  # under a tape: the per-cell kernel, which Warp differentiates
            wp.launch(self.k.velocity, dim=cells, inputs=vel, device=self.device)
        else:
            V, box, tiles, frame, n_frame = self.tiles
            (fx, fz, fp), (ox, oz, _), mv = st.vectors(V), out.vectors(V), mat.vectors(V)
            wp.launch(self.k.velocity_tiles[V], dim=frame + self.n_shots * n_frame, device=self.device, block_dim=TILE_THREADS,
                      inputs=[*vel, fx, fz, fp, *mv[:2], ox, oz, box, tiles, frame, n_frame, *tiled_recording(st, None, clock)[0],
                              *[None] * 8])  # fmt: skip
        wp.launch(self.k.pressure, dim=cells, device=self.device,
                  inputs=[o.vx, o.vz, f.p, f.r, mu, g, self.c1, self.c2, f.psi["p_x"], f.psi["p_z"], o.psi["p_x"], o.psi["p_z"], o.p,
                          o.r, *common])  # fmt: skip
        if sources is not None:
            amplitudes, (idx, w) = sources
            wp.launch(self.k.inject, dim=idx.shape[1:], inputs=[out.p, amplitudes, idx, w, n, clock, self.dtype(1.0 / self.dx**2)],
                      device=self.device)  # fmt: skip
        return out

    def record(self, st: State, data, receiver_op, k: int, clock=None):
        """Add sample k (+ clock[0]) of the receivers' vx, vz, p into data (vx, vz, pressure arrays (S, n_rec, >= k + 1))."""
        idx, w = receiver_op
        clock = self.clock if clock is None else clock
        wp.launch(self.k.record, dim=idx.shape[1:], inputs=[st.vx, st.vz, st.p, *data, idx, w, k, clock], device=self.device)
