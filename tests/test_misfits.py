"""Values of every misfit in adseismic.solve.misfits.MISFITS against hand-computed cases, and their adjoint sources
against central differences of those values.

The gradient tests (test_adjoint.py, test_gradient.py, test_elastic.py) check that a misfit's value and its adjoint
source agree with each other through the wave equation; they cannot see a misfit whose value and derivative are both
wrong in the same way (e.g. the correlation no longer normalised by the observed norm). These tests pin the values
to the definitions in the module's docstring. Each test says which deliberate bug it catches. Host NumPy only
(float64): the whole module runs in well under a second.
"""

import numpy as np
import pytest

from adseismic.solve.misfits import MISFITS, misfit
from adseismic.wavelets import ricker

# the misfits with value tests below; a misfit added to MISFITS without one fails test_every_misfit_has_a_value_test
VALUE_TESTED = {"l2", "correlation", "traveltime", "envelope"}


def test_every_misfit_has_a_value_test():
    assert set(MISFITS) == VALUE_TESTED


def trace(x):
    """One trace as (n_shots, n_receivers, nt) = (1, 1, nt)."""
    return np.asarray(x, dtype=float)[None, None]


# --- l2: J = 1/2 sum (d - o)^2 dt, dJ/dd = (d - o) dt ---------------------------------------------------------


def test_l2_value_and_adjoint_source():
    # d - o = (1, 2, 2) and (0, -1, 0) in two shots: sum r^2 = 9 + 1 = 10, dt = 0.5 -> J = 1/2 * 10 * 0.5 = 2.5.
    # Catches: dt dropped (J 5.0), the 1/2 dropped (5.0), one shot left out (2.25 or 0.25), dt applied twice to the
    # adjoint source or not at all ((0.25, 0.5, 0.5) or (1, 2, 2)), its sign flipped.
    d = np.array([[[1.0, 2.0, 3.0]], [[4.0, 4.0, 4.0]]])
    o = np.array([[[0.0, 0.0, 1.0]], [[4.0, 5.0, 4.0]]])
    J, g = misfit("l2", d, o, 0.5)
    assert J == pytest.approx(2.5, rel=1e-15)
    np.testing.assert_allclose(g, [[[0.5, 1.0, 1.0]], [[0.0, -0.5, 0.0]]], rtol=1e-15)
    assert misfit("l2", o, o, 0.5)[0] == 0.0


# --- correlation: J = sum over traces of 1 - <d, o> / (|d| |o|) -----------------------------------------------


def test_correlation_known_pairs():
    # Trace 1: d = (1, 0), o = (1, 1): <d, o> = 1, |d| = 1, |o| = sqrt(2): J = 1 - 1/sqrt(2) = 0.29289...
    # Trace 2: d = (0, 2), o = (3, 0) (orthogonal): J = 1. Trace 3: d = -o: J = 2. Sum 4 - 1/sqrt(2).
    # Catches the correlation no longer normalised by the observed norm (<d, o> / |d|: trace 1 gives 1 - 1 = 0,
    # trace 3 gives 1 + |o| = 1 + 5 = 6, sum 7) and by the synthetic norm (trace 1: 1 - 1/sqrt(2) still, trace 3:
    # 1 + 25 / 5 = 6).
    d = np.array([[[1.0, 0.0], [0.0, 2.0], [-3.0, 4.0]]])
    o = np.array([[[1.0, 1.0], [3.0, 0.0], [3.0, -4.0]]])
    J, _ = misfit("correlation", d, o, 1e-3)
    assert J == pytest.approx(4.0 - 1.0 / np.sqrt(2.0), rel=1e-14)
    # its adjoint source on trace 1: -(o / (|d| |o|) - c d / |d|^2), c = 1/sqrt(2): -((1, 1) - (1, 0)) / sqrt(2)
    _, g = misfit("correlation", d[:, :1], o[:, :1], 1e-3)
    np.testing.assert_allclose(g[0, 0], [0.0, -1.0 / np.sqrt(2.0)], rtol=1e-14, atol=1e-16)


@pytest.mark.parametrize("scale", [1e-9, 0.37, 3.0, 2.5e6])
def test_correlation_ignores_the_amplitudes_of_both(scale):
    # A scaled synthetic or a scaled observed changes nothing: the normalised zero-lag correlation of two shifted Rickers
    # (a value of about 0.25, computed here from its definition). Catches the observed (or synthetic) normalisation
    # dropped: the value then scales with |o| (or |d|), off by factors of 1e-9 .. 2.5e6 from the unscaled one.
    dt, nt = 1e-3, 300
    d = ricker(15.0, nt, dt, delay=0.1)
    o = ricker(15.0, nt, dt, delay=0.11) + 0.3 * ricker(25.0, nt, dt, delay=0.2)
    expected = 1.0 - float(d @ o) / (np.linalg.norm(d) * np.linalg.norm(o))
    assert 0.1 < expected < 1.9
    for dd, oo in ((d, o), (scale * d, o), (d, scale * o), (scale * d, scale * o)):
        assert misfit("correlation", trace(dd), trace(oo), dt)[0] == pytest.approx(expected, rel=1e-12)
    assert misfit("correlation", trace(scale * o), trace(o), dt)[0] == pytest.approx(0.0, abs=1e-14)


# --- traveltime: J = 1/2 sum over traces of tau^2, tau the lag (s) maximising the cross-correlation -----------


