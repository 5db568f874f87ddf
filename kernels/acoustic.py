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
parameter HICKS_B for wavenumbers up to pi/2, i.e. >= 4 points per wavelength), mirrored with a
sign change across a free surface. The Kaiser window has its edge value (1/I0(b), ~1%) subtracted so
that the weights are continuously differentiable in the position (source-location gradients).

All kernels write fresh outputs from inputs (or add with atomics), never read-modify their own
input, so each time step can be differentiated by wp.Tape when given its own arrays.
"""


import functools
import math

import numpy as np
import warp as wp

from adseismic.numerics import FIRST_DERIVATIVE, SECOND_DERIVATIVE

HICKS_RADIUS = 4
HICKS_B = 6.31
_I0_TERMS = 20


def _i0(x: float) -> float:
    total, term = 1.0, 1.0
    for k in range(1, _I0_TERMS + 1):
        term *= (x / 2.0) ** 2 / k**2
        total += term
    return total


@functools.lru_cache(maxsize=None)
def build(ndim: int, order: int, dtype, free_surface: bool):
    """Kernels for one (ndim, order, dtype, free_surface) combination, compiled once per process."""
    R = order // 2
    A = SECOND_DERIVATIVE[order]
    B = FIRST_DERIVATIVE[order]
    HR = HICKS_RADIUS
    W = 2 * HR
    NPTS = W**ndim
    WINDOW_NORM = 1.0 / (_i0(HICKS_B) - 1.0)
    fs = bool(free_surface)
    three = ndim == 3
    arr1 = wp.array(dtype=dtype)
    arr3 = wp.array3d(dtype=dtype)
    arr4 = wp.array4d(dtype=dtype)

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
    dpsi_z, dpsi_y, dpsi_x = d1  # d(psi)/dx inside the strips
    sdp_z, sdp_y, sdp_x = d1t

    def make_psi(axis: int):
        # psi along one axis (0: z, 1: y, 2: x) for every cell of that axis' strip.
        deriv = d1[axis]
        @wp.kernel(module="unique")
        def psi_kernel(u: arr4, psi_old: arr4, psi_new: arr4, ax: Axis, inv_dx: dtype):
            s, i, j, k = wp.tid()
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

        return psi_kernel


    @wp.kernel(module="unique")
    def step(
        u: arr4, u_prev: arr4, u_next: arr4, v: arr3,
        psi_z: arr4, psi_y: arr4, psi_x: arr4,
        zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        zeta_z_new: arr4, zeta_y_new: arr4, zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis,
        dt2: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        s, zi, yi, xi = wp.tid()
        z = zi + wp.static(R)
        x = xi + wp.static(R)
        y = yi
        if wp.static(three):
            y = yi + wp.static(R)
        if wp.static(fs):
            if z == top:
                u_next[s, z, y, x] = dtype(0.0)
                return
        inv_dx2 = inv_dx * inv_dx
        uzz = d2z(u, s, z, y, x, top) * inv_dx2
        jz = az.store[z]
        if jz >= 0:
            g = uzz + dpsi_z(psi_z, s, jz, y, x) * inv_dx
            zn = az.b[z] * zeta_z[s, jz, y, x] + az.a[z] * g
            zeta_z_new[s, jz, y, x] = zn
            uzz = g + zn
        uxx = d2x(u, s, z, y, x, top) * inv_dx2
        jx = ax.store[x]
        if jx >= 0:
            g = uxx + dpsi_x(psi_x, s, z, y, jx) * inv_dx
            zn = ax.b[x] * zeta_x[s, z, y, jx] + ax.a[x] * g
            zeta_x_new[s, z, y, jx] = zn
            uxx = g + zn
        lap = uzz + uxx
        if wp.static(three):
            uyy = d2y(u, s, z, y, x, top) * inv_dx2
            jy = ay.store[y]
            if jy >= 0:
                g = uyy + dpsi_y(psi_y, s, z, jy, x) * inv_dx
                zn = ay.b[y] * zeta_y[s, z, jy, x] + ay.a[y] * g
                zeta_y_new[s, z, jy, x] = zn
                uyy = g + zn
            lap = lap + uyy
        vv = v[z, y, x]
        u_next[s, z, y, x] = dtype(2.0) * u[s, z, y, x] - u_prev[s, z, y, x] + vv * vv * dt2 * lap

    # --- Hand-written adjoints of psi_kernel and step (scatter form). They match Warp's generated
    # adjoints (tests/test_gradient.py) without replaying every read, and are what the taped steps use.

    def make_psi_adjoint(axis: int):
        deriv_t = d1t[axis]

        @wp.kernel(module="unique")
        def psi_adjoint(adj_u: arr4, adj_psi_old: arr4, adj_psi_new: arr4, ax: Axis, inv_dx: dtype):
            s, i, j, k = wp.tid()
            if wp.static(axis == 0):
                p = ax.pos[i]
            elif wp.static(axis == 1):
                p = ax.pos[j]
            else:
                p = ax.pos[k]
            a = ax.a[p]
            lam = adj_psi_new[s, i, j, k]
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

        return psi_adjoint

    @wp.func
    def add_z(adj_u: arr4, s: int, z: int, y: int, x: int, top: int, val: dtype):
        # adjoint of at(): a read above the free surface came from the mirrored cell, sign flipped
        if wp.static(fs):
            if z < top:
                wp.atomic_add(adj_u, s, 2 * top - z, y, x, -val)
                return
        wp.atomic_add(adj_u, s, z, y, x, val)

    def make_scatter_d2(axis: int):
        # adjoint of the second-derivative stencil along one axis: adj_u[stencil] += A_k g
        @wp.func
        def scatter_d2(adj_u: arr4, s: int, z: int, y: int, x: int, top: int, g: dtype):
            wp.atomic_add(adj_u, s, z, y, x, dtype(wp.static(A[0])) * g)
            for k in range(wp.static(R)):
                c = dtype(wp.static(A[k + 1])) * g
                if wp.static(axis == 0):
                    add_z(adj_u, s, z + k + 1, y, x, top, c)
                    add_z(adj_u, s, z - k - 1, y, x, top, c)
                elif wp.static(axis == 1):
                    wp.atomic_add(adj_u, s, z, y + k + 1, x, c)
                    wp.atomic_add(adj_u, s, z, y - k - 1, x, c)
                else:
                    wp.atomic_add(adj_u, s, z, y, x + k + 1, c)
                    wp.atomic_add(adj_u, s, z, y, x - k - 1, c)

        return scatter_d2

    sd2_z, sd2_y, sd2_x = make_scatter_d2(0), make_scatter_d2(1), make_scatter_d2(2)

    @wp.kernel(module="unique")
    def step_adjoint(
        u: arr4, v: arr3, psi_z: arr4, psi_y: arr4, psi_x: arr4, zeta_z: arr4, zeta_y: arr4, zeta_x: arr4,
        adj_u: arr4, adj_u_prev: arr4, adj_u_next: arr4, adj_v: arr3,
        adj_psi_z: arr4, adj_psi_y: arr4, adj_psi_x: arr4,
        adj_zeta_z: arr4, adj_zeta_y: arr4, adj_zeta_x: arr4,
        adj_zeta_z_new: arr4, adj_zeta_y_new: arr4, adj_zeta_x_new: arr4,
        az: Axis, ay: Axis, ax: Axis, dt2: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        s, zi, yi, xi = wp.tid()
        z = zi + wp.static(R)
        x = xi + wp.static(R)
        y = yi
        if wp.static(three):
            y = yi + wp.static(R)
        if wp.static(fs):
            if z == top:
                return  # u_next = 0 there: nothing flows back
        lam = adj_u_next[s, z, y, x]
        vv = v[z, y, x]
        q = vv * vv * dt2 * lam
        inv_dx2 = inv_dx * inv_dx
        wp.atomic_add(adj_u, s, z, y, x, dtype(2.0) * lam)
        wp.atomic_add(adj_u_prev, s, z, y, x, -lam)
        # z axis: T = g + zeta_new with g = d2 + dpsi and zeta_new = b zeta + a g (PML strip),
        # else T = d2. Recompute T for the model gradient; scatter the adjoint of g.
        t = d2z(u, s, z, y, x, top) * inv_dx2
        g = q
        jz = az.store[z]
        if jz >= 0:
            gz = t + dpsi_z(psi_z, s, jz, y, x) * inv_dx
            t = gz + az.b[z] * zeta_z[s, jz, y, x] + az.a[z] * gz
            adj_zn = q + adj_zeta_z_new[s, jz, y, x]
            g = q + az.a[z] * adj_zn
            wp.atomic_add(adj_zeta_z, s, jz, y, x, az.b[z] * adj_zn)
            sdp_z(adj_psi_z, s, jz, y, x, g * inv_dx)
        sd2_z(adj_u, s, z, y, x, top, g * inv_dx2)
        total = t
        t = d2x(u, s, z, y, x, top) * inv_dx2
        g = q
        jx = ax.store[x]
        if jx >= 0:
            gx = t + dpsi_x(psi_x, s, z, y, jx) * inv_dx
            t = gx + ax.b[x] * zeta_x[s, z, y, jx] + ax.a[x] * gx
            adj_zn = q + adj_zeta_x_new[s, z, y, jx]
            g = q + ax.a[x] * adj_zn
            wp.atomic_add(adj_zeta_x, s, z, y, jx, ax.b[x] * adj_zn)
            sdp_x(adj_psi_x, s, z, y, jx, g * inv_dx)
        sd2_x(adj_u, s, z, y, x, top, g * inv_dx2)
        total += t
        if wp.static(three):
            t = d2y(u, s, z, y, x, top) * inv_dx2
            g = q
            jy = ay.store[y]
            if jy >= 0:
                gy = t + dpsi_y(psi_y, s, z, jy, x) * inv_dx
                t = gy + ay.b[y] * zeta_y[s, z, jy, x] + ay.a[y] * gy
                adj_zn = q + adj_zeta_y_new[s, z, jy, x]
                g = q + ay.a[y] * adj_zn
                wp.atomic_add(adj_zeta_y, s, z, jy, x, ay.b[y] * adj_zn)
                sdp_y(adj_psi_y, s, z, jy, x, g * inv_dx)
            sd2_y(adj_u, s, z, y, x, top, g * inv_dx2)
            total += t
        wp.atomic_add(adj_v, z, y, x, dtype(2.0) * vv * dt2 * lam * total)

    @wp.func
    def hicks(d: dtype) -> dtype:
        # Kaiser-windowed sinc weight at distance d (cells). The window is the Kaiser series written in
        # q = 1 - d^2/r^2 (no square root) minus its edge value, so the weight and its derivative vanish
        # at |d| = r: the operator is C^1 in the position, also for positions on grid nodes.
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

    @wp.func
    def point(loc: arr3, s: int, n: int, q: int, origin: wp.vec3i, inv_dx: dtype, top: int):
        # q-th stencil node of the operator at loc[s, n] (metres, (z, y, x)): padded index and weight.
        zc = loc[s, n, 0] * inv_dx + dtype(origin[0])
        xc = loc[s, n, 2] * inv_dx + dtype(origin[2])
        qz = q // wp.static(W ** (ndim - 1))
        qx = q % wp.static(W)
        iz = int(wp.floor(zc)) - wp.static(HR - 1) + qz
        ix = int(wp.floor(xc)) - wp.static(HR - 1) + qx
        w = hicks(dtype(iz) - zc) * hicks(dtype(ix) - xc)
        iy = int(0)
        if wp.static(three):
            yc = loc[s, n, 1] * inv_dx + dtype(origin[1])
            iy = int(wp.floor(yc)) - wp.static(HR - 1) + (q // wp.static(W)) % wp.static(W)
            w = w * hicks(dtype(iy) - yc)
        if wp.static(fs):
            if iz == top:
                w = dtype(0.0)
            elif iz < top:
                iz = 2 * top - iz
                w = -w
        return wp.vec3i(iz, iy, ix), w

    @wp.kernel(module="unique")
    def inject(
        u_next: arr4, v: arr3, amp: arr3, loc: arr3, n: int,
        origin: wp.vec3i, scale: dtype, inv_dx: dtype, top: int,
    ):  # fmt: skip
        # u_next += v^2 dt^2 s[n] w / dx^ndim at the operator's nodes (scale = dt^2 / dx^ndim).
        s, src, q = wp.tid()
        idx, w = point(loc, s, src, q, origin, inv_dx, top)
        if w != dtype(0.0):
            vv = v[idx[0], idx[1], idx[2]]
            wp.atomic_add(u_next, s, idx[0], idx[1], idx[2], scale * vv * vv * w * amp[s, src, n])

    @wp.kernel(module="unique")
    def record(u: arr4, data: arr3, loc: arr3, n: int, origin: wp.vec3i, inv_dx: dtype, top: int):
        s, rec, q = wp.tid()
        idx, w = point(loc, s, rec, q, origin, inv_dx, top)
        if w != dtype(0.0):
            wp.atomic_add(data, s, rec, n, w * u[s, idx[0], idx[1], idx[2]])

    # Precomputed operator (positions that are not differentiated, e.g. receivers): the node index and
    # weight of every stencil point, computed once per run instead of at every time step.
    @wp.kernel(module="unique")
    def weights(loc: arr3, origin: wp.vec3i, inv_dx: dtype, top: int, idx: wp.array3d(dtype=wp.vec3i), w: arr3):
        s, n, q = wp.tid()
        i, wq = point(loc, s, n, q, origin, inv_dx, top)
        idx[s, n, q] = i
        w[s, n, q] = wq

    @wp.kernel(module="unique")
    def inject_fixed(u_next: arr4, v: arr3, amp: arr3, idx: wp.array3d(dtype=wp.vec3i), w: arr3, n: int, scale: dtype):
        s, src, q = wp.tid()
        wq = w[s, src, q]
        if wq != dtype(0.0):
            i = idx[s, src, q]
            vv = v[i[0], i[1], i[2]]
            wp.atomic_add(u_next, s, i[0], i[1], i[2], scale * vv * vv * wq * amp[s, src, n])

    @wp.kernel(module="unique")
    def record_fixed(u: arr4, data: arr3, idx: wp.array3d(dtype=wp.vec3i), w: arr3, n: int):
        s, rec, q = wp.tid()
        wq = w[s, rec, q]
        if wq != dtype(0.0):
            i = idx[s, rec, q]
            wp.atomic_add(data, s, rec, n, wq * u[s, i[0], i[1], i[2]])

    @wp.kernel(module="unique")
    def pad_model(v: arr3, vpad: arr3, origin: wp.vec3i):
        # Padded model from the physical one, extended by edge replication into PML and halo.
        z, y, x = wp.tid()
        iz = wp.clamp(z - origin[0], 0, v.shape[0] - 1)
        iy = wp.clamp(y - origin[1], 0, v.shape[1] - 1)
        ix = wp.clamp(x - origin[2], 0, v.shape[2] - 1)
        vpad[z, y, x] = v[iz, iy, ix]

    @wp.kernel(module="unique")
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

    @wp.kernel(module="unique")
    def energy(u: arr4, e: arr3):
        # e += sum over shots of u^2 (illumination, for the pseudo-Hessian preconditioner)
        s, z, y, x = wp.tid()
        val = u[s, z, y, x]
        wp.atomic_add(e, z, y, x, val * val)

    @wp.kernel(module="unique")
    def monitor(u: arr4, stats: arr1):
        # stats[0] = max |u|, stats[1] = number of non-finite values (blow-up detection).
        s, z, y, x = wp.tid()
        val = u[s, z, y, x]
        if wp.isfinite(val):
            wp.atomic_max(stats, 0, wp.abs(val))
        else:
            wp.atomic_add(stats, 1, dtype(1.0))

    return _Kernels(
        Axis=Axis, step=step, psi=(make_psi(0), make_psi(1), make_psi(2)), inject=inject, step_adjoint=step_adjoint,
        psi_adjoint=(make_psi_adjoint(0), make_psi_adjoint(1), make_psi_adjoint(2)),
        record=record, weights=weights, inject_fixed=inject_fixed, record_fixed=record_fixed, pad_model=pad_model, scatter=scatter, energy=energy, monitor=monitor, halo=R, operator_points=NPTS,
    )  # fmt: skip


class _Kernels:
    """Namespace of the compiled kernels of one configuration (see build)."""

    def __init__(self, **kw):
        self.__dict__.update(kw)


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
    absorbing side; positions passed to inject/record are metres from the physical grid's node 0.
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
        self.interior = (self.n_shots, self.padded[0] - 2 * R, self.padded[1] - 2 * halo[1], self.padded[2] - 2 * R)
        self.inv_dx = dtype(1.0 / dx)
        self.dt2 = dtype(dt * dt)
        self.src_scale = dtype(dt * dt / dx**self.ndim)

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

    def pad_model(self, v, requires_grad=False):
        """Padded model (Lz, Ly, Lx) from the physical one (wp.array3d, (nz, ny, nx), m/s)."""
        vpad = wp.zeros(self.padded, dtype=self.dtype, device=self.device, requires_grad=requires_grad)
        wp.launch(self.k.pad_model, dim=self.padded, inputs=[v, vpad, self.origin], device=self.device)
        return vpad

    def step(self, st: State, vpad, out: State | None = None, tape=None) -> State:
        """Advance st (level n) to level n+1. With out=None the step is done in place (forward only);
        with `out` (fresh arrays, e.g. under a tape) st is left unchanged and out is returned. With
        `tape` (the active wp.Tape, out given) the hand-written adjoint is recorded for this step
        instead of Warp's generated one."""
        if out is None:
            out = State(st.u, st.u_prev, st.psi, st.zeta)  # u[n+1] overwrites u[n-1]; psi, zeta in place
            u_next = st.u_prev
        else:
            out = State(st.u, out.u, out.psi, out.zeta)
            u_next = out.u
        record = tape is None
        axes = [a for a in range(3) if self.strip_width[a]]
        for a in axes:
            wp.launch(self.k.psi[a], dim=self.strip_shape(a), inputs=[st.u, st.psi[a], out.psi[a], self.axes[a], self.inv_dx],
                      device=self.device, record_tape=record)  # fmt: skip
        wp.launch(self.k.step, dim=self.interior,
                  inputs=[st.u, st.u_prev, u_next, vpad, *out.psi, *st.zeta, *out.zeta, *self.axes,
                          self.dt2, self.inv_dx, self.top], device=self.device, record_tape=record)  # fmt: skip
        if tape is not None:

            def backward():
                wp.launch(self.k.step_adjoint, dim=self.interior,
                          inputs=[st.u, vpad, *out.psi, *st.zeta, st.u.grad, st.u_prev.grad, u_next.grad, vpad.grad,
                                  *(p.grad for p in out.psi), *(z.grad for z in st.zeta), *(z.grad for z in out.zeta),
                                  *self.axes, self.dt2, self.inv_dx, self.top], device=self.device)  # fmt: skip
                for a in axes:
                    wp.launch(self.k.psi_adjoint[a], dim=self.strip_shape(a),
                              inputs=[st.u.grad, st.psi[a].grad, out.psi[a].grad, self.axes[a], self.inv_dx], device=self.device)  # fmt: skip

            tape.record_func(backward, arrays=[*st.arrays(), *out.arrays(), vpad])
        return out

    def operator(self, locations, differentiable=False):
        """The source/receiver operator at locations (wp.array (S, n, 3), metres): the locations
        themselves when they are to be differentiated (weights recomputed every step), else the
        precomputed node indices and weights (S, n, points)."""
        if differentiable:
            return locations
        shape = (self.n_shots, locations.shape[1], self.k.operator_points)
        idx = wp.zeros(shape, dtype=wp.vec3i, device=self.device)
        w = wp.zeros(shape, dtype=self.dtype, device=self.device)
        wp.launch(self.k.weights, dim=shape, inputs=[locations, self.origin, self.inv_dx, self.top, idx, w], device=self.device)
        return (idx, w)

    def inject(self, u, vpad, amplitudes, op, n: int):
        """Add source samples n (amplitudes (S, n_src, nt)) through the operator op into u."""
        if isinstance(op, tuple):
            wp.launch(self.k.inject_fixed, dim=op[1].shape, inputs=[u, vpad, amplitudes, op[0], op[1], n, self.src_scale], device=self.device)
        else:
            wp.launch(self.k.inject, dim=(self.n_shots, op.shape[1], self.k.operator_points),
                      inputs=[u, vpad, amplitudes, op, n, self.origin, self.src_scale, self.inv_dx, self.top], device=self.device)  # fmt: skip

    def record(self, u, data, op, n: int):
        """data[:, :, n] += receiver samples of u through the operator op."""
        if isinstance(op, tuple):
            wp.launch(self.k.record_fixed, dim=op[1].shape, inputs=[u, data, op[0], op[1], n], device=self.device)
        else:
            wp.launch(self.k.record, dim=(self.n_shots, op.shape[1], self.k.operator_points),
                      inputs=[u, data, op, n, self.origin, self.inv_dx, self.top], device=self.device)  # fmt: skip

    def scatter(self, du_next, u_next, u, u_prev, vpad, dvpad):
        """du_next += 2 dv/v (u_next - 2 u + u_prev): the Born (tangent-linear) source term."""
        wp.launch(self.k.scatter, dim=self.interior, inputs=[du_next, u_next, u, u_prev, vpad, dvpad], device=self.device)

    def accumulate_energy(self, u, e):
        """e (padded model shape) += sum over shots of u^2; never recorded on a tape."""
        wp.launch(self.k.energy, dim=u.shape, inputs=[u, e], device=self.device, record_tape=False)

    def physical(self, a):
        """View of the physical grid (nz, ny, nx) of a padded model-shaped array."""
        o = self.origin
        ny = self.shape[1] if self.ndim == 3 else 1
        return a[o[0] : o[0] + self.shape[0], o[1] : o[1] + ny, o[2] : o[2] + self.shape[-1]]

    def monitor(self, u, stats):
        """stats (2,) <- [max |u|, count of non-finite values]."""
        stats.zero_()
        wp.launch(self.k.monitor, dim=u.shape, inputs=[u, stats], device=self.device)
