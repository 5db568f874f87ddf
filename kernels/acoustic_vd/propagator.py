"""Warp kernels for the variable-density acoustic wave equation in 2D and 3D: pressure-velocity on the standard
staggered grid (Virieux 1986), the lossless case of kernels/viscoacoustic (whose 2D derivatives, velocity half step,
CPML update and source/receiver kernels it imports) and, in 3D, on kernels/elastic3d's stencils and operators.

Equations (axes (z, x) or (z, y, x), z down; b = 1/rho, K = rho vp^2):

    dv/dt = -b grad p,      dp/dt = -K div v + dS/dt delta(x - x_s),

S(t) the explosive source's isotropic moment (N m per metre of line in 2D, N m in 3D: the convention of
kernels/viscoacoustic and kernels/elastic3d, so p in Pa is theirs for the same S).

Staggering, positions in cells from padded node 0; the array index (i, [j,] k) of

    p, vp, rho, K   (i, [j,] k)      vx (.., k + 1/2)      vy (i, j + 1/2, k)      vz (i + 1/2, ..)

the buoyancy at a velocity node the arithmetic mean of 1/rho at its two neighbours. Staggered derivatives of order
2/4/8 (numerics.STAGGERED_DERIVATIVE). Time (leapfrog): level n holds v at t = (n - 1/2) dt and p at t = n dt; a step
is v^{n+1/2} = v^{n-1/2} - dt b grad p^n, then p^{n+1} = p^n - dt K div v^{n+1/2} + (S(t_{n+1}) - S(t_n)) w / dx^ndim.
A recorded sample n of a velocity is v at t = (n - 1/2) dt, of p at t = n dt.

Layout: fields (n_shots, Lz, [Ly,] Lx), models (Lz, [Ly,] Lx), every axis padded as [halo R][PML][grid][PML][halo R],
R = order / 2 (no PML on top with a free surface), halo cells zero and never written. CPML (Komatitsch & Martin
2007, kappa = 1; elastic.propagator.cpml_axes): one memory variable per spatial derivative (PSI[ndim]: "v<a>_<a>"
for dp/da at the velocity v_a's nodes, "p_<a>" for dv_a/da at the p nodes), stored in strips along its axis.

Free surface (pressure release), as kernels/viscoacoustic: p = 0 on the top row of p nodes (padded row `top`,
physical z = 0); above it p is the odd and vz the even image of the field below, so every stencil keeps its full
order. Sources and receivers: the Kaiser-windowed sinc operator (kernels/common.hicks_axis) at each field's staggered
position, folded across a free surface (odd for p, vx, vy; even for vz); weights computed once per run (`weights`).

Kernels, plain per-cell Warp kernels that Warp differentiates (Tape): `velocity`, `pressure` (a half step each, in
place or out of place), `inject`, `record`, `weights`, `materials` (vp, rho -> MATERIALS), `pad_model`. The field
kernels take flat views (State.flat, Materials.flat) and a 1D launch with int32 flat offsets (2D: kernels/viscoacoustic's
Grid and stencils; 3D: kernels/elastic3d's flat stencils, Grid and strips). A 2D step outside a tape runs `tiled[V]`
instead, never differentiated: each half step as one launch of register tiles (V adjacent cells a load, rows along z
in a sliding window) over the core, where no CPML strip or free-surface image is in reach, and of the per-cell
arithmetic over the frame around it (kernels/viscoacoustic's _velocity_tiles and tile_plan, _pressure_tiles here; equal
to the per-cell kernels bit for bit on a CPU). Its pressure launch adds the explosive sources' terms too, inject's
arithmetic without its launch (AcousticVD.source_operator's plan), and in a captured time loop its launches record
the receivers (AcousticVD.step's record=).
"""

import contextlib
import functools
import math
from types import SimpleNamespace

import numpy as np
import warp as wp

from adseismic.kernels.common import (
    HICKS_RADIUS,
    Kernels,
    as_vectors,
    check_flat_cells,
    flat_cpml,
    hicks_axis,
    host_operator,
    lower_bound,
    unique_kernel,
)
from adseismic.kernels.elastic.propagator import build as elastic_build
from adseismic.kernels.elastic.propagator import cpml_axes
from adseismic.kernels.elastic3d.propagator import build as elastic3d_build
from adseismic.kernels.elastic3d.propagator import Grid as Flat3
from adseismic.kernels.elastic3d.propagator import flat_cell, flat_grid, flat_strips, make_flat_derivative, make_point
from adseismic.kernels.numerics import STAGGERED_DERIVATIVE
from adseismic.kernels.viscoacoustic.propagator import (
    TILE_LANES,
    TILE_ROWS,
    TILE_THREADS,
    Grid,
    Materials,
    _derivatives,
    _points,
    _velocity,
    _velocity_tiles,
    field_grid,
    tile_plan,
    tiled_recording,
)

# per ndim: the velocities, the CPML memory variables (name -> axis of its derivative and strips) of the velocity and
# the pressure half steps, the materials (buoyancy at each velocity's nodes, K = rho vp^2 at the p nodes)
VELOCITIES = {2: ("vx", "vz"), 3: ("vx", "vy", "vz")}
PSI = {2: {"vx_x": 1, "vz_z": 0, "p_x": 1, "p_z": 0}, 3: {"vx_x": 2, "vy_y": 1, "vz_z": 0, "p_x": 2, "p_y": 1, "p_z": 0}}
MATERIALS = {2: ("bx", "bz", "k"), 3: ("bx", "by", "bz", "k")}


