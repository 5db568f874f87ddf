"""Warp kernels for the 3D isotropic elastic wave equation, velocity-stress on the standard staggered grid (Virieux 1986;
Graves 1996).

Equations (axes (z, y, x), z down; b = 1/rho, lambda = rho (vp^2 - 2 vs^2), mu = rho vs^2; i, j in {x, y, z}):

    dv_i/dt = b sum_j ds_ij/dx_j + b f_i(t) delta,
    ds_ij/dt = lambda delta_ij div v + mu (dv_i/dx_j + dv_j/dx_i) - dM_ij/dt delta.

Staggering, positions in cells from padded node (0, 0, 0) as (z, y, x); the array index (i, j, k) of

    sxx, syy, szz, vp, vs, rho   (i, j, k)               vx   (i, j, k + 1/2)
    sxy                          (i, j + 1/2, k + 1/2)   vy   (i, j + 1/2, k)
    sxz                          (i + 1/2, j, k + 1/2)   vz   (i + 1/2, j, k)
    syz                          (i + 1/2, j + 1/2, k)

mu at a shear node is the harmonic mean of its four neighbours in the shear's plane (0 if any is 0), the buoyancy at
a velocity node the arithmetic mean of 1/rho at its two neighbours (`materials`, differentiated by Warp: the chain
rule to vp, vs, rho). Staggered derivatives of order 2/4/8 (numerics.STAGGERED_DERIVATIVE). Time (leapfrog) as
kernels/elastic: level n holds v at t = (n - 1/2) dt and the stresses at t = n dt; a step is v^{n+1/2} = v^{n-1/2} +
dt b (div s^n + f(t_n) delta), then s^{n+1} = s^n + dt C : grad v^{n+1/2} - (M(t_{n+1}) - M(t_n)) delta. Recorded
sample n: v at t = (n - 1/2) dt, pressure -(sxx + syy + szz)/3 at t = n dt.

Layout: fields (n_shots, Lz, Ly, Lx), models (Lz, Ly, Lx), every axis padded as [halo R][PML][grid][PML][halo R],
R = order / 2 (no PML on top with a free surface), halo cells zero and never written. CPML (Komatitsch & Martin 2007,
kappa = 1; kernels/elastic's cpml_axes): one memory variable per spatial derivative (18), stored per axis in strips
along that axis as 4D arrays (3 n_shots, ...) whose first index is 3 s + c: PSI["v_a"] for the velocity update's
derivative along axis a of the stress s_{c a} (c: vx, vy, vz = 0, 1, 2), PSI["s_a"] for the stress update's dv_c/da.
`velocity` and `stress` read all of these as flat 1D views (State.flat) with int32 flat indices (Grid): field cell
((s Lz + z) Ly + y) Lx + x, model cell (z Ly + y) Lx + x, a strip cell likewise with the strip index in place of its
axis's coordinate; steps along x, y, z are 1, Lx, Lx Ly (arrays must stay below 2^31 cells).

Free surface (stress imaging, Levander 1988; Graves 1996), as kernels/elastic in 2D: the top row of normal-stress
nodes (padded row `top`, physical z = 0) is the surface, szz = 0 there and sxx, syy follow from szz = 0
(ds_xx/dt = (l2m - lam^2/l2m) dvx/dx + (lam - lam^2/l2m) dvy/dy); szz, sxz, syz above it are the odd images of those
below. The velocities' z-derivatives whose full stencil would reach above the surface use the highest staggered
order that fits (order 2 on the first row). Sources and receivers: the Kaiser-windowed sinc operator
(kernels/common.hicks_axis) at each field's position, W^3 points, W = 2 HICKS_RADIUS, folded across a free surface
as kernels/elastic's make_point (odd for szz, sxz, syz; a point on the surface row gets no szz weight); its weights
are computed once per run (`weights`).

Kernels, plain per-cell Warp kernels that Warp differentiates (Tape): `velocity`, `stress` (a half step each, in place
or out of place: a cell reads only its own old value of a field it writes; a 1D launch over the interior cells of
every shot, decomposed in int32 by flat_cell: less index arithmetic than 4D arrays and a 4D launch), `inject_force`,
`inject_moment`, `record`, `weights`, `materials`, `pad_model`. The flat stencils (make_flat_derivative,
make_flat_reduced_dz, flat_strips) serve any staggered 3D field (kernels/acoustic_vd's 3D kernels too). The field
kernels load everything before their first store (the CPML pair kernels/common.flat_cpml): Warp's arrays may alias,
so the compiler holds each load after a store until that store is done.
"""

import functools
import math
from types import SimpleNamespace

import warp as wp

from adseismic.kernels.common import HICKS_RADIUS, Kernels, check_flat_cells, flat_cpml, hicks_axis, host_operator, unique_kernel
from adseismic.kernels.elastic.propagator import cpml_axes
from adseismic.kernels.numerics import STAGGERED_DERIVATIVE

