"""Visco-acoustic physics with constant Q (issue 26 item 2; kernels/viscoacoustic/, adseismic.solve.viscoacoustic):
(a) the fitted Q over the band, (b) a homogeneous medium against the frequency-domain analytic solution with the same
mechanisms, (c) the lossless limit against acoustic_vd (the elastic solver with vs = 0), (d) gradients in vp, q, rho
where q = inf and in float32 (the dot-product, Taylor and checkpoint tests are the shared ones, tests/test_adjoint.py),
and the input checks. All float64."""

import functools

import numpy as np
import pytest
from scipy.fft import irfft, next_fast_len, rfft, rfftfreq
from scipy.special import hankel2

from adseismic.kernels.viscoacoustic import Viscoacoustic, fit_mechanisms
from adseismic.solve import viscoacoustic
from adseismic.solve.elastic import forward_elastic
from adseismic.solve.viscoacoustic import COMPONENTS, unrelaxed_velocity
from adseismic.wavelets import make_wavelet

from .conftest import DEVICE

forward_viscoacoustic = functools.partial(viscoacoustic.forward_viscoacoustic, device=DEVICE)
gradient_viscoacoustic = functools.partial(viscoacoustic.gradient_viscoacoustic, device=DEVICE)

BAND = (3.0, 25.0)  # Hz: a 10 Hz Ricker's band (-20 dB near 2.2 f_peak)
F_PEAK = 10.0

# --------------------------------------------------------------------------- (a) the fitted Q


@pytest.mark.parametrize("mechanisms, band, q, limit", [
    (3, BAND, 1000.0, 0.05), (3, BAND, 50.0, 0.05), (3, BAND, 20.0, 0.05), (3, BAND, 10.0, 0.05),
    (5, (1.0, 100.0), 20.0, 0.05),  # two decades: 4.3% (6.4% at Q = 5: more mechanisms for lower Q)
])  # fmt: skip
def test_fitted_q_is_flat_over_the_band(mechanisms, band, q, limit):
    # The mechanisms' exact Q(f) = Re M / Im M over 500 log-spaced frequencies of the band against the target: the
    # issue's 5%. Measured (L = 3, 3-25 Hz): 2.6% (Q = 1000), 2.8% (50), 3.1% (20), 3.7% (10); L = 5 over 1-100 Hz:
    # 4.3% (Q = 20). The ripple of the low-loss fit sets the high-Q figure; the series in 1/Q
    # (relaxation.SERIES_TERMS) keeps low Q from drifting (2 terms: 5.9% at Q = 10).
    mech = fit_mechanisms(*band, mechanisms)
    f = np.geomspace(*band, 500)
    err = np.abs(mech.quality(f, q) / q - 1.0).max()
    assert err <= limit, f"max |Q(f)/Q - 1| = {err:.4f}"
    assert np.all(mech.y(q) > 0)  # positive weights: every mechanism dissipates (a negative one would add energy)


# --------------------------------------------------------------------------- (b) against the analytic solution


def analytic_pressure(S, dt, r, vp, q, rho, mech, f_ref):
    """p(r, t_k) (Pa) of the explosive line source S(t) (N m/m, (nt,)) at distance r (m) in a homogeneous medium of the
    same mechanisms: P(w) = (i/4) k^2 S(w) H0^(2)(k r), k = w / c(w), c(w) = sqrt(M(w) / rho) (vp the phase velocity at
    f_ref), numpy's e^{+iwt} convention (the solution of lap p + k^2 p = k^2 S delta). Evaluated at w - i eps on a long,
    zero-padded FFT (Kosloff & Kosloff 1983, as adseismic.analytic.acoustic_2d): exp(-eps T) = 1e-10, no wrap-around.
    rho does not enter (p of a moment source is independent of it)."""
    nt = S.size
    n = next_fast_len(8 * nt)
    eps = np.log(10.0) * 10.0 / (n * dt)
    t = np.arange(n) * dt
    w = 2.0 * np.pi * rfftfreq(n, dt) - 1j * eps
    y = mech.y(q)

    def m(w):
        wt = w[:, None] * mech.tau
        return 1.0 + (y * 1j * wt / (1.0 + 1j * wt)).sum(-1)

    c = vp * np.real(m(np.array([2.0 * np.pi * f_ref]))[0] ** -0.5) * np.sqrt(m(w))
    k = w / c
    P = 0.25j * k**2 * hankel2(0, k * r)
    P[-1] = P[-1].real  # irfft reads the real part of the Nyquist bin
    return irfft(rfft(S * np.exp(-eps * t[:nt]), n) * P, n)[:nt] * np.exp(eps * t[:nt])