def _kernels_2d(ns):
    """The 2D velocity (kernels/viscoacoustic's), pressure, materials and point kernels, and the tiled half steps."""
    M, fs, dtype, arr1, arr2, Axis = ns.M, ns.fs, ns.dtype, ns.arr1, ns.arr2, ns.Axis
    weights, inject, record, record_thread = _points(ns)
    velocity, velocity_cell, cell, lanes, velocity_tiles = _velocity(ns, record_thread)
    cpml_psi, store_psi = flat_cpml(dtype)
    dvx_dx, dvz_dz = _derivatives(ns)[2:]

    @wp.func
    def pressure_cell(vx: arr1, vz: arr1, p: arr1, k: arr1, o_p_x: arr1, o_p_z: arr1, n_p_x: arr1, n_p_z: arr1, p_new: arr1, az: Axis,
                      ax: Axis, dt: dtype, inv_dx: dtype, top: int, grid: Grid, s: int, z: int, x: int, m: int, c: int):  # fmt: skip
        # p_new = p - dt K div v at cell (s, z, x) (m: its model cell, c: its field cell); 0 on a free surface's row; for
        # untaped kernels (pressure's own is written out)
        jz = az.store[z]
        jx = ax.store[x]
        kx = (s * grid.lz + z) * grid.wx + jx
        kz = (s * grid.wz + jz) * grid.lx + x
        ex = dvx_dx(vx, c) * inv_dx
        ez = dvz_dz(vz, c, z, grid.lx, top) * inv_dx
        qx = cpml_psi(ex, jx, x, ax.a, ax.b, o_p_x, kx)
        qz = cpml_psi(ez, jz, z, az.a, az.b, o_p_z, kz)
        keep = dtype(1.0)
        if wp.static(fs):
            if z == top:
                keep = dtype(0.0)
        pc = p[c]
        km = k[m]
        store_psi(jx, n_p_x, kx, qx)
        store_psi(jz, n_p_z, kz, qz)
        p_new[c] = keep * (pc - dt * km * ((ex + qx) + (ez + qz)))

    @unique_kernel(grid_stride=False)
    def pressure(vx: arr1, vz: arr1, p: arr1, k: arr1, o_p_x: arr1, o_p_z: arr1, n_p_x: arr1, n_p_z: arr1, p_new: arr1, az: Axis,
                 ax: Axis, dt: dtype, inv_dx: dtype, top: int, grid: Grid):  # fmt: skip
        # p_new = p - dt K div v; 0 on a free surface's row: pressure_cell written out, as velocity's (kernels/viscoacoustic)
        s, z, x, m, c = cell(grid, wp.tid())
        jz = az.store[z]
        jx = ax.store[x]
        kx = (s * grid.lz + z) * grid.wx + jx
        kz = (s * grid.wz + jz) * grid.lx + x
        ex = dvx_dx(vx, c) * inv_dx
        ez = dvz_dz(vz, c, z, grid.lx, top) * inv_dx
        qx = cpml_psi(ex, jx, x, ax.a, ax.b, o_p_x, kx)
        qz = cpml_psi(ez, jz, z, az.a, az.b, o_p_z, kz)
        keep = dtype(1.0)
        if wp.static(fs):
            if z == top:
                keep = dtype(0.0)
        pc = p[c]
        km = k[m]
        store_psi(jx, n_p_x, kx, qx)
        store_psi(jz, n_p_z, kz, qz)
        p_new[c] = keep * (pc - dt * km * ((ex + qx) + (ez + qz)))

    tiled = {V: (velocity_tiles[V], _pressure_tiles(ns, lanes[V], pressure_cell, record_thread)) for V in TILE_LANES}
    adjoint_velocity_cell, adjoint_pressure_cell = _adjoint_cells(ns)
    adjoint_tiled = {V: (_velocity_tiles(ns, lanes[V], adjoint_velocity_cell, record_thread, image=True),
                         _pressure_tiles(ns, lanes[V], adjoint_pressure_cell, record_thread, image=True)) for V in TILE_LANES}  # fmt: skip

    @unique_kernel
    def materials(vp: arr2, rho: arr2, bx: arr2, bz: arr2, k: arr2):
        # MATERIALS at the interior nodes from the padded vp (m/s) and rho (kg/m^3)
        zi, xi = wp.tid()
        z = zi + wp.static(M)
        x = xi + wp.static(M)
        r = rho[z, x]
        bx[z, x] = dtype(0.5) * (dtype(1.0) / r + dtype(1.0) / rho[z, x + 1])
        bz[z, x] = dtype(0.5) * (dtype(1.0) / r + dtype(1.0) / rho[z + 1, x])
        k[z, x] = r * vp[z, x] * vp[z, x]

    return dict(velocity=velocity, pressure=pressure, materials=materials, weights=weights, inject=inject, record=record,
                pad_model=elastic_build(ns.order, dtype, fs).pad_model, operator_points=ns.W**2, tiled=tiled, adjoint_tiled=adjoint_tiled,
                **_adjoint_kernels(ns))  # fmt: skip