PSI = {"v_z": 0, "v_y": 1, "v_x": 2, "s_z": 0, "s_y": 1, "s_x": 2}  # name -> axis of its derivatives (and strips)
MATERIALS = ("bx", "by", "bz", "l2m", "lam", "mxy", "mxz", "myz")  # buoyancies, lambda + 2 mu, lambda, shear moduli
FIELDS = ("vx", "vy", "vz", "sxx", "syy", "szz", "sxy", "sxz", "syz")
# threads a block of the velocity and stress launches and of Warp's adjoints of them (recorded with the launch): 128
# beat Warp's 256 by ~6% forward and gradient on an H200 (docs/benchmarks.md, 2026-11-28)
FIELD_THREADS = 128
# the operators of weights: (z, y, x) offset of the field's index, odd image across a free surface; 3 serves sxx, syy
POINTS = ((0.0, 0.0, 0.5, False), (0.0, 0.5, 0.0, False), (0.5, 0.0, 0.0, False), (0.0, 0.0, 0.0, False), (0.0, 0.0, 0.0, True),
          (0.0, 0.5, 0.5, False), (0.5, 0.0, 0.5, True), (0.5, 0.5, 0.0, True))  # fmt: skip


@wp.struct
class Grid:
    """Sizes of a flat 3D layout (int32, kernels' flat indexing): the interior (the launch) and the padded axes,
    their products and the CPML strips' widths and sizes."""

    nz: int  # interior cells along z, y, x (padded minus the halos)
    ny: int
    nx: int
    lz: int  # padded Lz, Ly, Lx
    ly: int
    lx: int
    lxy: int  # Lx Ly (a z step), Lx Ly Lz (a shot)
    shot: int
    wz: int  # strip widths along z, y, x
    wy: int
    wx: int
    sz: int  # the size of one component's strip of each axis (wz Ly Lx, Lz wy Lx, Lz Ly wx)
    sy: int
    sx: int


def flat_grid(interior, padded, widths) -> Grid:
    """The Grid of interior (nz, ny, nx), padded (Lz, Ly, Lx) and strip widths (wz, wy, wx) cells."""
    g = Grid()
    (g.nz, g.ny, g.nx), (g.lz, g.ly, g.lx), (g.wz, g.wy, g.wx) = interior, padded, widths
    g.lxy, g.shot = g.lx * g.ly, g.lx * g.ly * g.lz
    g.sz, g.sy, g.sx = g.wz * g.lxy, g.lz * g.wy * g.lx, g.lz * g.ly * g.wx
    return g


@wp.func
def flat_cell(t: int, g: Grid, halo: int) -> wp.vec4i:
    """(s, z, y, x) padded of a 1D launch's thread t over (n_shots, nz, ny, nx) interior cells."""
    r = t / g.nx
    x = t - r * g.nx
    q = r / g.ny
    y = r - q * g.ny
    s = q / g.nz
    z = q - s * g.nz
    return wp.vec4i(s, z + halo, y + halo, x + halo)


@wp.func
def flat_strips(g: Grid, k: int, z: int, y: int, x: int, jz: int, jy: int, jx: int) -> wp.vec3i:
    """The flat cells of (z, y, x) in the z, y and x strips (strip index jz, jy, jx in place of that coordinate) of
    component k (the strip arrays' first index); component k + i is i g.sz, g.sy, g.sx further."""
    cz = (k * g.wz + jz) * g.lxy + y * g.lx + x
    cy = ((k * g.lz + z) * g.wy + jy) * g.lx + x
    return wp.vec3i(cz, cy, ((k * g.lz + z) * g.ly + y) * g.wx + jx)


def make_flat_derivative(ns, axis: int, half_in: bool, mr: int, image: bool, even: bool = False):
    """d/d(axis) times dx with mr staggered weights of a field on half (half_in) or integer nodes of that axis, at the
    other kind of node; image: the odd (even: the even) image above row `top` (z only, with a free surface). On a flat
    field: d(f, c, step, z, top), f 1D, c the flat cell, step its stride along the axis
    (1, Lx or Lx Ly), z the cell's padded row, top the surface row (read only by a z derivative's image)."""
    dtype, arr1, fs = ns.dtype, ns.arr1, ns.fs
    c = STAGGERED_DERIVATIVE[2 * mr]
    h = 1 if half_in else 0
    mirrored = bool(image and fs and axis == 0)
    sign = 1.0 if even else -1.0

    @wp.func
    def read(f: arr1, cell: int, k: int, step: int, z: int, top: int) -> dtype:
        # the value k cells along the axis from cell (of row z)
        if wp.static(mirrored):
            if z + k < top:
                return dtype(wp.static(sign)) * f[cell + (2 * top - wp.static(h) - 2 * z - k) * step]
        if wp.static(axis == 2):
            return f[cell + k]
        return f[cell + k * step]

    @wp.func
    def d(f: arr1, cell: int, step: int, z: int, top: int) -> dtype:
        acc = dtype(0.0)
        for m in range(wp.static(mr)):
            up = read(f, cell, m + wp.static(1 - h), step, z, top)
            down = read(f, cell, -m - wp.static(h), step, z, top)
            acc += dtype(wp.static(c[m])) * (up - down)
        return acc

    return d


def make_flat_reduced_dz(ns, half_in: bool):
    """d/dz times dx of a velocity on half (vz) or integer (vx, vy) z nodes, of the highest order whose stencil stays
    below a free surface (order 2 q for the q-th row, q = z - top + 1 - half_in, while q < M, else full order), on a
    flat field: dz(f, c, step, z, top) as make_flat_derivative's d (step = Lx Ly)."""
    M, fs, dtype, arr1 = ns.M, ns.fs, ns.dtype, ns.arr1
    h = 1 if half_in else 0
    full = make_flat_derivative(ns, 0, half_in, M, False)
    d1, d2, d3 = (make_flat_derivative(ns, 0, half_in, m, False) for m in (1, 2, 3))

    @wp.func
    def dz(f: arr1, cell: int, step: int, z: int, top: int) -> dtype:
        q = z - top + wp.static(1 - h)
        if wp.static(fs and M >= 2):
            if q == 1:
                return d1(f, cell, step, z, top)
        if wp.static(fs and M >= 3):
            if q == 2:
                return d2(f, cell, step, z, top)
        if wp.static(fs and M >= 4):
            if q == 3:
                return d3(f, cell, step, z, top)
        return full(f, cell, step, z, top)

    return dz