def homogeneous_errors(q, wavelengths, depth, dx=10.0, dt=5e-4, order=8, vp=2000.0, rho=1000.0, free_surface=False):
    """Amplitude and phase errors of the simulated pressure against analytic_pressure, `wavelengths` wavelengths
    (at F_PEAK) from the source along x, source and receiver `depth` (m) below the top (a free surface, the analytic
    solution then less that of the image source at -depth) and above the bottom PML: the largest
    | |P_num / P_ana| - 1 | and |arg(P_num / P_ana)| (radians) over 5-20 Hz (the Ricker's band within -6 dB).
    Returns (amplitude error, phase error)."""
    x = wavelengths * vp / F_PEAK
    nz, nx = int(round(2 * depth / dx)) + 1, int(round((x + 300.0) / dx)) + 1
    nt = int((3.5 / F_PEAK + x / vp) / dt)
    S = 1e6 * make_wavelet("ricker", nt, dt, peak_frequency=F_PEAK)
    model = {k: np.full((nz, nx), v) for k, v in (("vp", vp), ("q", q), ("rho", rho))}
    out = forward_viscoacoustic(model["vp"], model["q"], model["rho"], dx, dt, S[None, None], np.array([[[depth, 150.0]]]),
                                np.array([[[depth, 150.0 + x]]]), q_band=BAND, f_ref=F_PEAK, order=order, precision="float64",
                                free_surface=free_surface)  # fmt: skip
    mech = fit_mechanisms(*BAND, 3)
    ana = analytic_pressure(S, dt, x, vp, q, rho, mech, F_PEAK)
    if free_surface:
        ana -= analytic_pressure(S, dt, np.hypot(x, 2.0 * depth), vp, q, rho, mech, F_PEAK)
    n = 4 * nt
    f = rfftfreq(n, dt)
    sel = (f >= 5.0) & (f <= 20.0)
    ratio = rfft(out.pressure[0, 0], n)[sel] / rfft(ana, n)[sel]
    return float(np.abs(np.abs(ratio) - 1.0).max()), float(np.abs(np.angle(ratio)).max())


# The "amplitude and phase within 1%": amplitude 1% of the analytic one, phase 1% of a cycle (2 pi / 100 rad),
# at every frequency of 5-20 Hz. Q = inf (the lossless limit) on the same grid is the scheme's own error: the
# attenuated run's error is no larger, so the mechanisms add none of their own (measured, order 8, dx 10 m = 20
# points per wavelength at 10 Hz, dt 0.5 ms: docs/viscoacoustic.md).
PHASE_LIMIT = 2.0 * np.pi / 100.0


def test_homogeneous_against_analytic_5_wavelengths():
    # measured: amplitude 1.1e-4 (Q = 30) / 2.4e-4 (Q = inf), phase 1.04e-2 / 1.02e-2 rad (the scheme's time
    # dispersion at 20 Hz), ~10 s
    errors = {q: homogeneous_errors(q, 5.0, 300.0) for q in (30.0, np.inf)}
    for q, (amp, phase) in errors.items():
        assert amp <= 0.01 and phase <= PHASE_LIMIT, (q, amp, phase)
    assert errors[30.0][0] <= errors[np.inf][0] + 1e-3 and errors[30.0][1] <= errors[np.inf][1] + 1e-3, errors