def _adjoint_cells(ns):
    """The frame cells of the hand-written adjoint step (AcousticVD.adjoint_step), with the signatures of velocity_cell
    and pressure_cell so that the tiled launches (_velocity_tiles, _pressure_tiles) run them around a core of the
    forward's tiles.

    The adjoint state is (nu, mu) = (b lambda_v, K lambda_p) (lambda: the adjoints of v and of p after the free
    surface's zeroing; b at each velocity's nodes) and the adjoints lambda_psi of the CPML memory variables. Where no
    CPML or image is in reach it steps as the forward does with dt -> -dt (d = -dt below): nu -= d b grad mu, then mu
    -= d K div nu. In the frame, with psi_new = b psi_old + a g at a strip cell, the adjoint of the damped derivative
    g + psi_new whose update's adjoint is u = d f (f: mu or nu) is e = u + a (u + lambda_psi_new), and lambda_psi_old =
    b (u + lambda_psi_new); the transposed stencils are the forward's (D^T = -G), p's odd and vz's even images above
    a free surface included (transposed into each other: exact while mu = 0 on the surface row, which its zeroing
    keeps).

    adjoint_velocity_cell: nu_new = nu - b G(e_p) at the cell's velocity nodes from mu (p) and the p nodes' lambda_psi
    (o_*: their level n + 1's, n_*: level n's, written at the cell's p node); adjoint_pressure_cell: mu_new = keep (mu
    - K D(e_v)) from nu and the velocity nodes' lambda_psi likewise."""
    M, C, fs, dtype, arr1, Axis = ns.M, ns.C, ns.fs, ns.dtype, ns.arr1, ns.Axis
    store_psi = flat_cpml(dtype)[1]

    @wp.func
    def damped(u: dtype, j: int, a: dtype, lam: arr1, k: int) -> dtype:
        # e = u + a (u + lambda_psi[k]) at a strip cell (j >= 0), u elsewhere
        if j < 0:
            return u
        return u + a * (u + lam[k])

    @wp.func
    def along_x(f: arr1, lam: arr1, a: arr1, ax: Axis, d: dtype, s: int, z: int, x: int, c: int, grid: Grid) -> dtype:
        # e at column x of row z (field cell c) for the x derivative's memory variable
        j = ax.store[x]
        return damped(d * f[c], j, a[x], lam, (s * grid.lz + z) * grid.wx + j)

    @wp.func
    def along_z(f: arr1, lam: arr1, a: arr1, az: Axis, d: dtype, s: int, z: int, x: int, c: int, grid: Grid) -> dtype:
        # e at row z of column x (field cell c) for the z derivative's memory variable
        j = az.store[z]
        return damped(d * f[c], j, a[z], lam, (s * grid.wz + j) * grid.lx + x)

    @wp.func
    def p_image(f: arr1, lam: arr1, az: Axis, d: dtype, s: int, z: int, x: int, c: int, grid: Grid, top: int) -> dtype:
        # e of the p nodes at row z, the odd image of row 2 top - z above a free surface
        if wp.static(fs):
            if z < top:
                return -along_z(f, lam, az.a, az, d, s, 2 * top - z, x, c + 2 * (top - z) * grid.lx, grid)
        return along_z(f, lam, az.a, az, d, s, z, x, c, grid)

    @wp.func
    def vz_image(f: arr1, lam: arr1, az: Axis, d: dtype, s: int, z: int, x: int, c: int, grid: Grid, top: int) -> dtype:
        # e of the vz nodes at row z, the even image of row 2 top - 1 - z above a free surface
        if wp.static(fs):
            if z < top:
                return along_z(f, lam, az.ah, az, d, s, 2 * top - 1 - z, x, c + (2 * (top - z) - 1) * grid.lx, grid)
        return along_z(f, lam, az.ah, az, d, s, z, x, c, grid)

    @wp.func
    def adjoint_velocity_cell(
        vx: arr1, vz: arr1, p: arr1, bx: arr1, bz: arr1, o_vx_x: arr1, o_vz_z: arr1, n_vx_x: arr1, n_vz_z: arr1,
        vx_new: arr1, vz_new: arr1, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int, grid: Grid,
        s: int, z: int, x: int, m: int, c: int, f1: arr1, f2: arr1, g1: arr1, g2: arr1,
    ):  # fmt: skip
        # (vx, vz, p) = (nu_x, nu_z, mu); o_*, n_*: the p nodes' lambda_psi (p_x, p_z) of levels n + 1 and n; dt = d;
        # g1 += f1 (nu_x_new - nu_x), g2 likewise (the image: _velocity_tiles)
        gx = dtype(0.0)
        gz = dtype(0.0)
        lx = grid.lx
        for k in range(wp.static(M)):
            gx += dtype(wp.static(C[k])) * (along_x(p, o_vx_x, ax.a, ax, dt, s, z, x + k + 1, c + k + 1, grid)
                                             - along_x(p, o_vx_x, ax.a, ax, dt, s, z, x - k, c - k, grid))  # fmt: skip
            gz += dtype(wp.static(C[k])) * (p_image(p, o_vz_z, az, dt, s, z + k + 1, x, c + (k + 1) * lx, grid, top)
                                             - p_image(p, o_vz_z, az, dt, s, z - k, x, c - k * lx, grid, top))  # fmt: skip
        jz = az.store[z]
        jx = ax.store[x]
        kx = (s * grid.lz + z) * grid.wx + jx
        kz = (s * grid.wz + jz) * grid.lx + x
        u = dt * p[c]
        qx = dtype(0.0)
        qz = dtype(0.0)
        if jx >= 0:
            qx = ax.b[x] * (u + o_vx_x[kx])
        if jz >= 0:
            qz = az.b[z] * (u + o_vz_z[kz])
        ux = vx[c]
        uz = vz[c]
        bxm = bx[m]
        bzm = bz[m]
        a1 = f1[c]
        a2 = f2[c]
        s1 = g1[c]
        s2 = g2[c]
        store_psi(jx, n_vx_x, kx, qx)
        store_psi(jz, n_vz_z, kz, qz)
        ox = ux - bxm * (gx * inv_dx)
        oz = uz - bzm * (gz * inv_dx)
        vx_new[c] = ox
        vz_new[c] = oz
        g1[c] = s1 + a1 * (ox - ux)
        g2[c] = s2 + a2 * (oz - uz)

    @wp.func
    def adjoint_pressure_cell(vx: arr1, vz: arr1, p: arr1, k: arr1, o_p_x: arr1, o_p_z: arr1, n_p_x: arr1, n_p_z: arr1, p_new: arr1,
                              az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int, grid: Grid, s: int, z: int, x: int, m: int,
                              c: int, f1: arr1, g1: arr1):  # fmt: skip
        # (vx, vz, p) = (nu_x, nu_z, mu); o_*, n_*: the velocity nodes' lambda_psi (vx_x, vz_z) of levels n + 1 and n;
        # g1 += f1 (mu_new - mu)
        ex = dtype(0.0)
        ez = dtype(0.0)
        lx = grid.lx
        for i in range(wp.static(M)):
            ex += dtype(wp.static(C[i])) * (along_x(vx, o_p_x, ax.ah, ax, dt, s, z, x + i, c + i, grid)
                                             - along_x(vx, o_p_x, ax.ah, ax, dt, s, z, x - i - 1, c - i - 1, grid))  # fmt: skip
            ez += dtype(wp.static(C[i])) * (vz_image(vz, o_p_z, az, dt, s, z + i, x, c + i * lx, grid, top)
                                             - vz_image(vz, o_p_z, az, dt, s, z - i - 1, x, c - (i + 1) * lx, grid, top))  # fmt: skip
        jz = az.store[z]
        jx = ax.store[x]
        kx = (s * grid.lz + z) * grid.wx + jx
        kz = (s * grid.wz + jz) * grid.lx + x
        qx = dtype(0.0)
        qz = dtype(0.0)
        if jx >= 0:
            qx = ax.bh[x] * (dt * vx[c] + o_p_x[kx])
        if jz >= 0:
            qz = az.bh[z] * (dt * vz[c] + o_p_z[kz])
        keep = dtype(1.0)
        if wp.static(fs):
            if z == top:
                keep = dtype(0.0)
        pc = p[c]
        km = k[m]
        a1 = f1[c]
        s1 = g1[c]
        store_psi(jx, n_p_x, kx, qx)
        store_psi(jz, n_p_z, kz, qz)
        o = keep * (pc - km * ((ex * inv_dx) + (ez * inv_dx)))
        p_new[c] = o
        g1[c] = s1 + a1 * (o - pc)

    return adjoint_velocity_cell, adjoint_pressure_cell


def _adjoint_kernels(ns):
    """The hand-written adjoint step's point kernels (AcousticVD.adjoint_step): the explosive sources' adjoint
    (`source_adjoint`), the receivers' residuals into the adjoint state (`record_adjoint`), and the image's sums into
    the adjoints of MATERIALS (`material_adjoints`).

    The image: with the forward levels P^n, V^n and the adjoint's mu^n, nu^n (nu after the step's velocity launch),
    dJ/dK = sum_n (P^{n+1} - P^n - S^{n+1}) mu^{n+1} / K^2 (-dt K div v = P^{n+1} - P^n - S^{n+1}, S the sources'
    terms) and dJ/db = sum_n (V^{n+1} - V^n) nu^{n+1} / b^2, summed by parts: each step adds P^n (mu^n - mu^{n+1}) and
    V^{n+1} (nu's change in its velocity launch) where it changes mu and nu (the tiled launches' `image`, the
    residuals here), and S^{n+1} mu^{n+1} out (P^0 = V^0 = 0, and the adjoint is 0 at the last level). The sums are
    per shot, (S, Lz, Lx): gbx, gbz, gk."""
    M, dtype, arr2, arr3, arr4, iarr1, idx4 = ns.M, ns.dtype, ns.arr2, ns.arr3, ns.arr4, ns.iarr1, ns.idx4

    @unique_kernel(enable_backward=False)
    def source_adjoint(mu: arr3, k: arr2, amp: arr3, idx: idx4, w: arr4, n: int, clock: iarr1, scale: dtype, gk: arr3, g_amp: arr3):
        # the adjoint of inject's term of step n: the amplitudes' (lambda_p = mu / K at the point: the surface row has
        # no weight), and its term S^{n+1} mu^{n+1} out of gk
        s, src, q = wp.tid()
        t = n + clock[0]
        wq = w[0, s, src, q]
        if wq != dtype(0.0):
            i = idx[0, s, src, q]
            u = mu[s, i[0], i[1]]
            wp.atomic_add(gk, s, i[0], i[1], -scale * (amp[s, src, t + 1] - amp[s, src, t]) * wq * u)
            g = scale * wq * u / k[i[0], i[1]]
            wp.atomic_add(g_amp, s, src, t + 1, g)
            wp.atomic_add(g_amp, s, src, t, -g)

    @wp.func
    def residual_point(j: int, f: arr3, mat: arr2, res: arr3, fwd: arr3, g: arr3, idx: idx4, w: arr4, s: int, r: int, q: int, t: int):
        # operator j's point q of receiver r: f += mat w res (f = mat lambda), its image term fwd (level n) times that into g
        wq = w[j, s, r, q]
        if wq != dtype(0.0):
            i = idx[j, s, r, q]
            u = mat[i[0], i[1]] * wq * res[s, r, t]
            wp.atomic_add(f, s, i[0], i[1], u)
            wp.atomic_add(g, s, i[0], i[1], fwd[s, i[0], i[1]] * u)

    @unique_kernel(enable_backward=False)
    def record_adjoint(nux: arr3, nuz: arr3, mu: arr3, bx: arr2, bz: arr2, k: arr2, r_vx: arr3, r_vz: arr3, r_p: arr3, idx: idx4,
                       w: arr4, n: int, clock: iarr1, vx: arr3, vz: arr3, p: arr3, gbx: arr3, gbz: arr3, gk: arr3, parts: int):  # fmt: skip
        # the adjoint of record's sample n: the residuals through the operators' transposes into lambda, as nu = b lambda_v
        # and mu = K lambda_p (no weight on a free surface's row), and their image terms with level n's vx, vz, p; parts
        # (record_point's bits): p's (1), the velocities' (2)
        s, r, q = wp.tid()
        t = n + clock[0]
        if (parts & 1) != 0:
            residual_point(0, mu, k, r_p, p, gk, idx, w, s, r, q, t)
        if (parts & 2) != 0:
            residual_point(1, nux, bx, r_vx, vx, gbx, idx, w, s, r, q, t)
            residual_point(2, nuz, bz, r_vz, vz, gbz, idx, w, s, r, q, t)

    @unique_kernel(enable_backward=False)
    def material_adjoints(gbx: arr3, gbz: arr3, gk: arr3, bx: arr2, bz: arr2, k: arr2, a_bx: arr2, a_bz: arr2, a_k: arr2):
        # dJ/d(bx, bz, K) at an interior node: the sums over the shots / b^2, / K^2
        zi, xi = wp.tid()
        z = zi + wp.static(M)
        x = xi + wp.static(M)
        sx = dtype(0.0)
        sz = dtype(0.0)
        sk = dtype(0.0)
        for s in range(gk.shape[0]):
            sx += gbx[s, z, x]
            sz += gbz[s, z, x]
            sk += gk[s, z, x]
        a_bx[z, x] = sx / (bx[z, x] * bx[z, x])
        a_bz[z, x] = sz / (bz[z, x] * bz[z, x])
        a_k[z, x] = sk / (k[z, x] * k[z, x])

    return dict(source_adjoint=source_adjoint, record_adjoint=record_adjoint, material_adjoints=material_adjoints)