def _velocity(ns):
    """The velocity half step: v_new = v + dt b div s at every interior velocity node (flat arrays, a 1D launch)."""
    M, dtype, arr1, Axis = ns.M, ns.dtype, ns.arr1, ns.Axis
    cpml_psi, store_psi = flat_cpml(dtype)
    dx_int, dx_half = make_flat_derivative(ns, 2, False, M, False), make_flat_derivative(ns, 2, True, M, False)
    dy_int, dy_half = make_flat_derivative(ns, 1, False, M, False), make_flat_derivative(ns, 1, True, M, False)
    dz_int, dz_half = make_flat_derivative(ns, 0, False, M, True), make_flat_derivative(ns, 0, True, M, True)  # szz; sxz, syz

    @unique_kernel(grid_stride=False)
    def velocity(
        vx: arr1, vy: arr1, vz: arr1, sxx: arr1, syy: arr1, szz: arr1, sxy: arr1, sxz: arr1, syz: arr1, bx: arr1, by: arr1,
        bz: arr1, o_z: arr1, o_y: arr1, o_x: arr1, n_z: arr1, n_y: arr1, n_x: arr1, vx_new: arr1, vy_new: arr1, vz_new: arr1,
        az: Axis, ay: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int, g: Grid,
    ):  # fmt: skip
        p = flat_cell(wp.tid(), g, wp.static(M))
        t = p[0]
        z = p[1]
        y = p[2]
        x = p[3]
        m = (z * g.ly + y) * g.lx + x  # model cell
        f = t * g.shot + m  # field cell
        jz = az.store[z]
        jy = ay.store[y]
        jx = ax.store[x]
        k = flat_strips(g, 3 * t, z, y, x, jz, jy, jx)  # component vx's; vy, vz one strip (g.sz, g.sy, g.sx) further
        # vx at (z, y, x + 1/2): dsxx/dx + dsxy/dy + dsxz/dz; vy at (z, y + 1/2, x): dsxy/dx + dsyy/dy + dsyz/dz; vz at
        # (z + 1/2, y, x): dsxz/dx + dsyz/dy + dszz/dz. Every load before the first store.
        d1 = dx_int(sxx, f, 1, z, top) * inv_dx
        d2 = dy_half(sxy, f, g.lx, z, top) * inv_dx
        d3 = dz_half(sxz, f, g.lxy, z, top) * inv_dx
        d4 = dx_half(sxy, f, 1, z, top) * inv_dx
        d5 = dy_int(syy, f, g.lx, z, top) * inv_dx
        d6 = dz_half(syz, f, g.lxy, z, top) * inv_dx
        d7 = dx_half(sxz, f, 1, z, top) * inv_dx
        d8 = dy_half(syz, f, g.lx, z, top) * inv_dx
        d9 = dz_int(szz, f, g.lxy, z, top) * inv_dx
        q1 = cpml_psi(d1, jx, x, ax.ah, ax.bh, o_x, k[2])
        q2 = cpml_psi(d2, jy, y, ay.a, ay.b, o_y, k[1])
        q3 = cpml_psi(d3, jz, z, az.a, az.b, o_z, k[0])
        q4 = cpml_psi(d4, jx, x, ax.a, ax.b, o_x, k[2] + g.sx)
        q5 = cpml_psi(d5, jy, y, ay.ah, ay.bh, o_y, k[1] + g.sy)
        q6 = cpml_psi(d6, jz, z, az.a, az.b, o_z, k[0] + g.sz)
        q7 = cpml_psi(d7, jx, x, ax.a, ax.b, o_x, k[2] + 2 * g.sx)
        q8 = cpml_psi(d8, jy, y, ay.a, ay.b, o_y, k[1] + 2 * g.sy)
        q9 = cpml_psi(d9, jz, z, az.ah, az.bh, o_z, k[0] + 2 * g.sz)
        ux = vx[f]
        uy = vy[f]
        uz = vz[f]
        bxm = bx[m]
        bym = by[m]
        bzm = bz[m]
        store_psi(jx, n_x, k[2], q1)
        store_psi(jy, n_y, k[1], q2)
        store_psi(jz, n_z, k[0], q3)
        store_psi(jx, n_x, k[2] + g.sx, q4)
        store_psi(jy, n_y, k[1] + g.sy, q5)
        store_psi(jz, n_z, k[0] + g.sz, q6)
        store_psi(jx, n_x, k[2] + 2 * g.sx, q7)
        store_psi(jy, n_y, k[1] + 2 * g.sy, q8)
        store_psi(jz, n_z, k[0] + 2 * g.sz, q9)
        vx_new[f] = ux + dt * bxm * ((d1 + q1) + (d2 + q2) + (d3 + q3))
        vy_new[f] = uy + dt * bym * ((d4 + q4) + (d5 + q5) + (d6 + q6))
        vz_new[f] = uz + dt * bzm * ((d7 + q7) + (d8 + q8) + (d9 + q9))

    return velocity


