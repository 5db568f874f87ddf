"""3D isotropic elastic physics (kernels/elastic3d, adseismic/solve/elastic3d.py), float64 on the test device: a point force
against Stokes' solution (Aki & Richards eq. 4.23) and the measured convergence order, an explosive source against
the analytic P potential and its isotropy, the free surface (the Miller-Pursey on-axis P amplitude, the x/y symmetry
of its update), the input refusals. Numbers: docs/elastic3d.md. Gradients: the shared tests in test_adjoint.py
(elastic3d cases)."""

import math

import numpy as np
import pytest
from scipy.fft import irfft, next_fast_len, rfft, rfftfreq

from adseismic.analytic import elastic_3d_force
from adseismic.kernels.elastic3d import DESCRIPTION, Elastic3D
from adseismic.solve.elastic3d import forward_elastic3d
from adseismic.wavelets import ricker

from .conftest import DEVICE

VP, VS, RHO = 2000.0, 1000.0, 2000.0
F0 = 8.0  # Hz: the S wavelength at the peak frequency is 125 m


def homogeneous(shape):
    return np.full(shape, VP), np.full(shape, VS), np.full(shape, RHO)


def two_receivers(dx: float, source_type: str, distance: float = 150.0, order: int = 8):
    """A homogeneous run with one source (a Ricker of F0 Hz) and two receivers `distance` m from it along z and along
    x: Courant number 0.4, the source off the grid (0.37, 0.21, 0.43) cells, 5 cells of medium beyond the receivers,
    a 10-cell PML. Returns (result, offsets (2, 3) m, source samples (nt,), dt)."""
    dt = 0.4 * dx / VP
    nt = int((distance / VS + 2.2 / F0) / dt)
    m = 5
    n = int(round(distance / dx)) + 2 * m + 1
    shape = (n, 2 * m + 1, n)
    src = np.array([[[(m + 0.37) * dx, (m + 0.21) * dx, (m + 0.43) * dx]]])
    offsets = np.array([[distance, 0.0, 0.0], [0.0, 0.0, distance]])
    amp = ricker(F0, nt, dt)[None, None]
    r = forward_elastic3d(*homogeneous(shape), dx, dt, amp, src, (src[0, 0] + offsets)[None], source_type=source_type, order=order,
                          pml_width=10, precision="float64", device=DEVICE)  # fmt: skip
    return r, offsets, amp[0, 0], dt


def stokes_errors(dx: float):
    """Max |v - v_Stokes| / max |v_Stokes| of vz at the receivers along a vertical point force and across it
    (two_receivers). The analytic velocity at the record's times (k - 1/2) dt is the centred difference of the
    displacement at k dt and (k - 1) dt (an O((w dt)^2 / 24) error, 4e-4 at the peak for dx = 10 m)."""
    r, offsets, s, dt = two_receivers(dx, "force")
    u = elastic_3d_force(s, dt, offsets, VP, VS, RHO, (1.0, 0.0, 0.0))[0]  # u_z (2, nt)
    v = np.zeros_like(u)
    v[:, 1:] = np.diff(u, axis=-1) / dt
    # vx vanishes on both lines in the whole space; here the PML's reflections (the source 5 cells from one face, 20 from
    # the other) and the off-grid operators leave 1e-4 of the vz peak (measured)
    assert np.abs(r.vx).max() <= 1e-3 * np.abs(v).max()
    return [float(np.abs(r.vz[0, j] - v[j]).max() / np.abs(v[j]).max()) for j in range(2)]


def test_point_force_against_stokes_coarse():
    # 12.5 points per S wavelength at the peak (dx = 10 m, order 8). Measured 0.60% along the force and 1.04% across
    # it (the S-wave side); the error falls as dx^1.7-1.9 (test_point_force_against_stokes_converges), so 2% here is
    # the coarse grid's bound; 1% (the number) holds at dx = 5 m.
    along, across = stokes_errors(10.0)
    assert along <= 0.02 and across <= 0.02