def _pressure_tiles(ns, L, pressure_cell, record_thread, image=False):
    """The pressure half step untaped, as kernels/viscoacoustic's _velocity_tiles does the velocity one (L: its
    _lanes): `records` threads recording the receivers' velocities (fvx, fvz: the arrays vx, vz are, which the launch
    only reads) into `sample` (+ clock[0]), core tiles with the rows of vz in a sliding window, frame cells by
    pressure_cell. Then each thread t adds the explosive sources' terms at the cells it stepped (AcousticVD.source_plan:
    terms span[t] .. span[t + 1] - 1, in inject's order; none where span has one element): inject's arithmetic on the
    level's new p, without its launch. With `image` (the adjoint's) each cell also adds f1 (p_new - p) into g1 (flat
    and as vectors; pressure_cell takes f1, g1 last); otherwise they are None."""
    M, C, dtype, arr1, arr3, Axis, rows = ns.M, ns.C, ns.dtype, ns.arr1, ns.arr3, ns.Axis, TILE_ROWS
    arr4, iarr1, idx4, idx1 = ns.arr4, ns.iarr1, ns.idx4, wp.array(dtype=wp.vec2i)
    V, NB, vec, arrv, load, put = L.V, L.NB, L.vec, L.arrv, L.load, L.put
    row_line, window, slide, tile, frame_cell = L.row_line, L.window, L.slide, L.tile, L.frame_cell

    @wp.func
    def pressure_tile(t: int, vx: arrv, vz: arrv, p: arrv, k: arrv, p_new: arrv, dt: dtype, inv_dx: dtype, box: wp.vec4i, lz: int,
                      lx: int, f1: arrv, g1: arrv):  # fmt: skip
        tl = tile(t, box, lz, lx)
        n = lx // wp.static(V)
        c = tl[1] // wp.static(V)
        i = tl[2] // wp.static(V)
        w = window(vz, i, n, wp.static(-M))  # vz at rows z - M .. z + M - 1
        for r in range(wp.static(rows)):
            if tl[0] + r < box[1]:
                xl = row_line(vx, i, load(vx, i))
                pc = load(p, i)
                km = load(k, c)
                o = vec()
                for j in range(wp.static(V)):
                    ex = dtype(0.0)
                    ez = dtype(0.0)
                    for m in range(wp.static(M)):
                        ex += dtype(wp.static(C[m])) * (xl[wp.static(NB * V + m) + j] - xl[wp.static(NB * V - m - 1) + j])
                        ez += dtype(wp.static(C[m])) * (w[wp.static(M + m), j] - w[wp.static(M - 1 - m), j])
                    o[j] = pc[j] - dt * km[j] * ((ex * inv_dx) + (ez * inv_dx))
                put(p_new, i, o)
                if wp.static(image):
                    a1 = load(f1, i)
                    s1 = load(g1, i)
                    for j in range(wp.static(V)):
                        s1[j] = s1[j] + a1[j] * (o[j] - pc[j])
                    put(g1, i, s1)
                if wp.static(r + 1 < rows):
                    w = slide(w, load(vz, i + wp.static(M) * n))
                i += n
                c += n

    @unique_kernel(grid_stride=False, enable_backward=False)
    def pressure_tiles(
        vx: arr1, vz: arr1, p: arr1, k: arr1, o_p_x: arr1, o_p_z: arr1, n_p_x: arr1, n_p_z: arr1, p_new: arr1, az: Axis, ax: Axis,
        dt: dtype, inv_dx: dtype, top: int, grid: Grid, vxv: arrv, vzv: arrv, pv: arrv, kv: arrv, p_newv: arrv, box: wp.vec4i,
        tiles: int, frame: int, cells: int, fvx: arr3, fvz: arr3, fp: arr3, d_vx: arr3, d_vz: arr3, d_p: arr3, idx: idx4, w: arr4,
        sample: int, clock: iarr1, records: int, span: iarr1, term_cell: iarr1, term_source: idx1, term_w: arr1, amp: arr3, level: int,
        scale: dtype, f1: arr1, g1: arr1, f1v: arrv, g1v: arrv,
    ):  # fmt: skip
        t = wp.tid()
        if t < records:
            record_thread(t, fvx, fvz, fp, d_vx, d_vz, d_p, idx, w, sample + clock[0], 2)
            return
        t -= records
        if t < frame:
            if t < tiles:
                pressure_tile(t, vxv, vzv, pv, kv, p_newv, dt, inv_dx, box, grid.lz, grid.lx, f1v, g1v)
        else:
            s = (t - frame) // cells
            zx = frame_cell(t - frame - s * cells, grid.lz, grid.lx, box)
            m = zx[0] * grid.lx + zx[1]
            if wp.static(image):
                pressure_cell(vx, vz, p, k, o_p_x, o_p_z, n_p_x, n_p_z, p_new, az, ax, dt, inv_dx, top, grid, s, zx[0], zx[1], m,
                              s * grid.lz * grid.lx + m, f1, g1)  # fmt: skip
            else:
                pressure_cell(vx, vz, p, k, o_p_x, o_p_z, n_p_x, n_p_z, p_new, az, ax, dt, inv_dx, top, grid, s, zx[0], zx[1], m,
                              s * grid.lz * grid.lx + m)  # fmt: skip
        if t + 1 < span.shape[0]:
            n = level + clock[0]
            for e in range(span[t], span[t + 1]):
                c = term_cell[e]
                sq = term_source[e]
                p_new[c] = p_new[c] + scale * (amp[sq[0], sq[1], n + 1] - amp[sq[0], sq[1], n]) * term_w[e]

    return pressure_tiles