@pytest.mark.slow
def test_homogeneous_against_analytic_20_wavelengths():
    # 4000 m, the PML 600 m from the line (its reflections arrive after the pulse); measured: docs/viscoacoustic.md
    errors = {q: homogeneous_errors(q, 20.0, 600.0) for q in (30.0, np.inf)}
    for q, (amp, phase) in errors.items():
        assert amp <= 0.01 and phase <= PHASE_LIMIT, (q, amp, phase)


def test_free_surface_against_image_source():
    # p = 0 at z = 0 (odd image of p, even of vz): source and receiver 100 m deep, 3 wavelengths apart, Q = 30; the
    # analytic solution is the direct wave less the image source's. Measured: docs/viscoacoustic.md
    amp, phase = homogeneous_errors(30.0, 3.0, 100.0, free_surface=True)
    assert amp <= 0.01 and phase <= PHASE_LIMIT, (amp, phase)


# --------------------------------------------------------------------------- (c) the lossless limit

NZ, NX, DX, DT, NT = 40, 50, 10.0, 1e-3, 260


def small_problem(shots=1):
    """A two-layer (vp, rho) model with a smooth Q anomaly, a Ricker of 10 Hz (N m/m), explosive sources near the
    top and four receivers."""
    vp = np.full((NZ, NX), 2000.0)
    vp[22:] = 2400.0
    rho = np.full((NZ, NX), 1800.0)
    rho[22:] = 2200.0
    zz, xx = np.mgrid[:NZ, :NX]
    q = 40.0 - 20.0 * np.exp(-((zz - 15) ** 2 + (xx - 25) ** 2) / 50.0)
    amp = 1e6 * np.broadcast_to(make_wavelet("ricker", NT, DT, peak_frequency=F_PEAK), (shots, 1, NT)).copy()
    src = np.array([[[52.0 + 10 * s, 123.0 + 40 * s]] for s in range(shots)])
    rec = np.broadcast_to(np.array([[30.0, 60.0], [30.0, 410.0], [300.0, 250.0], [150.0, 333.0]]), (shots, 4, 2)).copy()
    return dict(vp=vp, q=q, rho=rho, source_amplitudes=amp), src, rec


KW = dict(order=4, pml_width=10, precision="float64", q_band=BAND, f_ref=F_PEAK)


@pytest.mark.parametrize("free_surface", [False, True])
def test_lossless_limit_is_acoustic_vd(free_surface):
    # Q = inf is acoustic_vd's scheme (the elastic kernels with vs = 0: sxx = szz = -p, sxz = 0) term for term:
    # measured 5e-16 .. 1.8e-15 relative (p, vx, vz) without a free surface. With one, the elastic kernels shorten the
    # vertical stencils next to the surface (Levander's stress imaging) where these image p (odd) and vz (even) at full
    # order (checked against the image-source solution in test_free_surface_against_image_source): measured 5.8e-4,
    # 1.6e-3, 9.6e-4 with receivers 30 m below it. Q = 1e6: plus the attenuation and dispersion of 1/Q over ~2
    # wavelengths, measured 2.1e-6 .. 4.1e-6.
    base, src, rec = small_problem()
    ref = forward_elastic(base["vp"], 0 * base["vp"], base["rho"], DX, DT, base["source_amplitudes"], src, rec, source_type="explosive",
                          order=4, pml_width=10, pml_velocity=2400.0, pml_frequency=F_PEAK, precision="float64",
                          free_surface=free_surface)  # fmt: skip
    exact_limit = 2e-3 if free_surface else 1e-13
    for q, limit in ((np.inf, exact_limit), (1e6, exact_limit + 1e-5)):
        out = forward_viscoacoustic(base["vp"], np.full((NZ, NX), q), base["rho"], DX, DT, base["source_amplitudes"], src, rec,
                                    free_surface=free_surface, pml_velocity=2400.0, pml_frequency=F_PEAK, **KW)  # fmt: skip
        for c in COMPONENTS:
            a, b = getattr(out, c), getattr(ref, c)
            err = np.abs(a - b).max() / np.abs(b).max()
            assert err <= limit, (q, c, err)