def _stress(ns):
    """The stress half step from the new velocities (flat arrays, a 1D launch); on a free surface's row szz = 0 and
    sxx, syy from szz = 0."""
    M, fs, dtype, arr1, Axis = ns.M, ns.fs, ns.dtype, ns.arr1, ns.Axis
    cpml_psi, store_psi = flat_cpml(dtype)
    dx_int, dx_half = make_flat_derivative(ns, 2, False, M, False), make_flat_derivative(ns, 2, True, M, False)
    dy_int, dy_half = make_flat_derivative(ns, 1, False, M, False), make_flat_derivative(ns, 1, True, M, False)
    dz_int, dz_half = make_flat_reduced_dz(ns, False), make_flat_reduced_dz(ns, True)  # vx, vy; vz

    @unique_kernel(grid_stride=False)
    def stress(
        vx: arr1, vy: arr1, vz: arr1, sxx: arr1, syy: arr1, szz: arr1, sxy: arr1, sxz: arr1, syz: arr1, l2m: arr1, lam: arr1,
        mxy: arr1, mxz: arr1, myz: arr1, o_z: arr1, o_y: arr1, o_x: arr1, n_z: arr1, n_y: arr1, n_x: arr1, sxx_new: arr1,
        syy_new: arr1, szz_new: arr1, sxy_new: arr1, sxz_new: arr1, syz_new: arr1, az: Axis, ay: Axis, ax: Axis, dt: dtype,
        inv_dx: dtype, top: int, g: Grid,
    ):  # fmt: skip
        p = flat_cell(wp.tid(), g, wp.static(M))
        t = p[0]
        z = p[1]
        y = p[2]
        x = p[3]
        m = (z * g.ly + y) * g.lx + x  # model cell
        f = t * g.shot + m  # field cell
        jz = az.store[z]
        jy = ay.store[y]
        jx = ax.store[x]
        k = flat_strips(g, 3 * t, z, y, x, jz, jy, jx)  # component 0's; components 1, 2 one, two strips further
        # normal stresses at (z, y, x); shear: sxy at (z, y + 1/2, x + 1/2), sxz at (z + 1/2, y, x + 1/2), syz at
        # (z + 1/2, y + 1/2, x). Every load before the first store.
        d1 = dx_half(vx, f, 1, z, top) * inv_dx
        d2 = dy_half(vy, f, g.lx, z, top) * inv_dx
        d3 = dz_half(vz, f, g.lxy, z, top) * inv_dx
        d4 = dy_int(vx, f, g.lx, z, top) * inv_dx
        d5 = dx_int(vy, f, 1, z, top) * inv_dx
        d6 = dz_int(vx, f, g.lxy, z, top) * inv_dx
        d7 = dx_int(vz, f, 1, z, top) * inv_dx
        d8 = dz_int(vy, f, g.lxy, z, top) * inv_dx
        d9 = dy_int(vz, f, g.lx, z, top) * inv_dx
        q1 = cpml_psi(d1, jx, x, ax.a, ax.b, o_x, k[2])
        q2 = cpml_psi(d2, jy, y, ay.a, ay.b, o_y, k[1] + g.sy)
        q3 = cpml_psi(d3, jz, z, az.a, az.b, o_z, k[0] + 2 * g.sz)
        q4 = cpml_psi(d4, jy, y, ay.ah, ay.bh, o_y, k[1])
        q5 = cpml_psi(d5, jx, x, ax.ah, ax.bh, o_x, k[2] + g.sx)
        q6 = cpml_psi(d6, jz, z, az.ah, az.bh, o_z, k[0])
        q7 = cpml_psi(d7, jx, x, ax.ah, ax.bh, o_x, k[2] + 2 * g.sx)
        q8 = cpml_psi(d8, jz, z, az.ah, az.bh, o_z, k[0] + g.sz)
        q9 = cpml_psi(d9, jy, y, ay.ah, ay.bh, o_y, k[1] + 2 * g.sy)
        exx = d1 + q1
        eyy = d2 + q2
        ezz = d3 + q3
        exy = (d4 + q4) + (d5 + q5)
        exz = (d6 + q6) + (d7 + q7)
        eyz = (d8 + q8) + (d9 + q9)
        pm = l2m[m]
        q = lam[m]
        cxy = mxy[m]
        cxz = mxz[m]
        cyz = myz[m]
        fxx = sxx[f]
        fyy = syy[f]
        fzz = szz[f]
        fxy = sxy[f]
        fxz = sxz[f]
        fyz = syz[f]
        store_psi(jx, n_x, k[2], q1)
        store_psi(jy, n_y, k[1] + g.sy, q2)
        store_psi(jz, n_z, k[0] + 2 * g.sz, q3)
        store_psi(jy, n_y, k[1], q4)
        store_psi(jx, n_x, k[2] + g.sx, q5)
        store_psi(jz, n_z, k[0], q6)
        store_psi(jx, n_x, k[2] + 2 * g.sx, q7)
        store_psi(jz, n_z, k[0] + g.sz, q8)
        store_psi(jy, n_y, k[1] + 2 * g.sy, q9)
        surface = False
        if wp.static(fs):
            surface = z == top
        if surface:
            r = q * q / pm
            sxx_new[f] = fxx + dt * ((pm - r) * exx + (q - r) * eyy)
            syy_new[f] = fyy + dt * ((q - r) * exx + (pm - r) * eyy)
            szz_new[f] = dtype(0.0)
        else:
            div = exx + eyy + ezz
            sxx_new[f] = fxx + dt * (q * div + (pm - q) * exx)
            syy_new[f] = fyy + dt * (q * div + (pm - q) * eyy)
            szz_new[f] = fzz + dt * (q * div + (pm - q) * ezz)
        sxy_new[f] = fxy + dt * cxy * exy
        sxz_new[f] = fxz + dt * cxz * exz
        syz_new[f] = fyz + dt * cyz * eyz

    return stress


