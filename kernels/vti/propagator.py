"""Warp kernels for 2D pseudo-acoustic VTI (Duveneck & Bakker 2011, Geophysics 76(5), WB41), velocity-stress on a
staggered grid.

Equations (z down, x right; vp the vertical P speed, epsilon and delta Thomsen's parameters, rho the density):

    rho dvx/dt = d(sH)/dx,      d(sH)/dt = c11 dvx/dx + c13 dvz/dz - dM/dt delta(x - x_s),
    rho dvz/dt = d(sV)/dz,      d(sV)/dt = c13 dvx/dx + c33 dvz/dz - dM/dt delta(x - x_s),

    c33 = rho vp^2,  c11 = c33 (1 + 2 epsilon),  c13 = c33 sqrt(1 + 2 delta):

an elastic VTI medium with C55 = 0, whose energy c11 e_xx^2 + 2 c13 e_xx e_zz + c33 e_zz^2 is positive iff
c11 c33 >= c13^2, i.e. epsilon >= delta. With epsilon = delta = 0 it is the variable-density acoustic system (sH = sV
= -p). The explosive source M(t) = s(t) enters both stresses as the elastic solver's moment source (1, 1, 0) does.

Staggering (Virieux 1986), positions in cells from padded node (0, 0) as (z, x); array index (i, k) stands for:

    sH, sV, vp, epsilon, delta, rho, c11, c13, c33   (i, k)      vx, bx   (i, k + 1/2)      vz, bz   (i + 1/2, k)

with the buoyancy b = 1/rho at a velocity node the mean of 1/rho at its two neighbours (as kernels/elastic). Staggered
first derivatives of order 2/4/8 (numerics.STAGGERED_DERIVATIVE; kernels/viscoacoustic's flat ones: the stresses'
images are odd as its p, vz's even). Time: leapfrog; level n holds v at t = (n - 1/2) dt
and the stresses at t = n dt; one step: v^{n+1/2} = v^{n-1/2} + dt b div(s^n), s^{n+1} = s^n + dt C grad(v^{n+1/2})
- (M(t_{n+1}) - M(t_n)) delta.

Layout: fields (n_shots, Lz, Lx), x contiguous; every axis padded as [halo R][PML][physical][PML][halo R], R = order/2;
the halo stays zero. CPML (Komatitsch & Martin 2007, kappa = 1; profiles of kernels/elastic's cpml_axis at integer and
half positions): one memory variable per derivative (4), stored on the whole padded grid (zero where a = 0, b = 1,
outside the layers), so the kernels have no branch for it.

Free surface (pressure release at z = 0, padded row `top`): sH = sV = 0 on that row, and the method of images above
it: the stresses are odd about z = 0, vz even, vx odd (so vx = 0 on the surface row, as sH = 0 there). The discrete
solution is exactly the whole-space one of the mirrored model with an odd image source. Sources and receivers use
kernels/common's Hicks operator folded onto the images (kernels/elastic's make_point: odd for the stresses and vx,
even for vz).

Kernels are per cell and written for Warp's generated adjoints (gradients through wp.Tape): they may run in place
(each cell reads only its own old value of a field it writes) or out of place into a level's own arrays. `velocity` and
`stress` take the arrays' flat views (State.flat, Materials.flat: same memory and .grad) and a 1D launch over the
interior cells, indexing with int32 flat offsets (kernels/viscoacoustic's Grid; psi at the field's own cell).
"""

import functools
import math
from types import SimpleNamespace

import numpy as np
import warp as wp

from adseismic.kernels.common import HICKS_RADIUS, Kernels, hicks_axis, host_operator, unique_kernel
from adseismic.kernels.elastic.propagator import cpml_axes, make_point
from adseismic.kernels.numerics import STAGGERED_DERIVATIVE
from adseismic.kernels.viscoacoustic.propagator import Grid, Materials, _cell, _derivatives, field_grid