def test_attenuation_lowers_amplitude():
    # Q = 20 against Q = inf over ~2 wavelengths: the direct pressure's peak drops (exp(-pi f r / (Q v)) ~ 0.85 at
    # 10 Hz, 400 m) and arrives a little earlier (the unrelaxed speed at frequencies above f_ref): not an
    # accuracy check (that is (b)), a sign check of the memory variables (a wrong sign grows or blows up)
    base, src, rec = small_problem()
    runs = {q: forward_viscoacoustic(base["vp"], np.full((NZ, NX), q), base["rho"], DX, DT, base["source_amplitudes"], src, rec, **KW)
            for q in (20.0, np.inf)}  # fmt: skip
    ratio = np.abs(runs[20.0].pressure[0, 1]).max() / np.abs(runs[np.inf].pressure[0, 1]).max()
    assert 0.75 < ratio < 0.95, ratio


# --------------------------------------------------------------------------- (d) gradients


def data(base, src, rec, **changes):
    a = dict(base, **changes)
    r = forward_viscoacoustic(a["vp"], a["q"], a["rho"], DX, DT, a["source_amplitudes"], src, rec, pml_velocity=2600.0,
                              pml_frequency=F_PEAK, **KW)  # fmt: skip
    return {c: getattr(r, c) for c in COMPONENTS}


def gradient(base, src, rec, misfit, observed=None, **kw):
    return gradient_viscoacoustic(base["vp"], base["q"], base["rho"], DX, DT, base["source_amplitudes"], src, rec, observed,
                                  misfit=misfit, pml_velocity=2600.0, pml_frequency=F_PEAK, **KW, **kw)  # fmt: skip


def test_lossless_cells_and_float32():
    # q = inf on half the grid (lossless there): every gradient finite, the one of q exactly 0 there; float32 against
    # float64 on the same problem: measured 4.5e-7 relative (float32's rounding over 260 steps)
    base, src, rec = small_problem()
    base = dict(base, q=np.where(np.arange(NX)[None, :] < 25, np.inf, base["q"]))
    g = gradient(base, src, rec, "l2", data(dict(base, vp=base["vp"] * 1.01), src, rec), wrt=("vp", "q", "rho"))
    assert all(np.isfinite(getattr(g, k)).all() for k in ("vp", "q", "rho"))
    assert np.all(g.q[:, :25] == 0.0) and np.abs(g.q[:, 25:]).max() > 0.0
    runs = [forward_viscoacoustic(base["vp"], base["q"], base["rho"], DX, DT, base["source_amplitudes"], src, rec,
                                  **dict(KW, precision=p)).pressure for p in ("float32", "float64")]  # fmt: skip
    assert np.abs(runs[0] - runs[1]).max() <= 1e-5 * np.abs(runs[1]).max()


# --------------------------------------------------------------------------- input checks


@pytest.mark.parametrize("change, message", [
    (dict(q=0.0), "q has"), (dict(q=-5.0), "q has"), (dict(q=np.nan), "q has"), (dict(vp=np.inf), "vp has"),
    (dict(rho=0.0), "rho has"), (dict(q_band=(20.0, 5.0)), "q_band"), (dict(mechanisms=0), "mechanisms"),
    (dict(f_ref=-1.0), "f_ref"), (dict(dt=5e-3), "unstable"),
])  # fmt: skip
def test_bad_inputs_are_refused(change, message):
    base, src, rec = small_problem()
    a = dict(base, q_band=BAND, f_ref=F_PEAK, mechanisms=3, dt=DT)
    for k in ("vp", "q", "rho"):
        if k in change:
            a[k] = np.full((NZ, NX), change[k])
    a.update({k: v for k, v in change.items() if k not in ("vp", "q", "rho")})
    with pytest.raises(ValueError, match=message):
        forward_viscoacoustic(a["vp"], a["q"], a["rho"], DX, a["dt"], a["source_amplitudes"], src, rec, q_band=a["q_band"],
                              f_ref=a["f_ref"], mechanisms=a["mechanisms"], order=4, precision="float64")  # fmt: skip