def make_point(ns, hicks, oz: float, oy: float, ox: float, odd: bool):
    """The q-th operator node (padded index, weight) of a field whose index (i, j, k) sits at (i + oz, j + oy, k + ox),
    folded across a free surface as kernels/elastic's 2D make_point (odd: sign change, no weight on the surface row)."""
    HR, W, fs, dtype, arr3 = ns.HR, ns.W, ns.fs, ns.dtype, ns.arr3
    fold = 1 if oz > 0.0 else 0

    @wp.func
    def point(loc: arr3, s: int, n: int, q: int, origin: wp.vec3i, inv_dx: dtype, top: int):
        zc = loc[s, n, 0] * inv_dx + dtype(origin[0]) - dtype(wp.static(oz))
        yc = loc[s, n, 1] * inv_dx + dtype(origin[1]) - dtype(wp.static(oy))
        xc = loc[s, n, 2] * inv_dx + dtype(origin[2]) - dtype(wp.static(ox))
        iz = int(wp.floor(zc)) - wp.static(HR - 1) + q // wp.static(W * W)
        iy = int(wp.floor(yc)) - wp.static(HR - 1) + (q // wp.static(W)) % wp.static(W)
        ix = int(wp.floor(xc)) - wp.static(HR - 1) + q % wp.static(W)
        w = hicks(dtype(iz) - zc, zc) * hicks(dtype(iy) - yc, yc) * hicks(dtype(ix) - xc, xc)
        if wp.static(fs):
            if wp.static(odd and fold == 0):
                if iz == top:
                    w = dtype(0.0)
            if iz + wp.static(fold) <= top - wp.static(1 - fold):
                iz = 2 * top - wp.static(fold) - iz
                if wp.static(odd):
                    w = -w
        return wp.vec3i(iz, iy, ix), w

    return point


def _points(ns):
    """The sources' and receivers' kernels: the fixed operators' weights (POINTS), the force and moment injections and
    the recording of vx, vy, vz and pressure."""
    dtype, arr3, arr4, iarr1, idx4 = ns.dtype, ns.arr3, ns.arr4, ns.iarr1, ns.idx4
    hicks = hicks_axis(dtype)
    pts = [make_point(ns, hicks, *p) for p in POINTS]
    p0, p1, p2, p3, p4, p5, p6, p7 = pts

    @wp.func
    def put(idx: idx4, w: arr4, k: int, s: int, r: int, q: int, i: wp.vec3i, wq: dtype):
        idx[k, s, r, q] = i
        w[k, s, r, q] = wq

    @unique_kernel(enable_backward=False)  # computed once per run, never differentiated (locations are fixed)
    def weights(loc: arr3, origin: wp.vec3i, inv_dx: dtype, top: int, idx: idx4, w: arr4):
        # node and weight of point q of location r (metres (z, y, x)) for each operator of POINTS (first index)
        s, r, q = wp.tid()
        i, wq = p0(loc, s, r, q, origin, inv_dx, top)
        put(idx, w, 0, s, r, q, i, wq)
        i, wq = p1(loc, s, r, q, origin, inv_dx, top)
        put(idx, w, 1, s, r, q, i, wq)
        i, wq = p2(loc, s, r, q, origin, inv_dx, top)
        put(idx, w, 2, s, r, q, i, wq)
        i, wq = p3(loc, s, r, q, origin, inv_dx, top)
        put(idx, w, 3, s, r, q, i, wq)
        i, wq = p4(loc, s, r, q, origin, inv_dx, top)
        put(idx, w, 4, s, r, q, i, wq)
        i, wq = p5(loc, s, r, q, origin, inv_dx, top)
        put(idx, w, 5, s, r, q, i, wq)
        i, wq = p6(loc, s, r, q, origin, inv_dx, top)
        put(idx, w, 6, s, r, q, i, wq)
        i, wq = p7(loc, s, r, q, origin, inv_dx, top)
        put(idx, w, 7, s, r, q, i, wq)

    @wp.func
    def add(f: arr4, b: arr3, s: int, i: wp.vec3i, w: dtype, a: dtype):
        # f += a b w at node i (b: the buoyancy at f's nodes); points of weight 0 skipped
        if w != dtype(0.0):
            wp.atomic_add(f, s, i[0], i[1], i[2], a * b[i[0], i[1], i[2]] * w)

    @wp.func
    def add_moment(f: arr4, s: int, i: wp.vec3i, w: dtype, a: dtype):
        if w != dtype(0.0):
            wp.atomic_add(f, s, i[0], i[1], i[2], a * w)

    @unique_kernel
    def inject_force(vx: arr4, vy: arr4, vz: arr4, bx: arr3, by: arr3, bz: arr3, amp: arr3, comp: arr3, idx: idx4, w: arr4, n: int,
                     clock: iarr1, scale: dtype):  # fmt: skip
        # v += dt b f(t_n) w / dx^3 (scale = dt / dx^3); comp (S, n_src, 3) = (fz, fy, fx); the sample is n + clock[0]
        # (a device counter, for graph replays), here and in inject_moment and record
        s, src, q = wp.tid()
        a = scale * amp[s, src, n + clock[0]]
        add(vx, bx, s, idx[0, s, src, q], w[0, s, src, q], a * comp[s, src, 2])
        add(vy, by, s, idx[1, s, src, q], w[1, s, src, q], a * comp[s, src, 1])
        add(vz, bz, s, idx[2, s, src, q], w[2, s, src, q], a * comp[s, src, 0])

    @unique_kernel
    def inject_moment(sxx: arr4, syy: arr4, szz: arr4, sxy: arr4, sxz: arr4, syz: arr4, amp: arr3, comp: arr3, idx: idx4, w: arr4,
                      n: int, clock: iarr1, scale: dtype):  # fmt: skip
        # s_ij -= (M(t_{n+1}) - M(t_n)) m_ij w / dx^3 (scale = 1 / dx^3); comp (S, n_src, 6) = (Mzz, Myy, Mxx, Myz, Mxz, Mxy)
        s, src, q = wp.tid()
        a = -scale * (amp[s, src, n + clock[0] + 1] - amp[s, src, n + clock[0]])
        add_moment(sxx, s, idx[3, s, src, q], w[3, s, src, q], a * comp[s, src, 2])
        add_moment(syy, s, idx[3, s, src, q], w[3, s, src, q], a * comp[s, src, 1])
        add_moment(szz, s, idx[4, s, src, q], w[4, s, src, q], a * comp[s, src, 0])
        add_moment(sxy, s, idx[5, s, src, q], w[5, s, src, q], a * comp[s, src, 5])
        add_moment(sxz, s, idx[6, s, src, q], w[6, s, src, q], a * comp[s, src, 4])
        add_moment(syz, s, idx[7, s, src, q], w[7, s, src, q], a * comp[s, src, 3])

    @wp.func
    def sample(f: arr4, s: int, i: wp.vec3i, w: dtype) -> dtype:
        if w != dtype(0.0):
            return w * f[s, i[0], i[1], i[2]]
        return dtype(0.0)

    @unique_kernel
    def record(vx: arr4, vy: arr4, vz: arr4, sxx: arr4, syy: arr4, szz: arr4, d_vx: arr3, d_vy: arr3, d_vz: arr3, d_p: arr3, idx: idx4,
               w: arr4, n: int, clock: iarr1):  # fmt: skip
        # sample n of each receiver's vx, vy, vz and pressure -(sxx + syy + szz) / 3
        s, r, q = wp.tid()
        t = n + clock[0]
        wp.atomic_add(d_vx, s, r, t, sample(vx, s, idx[0, s, r, q], w[0, s, r, q]))
        wp.atomic_add(d_vy, s, r, t, sample(vy, s, idx[1, s, r, q], w[1, s, r, q]))
        wp.atomic_add(d_vz, s, r, t, sample(vz, s, idx[2, s, r, q], w[2, s, r, q]))
        i = idx[3, s, r, q]
        normal = sample(sxx, s, i, w[3, s, r, q]) + sample(syy, s, i, w[3, s, r, q]) + sample(szz, s, idx[4, s, r, q], w[4, s, r, q])
        wp.atomic_add(d_p, s, r, t, dtype(-1.0 / 3.0) * normal)

    return dict(weights=weights, inject_force=inject_force, inject_moment=inject_moment, record=record)


def _models(ns):
    """MATERIALS from the padded vp, vs, rho (materials) and the padding of a physical model (pad_model)."""
    M, dtype, arr3 = ns.M, ns.dtype, ns.arr3

    @wp.func
    def harmonic(m1: dtype, m2: dtype, m3: dtype, m4: dtype) -> dtype:
        # the harmonic mean of four shear moduli, 0 if any is 0 (a fluid carries no shear)
        h = dtype(0.0)
        if m1 > dtype(0.0) and m2 > dtype(0.0) and m3 > dtype(0.0) and m4 > dtype(0.0):
            h = dtype(4.0) / (dtype(1.0) / m1 + dtype(1.0) / m2 + dtype(1.0) / m3 + dtype(1.0) / m4)
        return h

    @wp.func
    def shear(vs: arr3, rho: arr3, z: int, y: int, x: int) -> dtype:
        return rho[z, y, x] * vs[z, y, x] * vs[z, y, x]

    @unique_kernel
    def materials(vp: arr3, vs: arr3, rho: arr3, bx: arr3, by: arr3, bz: arr3, l2m: arr3, lam: arr3, mxy: arr3, mxz: arr3, myz: arr3):
        # MATERIALS at the interior nodes (module docstring)
        zi, yi, xi = wp.tid()
        z = zi + wp.static(M)
        y = yi + wp.static(M)
        x = xi + wp.static(M)
        b = dtype(1.0) / rho[z, y, x]
        bx[z, y, x] = dtype(0.5) * (b + dtype(1.0) / rho[z, y, x + 1])
        by[z, y, x] = dtype(0.5) * (b + dtype(1.0) / rho[z, y + 1, x])
        bz[z, y, x] = dtype(0.5) * (b + dtype(1.0) / rho[z + 1, y, x])
        m0 = shear(vs, rho, z, y, x)
        c = rho[z, y, x] * vp[z, y, x] * vp[z, y, x]
        l2m[z, y, x] = c
        lam[z, y, x] = c - dtype(2.0) * m0
        mz, my, mx = shear(vs, rho, z + 1, y, x), shear(vs, rho, z, y + 1, x), shear(vs, rho, z, y, x + 1)
        mxy[z, y, x] = harmonic(m0, my, mx, shear(vs, rho, z, y + 1, x + 1))
        mxz[z, y, x] = harmonic(m0, mz, mx, shear(vs, rho, z + 1, y, x + 1))
        myz[z, y, x] = harmonic(m0, mz, my, shear(vs, rho, z + 1, y + 1, x))

    @unique_kernel
    def pad_model(v: arr3, vpad: arr3, origin: wp.vec3i):
        # padded model from the physical one, extended by edge replication into PML and halo
        z, y, x = wp.tid()
        vpad[z, y, x] = v[wp.clamp(z - origin[0], 0, v.shape[0] - 1), wp.clamp(y - origin[1], 0, v.shape[1] - 1),
                          wp.clamp(x - origin[2], 0, v.shape[2] - 1)]  # fmt: skip

    return dict(materials=materials, pad_model=pad_model)


@functools.lru_cache(maxsize=None)
def build(order: int, dtype, free_surface: bool):
    """Kernels for one (order, dtype, free_surface), compiled once per process."""
    M = order // 2

    @wp.struct
    class Axis:
        store: wp.array(dtype=wp.int32)  # strip index per padded index, -1 outside the PML strips
        a: wp.array(dtype=dtype)  # CPML a, b at integer positions
        b: wp.array(dtype=dtype)
        ah: wp.array(dtype=dtype)  # at half positions (index p stands for p + 1/2)
        bh: wp.array(dtype=dtype)

    ns = SimpleNamespace(M=M, HR=HICKS_RADIUS, W=2 * HICKS_RADIUS, fs=bool(free_surface), dtype=dtype, arr1=wp.array(dtype=dtype),
                         arr2=wp.array2d(dtype=dtype), arr3=wp.array3d(dtype=dtype), arr4=wp.array4d(dtype=dtype),
                         iarr1=wp.array(dtype=wp.int32), idx4=wp.array4d(dtype=wp.vec3i), Axis=Axis)  # fmt: skip
    return Kernels(Axis=Axis, velocity=_velocity(ns), stress=_stress(ns), **_points(ns), **_models(ns), halo=M,
                   operator_points=ns.W**3)  # fmt: skip


class State:
    """Fields at one time level n: vx, vy, vz (m/s) at t = (n - 1/2) dt, the stresses (Pa) at t = n dt (FIELDS, each
    (n_shots, Lz, Ly, Lx)), and the CPML memory variables psi (dict, see PSI)."""

    def __init__(self, fields, psi):
        self.f, self.psi = dict(zip(FIELDS, fields)), psi
        self._flat = None

    def __getattr__(self, name):
        if name in FIELDS:
            return self.__dict__["f"][name]
        raise AttributeError(name)

    def arrays(self):
        return [*(self.f[k] for k in FIELDS), *(self.psi[k] for k in PSI)]

    def flat(self) -> dict:
        """name (FIELDS, PSI) -> the array's 1D view, sharing its data and .grad; made again only if a .grad changed."""
        arrays = self.arrays()
        if self._flat is None or any(a.grad is not g for a, g in zip(arrays, self._flat[0])):
            self._flat = ([a.grad for a in arrays], dict(zip((*FIELDS, *PSI), flat_views(arrays))))
        return self._flat[1]


def flat_views(arrays) -> list:
    """The 1D views (wp.array.flatten) of contiguous arrays: their data and .grad as they are now."""
    return [a.flatten() for a in arrays]


class Elastic3D:
    """Launch helper: padded grid, CPML coefficients and one time step of the 3D elastic scheme.

    shape: physical grid (nz, ny, nx); dx (m), dt (s); pml_width cells on every absorbing face (all six, or five with
    free_surface); vmax: CPML reference speed (m/s). Locations passed to `operator` are metres (z, y, x) from the
    physical node 0."""

    def __init__(self, shape, dx, dt, order, n_shots, pml_width, pml_reflection, pml_frequency, vmax, free_surface=False,
                 dtype=wp.float32, device="cpu"):  # fmt: skip
        self.ndim = 3
        self.shape = tuple(int(n) for n in shape)
        self.dx, self.dt, self.order, self.n_shots = float(dx), float(dt), int(order), int(n_shots)
        self.dtype, self.device, self.free_surface = dtype, device, bool(free_surface)
        self.k = build(self.order, dtype, self.free_surface)
        R = self.k.halo
        nb = int(pml_width)
        lo = (0 if free_surface else nb, nb, nb)
        self.padded = tuple(self.shape[a] + lo[a] + nb + 2 * R for a in range(3))
        self.origin = wp.vec3i(R + lo[0], R + lo[1], R + lo[2])
        self.top = R
        self.axes, self.strip_width = cpml_axes(self.k.Axis, lo, nb, self.padded, R, dx, dt, vmax, pml_reflection, pml_frequency, dtype,
                                                device)  # fmt: skip
        self.interior = (self.n_shots, *(n - 2 * R for n in self.padded))
        largest = self.n_shots * max(math.prod(self.padded), *(3 * math.prod(self.psi_shape(k)[1:]) for k in PSI))
        check_flat_cells(largest, f"n_shots = {self.n_shots} on a padded grid {self.padded}")
        self.grid = flat_grid(self.interior[1:], self.padded, self.strip_width)
        self._mat = (None, None)  # the materials last stepped with and their 1D views
        self.inv_dx = dtype(1.0 / dx)
        self.dt_device = dtype(dt)
        self.cuda = wp.get_device(device).is_cuda
        self.clock = wp.zeros(1, dtype=wp.int32, device=device)  # stays 0: plain launches pass n itself

    def psi_shape(self, name):
        axis = PSI[name]
        shape = [3 * self.n_shots, *self.padded]
        shape[axis + 1] = self.strip_width[axis]
        return tuple(shape)

    def new_state(self, requires_grad=False) -> State:
        def zeros(shape):
            return wp.zeros(shape, dtype=self.dtype, device=self.device, requires_grad=requires_grad)

        return State([zeros((self.n_shots, *self.padded)) for _ in FIELDS], {k: zeros(self.psi_shape(k)) for k in PSI})

    def pad_model(self, m, requires_grad=False):
        """Padded model (Lz, Ly, Lx) from a physical one (wp.array3d (nz, ny, nx)), extended by edge replication."""
        out = wp.zeros(self.padded, dtype=self.dtype, device=self.device, requires_grad=requires_grad)
        wp.launch(self.k.pad_model, dim=self.padded, inputs=[m, out, self.origin], device=self.device)
        return out

    def materials(self, vp, vs, rho, requires_grad=False, out=None):
        """MATERIALS (padded arrays, interior nodes set) from the padded vp, vs (m/s) and rho (kg/m^3); into out (an
        earlier call's) if given."""
        if out is None:
            out = tuple(wp.zeros(self.padded, dtype=self.dtype, device=self.device, requires_grad=requires_grad) for _ in MATERIALS)
        wp.launch(self.k.materials, dim=self.interior[1:], inputs=[vp, vs, rho, *out], device=self.device)
        return out

    def operator(self, loc: wp.array):
        """The fixed operators of locations loc (S, n, 3) metres (z, y, x): (idx (8, S, n, points) vec3i, weights (8, S,
        n, points)) for the POINTS."""
        shape = (len(POINTS), *loc.shape[:2], self.k.operator_points)
        return host_operator(self.k.weights, loc, [self.origin, self.inv_dx, self.top], shape, wp.vec3i, self.dtype, self.device)

    def step(self, st: State, mat, sources, n: int, out: State | None = None, clock=None) -> State:
        """Advance st (level n) to level n + 1 with source sample n (force) or samples n and n + 1 (moment), + clock[0].
        mat: MATERIALS (materials); sources: (kind "force" or "moment", amplitudes (S, n_src, >= n + 2), components (S,
        n_src, 3 | 6), their operator) or None. With out=None in place; else into out's arrays (st unchanged)."""
        out = st if out is None else out
        clock = self.clock if clock is None else clock
        bx, by, bz, l2m, lam, mxy, mxz, myz = mat
        if self._mat[0] is not mat:
            self._mat = (mat, flat_views(mat))
        fmat, fst, fout = self._mat[1], st.flat(), out.flat()
        common = [*self.axes, self.dt_device, self.inv_dx, self.top, self.grid]
        cells = math.prod(self.interior)
        old, new = [fst[k] for k in ("v_z", "v_y", "v_x")], [fout[k] for k in ("v_z", "v_y", "v_x")]
        wp.launch(self.k.velocity, dim=cells, block_dim=FIELD_THREADS, device=self.device,
                  inputs=[*(fst[k] for k in FIELDS), *fmat[:3], *old, *new, *(fout[k] for k in FIELDS[:3]), *common])  # fmt: skip
        if sources is not None and sources[0] == "force":
            _, amp, comp, (idx, w) = sources
            wp.launch(self.k.inject_force, dim=idx.shape[1:], device=self.device,
                      inputs=[out.vx, out.vy, out.vz, bx, by, bz, amp, comp, idx, w, n, clock,
                              self.dtype(self.dt / self.dx**3)])  # fmt: skip
        old, new = [fst[k] for k in ("s_z", "s_y", "s_x")], [fout[k] for k in ("s_z", "s_y", "s_x")]
        wp.launch(self.k.stress, dim=cells, block_dim=FIELD_THREADS, device=self.device,
                  inputs=[*(fout[k] for k in FIELDS[:3]), *(fst[k] for k in FIELDS[3:]), *fmat[3:], *old, *new,
                          *(fout[k] for k in FIELDS[3:]), *common])  # fmt: skip
        if sources is not None and sources[0] == "moment":
            _, amp, comp, (idx, w) = sources
            wp.launch(self.k.inject_moment, dim=idx.shape[1:], device=self.device,
                      inputs=[*(out.f[k] for k in FIELDS[3:]), amp, comp, idx, w, n, clock, self.dtype(1.0 / self.dx**3)])  # fmt: skip
        return out

    def record(self, st: State, data, receiver_op, k: int, clock=None):
        """Add sample k (+ clock[0]) of the receivers' vx, vy, vz, pressure into data (4 arrays (S, n_rec, >= k + 1))."""
        idx, w = receiver_op
        clock = self.clock if clock is None else clock
        wp.launch(self.k.record, dim=idx.shape[1:], inputs=[st.vx, st.vy, st.vz, st.sxx, st.syy, st.szz, *data, idx, w, k, clock],
                  device=self.device)  # fmt: skip