MATERIALS = ("bx", "bz", "c11", "c13", "c33")
PSI = ("h_x", "v_z", "x", "z")  # d(sH)/dx at vx nodes, d(sV)/dz at vz nodes, d(vx)/dx and d(vz)/dz at stress nodes
OPERATOR = ("vx", "vz", "stress")  # the fixed operator's node kinds (first index of VTI.operator's arrays)


@functools.lru_cache(maxsize=None)
def build(order: int, dtype, free_surface: bool):
    """Kernels for one (order, dtype, free_surface), compiled on first launch (unique_kernel)."""
    M = order // 2
    C = STAGGERED_DERIVATIVE[order]
    fs = bool(free_surface)
    W = 2 * HICKS_RADIUS
    arr1, arr2, arr3, arr4 = wp.array(dtype=dtype), wp.array2d(dtype=dtype), wp.array3d(dtype=dtype), wp.array4d(dtype=dtype)
    iarr1 = wp.array(dtype=wp.int32)
    idx4 = wp.array4d(dtype=wp.vec2i)

    # kernels/viscoacoustic's staggered derivatives (times dx) on flat fields: along x at x + 1/2 of a field on integer
    # nodes (dp_dx) and at x of one on half nodes (dvx_dx); along z at z + 1/2 of a stress with its odd image above a
    # free surface (dp_dz, p's), at z of vz with its even image (dvz_dz)
    ns = SimpleNamespace(M=M, C=C, fs=fs, dtype=dtype, arr1=arr1, arr3=arr3, HR=HICKS_RADIUS, W=W)
    dx_int, dz_stress, dx_half, dz_vz = _derivatives(ns)
    cell = _cell(ns)

    @unique_kernel
    def materials(vp: arr2, eps: arr2, delta: arr2, rho: arr2, origin: wp.vec2i, bx: arr2, bz: arr2, c11: arr2, c13: arr2, c33: arr2):
        # MATERIALS at the interior nodes from the physical models (nz, nx), extended by edge replication into the PML
        zi, xi = wp.tid()
        z = zi + wp.static(M)
        x = xi + wp.static(M)
        nz = vp.shape[0] - 1
        nx = vp.shape[1] - 1
        i = wp.clamp(z - origin[0], 0, nz)
        k = wp.clamp(x - origin[1], 0, nx)
        r = rho[i, k]
        bx[z, x] = dtype(0.5) * (dtype(1.0) / r + dtype(1.0) / rho[i, wp.clamp(x + 1 - origin[1], 0, nx)])
        bz[z, x] = dtype(0.5) * (dtype(1.0) / r + dtype(1.0) / rho[wp.clamp(z + 1 - origin[0], 0, nz), k])
        m = r * vp[i, k] * vp[i, k]
        c33[z, x] = m
        c11[z, x] = m * (dtype(1.0) + dtype(2.0) * eps[i, k])
        c13[z, x] = m * wp.sqrt(dtype(1.0) + dtype(2.0) * delta[i, k])

    @unique_kernel(grid_stride=False)
    def velocity(vx: arr1, vz: arr1, sh: arr1, sv: arr1, bx: arr1, bz: arr1, p_hx: arr1, p_vz: arr1, n_hx: arr1, n_vz: arr1,
                 vx_new: arr1, vz_new: arr1, ax_ah: arr1, ax_bh: arr1, az_ah: arr1, az_bh: arr1, dt: dtype, inv_dx: dtype,
                 top: int, grid: Grid):  # fmt: skip
        # v += dt b (ds/dx_i + psi), psi = b_pml psi + a_pml ds/dx_i at the derivative's own (half) position
        s, z, x, m, c = cell(grid, wp.tid())
        d1 = dx_int(sh, c) * inv_dx
        d2 = dz_stress(sv, c, z, grid.lx, top) * inv_dx
        q1 = ax_bh[x] * p_hx[c] + ax_ah[x] * d1
        q2 = az_bh[z] * p_vz[c] + az_ah[z] * d2
        ux = vx[c]
        uz = vz[c]
        n_hx[c] = q1
        n_vz[c] = q2
        vx_new[c] = ux + dt * bx[m] * (d1 + q1)
        vz_new[c] = uz + dt * bz[m] * (d2 + q2)

    @unique_kernel(grid_stride=False)
    def stress(vx: arr1, vz: arr1, sh: arr1, sv: arr1, c11: arr1, c13: arr1, c33: arr1, p_x: arr1, p_z: arr1, n_x: arr1, n_z: arr1,
               sh_new: arr1, sv_new: arr1, ax_a: arr1, ax_b: arr1, az_a: arr1, az_b: arr1, dt: dtype, inv_dx: dtype, top: int,
               grid: Grid):  # fmt: skip
        # sH += dt (c11 ex + c13 ez), sV += dt (c13 ex + c33 ez), e the CPML'd strain rates at the stress node;
        # both stay 0 on a free surface
        s, z, x, m, c = cell(grid, wp.tid())
        d1 = dx_half(vx, c) * inv_dx
        d2 = dz_vz(vz, c, z, grid.lx, top) * inv_dx
        q1 = ax_b[x] * p_x[c] + ax_a[x] * d1
        q2 = az_b[z] * p_z[c] + az_a[z] * d2
        fh = sh[c]
        fv = sv[c]
        ex = d1 + q1
        ez = d2 + q2
        a11 = c11[m]
        a13 = c13[m]
        a33 = c33[m]
        n_x[c] = q1
        n_z[c] = q2
        surface = False
        if wp.static(fs):
            surface = z == top
        if surface:
            sh_new[c] = dtype(0.0)
            sv_new[c] = dtype(0.0)
        else:
            sh_new[c] = fh + dt * (a11 * ex + a13 * ez)
            sv_new[c] = fv + dt * (a13 * ex + a33 * ez)

    hicks = hicks_axis(dtype)
    point_vx = make_point(ns, hicks, 0.0, 0.5, True)
    point_vz = make_point(ns, hicks, 0.5, 0.0, False)
    point_stress = make_point(ns, hicks, 0.0, 0.0, True)

    @unique_kernel(enable_backward=False)  # computed once per run, never differentiated (locations are fixed)
    def weights(loc: arr3, origin: wp.vec2i, inv_dx: dtype, top: int, idx: idx4, w: arr4):
        # the fixed operator of locations loc (S, n, 2) m: node and weight of point q for vx, vz and the stresses
        s, r, q = wp.tid()
        i, wq = point_vx(loc, s, r, q, origin, inv_dx, top)
        idx[0, s, r, q] = i
        w[0, s, r, q] = wq
        i, wq = point_vz(loc, s, r, q, origin, inv_dx, top)
        idx[1, s, r, q] = i
        w[1, s, r, q] = wq
        i, wq = point_stress(loc, s, r, q, origin, inv_dx, top)
        idx[2, s, r, q] = i
        w[2, s, r, q] = wq

    @unique_kernel
    def inject(sh: arr3, sv: arr3, amp: arr3, idx: idx4, w: arr4, n: int, clock: iarr1, scale: dtype):
        # explosive source: sH, sV -= (s(t_{n+1}) - s(t_n)) w / dx^2 (scale = 1 / dx^2); sample n + clock[0]
        s, src, q = wp.tid()
        t = n + clock[0]
        wq = w[2, s, src, q]
        if wq != dtype(0.0):
            i = idx[2, s, src, q]
            a = -scale * (amp[s, src, t + 1] - amp[s, src, t]) * wq
            wp.atomic_add(sh, s, i[0], i[1], a)
            wp.atomic_add(sv, s, i[0], i[1], a)

    @unique_kernel
    def record(vx: arr3, vz: arr3, sh: arr3, sv: arr3, d_vx: arr3, d_vz: arr3, d_p: arr3, idx: idx4, w: arr4, n: int, clock: iarr1):
        # sample n + clock[0] of vx, vz and the pressure -(sH + sV) / 2 through the receivers' fixed operator
        s, r, q = wp.tid()
        t = n + clock[0]
        i = idx[0, s, r, q]
        wp.atomic_add(d_vx, s, r, t, w[0, s, r, q] * vx[s, i[0], i[1]])
        i = idx[1, s, r, q]
        wp.atomic_add(d_vz, s, r, t, w[1, s, r, q] * vz[s, i[0], i[1]])
        i = idx[2, s, r, q]
        wp.atomic_add(d_p, s, r, t, dtype(-0.5) * w[2, s, r, q] * (sh[s, i[0], i[1]] + sv[s, i[0], i[1]]))

    return Kernels(materials=materials, velocity=velocity, stress=stress, weights=weights, inject=inject, record=record, halo=M,
                   operator_points=W * W)  # fmt: skip