def test_too_many_cells_for_int32_indices_is_refused():
    # the field kernels index flat arrays with int32 (kernels/viscoacoustic Grid): 2 shots x 3 mechanisms x ~19000^2
    # padded cells (2.2e9 >= 2^31) must fail before any field is allocated, naming the fix
    with pytest.raises(ValueError, match="int32 flat indices.*fewer shots"):
        Viscoacoustic((19000, 19000), 10.0, 1e-3, 4, 2, fit_mechanisms(*BAND, 3), F_PEAK, 10, 1e-3, F_PEAK, 2500.0)


def test_unrelaxed_velocity_is_the_mechanisms_high_frequency_limit():
    # unrelaxed_velocity folds the mechanisms into polynomials in 1/q (Horner); it must equal the direct sum over the
    # mechanisms' weights y_l (module formula) to rounding, and vp where q = inf (lossless)
    mech = fit_mechanisms(3.0, 25.0, 3)
    q = np.array([5.0, 20.0, 100.0, 1000.0, np.inf])
    vp = np.array([1500.0, 2000.0, 2500.0, 3000.0, 3500.0])
    y = mech.y(q)
    wt = 2 * np.pi * 10.0 * mech.tau
    m_ref = 1.0 + (y * (1j * wt) / (1.0 + 1j * wt)).sum(axis=-1)
    direct = vp * np.real(m_ref**-0.5) * np.sqrt(1.0 + y.sum(axis=-1))
    np.testing.assert_allclose(unrelaxed_velocity(vp, q, mech, 10.0), direct, rtol=1e-14)
    assert unrelaxed_velocity(vp, q, mech, 10.0)[-1] == vp[-1]
    assert np.all(np.diff(unrelaxed_velocity(np.full(4, 2000.0), q[:4], mech, 10.0)) < 0)  # more loss, faster at high f


@pytest.mark.parametrize("dtype, free_surface, shape", [("float64", True, (30, 44)), ("float32", False, (33, 38))])
def test_tiled_velocity_equals_the_per_cell_kernel(dtype, free_surface, shape):
    """The untaped step's velocity half step as register tiles (kernels/viscoacoustic _velocity_tiles; four and two
    lanes here) against the taped per-cell kernels: tests.test_acoustic_vd.assert_tiles_equal_the_taped_kernels."""
    import warp as wp

    from tests.test_acoustic_vd import assert_tiles_equal_the_taped_kernels

    wdtype = getattr(wp, dtype)
    prop = Viscoacoustic(shape, 10.0, 1e-3, 4, 2, fit_mechanisms(*BAND, 3), F_PEAK, 6, 1e-3, F_PEAK, 2500.0, free_surface=free_surface,
                         dtype=wdtype, device=DEVICE)  # fmt: skip
    assert prop.tiles[2] > 0
    lz, lx = prop.padded
    rng = np.random.default_rng(5)
    vp, rho = (wp.array(2000.0 + rng.uniform(0, 500, (lz, lx)), dtype=wdtype, device=DEVICE) for _ in range(2))
    q = wp.array(30.0 + rng.uniform(0, 50, (lz, lx)), dtype=wdtype, device=DEVICE)
    assert_tiles_equal_the_taped_kernels(prop, prop.materials(vp, q, rho), dtype)