@pytest.mark.parametrize("shift", [7.3e-3, -4.6e-3, 12.25e-3])
def test_traveltime_recovers_a_known_shift(shift):
    # d = o delayed by `shift` (not a whole number of samples, dt = 1 ms): J = 1/2 shift^2 (s^2), the lag found on the
    # band-limited correlation (measured relative error 7e-16 .. 4e-15). Catches: the lag left at the best whole sample
    # (7 ms for 7.3 ms: J 8% low), the lag in samples instead of seconds (J 1e6 too large), the 1/2 dropped.
    # Along d's time derivative d' (d + eps d' = d delayed by shift - eps) the lag falls by eps, so
    # <dJ/dd, d'> = -shift (the sign of the adjoint source and its scale; measured 3e-15 relative).
    dt, nt, f, t0 = 1e-3, 400, 15.0, 0.15
    o = ricker(f, nt, dt, delay=t0)
    d = ricker(f, nt, dt, delay=t0 + shift)
    J, g = misfit("traveltime", trace(d), trace(o), dt)
    assert J == pytest.approx(0.5 * shift**2, rel=1e-9)
    tau = np.arange(nt) * dt - (t0 + shift)
    a = (np.pi * f * tau) ** 2
    d_prime = 2.0 * np.pi**2 * f**2 * tau * np.exp(-a) * (2.0 * a - 3.0)  # d/dt of the Ricker
    assert float(np.sum(g * d_prime)) == pytest.approx(-shift, rel=1e-9)


def test_traveltime_sums_over_traces_and_shots():
    # two shots of two receivers, shifts 3.5, -2, 0 and 6.25 ms: J = 1/2 sum shift^2
    dt, nt = 1e-3, 400
    shifts = np.array([[3.5e-3, -2e-3], [0.0, 6.25e-3]])
    o = np.broadcast_to(ricker(12.0, nt, dt, delay=0.15), (2, 2, nt))
    d = np.array([[ricker(12.0, nt, dt, delay=0.15 + s) for s in row] for row in shifts])
    assert misfit("traveltime", d, o, dt)[0] == pytest.approx(0.5 * float(np.sum(shifts**2)), rel=1e-9)


# --- envelope: J = 1/2 sum (E(d) - E(o))^2 dt, E(x) = sqrt(x^2 + H(x)^2 + eps^2) ------------------------------


def test_envelope_of_cosines_is_their_amplitude():
    # A cosine of a whole number of periods over the record has the discrete Hilbert transform A sin: its envelope is
    # its amplitude A at every sample, whatever its phase. d = 3 cos(.. + 0.3), o = 1.25 cos(.. - 1.1):
    # J = 1/2 (3 - 1.25)^2 N dt = 0.784 (eps = 1e-6 * 1.25 shifts it by 4e-13 relative). The same amplitude at
    # another phase: J = 0. Catches: the envelope without its Hilbert part (E = |x|: J 0.732 and the phase test
    # 0.139), dt dropped (J / dt), the 1/2 dropped, H's sign or scale wrong (E no longer constant).
    n_samples, dt = 256, 2e-3
    phase = 2.0 * np.pi * 5.0 * np.arange(n_samples) / n_samples
    d, o = 3.0 * np.cos(phase + 0.3), 1.25 * np.cos(phase - 1.1)
    J, _ = misfit("envelope", trace(d), trace(o), dt)
    assert J == pytest.approx(0.5 * (3.0 - 1.25) ** 2 * n_samples * dt, rel=1e-11)
    J_phase, g = misfit("envelope", trace(1.25 * np.cos(phase + 0.7)), trace(o), dt)
    assert J_phase == pytest.approx(0.0, abs=1e-20) and np.abs(g).max() < 1e-12


# --- adjoint sources against the values -------------------------------------------------------------------------


@pytest.mark.parametrize("name", MISFITS)
def test_adjoint_source_is_the_values_derivative(name):
    # <dJ/dd, v> against central differences of J along a random v (float64, step 1e-6 of the data); measured
    # 1e-10 (l2, traveltime) and 2e-8 (correlation, envelope: the O(h^2) truncation), target 1e-6. Catches an adjoint
    # source of the wrong sign or scale (O(1) errors; the value tests above fix the value itself).
    dt, nt = 1e-3, 300
    rng = np.random.default_rng(3)
    o = np.array([[ricker(15.0, nt, dt, delay=0.1), 0.5 * ricker(12.0, nt, dt, delay=0.14)]])
    d = np.array([[1.3 * ricker(15.0, nt, dt, delay=0.1043), 0.4 * ricker(12.0, nt, dt, delay=0.1345)]])
    d = d + 0.02 * rng.standard_normal(d.shape)
    v = rng.standard_normal(d.shape)
    h = 1e-6
    J, g = misfit(name, d, o, dt)
    fd = (misfit(name, d + h * v, o, dt)[0] - misfit(name, d - h * v, o, dt)[0]) / (2.0 * h)
    assert J > 0
    assert float(np.sum(g * v)) == pytest.approx(fd, rel=1e-6)


def test_bad_name_and_shapes_are_refused():
    with pytest.raises(ValueError, match="is not one of"):
        misfit("l1", np.zeros((1, 1, 4)), np.zeros((1, 1, 4)), 1e-3)
    with pytest.raises(ValueError, match="observed data has shape"):
        misfit("l2", np.zeros((1, 1, 4)), np.zeros((1, 2, 4)), 1e-3)