class State:
    """Fields at one time level n: vx, vz (m/s) at t = (n - 1/2) dt, sH, sV (Pa) at t = n dt, each (S, Lz, Lx), and the
    CPML memory variables psi (dict, see PSI; same shape)."""

    def __init__(self, vx, vz, sh, sv, psi):
        self.vx, self.vz, self.sh, self.sv, self.psi = vx, vz, sh, sv, psi
        self._flat = None

    def arrays(self):
        return [self.vx, self.vz, self.sh, self.sv, *(self.psi[k] for k in PSI)]

    def flat(self) -> "State":
        """The State of the arrays' flat (1D) views, the field kernels' inputs; made once, they share memory and .grad
        with the arrays."""
        if self._flat is None:
            self._flat = State(*(a.flatten() for a in (self.vx, self.vz, self.sh, self.sv)), {k: self.psi[k].flatten() for k in PSI})
        return self._flat


class VTI:
    """Launch helper: padded grid, CPML coefficients and one time step of the 2D pseudo-acoustic VTI scheme.

    shape: physical grid (nz, nx) nodes; dx (m), dt (s); order 2, 4 or 8; pml_width cells on every absorbing side (all
    four, or three with free_surface); vmax: CPML reference speed (m/s). Locations given to operator() are metres (z, x)
    from the physical grid's node 0.
    """

    def __init__(self, shape, dx, dt, order, n_shots, pml_width, pml_reflection, pml_frequency, vmax, free_surface=False,
                 dtype=wp.float64, device="cpu"):  # fmt: skip
        self.ndim = 2
        self.shape = tuple(int(n) for n in shape)
        self.dx, self.dt, self.order, self.n_shots = float(dx), float(dt), int(order), int(n_shots)
        self.dtype, self.device, self.free_surface = dtype, device, bool(free_surface)
        self.cuda = wp.get_device(device).is_cuda
        self.k = build(self.order, dtype, self.free_surface)
        R, nb = self.k.halo, int(pml_width)
        lo = (0 if free_surface else nb, nb)
        self.padded = tuple(self.shape[a] + lo[a] + nb + 2 * R for a in range(2))
        self.origin = wp.vec2i(R + lo[0], R + lo[1])
        self.top = R
        # per axis (z, x): CPML a, b at integer and ah, bh at half positions
        self.axes = cpml_axes(SimpleNamespace, lo, nb, self.padded, R, dx, dt, vmax, pml_reflection, pml_frequency, dtype, device)[0]
        self.interior = (self.n_shots, self.padded[0] - 2 * R, self.padded[1] - 2 * R)
        # psi lies on the whole padded grid: strips as wide as the grid, so its flat cell is the field's
        self.grid = field_grid(self.padded, R, self.padded, self.n_shots * math.prod(self.padded))
        self.inv_dx = dtype(1.0 / dx)
        self.dt_device = dtype(dt)
        self.clock = wp.zeros(1, dtype=wp.int32, device=device)  # stays 0: plain launches pass n itself

    def new_state(self, requires_grad=False) -> State:
        def zeros():
            return wp.zeros((self.n_shots, *self.padded), dtype=self.dtype, device=self.device, requires_grad=requires_grad)

        return State(zeros(), zeros(), zeros(), zeros(), {k: zeros() for k in PSI})

    def materials(self, vp, epsilon, delta, rho, requires_grad=False, out=None):
        """MATERIALS (padded (Lz, Lx) arrays, interior nodes set; a viscoacoustic Materials, with their flat views) from
        the physical models (nz, nx) wp.array2d; into out (an earlier call's Materials) if given."""
        if out is None:
            out = Materials([wp.zeros(self.padded, dtype=self.dtype, device=self.device, requires_grad=requires_grad) for _ in MATERIALS])
        wp.launch(self.k.materials, dim=self.interior[1:], inputs=[vp, epsilon, delta, rho, self.origin, *out], device=self.device)
        return out

    def step(self, st: State, mat, sources, n: int, out: State | None = None, clock=None) -> State:
        """Advance st (level n) to level n + 1 with source sample n (+ clock[0]). mat: MATERIALS; sources: (amplitudes
        (S, n_src, >= n + 2), operator (VTI.operator)) or None. mat: MATERIALS (materials' Materials). out=None: in place;
        else into out (st unchanged)."""
        out = st if out is None else out
        clock = self.clock if clock is None else clock
        f, o = st.flat(), out.flat()
        bx, bz, c11, c13, c33 = mat.flat
        P, Q = f.psi, o.psi
        az, ax = self.axes
        common = [self.dt_device, self.inv_dx, self.top, self.grid]
        cells = math.prod(self.interior)
        wp.launch(self.k.velocity, dim=cells, device=self.device,
                  inputs=[f.vx, f.vz, f.sh, f.sv, bx, bz, P["h_x"], P["v_z"], Q["h_x"], Q["v_z"], o.vx, o.vz, ax.ah, ax.bh, az.ah, az.bh,
                          *common])  # fmt: skip
        wp.launch(self.k.stress, dim=cells, device=self.device,
                  inputs=[o.vx, o.vz, f.sh, f.sv, c11, c13, c33, P["x"], P["z"], Q["x"], Q["z"], o.sh, o.sv, ax.a, ax.b, az.a, az.b,
                          *common])  # fmt: skip
        if sources is not None:
            amp, (idx, w) = sources
            wp.launch(self.k.inject, dim=w.shape[1:], inputs=[out.sh, out.sv, amp, idx, w, n, clock, self.dtype(1.0 / self.dx**2)],
                      device=self.device)  # fmt: skip
        return out

    def operator(self, locations):
        """The fixed operator of points at locations (S, n, 2) m: node indices and weights (3, S, n, points) at the vx,
        vz and stress nodes (OPERATOR)."""
        shape = (len(OPERATOR), self.n_shots, locations.shape[1], self.k.operator_points)
        return host_operator(self.k.weights, locations, [self.origin, self.inv_dx, self.top], shape, wp.vec2i, self.dtype, self.device)

    def record(self, st: State, data, op, n: int, clock=None):
        """data = (vx, vz, pressure) arrays (S, n_rec, levels): add sample n (+ clock[0]) through the receivers'
        operator op (VTI.operator)."""
        clock = self.clock if clock is None else clock
        wp.launch(self.k.record, dim=op[1].shape[1:], inputs=[st.vx, st.vz, st.sh, st.sv, *data, *op, n, clock], device=self.device)


def thomsen_check(epsilon: np.ndarray, delta: np.ndarray):
    """Raise ValueError at the first node where the pseudo-acoustic VTI system is not stable: epsilon < delta (its
    energy is not positive) or delta <= -1/2 (sqrt(1 + 2 delta) undefined)."""
    for bad, what, fix in ((delta <= -0.5, "delta <= -0.5 makes sqrt(1 + 2 delta) undefined", "use delta > -0.5"),
                           (epsilon < delta, "epsilon < delta: the pseudo-acoustic VTI system (C55 = 0) has negative energy "
                            "there and blows up", "use epsilon >= delta (e.g. delta = min(delta, epsilon))")):  # fmt: skip
        if bad.any():
            i = tuple(int(k) for k in np.argwhere(bad)[0])
            raise ValueError(f"{what}: epsilon = {epsilon[i]:g}, delta = {delta[i]:g} at index (z, x) = {i} ({int(bad.sum())} nodes); "
                             f"{fix}")