def _field_kernels_3d(ns):
    """The 3D velocity and pressure half steps on flat views (kernels/elastic3d's flat stencils, Grid and strips)."""
    M, fs, dtype, arr1, Axis = ns.M, ns.fs, ns.dtype, ns.arr1, ns.Axis
    cpml_psi, store_psi = flat_cpml(dtype)
    dp_dx, dp_dy = make_flat_derivative(ns, 2, False, M, False), make_flat_derivative(ns, 1, False, M, False)
    dp_dz = make_flat_derivative(ns, 0, False, M, True)  # p: odd image above a free surface
    dvx_dx, dvy_dy = make_flat_derivative(ns, 2, True, M, False), make_flat_derivative(ns, 1, True, M, False)
    dvz_dz = make_flat_derivative(ns, 0, True, M, True, even=True)  # vz: even image

    @unique_kernel(grid_stride=False)
    def velocity(
        vx: arr1, vy: arr1, vz: arr1, p: arr1, bx: arr1, by: arr1, bz: arr1, o_x: arr1, o_y: arr1, o_z: arr1, n_x: arr1, n_y: arr1,
        n_z: arr1, vx_new: arr1, vy_new: arr1, vz_new: arr1, az: Axis, ay: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int,
        g: Flat3,
    ):  # fmt: skip
        # v_new = v - dt b grad p at every interior velocity node
        q = flat_cell(wp.tid(), g, wp.static(M))
        t = q[0]
        z = q[1]
        y = q[2]
        x = q[3]
        m = (z * g.ly + y) * g.lx + x  # model cell
        f = t * g.shot + m  # field cell
        jz = az.store[z]
        jy = ay.store[y]
        jx = ax.store[x]
        k = flat_strips(g, t, z, y, x, jz, jy, jx)
        gx = dp_dx(p, f, 1, z, top) * inv_dx
        gy = dp_dy(p, f, g.lx, z, top) * inv_dx
        gz = dp_dz(p, f, g.lxy, z, top) * inv_dx
        qx = cpml_psi(gx, jx, x, ax.ah, ax.bh, o_x, k[2])
        qy = cpml_psi(gy, jy, y, ay.ah, ay.bh, o_y, k[1])
        qz = cpml_psi(gz, jz, z, az.ah, az.bh, o_z, k[0])
        ux = vx[f]
        uy = vy[f]
        uz = vz[f]
        bxm = bx[m]
        bym = by[m]
        bzm = bz[m]
        store_psi(jx, n_x, k[2], qx)
        store_psi(jy, n_y, k[1], qy)
        store_psi(jz, n_z, k[0], qz)
        vx_new[f] = ux - dt * bxm * (gx + qx)
        vy_new[f] = uy - dt * bym * (gy + qy)
        vz_new[f] = uz - dt * bzm * (gz + qz)

    @unique_kernel(grid_stride=False)
    def pressure(
        vx: arr1, vy: arr1, vz: arr1, p: arr1, k: arr1, o_x: arr1, o_y: arr1, o_z: arr1, n_x: arr1, n_y: arr1, n_z: arr1,
        p_new: arr1, az: Axis, ay: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int, g: Flat3,
    ):  # fmt: skip
        # p_new = p - dt K div v; 0 on a free surface's row
        q = flat_cell(wp.tid(), g, wp.static(M))
        t = q[0]
        z = q[1]
        y = q[2]
        x = q[3]
        m = (z * g.ly + y) * g.lx + x
        f = t * g.shot + m
        jz = az.store[z]
        jy = ay.store[y]
        jx = ax.store[x]
        c = flat_strips(g, t, z, y, x, jz, jy, jx)
        ex = dvx_dx(vx, f, 1, z, top) * inv_dx
        ey = dvy_dy(vy, f, g.lx, z, top) * inv_dx
        ez = dvz_dz(vz, f, g.lxy, z, top) * inv_dx
        qx = cpml_psi(ex, jx, x, ax.a, ax.b, o_x, c[2])
        qy = cpml_psi(ey, jy, y, ay.a, ay.b, o_y, c[1])
        qz = cpml_psi(ez, jz, z, az.a, az.b, o_z, c[0])
        keep = dtype(1.0)
        if wp.static(fs):
            if z == top:
                keep = dtype(0.0)
        pf = p[f]
        km = k[m]
        store_psi(jx, n_x, c[2], qx)
        store_psi(jy, n_y, c[1], qy)
        store_psi(jz, n_z, c[0], qz)
        p_new[f] = keep * (pf - dt * km * ((ex + qx) + (ey + qy) + (ez + qz)))

    return velocity, pressure