@pytest.mark.slow
def test_point_force_against_stokes_converges():
    # dx = 10, 7.5, 5 m (order 8, Courant 0.4): measured errors 0.60 / 0.38 / 0.18 % along the force and 1.04 / 0.63 /
    # 0.27 % across it; fitted orders 1.7 and 1.9: the leapfrog's second order in time (at fixed Courant number,
    # dt ~ dx) dominates order 8 in space. The 1% holds at dx = 5 m with margin.
    dxs = np.array([10.0, 7.5, 5.0])
    errors = np.array([stokes_errors(dx) for dx in dxs])
    assert np.all(errors[-1] <= 0.01)
    for j in range(2):
        slope = np.polyfit(np.log(dxs), np.log(errors[:, j]), 1)[0]
        assert 1.5 <= slope <= 2.5, (j, errors[:, j])


def test_explosive_source_against_analytic():
    # An isotropic moment M0 s(t) radiates the potential phi = -M0 s(t - r/vp) / (4 pi rho vp^2 r) (the stress glut
    # -M0 delta_ij delta(x): rho phi'' = rho vp^2 lap phi - M0 s delta), so v_r = M0 / (rho vp^2) (A'/r + A''/vp),
    # A = s(t - r/vp) / (4 pi r); evaluated at the record's times (k - 1/2) dt by Fourier phase shifts. The radial
    # velocity along z and along x, dx = 10 m (16.7 points per P wavelength at the peak): measured 0.66% and 0.67%;
    # bound 2% as the force's coarse test (same grid, same scheme).
    r, offsets, s, dt = two_receivers(10.0, "explosive")
    dist = 150.0
    n = next_fast_len(4 * (s.size + int(dist / VP / dt)))
    w = 2.0 * np.pi * rfftfreq(n, dt)
    a = rfft(s, n) * np.exp(-1j * w * (dist / VP + 0.5 * dt)) / (4.0 * np.pi * dist)
    v = irfft((1j * w / dist + (1j * w) ** 2 / VP) * a / (RHO * VP * VP), n)[: s.size]
    for got in (r.vz[0, 0], r.vx[0, 1]):
        assert np.abs(got - v).max() <= 0.02 * np.abs(v).max()


def test_free_surface_on_axis_p_and_symmetry():
    # A vertical force on the free surface: straight below it the far-field P wave is twice the whole space's
    # (Miller & Pursey 1954: u_r = F cos(t) (k^2 - 2 sin^2 t) / (2 pi mu r F0(sin t)), 1 / (2 pi rho vp^2 r) at t = 0).
    # At 200 m (1.6 P wavelengths at the peak) the near field still adds 12% to the whole space's peak, so the
    # ratio need not be 2 exactly: measured 2.012, bound 2 +- 3% (a missing or rigid surface gives ~1 or ~0).
    # The update treats x and y alike: vx at (0, 0, +60 m) from the source equals vy at (0, +60 m, 0), and vz at the
    # two, to rounding (measured exactly equal).
    dx, D, m = 10.0, 200.0, 8
    dt = 0.4 * dx / VP
    nt = int((D / VP + 2.5 / F0) / dt)
    shape = (int(D / dx) + m, 2 * m + 1, 2 * m + 1)
    c = m * dx
    src = np.array([[[0.0, c, c]]])
    rec = np.array([[[D, c, c], [0.0, c, c + 60.0], [0.0, c + 60.0, c]]])
    amp = ricker(F0, nt, dt)[None, None]
    r = forward_elastic3d(*homogeneous(shape), dx, dt, amp, src, rec, order=8, pml_width=10, free_surface=True, precision="float64",
                          device=DEVICE)
    u = elastic_3d_force(amp[0, 0], dt, (D, 0.0, 0.0), VP, VS, RHO, (1.0, 0.0, 0.0))[0]
    ratio = np.abs(r.vz[0, 0]).max() / (np.abs(np.diff(u)).max() / dt)
    assert abs(ratio - 2.0) <= 0.06, ratio
    assert np.abs(r.vx[0, 1]).max() > 0
    assert np.abs(r.vx[0, 1] - r.vy[0, 2]).max() <= 1e-12 * np.abs(r.vx[0, 1]).max()
    assert np.abs(r.vz[0, 1] - r.vz[0, 2]).max() <= 1e-12 * np.abs(r.vz[0, 1]).max()


