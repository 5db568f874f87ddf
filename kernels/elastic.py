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
mean of 1/rho at its two neighbours; all of these are computed inside the kernels from the padded vp, vs,
rho, so that Warp differentiates through them. Staggered derivatives of order 2/4/8
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

Sources and receivers use the Kaiser-windowed sinc operator of kernels/acoustic.py (HICKS_RADIUS,
C^1 in the position) at each field's own staggered position. Near a free surface the operator's points
above it are folded onto their mirror nodes, with a sign change for szz and sxz (odd images) and
without for vx, vz, sxx; a normal-stress node on the surface gets no szz weight.

All kernels write fresh outputs from inputs (sources add with atomics), never read-modify their own
input, so each time step can be differentiated by wp.Tape when given its own arrays.
"""


import functools
import math

import numpy as np
import warp as wp

from adseismic.kernels.acoustic import _I0_TERMS, HICKS_B, HICKS_RADIUS, _i0
from adseismic.numerics import STAGGERED_DERIVATIVE

# CPML memory variables: name -> axis of their derivative and strip (0 = z, 1 = x). vx_x is d(sxx)/dx at
# vx nodes, vx_z d(sxz)/dz at vx nodes, s_x d(vx)/dx at normal-stress nodes, xz_z d(vx)/dz at sxz nodes...
PSI = {"vx_x": 1, "vx_z": 0, "vz_x": 1, "vz_z": 0, "s_x": 1, "s_z": 0, "xz_z": 0, "xz_x": 1}


@functools.lru_cache(maxsize=None)
def build(order: int, dtype, free_surface: bool):
    """Kernels for one (order, dtype, free_surface) combination, compiled once per process."""
    M = order // 2
    HR = HICKS_RADIUS
    W = 2 * HR
    NPTS = W * W
    WINDOW_NORM = 1.0 / (_i0(HICKS_B) - 1.0)
    fs = bool(free_surface)
    arr1 = wp.array(dtype=dtype)
    arr2 = wp.array2d(dtype=dtype)
    arr3 = wp.array3d(dtype=dtype)

    @wp.struct
    class Axis:
        store: wp.array(dtype=wp.int32)  # strip index per padded index, -1 outside the PML strips
        a: wp.array(dtype=dtype)  # CPML a, b at integer positions
        b: wp.array(dtype=dtype)
        ah: wp.array(dtype=dtype)  # CPML a, b at half positions (index p stands for p + 1/2)
        bh: wp.array(dtype=dtype)

    def make_dz(mr: int, half_in: bool, image: bool):
        # d/dz (times dz) with mr staggered weights of a field on half (half_in) or integer z nodes,
        # evaluated at integer (half_in) or half nodes; `image`: antisymmetric image above row `top`.
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

        return dz

    def make_dx(half_in: bool):
        c = STAGGERED_DERIVATIVE[order]
        h = 1 if half_in else 0

        @wp.func
        def dx(f: arr3, s: int, z: int, x: int) -> dtype:
            acc = dtype(0.0)
            for m in range(wp.static(M)):
                acc += dtype(wp.static(c[m])) * (f[s, z, x + m + wp.static(1 - h)] - f[s, z, x - m - wp.static(h)])
            return acc

        return dx

    dx_of_int, dx_of_half = make_dx(False), make_dx(True)
    dz_szz = make_dz(M, False, True)  # at vz nodes
    dz_sxz = make_dz(M, True, True)  # at vx nodes
    # velocity z-derivatives in the stress update: full order, and orders 2, 4, 6 (m = 1, 2, 3 weights) for
    # the rows next to a free surface
    dz_vz1, dz_vz2, dz_vz3 = (make_dz(m, True, False) for m in (1, 2, 3))
    dz_vx1, dz_vx2, dz_vx3 = (make_dz(m, False, False) for m in (1, 2, 3))
    dz_vz = make_dz(M, True, False)
    dz_vx = make_dz(M, False, False)

    @wp.func
    def cpml(d: dtype, j: int, p: int, a: arr1, b: arr1, old: arr3, new: arr3, s: int, row: int, col: int) -> dtype:
        # d + psi with psi = b psi_old + a d at strip cell (row, col); d unchanged outside the strips
        if j < 0:
            return d
        psi = b[p] * old[s, row, col] + a[p] * d
        new[s, row, col] = psi
        return d + psi

    @wp.kernel(module="unique")
    def velocity(
        vx: arr3, vz: arr3, sxx: arr3, szz: arr3, sxz: arr3, rho: arr2,
        p_vx_x: arr3, p_vx_z: arr3, p_vz_x: arr3, p_vz_z: arr3,
        n_vx_x: arr3, n_vx_z: arr3, n_vz_x: arr3, n_vz_z: arr3,
        vx_new: arr3, vz_new: arr3, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        s, zi, xi = wp.tid()
        z = zi + wp.static(M)
        x = xi + wp.static(M)
        jz = az.store[z]
        jx = ax.store[x]
        # vx at (z, x + 1/2)
        d1 = cpml(dx_of_int(sxx, s, z, x) * inv_dx, jx, x, ax.ah, ax.bh, p_vx_x, n_vx_x, s, z, jx)
        d2 = cpml(dz_sxz(sxz, s, z, x, top) * inv_dx, jz, z, az.a, az.b, p_vx_z, n_vx_z, s, jz, x)
        bx = dtype(0.5) * (dtype(1.0) / rho[z, x] + dtype(1.0) / rho[z, x + 1])
        vx_new[s, z, x] = vx[s, z, x] + dt * bx * (d1 + d2)
        # vz at (z + 1/2, x)
        d3 = cpml(dx_of_half(sxz, s, z, x) * inv_dx, jx, x, ax.a, ax.b, p_vz_x, n_vz_x, s, z, jx)
        d4 = cpml(dz_szz(szz, s, z, x, top) * inv_dx, jz, z, az.ah, az.bh, p_vz_z, n_vz_z, s, jz, x)
        bz = dtype(0.5) * (dtype(1.0) / rho[z, x] + dtype(1.0) / rho[z + 1, x])
        vz_new[s, z, x] = vz[s, z, x] + dt * bz * (d3 + d4)

    @wp.func
    def shear_modulus(vs: arr2, rho: arr2, z: int, x: int) -> dtype:
        v = vs[z, x]
        return rho[z, x] * v * v

    @wp.kernel(module="unique")
    def stress(
        vx: arr3, vz: arr3, sxx: arr3, szz: arr3, sxz: arr3, vp: arr2, vs: arr2, rho: arr2,
        p_s_x: arr3, p_s_z: arr3, p_xz_z: arr3, p_xz_x: arr3,
        n_s_x: arr3, n_s_z: arr3, n_xz_z: arr3, n_xz_x: arr3,
        sxx_new: arr3, szz_new: arr3, sxz_new: arr3, az: Axis, ax: Axis, dt: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        s, zi, xi = wp.tid()
        z = zi + wp.static(M)
        x = xi + wp.static(M)
        jz = az.store[z]
        jx = ax.store[x]
        k = z - top
        # normal stresses at (z, x)
        dvx = cpml(dx_of_half(vx, s, z, x) * inv_dx, jx, x, ax.a, ax.b, p_s_x, n_s_x, s, z, jx)
        dvz_raw = dz_vz(vz, s, z, x, top)
        if wp.static(fs and M >= 2):
            if k == 1:
                dvz_raw = dz_vz1(vz, s, z, x, top)
        if wp.static(fs and M >= 3):
            if k == 2:
                dvz_raw = dz_vz2(vz, s, z, x, top)
        if wp.static(fs and M >= 4):
            if k == 3:
                dvz_raw = dz_vz3(vz, s, z, x, top)
        dvz = cpml(dvz_raw * inv_dx, jz, z, az.a, az.b, p_s_z, n_s_z, s, jz, x)
        mu = shear_modulus(vs, rho, z, x)
        vpp = vp[z, x]
        l2m = rho[z, x] * vpp * vpp
        lam = l2m - dtype(2.0) * mu
        sxx_rate = l2m * dvx + lam * dvz
        szz_rate = lam * dvx + l2m * dvz
        if wp.static(fs):
            if k == 0:
                sxx_rate = dtype(4.0) * mu * (lam + mu) / l2m * dvx
                szz_rate = dtype(0.0)
        sxx_new[s, z, x] = sxx[s, z, x] + dt * sxx_rate
        if wp.static(fs):
            if k == 0:
                szz_new[s, z, x] = dtype(0.0)
            else:
                szz_new[s, z, x] = szz[s, z, x] + dt * szz_rate
        else:
            szz_new[s, z, x] = szz[s, z, x] + dt * szz_rate
        # shear stress at (z + 1/2, x + 1/2)
        dvx_raw = dz_vx(vx, s, z, x, top)
        if wp.static(fs):
            if k == 0:
                dvx_raw = dz_vx1(vx, s, z, x, top)
        if wp.static(fs and M >= 3):
            if k == 1:
                dvx_raw = dz_vx2(vx, s, z, x, top)
        if wp.static(fs and M >= 4):
            if k == 2:
                dvx_raw = dz_vx3(vx, s, z, x, top)
        e1 = cpml(dvx_raw * inv_dx, jz, z, az.ah, az.bh, p_xz_z, n_xz_z, s, jz, x)
        e2 = cpml(dx_of_int(vz, s, z, x) * inv_dx, jx, x, ax.ah, ax.bh, p_xz_x, n_xz_x, s, z, jx)
        m1 = shear_modulus(vs, rho, z, x)
        m2 = shear_modulus(vs, rho, z + 1, x)
        m3 = shear_modulus(vs, rho, z, x + 1)
        m4 = shear_modulus(vs, rho, z + 1, x + 1)
        muh = dtype(0.0)
        if m1 > dtype(0.0) and m2 > dtype(0.0) and m3 > dtype(0.0) and m4 > dtype(0.0):
            muh = dtype(4.0) / (dtype(1.0) / m1 + dtype(1.0) / m2 + dtype(1.0) / m3 + dtype(1.0) / m4)
        sxz_new[s, z, x] = sxz[s, z, x] + dt * muh * (e1 + e2)

    @wp.func
    def hicks(d: dtype) -> dtype:
        # Kaiser-windowed sinc weight at distance d (cells), C^1 in d (see kernels/acoustic.py).
        q = dtype(1.0) - (d * d) / dtype(wp.static(float(HR * HR)))
        if q <= dtype(0.0):
            return dtype(0.0)
        pd = dtype(wp.static(math.pi)) * d
        sinc = dtype(1.0) - pd * pd / dtype(6.0)
        if wp.abs(pd) > dtype(1.0e-3):
            sinc = wp.sin(pd) / pd
        y2 = dtype(wp.static(HICKS_B * HICKS_B / 4.0)) * q
        term = dtype(1.0)
        total = dtype(0.0)
        for k in range(wp.static(_I0_TERMS)):
            term = term * y2 / dtype(wp.static(float((k + 1) * (k + 1))))
            total = total + term
        return sinc * total * dtype(wp.static(WINDOW_NORM))

    def make_point(oz: float, ox: float, odd: bool):
        # q-th operator node of a field whose index (i, k) sits at (i + oz, k + ox): padded index, weight
        fold = 1 if oz > 0.0 else 0

        @wp.func
        def point(loc: arr3, s: int, n: int, q: int, origin: wp.vec2i, inv_dx: dtype, top: int):
            zc = loc[s, n, 0] * inv_dx + dtype(origin[0]) - dtype(wp.static(oz))
            xc = loc[s, n, 1] * inv_dx + dtype(origin[1]) - dtype(wp.static(ox))
            iz = int(wp.floor(zc)) - wp.static(HR - 1) + q // wp.static(W)
            ix = int(wp.floor(xc)) - wp.static(HR - 1) + q % wp.static(W)
            w = hicks(dtype(iz) - zc) * hicks(dtype(ix) - xc)
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

    pt_vx = make_point(0.0, 0.5, False)
    pt_vz = make_point(0.5, 0.0, False)
    pt_sxx = make_point(0.0, 0.0, False)
    pt_szz = make_point(0.0, 0.0, True)
    pt_sxz = make_point(0.5, 0.5, True)

    @wp.kernel(module="unique")
    def inject_force(
        vx: arr3, vz: arr3, rho: arr2, amp: arr3, comp: arr3, loc: arr3, n: int,
        origin: wp.vec2i, scale: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        # v += dt b f(t_n) w / dx^2 (scale = dt / dx^2); comp (S, n_src, 2) = (f_z, f_x) direction weights
        s, src, q = wp.tid()
        a = scale * amp[s, src, n]
        i, w = pt_vx(loc, s, src, q, origin, inv_dx, top)
        if w != dtype(0.0):
            b = dtype(0.5) * (dtype(1.0) / rho[i[0], i[1]] + dtype(1.0) / rho[i[0], i[1] + 1])
            wp.atomic_add(vx, s, i[0], i[1], a * b * w * comp[s, src, 1])
        i, w = pt_vz(loc, s, src, q, origin, inv_dx, top)
        if w != dtype(0.0):
            b = dtype(0.5) * (dtype(1.0) / rho[i[0], i[1]] + dtype(1.0) / rho[i[0] + 1, i[1]])
            wp.atomic_add(vz, s, i[0], i[1], a * b * w * comp[s, src, 0])

    @wp.kernel(module="unique")
    def inject_moment(
        sxx: arr3, szz: arr3, sxz: arr3, amp: arr3, comp: arr3, loc: arr3, n: int,
        origin: wp.vec2i, scale: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        # s_ij -= (M(t_{n+1}) - M(t_n)) m_ij w / dx^2 (scale = 1 / dx^2); comp (S, n_src, 3) = (Mxx, Mzz, Mxz)
        s, src, q = wp.tid()
        a = -scale * (amp[s, src, n + 1] - amp[s, src, n])
        i, w = pt_sxx(loc, s, src, q, origin, inv_dx, top)
        if w != dtype(0.0):
            wp.atomic_add(sxx, s, i[0], i[1], a * w * comp[s, src, 0])
        i, w = pt_szz(loc, s, src, q, origin, inv_dx, top)
        if w != dtype(0.0):
            wp.atomic_add(szz, s, i[0], i[1], a * w * comp[s, src, 1])
        i, w = pt_sxz(loc, s, src, q, origin, inv_dx, top)
        if w != dtype(0.0):
            wp.atomic_add(sxz, s, i[0], i[1], a * w * comp[s, src, 2])

    @wp.kernel(module="unique")
    def record(
        vx: arr3, vz: arr3, sxx: arr3, szz: arr3, d_vx: arr3, d_vz: arr3, d_p: arr3, loc: arr3, n: int,
        origin: wp.vec2i, inv_dx: dtype, top: int,
    ):  # fmt: skip
        s, r, q = wp.tid()
        i, w = pt_vx(loc, s, r, q, origin, inv_dx, top)
        if w != dtype(0.0):
            wp.atomic_add(d_vx, s, r, n, w * vx[s, i[0], i[1]])
        i, w = pt_vz(loc, s, r, q, origin, inv_dx, top)
        if w != dtype(0.0):
            wp.atomic_add(d_vz, s, r, n, w * vz[s, i[0], i[1]])
        i, w = pt_sxx(loc, s, r, q, origin, inv_dx, top)
        if w != dtype(0.0):
            wp.atomic_add(d_p, s, r, n, dtype(-0.5) * w * sxx[s, i[0], i[1]])
        i, w = pt_szz(loc, s, r, q, origin, inv_dx, top)
        if w != dtype(0.0):
            wp.atomic_add(d_p, s, r, n, dtype(-0.5) * w * szz[s, i[0], i[1]])

    @wp.kernel(module="unique")
    def pad_model(v: arr2, vpad: arr2, origin: wp.vec2i):
        # padded model from the physical one, extended by edge replication into PML and halo
        z, x = wp.tid()
        vpad[z, x] = v[wp.clamp(z - origin[0], 0, v.shape[0] - 1), wp.clamp(x - origin[1], 0, v.shape[1] - 1)]

    @wp.kernel(module="unique")
    def monitor(u: arr3, stats: arr1):
        # stats[0] = max |u|, stats[1] = number of non-finite values
        s, z, x = wp.tid()
        val = u[s, z, x]
        if wp.isfinite(val):
            wp.atomic_max(stats, 0, wp.abs(val))
        else:
            wp.atomic_add(stats, 1, dtype(1.0))

    return _Kernels(
        Axis=Axis, velocity=velocity, stress=stress, inject_force=inject_force, inject_moment=inject_moment,
        record=record, pad_model=pad_model, monitor=monitor, halo=M, operator_points=NPTS,
    )  # fmt: skip


class _Kernels:
    """Namespace of the compiled kernels of one configuration (see build)."""

    def __init__(self, **kw):
        self.__dict__.update(kw)


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
        self.axes, self.strip_width = [], []
        for a in range(2):
            store, width, ca, cb, cah, cbh = cpml_axis(lo[a], nb, self.padded[a], R, dx, dt, vmax, pml_reflection, pml_frequency)
            axis = self.k.Axis()
            axis.store = wp.array(store, dtype=wp.int32, device=device)
            for name, val in (("a", ca), ("b", cb), ("ah", cah), ("bh", cbh)):
                setattr(axis, name, wp.array(val, dtype=dtype, device=device))
            self.axes.append(axis)
            self.strip_width.append(width)
        self.interior = (self.n_shots, self.padded[0] - 2 * R, self.padded[1] - 2 * R)
        self.inv_dx = dtype(1.0 / dx)
        self.dt_device = dtype(dt)

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

    def step(self, st: State, model, sources, n: int, out: State | None = None) -> State:
        """Advance st (level n) to level n + 1 with source sample n. model: padded (vp, vs, rho);
        sources: (kind, amplitudes (S, n_src, nt), components, locations (S, n_src, 2) m) with kind
        "force" or "moment", or None. With out=None the step is done in place (forward only); with
        `out` (fresh arrays, e.g. under a tape) st is left unchanged and out is returned."""
        vp, vs, rho = model
        out = st if out is None else out
        P, Q = st.psi, out.psi
        wp.launch(self.k.velocity, dim=self.interior,
                  inputs=[st.vx, st.vz, st.sxx, st.szz, st.sxz, rho,
                          P["vx_x"], P["vx_z"], P["vz_x"], P["vz_z"], Q["vx_x"], Q["vx_z"], Q["vz_x"], Q["vz_z"],
                          out.vx, out.vz, self.axes[0], self.axes[1], self.dt_device, self.inv_dx, self.top],
                  device=self.device)  # fmt: skip
        if sources is not None and sources[0] == "force":
            _, amp, comp, loc = sources
            wp.launch(self.k.inject_force, dim=(self.n_shots, loc.shape[1], self.k.operator_points),
                      inputs=[out.vx, out.vz, rho, amp, comp, loc, n, self.origin, self.dtype(self.dt / self.dx**2), self.inv_dx, self.top],
                      device=self.device)  # fmt: skip
        wp.launch(self.k.stress, dim=self.interior,
                  inputs=[out.vx, out.vz, st.sxx, st.szz, st.sxz, vp, vs, rho,
                          P["s_x"], P["s_z"], P["xz_z"], P["xz_x"], Q["s_x"], Q["s_z"], Q["xz_z"], Q["xz_x"],
                          out.sxx, out.szz, out.sxz, self.axes[0], self.axes[1], self.dt_device, self.inv_dx, self.top],
                  device=self.device)  # fmt: skip
        if sources is not None and sources[0] == "moment":
            _, amp, comp, loc = sources
            wp.launch(self.k.inject_moment, dim=(self.n_shots, loc.shape[1], self.k.operator_points),
                      inputs=[out.sxx, out.szz, out.sxz, amp, comp, loc, n, self.origin, self.dtype(1.0 / self.dx**2), self.inv_dx, self.top],
                      device=self.device)  # fmt: skip
        return out

    def record(self, st: State, data, locations, n: int):
        """data = (vx, vz, pressure) arrays (S, n_rec, nt): add sample n at locations (S, n_rec, 2) m."""
        wp.launch(self.k.record, dim=(self.n_shots, locations.shape[1], self.k.operator_points),
                  inputs=[st.vx, st.vz, st.sxx, st.szz, *data, locations, n, self.origin, self.inv_dx, self.top],
                  device=self.device)  # fmt: skip

    def physical(self, a):
        """View of the physical grid (nz, nx) of a padded model-shaped array."""
        o = self.origin
        return a[o[0] : o[0] + self.shape[0], o[1] : o[1] + self.shape[1]]

    def monitor(self, fields, stats):
        """stats (2,) <- [max |u| over the given fields, count of non-finite values]."""
        stats.zero_()
        for u in fields:
            wp.launch(self.k.monitor, dim=u.shape, inputs=[u, stats], device=self.device)