def _kernels_3d(ns):
    """The 3D field, materials and point kernels (operators of p, vx, vy, vz: elastic3d's make_point)."""
    M, dtype, arr3, arr4, iarr1, idx4 = ns.M, ns.dtype, ns.arr3, ns.arr4, ns.iarr1, ns.idx4
    velocity, pressure = _field_kernels_3d(ns)
    hicks = hicks_axis(dtype)
    pt_p, pt_vx = make_point(ns, hicks, 0.0, 0.0, 0.0, True), make_point(ns, hicks, 0.0, 0.0, 0.5, True)
    pt_vy, pt_vz = make_point(ns, hicks, 0.0, 0.5, 0.0, True), make_point(ns, hicks, 0.5, 0.0, 0.0, False)

    @unique_kernel
    def materials(vp: arr3, rho: arr3, bx: arr3, by: arr3, bz: arr3, k: arr3):
        # MATERIALS at the interior nodes from the padded vp (m/s) and rho (kg/m^3)
        zi, yi, xi = wp.tid()
        z = zi + wp.static(M)
        y = yi + wp.static(M)
        x = xi + wp.static(M)
        b = dtype(1.0) / rho[z, y, x]
        bx[z, y, x] = dtype(0.5) * (b + dtype(1.0) / rho[z, y, x + 1])
        by[z, y, x] = dtype(0.5) * (b + dtype(1.0) / rho[z, y + 1, x])
        bz[z, y, x] = dtype(0.5) * (b + dtype(1.0) / rho[z + 1, y, x])
        k[z, y, x] = rho[z, y, x] * vp[z, y, x] * vp[z, y, x]

    @unique_kernel(enable_backward=False)  # computed once per run, never differentiated (locations are fixed)
    def weights(loc: arr3, origin: wp.vec3i, inv_dx: dtype, top: int, idx: idx4, w: arr4):
        # node and weight of point q of location r (metres (z, y, x)) for p, vx, vy, vz (first index)
        s, r, q = wp.tid()
        i, wq = pt_p(loc, s, r, q, origin, inv_dx, top)
        idx[0, s, r, q] = i
        w[0, s, r, q] = wq
        i, wq = pt_vx(loc, s, r, q, origin, inv_dx, top)
        idx[1, s, r, q] = i
        w[1, s, r, q] = wq
        i, wq = pt_vy(loc, s, r, q, origin, inv_dx, top)
        idx[2, s, r, q] = i
        w[2, s, r, q] = wq
        i, wq = pt_vz(loc, s, r, q, origin, inv_dx, top)
        idx[3, s, r, q] = i
        w[3, s, r, q] = wq

    @unique_kernel
    def inject(p: arr4, amp: arr3, idx: idx4, w: arr4, n: int, clock: iarr1, scale: dtype):
        # p += (S(t_{n+1}) - S(t_n)) w / dx^3 (scale = 1 / dx^3) at the p operator's points; sample n + clock[0]
        s, src, q = wp.tid()
        t = n + clock[0]
        wq = w[0, s, src, q]
        if wq != dtype(0.0):
            i = idx[0, s, src, q]
            wp.atomic_add(p, s, i[0], i[1], i[2], scale * (amp[s, src, t + 1] - amp[s, src, t]) * wq)

    @wp.func
    def sample(f: arr4, s: int, i: wp.vec3i, w: dtype) -> dtype:
        if w != dtype(0.0):
            return w * f[s, i[0], i[1], i[2]]
        return dtype(0.0)

    @unique_kernel
    def record(vx: arr4, vy: arr4, vz: arr4, p: arr4, d_vx: arr3, d_vy: arr3, d_vz: arr3, d_p: arr3, idx: idx4, w: arr4, n: int,
               clock: iarr1):  # fmt: skip
        # sample n of each receiver's vx, vy, vz, p through its operators
        s, r, q = wp.tid()
        t = n + clock[0]
        wp.atomic_add(d_p, s, r, t, sample(p, s, idx[0, s, r, q], w[0, s, r, q]))
        wp.atomic_add(d_vx, s, r, t, sample(vx, s, idx[1, s, r, q], w[1, s, r, q]))
        wp.atomic_add(d_vy, s, r, t, sample(vy, s, idx[2, s, r, q], w[2, s, r, q]))
        wp.atomic_add(d_vz, s, r, t, sample(vz, s, idx[3, s, r, q], w[3, s, r, q]))

    return dict(velocity=velocity, pressure=pressure, materials=materials, weights=weights, inject=inject, record=record,
                pad_model=elastic3d_build(ns.order, dtype, ns.fs).pad_model, operator_points=ns.W**3)  # fmt: skip


@functools.lru_cache(maxsize=None)
def build(order: int, dtype, free_surface: bool, ndim: int):
    """Kernels for one (order, dtype, free_surface, ndim), compiled once per process."""
    M = order // 2

    @wp.struct
    class Axis:
        store: wp.array(dtype=wp.int32)  # strip index per padded index, -1 outside the PML strips
        a: wp.array(dtype=dtype)  # CPML a, b at integer positions
        b: wp.array(dtype=dtype)
        ah: wp.array(dtype=dtype)  # at half positions (index p stands for p + 1/2)
        bh: wp.array(dtype=dtype)

    ns = SimpleNamespace(order=order, M=M, C=STAGGERED_DERIVATIVE[order], HR=HICKS_RADIUS, W=2 * HICKS_RADIUS, fs=bool(free_surface),
                         dtype=dtype, arr1=wp.array(dtype=dtype), arr2=wp.array2d(dtype=dtype), arr3=wp.array3d(dtype=dtype),
                         arr4=wp.array4d(dtype=dtype), iarr1=wp.array(dtype=wp.int32),
                         idx4=wp.array4d(dtype=wp.vec2i if ndim == 2 else wp.vec3i), Axis=Axis)  # fmt: skip
    return Kernels(Axis=Axis, halo=M, **(_kernels_2d(ns) if ndim == 2 else _kernels_3d(ns)))


class State:
    """Fields at one time level n: the velocities (VELOCITIES[ndim], m/s) at t = (n - 1/2) dt and p (Pa) at t = n dt,
    each (n_shots, Lz, [Ly,] Lx), and the CPML memory variables psi (dict, see PSI)."""

    def __init__(self, v: dict, p, psi: dict):
        self.v, self.p, self.psi = v, p, psi
        self._flat = None
        self._vectors = {}

    def vectors(self, V: int) -> tuple:
        """The velocities' and p's flat views as vector(V) (kernels/common.as_vectors), the tiled half steps' inputs;
        made once per V."""
        if V not in self._vectors:
            self._vectors[V] = tuple(as_vectors(a, V) for a in (*self.v.values(), self.p))
        return self._vectors[V]

    def flat(self) -> "State":
        """The State of the arrays' flat (1D) views, the 2D field kernels' inputs; made once, they share memory and
        .grad with the arrays."""
        if self._flat is None:
            self._flat = State({k: a.flatten() for k, a in self.v.items()}, self.p.flatten(), {k: a.flatten() for k, a in self.psi.items()})
        return self._flat

    def __getattr__(self, name):
        v = self.__dict__["v"]
        if name in v:
            return v[name]
        raise AttributeError(name)

    def arrays(self):
        return [*self.v.values(), self.p, *self.psi.values()]