@pytest.mark.parametrize("order", [2, 4, 8])
def test_explosive_source_is_isotropic(order):
    # An explosive source radiates the same pressure and the same radial velocity along z, y and x (the moment's
    # three normal components and the Hicks operators of vx, vy, vz treat the axes alike): equal to rounding, at every
    # order.
    shape, dx, dt, nt = (21, 21, 21), 10.0, 1e-3, 120
    src = np.array([[[100.0, 100.0, 100.0]]])
    rec = src + np.array([[[60.0, 0.0, 0.0], [0.0, 60.0, 0.0], [0.0, 0.0, 60.0]]])
    r = forward_elastic3d(*homogeneous(shape), dx, dt, ricker(15.0, nt, dt)[None, None], src, rec, source_type="explosive",
                          order=order, pml_width=6, precision="float64", device=DEVICE)  # fmt: skip
    peak = np.abs(r.pressure).max()
    assert peak > 0 and np.abs(r.pressure[0] - r.pressure[0, :1]).max() <= 1e-12 * peak
    radial = np.stack([r.vz[0, 0], r.vy[0, 1], r.vx[0, 2]])
    assert np.abs(radial - radial[:1]).max() <= 1e-12 * np.abs(radial).max()


def test_refusals():
    shape, dx, dt, nt = (8, 8, 8), 10.0, 1e-3, 20
    vp, vs, rho = homogeneous(shape)
    amp = ricker(15.0, nt, dt)[None, None]
    src, rec = np.array([[[30.0, 30.0, 30.0]]]), np.array([[[40.0, 40.0, 40.0]]])
    kw = dict(precision="float64", pml_width=4)
    with pytest.raises(ValueError, match=r"\(nz, ny, nx\)"):
        forward_elastic3d(vp[0], vs[0], rho[0], dx, dt, amp, src, rec, **kw)
    with pytest.raises(ValueError, match="vs > vp / sqrt"):
        forward_elastic3d(vp, np.full(shape, 0.75 * VP), rho, dx, dt, amp, src, rec, **kw)
    limit = DESCRIPTION.cfl_limit(4, 3)  # 0.4949: 1 / (sqrt(3) (9/8 + 1/24))
    assert math.isclose(limit, 1.0 / (math.sqrt(3.0) * (9.0 / 8.0 + 1.0 / 24.0)))
    bad_dt = 1.01 * limit * dx / VP
    with pytest.raises(ValueError, match=f"use dt <= {limit * dx / VP:.6g}"):
        forward_elastic3d(vp, vs, rho, dx, bad_dt, amp, src, rec, **kw)
    with pytest.raises(ValueError, match="source_components must be"):
        forward_elastic3d(vp, vs, rho, dx, dt, amp, src, rec, source_components=np.ones((1, 1, 2)), **kw)
    with pytest.raises(ValueError, match="needs source_components"):
        forward_elastic3d(vp, vs, rho, dx, dt, amp, src, rec, source_type="moment", **kw)
    with pytest.raises(ValueError, match="receiver_locations must be"):
        forward_elastic3d(vp, vs, rho, dx, dt, amp, src, rec[:, :, :2], **kw)
    with pytest.raises(ValueError, match="outside the grid"):
        forward_elastic3d(vp, vs, rho, dx, dt, amp, src, rec + 100.0, **kw)
    # the kernels' flat int32 indices: 1302^3 padded cells (2.2e9 > 2^31) per shot and field are refused before any allocation
    with pytest.raises(ValueError, match="int32 flat indices; use fewer shots"):
        Elastic3D((1290, 1290, 1290), dx, dt, 4, 1, 4, 1e-3, 15.0, VP)