class AcousticVD:
    """Launch helper: padded grid, CPML coefficients and one time step of the variable-density acoustic scheme.

    shape: physical grid (nz, nx) or (nz, ny, nx); dx (m), dt (s); pml_width cells on every absorbing side (all, or
    all but the top with free_surface); vmax: CPML reference speed (m/s). Locations passed to `operator` are metres
    (z, [y,] x) from the physical node 0."""

    def __init__(self, shape, dx, dt, order, n_shots, pml_width, pml_reflection, pml_frequency, vmax, free_surface=False,
                 dtype=wp.float32, device="cpu"):  # fmt: skip
        self.shape = tuple(int(n) for n in shape)
        self.ndim = nd = len(self.shape)
        self.dx, self.dt, self.order, self.n_shots = float(dx), float(dt), int(order), int(n_shots)
        self.dtype, self.device, self.free_surface = dtype, device, bool(free_surface)
        self.k = build(self.order, dtype, self.free_surface, nd)
        R = self.k.halo
        nb = int(pml_width)
        lo = (0 if free_surface else nb, *(nb,) * (nd - 1))
        self.padded = tuple(self.shape[a] + lo[a] + nb + 2 * R for a in range(nd))
        self.origin = (wp.vec2i if nd == 2 else wp.vec3i)(*(R + n for n in lo))
        self.top = R
        self.axes, self.strip_width = cpml_axes(self.k.Axis, lo, nb, self.padded, R, dx, dt, vmax, pml_reflection, pml_frequency, dtype,
                                                device)  # fmt: skip
        self.interior = (self.n_shots, *(n - 2 * R for n in self.padded))
        if nd == 2:
            self.grid = field_grid(self.padded, R, self.strip_width, self.n_shots * math.prod(self.padded))
        else:
            check_flat_cells(self.n_shots * math.prod(self.padded), f"n_shots = {self.n_shots} on a padded grid {self.padded}")
            self.grid = flat_grid(self.interior[1:], self.padded, self.strip_width)
        self.inv_dx = dtype(1.0 / dx)
        self.dt_device = dtype(dt)
        self.cuda = wp.get_device(device).is_cuda
        self.clock = wp.zeros(1, dtype=wp.int32, device=device)  # stays 0: plain launches pass n itself
        self.tiles = self.adjoint_tiles = None
        if nd == 2:  # the adjoint's core keeps its stencils off the CPML strips (adjoint_step)
            self.tiles = tile_plan(self.axes, self.padded, R, self.n_shots, self.free_surface, self.top)
            self.adjoint_tiles = tile_plan(self.axes, self.padded, R, self.n_shots, self.free_surface, self.top, R)

    def psi_shape(self, name):
        axis = PSI[self.ndim][name]
        shape = [self.n_shots, *self.padded]
        shape[axis + 1] = self.strip_width[axis]
        return tuple(shape)

    def new_state(self, requires_grad=False, packed=False) -> State:
        """A State of zeros; packed: its arrays views of one flat array, its `packed` attribute (one copy copies the
        State: a checkpointed sweep copies a level twice a segment), each from a multiple of 64 values."""
        full = (self.n_shots, *self.padded)
        shapes = [full] * (1 + self.ndim) + [self.psi_shape(k) for k in PSI[self.ndim]]
        if packed:
            sizes = [-(-math.prod(s) // 64) * 64 for s in shapes]
            buf = wp.zeros(sum(sizes), dtype=self.dtype, device=self.device, requires_grad=requires_grad)
            starts = np.cumsum([0, *sizes])
            arrays = [buf[int(o) : int(o) + math.prod(s)].reshape(s) for o, s in zip(starts, shapes)]
        else:
            arrays = [wp.zeros(s, dtype=self.dtype, device=self.device, requires_grad=requires_grad) for s in shapes]
        nv = self.ndim
        st = State(dict(zip(VELOCITIES[nv], arrays[:nv])), arrays[nv], dict(zip(PSI[nv], arrays[nv + 1 :])))
        st.packed = buf if packed else None
        return st

    def pad_model(self, m, requires_grad=False):
        """Padded model (Lz, [Ly,] Lx) from a physical one (a wp.array of shape), extended by edge replication."""
        out = wp.zeros(self.padded, dtype=self.dtype, device=self.device, requires_grad=requires_grad)
        wp.launch(self.k.pad_model, dim=self.padded, inputs=[m, out, self.origin], device=self.device)
        return out

    def materials(self, vp, rho, requires_grad=False, out=None):
        """MATERIALS[ndim] (padded arrays, interior nodes set) from the padded vp (m/s) and rho (kg/m^3); into out (an
        earlier call's Materials) if given."""
        if out is None:
            zeros = [wp.zeros(self.padded, dtype=self.dtype, device=self.device, requires_grad=requires_grad) for _ in MATERIALS[self.ndim]]
            out = Materials(zeros)
        wp.launch(self.k.materials, dim=self.interior[1:], inputs=[vp, rho, *out], device=self.device)
        return out

    def operator(self, loc: wp.array):
        """The fixed operators of locations loc (S, n, ndim) metres: (idx (1 + ndim, S, n, points) vec2i | vec3i, weights
        (1 + ndim, S, n, points)) for p and the velocities (VELOCITIES[ndim])."""
        shape = (1 + self.ndim, *loc.shape[:2], self.k.operator_points)
        return host_operator(self.k.weights, loc, [self.origin, self.inv_dx, self.top], shape, wp.vec2i if self.ndim == 2 else wp.vec3i,
                             self.dtype, self.device)  # fmt: skip

    def source_operator(self, loc: wp.array):
        """operator(loc) for the explosive sources, and where the step is tiled (2D) the plan of adding their terms in
        the tiled pressure launch (source_plan): (idx, w[, span, term_cell, term_source, term_w]). Every array has a
        size fixed by the grid, shots and sources, so a kept loop can copy a later call's into its own."""
        op = self.operator(loc)
        return op if self.tiles is None else (*op, *self.source_plan(op))

    def source_plan(self, op) -> tuple:
        """(span, term_cell, term_source, term_w): the p operator's points of op (operator's) as terms of the tiled
        pressure launch, each given to the thread that steps its cell (a core tile's or a frame cell's; tile_plan's
        numbering), in inject's order (shot, source, point) within a thread: thread t adds terms span[t] ..
        span[t + 1] - 1, term e at flat p index term_cell[e] (shot included) from source term_source[e] (shot,
        source) with weight term_w[e]. Built from the small host copy of op's points; span (one int a thread) by a
        binary search on the device."""
        V, box, tiles, frame, cells = self.tiles
        R, (lz, lx), S = self.k.halo, self.padded, self.n_shots
        idx, w = op[0].numpy()[0], op[1].numpy()[0]  # (S, n_src, points, 2), (S, n_src, points)
        s, src = (a.ravel() for a in np.indices(w.shape)[:2])
        z, x = idx[..., 0].ravel(), idx[..., 1].ravel()
        z0, z1, x0, x1 = (int(b) for b in box)
        nxc, blocks = (x1 - x0) // V, -(-(z1 - z0) // TILE_ROWS)
        core = (z >= z0) & (z < z1) & (x >= x0) & (x < x1)
        nx = lx - 2 * R
        above, below, sides = (z0 - R) * nx, (lz - R - z1) * nx, (x0 - R) + (lx - R - x1)
        f = np.where(z < z0, (z - R) * nx + x - R, np.where(z >= z1, above + (z - z1) * nx + x - R,
                     above + below + (z - z0) * sides + np.where(x < x0, x - R, x - x1 + x0 - R)))  # fmt: skip
        owner = np.where(core, (s * blocks + (z - z0) // TILE_ROWS) * nxc + (x - x0) // V, frame + s * cells + f)
        order = np.argsort(owner, kind="stable")
        threads = frame + S * cells
        if owner.min() < 0 or owner.max() >= threads:
            raise ValueError(f"a source point lies outside the interior of the padded grid {self.padded}")

        def put(a, dtype):
            return wp.array(np.ascontiguousarray(a[order]), dtype=dtype, device=self.device)

        owners = put(owner, wp.int32)
        span = wp.empty(threads + 1, dtype=wp.int32, device=self.device)
        wp.launch(lower_bound, dim=threads + 1, inputs=[owners, span], device=self.device)
        return span, put(s * lz * lx + z * lx + x, wp.int32), put(np.stack([s, src], axis=1), wp.vec2i), put(w.ravel(), self.dtype)

    def records_in_step(self) -> bool:
        """Whether step can record (record=): the 2D tiled half steps, outside a tape."""
        return self.tiles is not None and wp._src.context.runtime.tape is None

    def step(self, st: State, mat, sources, n: int, out: State | None = None, clock=None, record=None) -> State:
        """Advance st (level n) to level n + 1 with the explosive sources' samples n and n + 1 (+ clock[0]); sources:
        (amplitudes (S, n_src, >= n + 2), their operator (operator, or source_operator: the tiled step then adds their
        terms in its pressure launch, no inject launch)) or None. mat: MATERIALS[ndim] (materials' Materials). With
        out=None in place; else into out's arrays (st unchanged), as under a tape (each level its own arrays).
        record = (data, receiver_op, k) where records_in_step: the receivers' p of level n into sample k (+ clock[0]) by
        threads of the velocity launch, and their velocities of level n + 1 into sample k + 1 (none past data's
        samples) by threads of the pressure launch (in place too: each launch records what it only reads); so the
        velocities of level 0 are never recorded (zero: every run starts at rest), and the last level's p is
        recorded by a further step."""
        if record is not None and not self.records_in_step():
            raise ValueError("record= needs the 2D tiled step outside a tape (records_in_step)")
        out = st if out is None else out
        clock = self.clock if clock is None else clock
        names = VELOCITIES[self.ndim]
        scale = self.dtype(self.dx**-self.ndim)
        vpsi = [f"{v}_{v[1]}" for v in names]
        ppsi = [f"p_{v[1]}" for v in names]
        common = [*self.axes, self.dt_device, self.inv_dx, self.top]
        f, o, m, common, dim = st.flat(), out.flat(), mat.flat, [*common, self.grid], math.prod(self.interior)  # flat views, a 1D launch
        vel = [*f.v.values(), f.p, *m[:-1], *(f.psi[k] for k in vpsi), *(o.psi[k] for k in vpsi), *o.v.values(), *common]
        pre = [*o.v.values(), f.p, m[-1], *(f.psi[k] for k in ppsi), *(o.psi[k] for k in ppsi), o.p, *common]
        fused = None
        if self.tiles is None or wp._src.context.runtime.tape is not None:  # 3D, or under a tape: the per-cell kernels
            wp.launch(self.k.velocity, dim=dim, inputs=vel, device=self.device)
            wp.launch(self.k.pressure, dim=dim, inputs=pre, device=self.device)
        else:
            V, box, tiles, frame, cells = self.tiles
            velocity, pressure = self.k.tiled[V]
            (fx, fz, fp), (ox, oz, op), mv = st.vectors(V), out.vectors(V), mat.vectors(V)
            dim, rest = frame + self.n_shots * cells, [box, tiles, frame, cells]
            rec, threads = tiled_recording(st, record, clock)
            wp.launch(velocity, dim=threads + dim, inputs=[*vel, fx, fz, fp, *mv[:2], ox, oz, *rest, *rec, *[None] * 8], device=self.device,
                      block_dim=TILE_THREADS)  # fmt: skip
            rec, threads = tiled_recording(out, None if record is None else (*record[:2], record[2] + 1), clock)
            fused = sources if sources is not None and len(sources[1]) > 2 else None
            terms = [*fused[1][2:], fused[0]] if fused is not None else [None] * 5
            wp.launch(pressure, dim=threads + dim, inputs=[*pre, ox, oz, fp, mv[2], op, *rest, *rec, *terms, n, scale, *[None] * 4],
                      device=self.device, block_dim=TILE_THREADS)  # fmt: skip
        if sources is not None and fused is None:
            amplitudes, (idx, w) = sources[0], sources[1][:2]
            wp.launch(self.k.inject, dim=idx.shape[1:], inputs=[out.p, amplitudes, idx, w, n, clock, scale], device=self.device)
        return out

    def adjoint_step(self, st: State, nxt: State, mat, adj: tuple, sums, sources, g_amp, residual, n: int, clock=None, side=None,
                     parts=3):  # fmt: skip
        """The hand-written adjoint of step(st, mat, sources, n, out=nxt) in 2D (_adjoint_cells: two tiled launches
        as the step's, their core the forward's tiles with dt -> -dt, their frame the adjoint's cells).

        adj = (a, b): two States sharing the adjoint fields (nu_x, nu_z, mu) = (b lambda_v, K lambda_p), each with its
        own lambda_psi: level n + 1's in b on entry, level n's in a on return (the fields in place). sums: Materials of
        the image's sums (gbx, gbz, gk) (S, Lz, Lx) (_adjoint_kernels), added to; sources as step's or None, g_amp:
        dJ/d amplitudes (S, n_src, >= n + 2), added to; residual = (r_vx, r_vz, r_p) arrays (S, n_rec, >= n + 1) and
        the receivers' operator: their sample n (+ clock[0]) into the adjoint of level n. side: None, or a second stream
        (accel.graphs.SideStream: `with side():`, side.join()) that runs the sources' adjoint beside the velocity launch
        (it reads mu, which that launch only reads). parts: which residuals to add, p's (1) and the velocities' (2)."""
        clock = self.clock if clock is None else clock
        V, box, tiles, frame, cells = self.adjoint_tiles
        velocity, pressure = self.k.adjoint_tiled[V]
        new, old = adj
        f, o, m, fv, mv, gv = new.flat(), old.flat(), mat.flat, new.vectors(V), mat.vectors(V), sums.vectors(V)
        scale = self.dtype(self.dx**-self.ndim)
        common = [*self.axes, self.dtype(-self.dt), self.inv_dx, self.top, self.grid]
        dim, rest = frame + self.n_shots * cells, [box, tiles, frame, cells]
        rec = tiled_recording(new, None, clock)[0]
        a, b = st.flat(), nxt.flat()
        vel = [*f.v.values(), f.p, *m[:-1], o.psi["p_x"], o.psi["p_z"], f.psi["p_x"], f.psi["p_z"], *f.v.values(), *common]
        image = [b.vx, b.vz, *sums.flat[:2], *nxt.vectors(V)[:2], *gv[:2]]
        if sources is not None:
            idx, w = sources[1][:2]
            with side() if side is not None else contextlib.nullcontext():
                wp.launch(self.k.source_adjoint, dim=idx.shape[1:], inputs=[new.p, mat[-1], sources[0], idx, w, n, clock, scale, sums[2],
                          g_amp], device=self.device)  # fmt: skip
        wp.launch(velocity, dim=dim, inputs=[*vel, *fv, *mv[:2], *fv[:2], *rest, *rec, *image], device=self.device, block_dim=TILE_THREADS)
        if side is not None:
            side.join()
        pre = [*f.v.values(), f.p, m[-1], o.psi["vx_x"], o.psi["vz_z"], f.psi["vx_x"], f.psi["vz_z"], f.p, *common]
        image = [a.p, sums.flat[2], st.vectors(V)[2], gv[2]]
        wp.launch(pressure, dim=dim, inputs=[*pre, *fv, mv[2], fv[2], *rest, *rec, *[None] * 5, n, scale, *image], device=self.device,
                  block_dim=TILE_THREADS)  # fmt: skip
        *res, (idx, w) = residual
        wp.launch(self.k.record_adjoint, dim=idx.shape[1:], inputs=[*new.v.values(), new.p, *mat, *res, idx, w, n, clock, *st.v.values(),
                  st.p, *sums, parts], device=self.device)  # fmt: skip

    def record(self, st: State, data, receiver_op, k: int, clock=None):
        """Add sample k (+ clock[0]) of the receivers' velocities and p into data (VELOCITIES[ndim] then pressure,
        arrays (S, n_rec, >= k + 1))."""
        idx, w = receiver_op
        clock = self.clock if clock is None else clock
        wp.launch(self.k.record, dim=idx.shape[1:], inputs=[*st.v.values(), st.p, *data, idx, w, k, clock], device=self.device)
