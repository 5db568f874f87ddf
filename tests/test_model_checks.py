"""The staggered physics' model checks (common.checked_models): the device check (fast_check: value ranges of the
models and of derived arrays) clears only valid models and finds the CFL speed the host finds; what it does not
clear, the NumPy check decides with its own message. Models given on the device keep the traces there. On the CPU
the setups run the NumPy check only; these tests run the device kernels and decisions on DEVICE (cpu, or
ADSEISMIC_TEST_DEVICE=cuda:0)."""

import re

import numpy as np
import pytest
import warp as wp

from adseismic.accel.reductions import value_ranges
from adseismic.kernels.viscoacoustic import fit_mechanisms
from adseismic.solve import acoustic_vd, common, elastic3d, viscoacoustic, vti

from .conftest import DEVICE

MECH = fit_mechanisms(10.0, 80.0, 3)
F_REF = 30.0


def models(physics, shape=(12, 9), seed=0):
    """Valid float64 models of a physics, in its MODELS order."""
    rng = np.random.default_rng(seed)
    vp = 1500.0 + 3000.0 * rng.random(shape)
    rho = 1000.0 + 1500.0 * rng.random(shape)
    if physics == "acoustic_vd":
        return [vp, rho]
    if physics == "viscoacoustic":
        return [vp, 5.0 + 200.0 * rng.random(shape), rho]
    if physics == "vti":
        eps = 0.3 * rng.random(shape)
        return [vp, eps, eps * rng.random(shape), rho]
    return [vp, vp * (0.2 + 0.5 * rng.random(shape)), rho]


CHECKS = {"acoustic_vd": (acoustic_vd.MODEL_CHECKS, acoustic_vd.MODELS),
          "viscoacoustic": (viscoacoustic.model_checks(MECH, F_REF), viscoacoustic.MODELS),
          "vti": (vti.MODEL_CHECKS, vti.MODELS), "elastic3d": (elastic3d.MODEL_CHECKS, elastic3d.MODELS)}  # fmt: skip


def on_device(arrays, dtype=wp.float32):
    return [wp.array(np.asarray(a, dtype=wp.dtype_to_numpy(dtype)), dtype=dtype, device=DEVICE) for a in arrays]


def test_value_ranges_equal_numpy_for_mixed_dtypes():
    a = np.array([3.0, -2.0, np.nan, 7.0, np.inf, 1.0], dtype=np.float32)
    b = np.linspace(-1.0, 2.0, 1027)
    b[5] = -np.inf
    ranges = value_ranges([wp.array(a, device=DEVICE), wp.array(b, dtype=wp.float64, device=DEVICE)])
    assert ranges == [(-2.0, 7.0, 2), (-1.0, 2.0, 1)]


def test_unrelaxed_velocity_kernel_equals_numpy():
    rng = np.random.default_rng(1)
    q = np.concatenate([rng.uniform(2.0, 500.0, 1000), [np.inf, 1.0, 0.5, 1e6]])
    vp = 1500.0 + 3000.0 * rng.random(q.size)
    for dtype in (wp.float32, wp.float64):
        a = on_device([vp, q], dtype)
        coef = wp.array(viscoacoustic.unrelaxed_coefficients(MECH, F_REF), dtype=wp.float64, device=DEVICE)
        u = common.elementwise(viscoacoustic.unrelaxed_velocity_kernel(dtype), a, coef).numpy()
        host = viscoacoustic.unrelaxed_velocity(a[0].numpy(), a[1].numpy(), MECH, F_REF)
        # both in float64, the complex power as |m|^-1/2 cos(arg m / 2): a few roundings apart (measured 4e-16)
        np.testing.assert_allclose(u, host, rtol=1e-12, atol=0)
        assert u[-4] == pytest.approx(vp[-4], rel=1e-7)  # q = inf: lossless, u = vp (vp rounded to dtype)
    bad = on_device([[2000.0] * 4, [0.0, -3.0, -np.inf, np.nan]])
    u = common.elementwise(viscoacoustic.unrelaxed_velocity_kernel(wp.float32), bad, coef).numpy()
    assert np.isnan(u).all()  # q not > 0: NaN, which the device check counts as bad


@pytest.mark.parametrize("physics", list(CHECKS))
def test_fast_check_clears_valid_models_with_the_host_speed(physics):
    checks, names = CHECKS[physics]
    host = [np.asarray(a, dtype=np.float32).astype(float) for a in models(physics)]
    vmax = common.fast_check(on_device(host), checks, exact=True)
    want = float(checks.speed(*host).max())
    # the device's speed in float64 of the same float32 values: vp itself, or sqrt / pow a few roundings from NumPy's
    assert vmax == pytest.approx(want, rel=1e-14, abs=0)
    if physics in ("acoustic_vd", "elastic3d"):
        assert vmax == want
    arrays, got = common.checked_models(dict(zip(names, on_device(host))), checks, wp.float32, DEVICE)
    assert got == pytest.approx(want, rel=1e-14, abs=0)
    assert all(np.array_equal(a.numpy(), h.astype(np.float32)) for a, h in zip(arrays, host))


BAD = [("acoustic_vd", 0, (3, 4), 0.0, "vp has 1 non-finite or out-of-range values"),
       ("acoustic_vd", 1, (0, 0), np.nan, "rho has 1 non-finite"),
       ("viscoacoustic", 1, (2, 5), -np.inf, "q has 1 non-finite or non-positive values (first"),
       ("viscoacoustic", 1, (2, 5), np.nan, "q has 1 non-finite or non-positive values (first"),
       ("vti", 2, (1, 1), 0.9, "epsilon < delta"),
       ("vti", 2, (1, 1), -0.6, "delta <= -0.5"),
       ("elastic3d", 1, (4, 4), 1e4, "vs > vp / sqrt(2) at index (4, 4)"),
       ("elastic3d", 1, (4, 4), -1.0, "vs has 1 non-finite")]  # fmt: skip


@pytest.mark.parametrize("physics, k, index, value, message", BAD)
def test_bad_models_are_not_cleared_and_keep_their_message(physics, k, index, value, message):
    checks, names = CHECKS[physics]
    m = models(physics)
    m[k][index] = value
    assert common.fast_check(on_device(m), checks, exact=False) is None
    said = []
    for device in ("cpu", DEVICE):  # the CPU's NumPy check and the device's fallback to it: one message
        with pytest.raises(ValueError, match=re.escape(message)) as err:
            common.checked_models(dict(zip(names, m)), checks, wp.float32, device)
        said.append(str(err.value))
    assert said[0] == said[1] and f"{index}" in said[0]


def test_unclear_models_fall_back_to_the_numpy_check():
    # q = inf is cleared on the device (lossless); epsilon == delta is cleared only where the device holds the
    # values unrounded, else the NumPy check passes it (rounding keeps order but may make two values equal)
    checks, names = CHECKS["viscoacoustic"]
    m = models("viscoacoustic")
    m[1][:3] = np.inf
    assert common.fast_check(on_device(m), checks, exact=False) == pytest.approx(float(checks.speed(*m).max()), rel=1e-6)
    checks, names = CHECKS["vti"]
    m = models("vti")
    m[2] = m[1].copy()
    assert common.fast_check(on_device(m), checks, exact=True) is not None
    assert common.fast_check(on_device(m), checks, exact=False) is None
    _, vmax = common.checked_models(dict(zip(names, m)), checks, wp.float32, DEVICE)
    # the host speed of the float64 models or the device's of their float32 copies: float32 rounding apart
    assert vmax == pytest.approx(float(vti.horizontal_speed(m[0], m[1]).max()), rel=2e-7)


def test_upload_keeps_or_copies_warp_arrays_of_dtype_and_rounds_the_rest():
    vp = wp.array(np.full((3, 4), 2000.0, dtype=np.float32), device=DEVICE)
    rho = np.full((3, 4), 1000.1)
    arrays, host, exact = common.upload_models({"vp": vp, "rho": rho}, wp.float32, DEVICE, requires_grad=("vp",))
    assert host[0] is None and arrays[0].ptr != vp.ptr and arrays[0].requires_grad and not arrays[1].requires_grad
    assert host[1] is not None and host[1].dtype == np.float64 and not exact  # 1000.1 is not a float32
    arrays, _, exact = common.upload_models({"vp": vp, "rho": rho.astype(np.float32)}, wp.float32, DEVICE)
    assert exact and arrays[0] is vp  # not differentiated: read where it is


SETUPS = {"acoustic_vd": acoustic_vd.setup_acoustic_vd, "viscoacoustic": viscoacoustic.setup_viscoacoustic,
          "vti": vti.setup_vti, "elastic3d": elastic3d.setup_elastic3d}  # fmt: skip


@pytest.mark.parametrize("physics", list(SETUPS))
def test_setup_on_the_device_finds_the_cpu_speed(physics, monkeypatch):
    # the setup's vmax (the CFL check's and the PML's speed) from float32 Warp models: on a GPU the device's, equal
    # to the CPU's NumPy one (vp itself) or a few float64 roundings apart (sqrt, pow); on the CPU the same path
    shape = (6, 5, 4) if physics == "elastic3d" else (6, 5)
    m = on_device([np.asarray(a, dtype=np.float32) for a in models(physics, shape)])
    ndim = len(shape)
    amp, loc = np.ones((1, 1, 8)), np.full((1, 1, ndim), 10.0)
    speeds = []
    monkeypatch.setattr(common, "check_courant", lambda physics, order, ndim, vmax, dx, dt: speeds.append(vmax))
    for device in ("cpu", DEVICE):
        su = SETUPS[physics](*m, 10.0, 1e-4, amp, loc, loc, pml_width=4, device=device)
        assert all(a.device == wp.get_device(device) for a in su.models)
    assert speeds[1] == pytest.approx(speeds[0], rel=1e-14, abs=0)
    assert physics not in ("acoustic_vd", "elastic3d") or speeds[1] == speeds[0]


FORWARDS = {"acoustic_vd": acoustic_vd.forward_acoustic_vd, "viscoacoustic": viscoacoustic.forward_viscoacoustic,
            "vti": vti.forward_vti, "elastic3d": elastic3d.forward_elastic3d}  # fmt: skip


@pytest.mark.parametrize("physics", list(FORWARDS))
def test_models_on_the_device_keep_the_traces_there(physics):
    # forward_elastic's convention over the staggered family: Warp models give Warp traces on their device (no copy
    # to the host), of the values NumPy models of the same float32 values give (equal on the CPU; on a GPU to the
    # order of float32 atomic adds)
    shape = (14, 12, 12) if physics == "elastic3d" else (24, 20)
    ndim = len(shape)
    m = [np.asarray(a, dtype=np.float32).astype(float) for a in models(physics, shape)]
    t = np.arange(60) * 2e-4
    amp = ((1 - 2 * (np.pi * 25 * (t - 0.04)) ** 2) * np.exp(-((np.pi * 25 * (t - 0.04)) ** 2)))[None, None]
    src, rec = np.full((1, 1, ndim), 40.0), np.array([[[30.0] * (ndim - 1) + [50.0], [60.0] * (ndim - 1) + [70.0]]])
    kw = dict(pml_width=4, pml_velocity=4600.0, pml_frequency=25.0, device=DEVICE)
    if physics == "viscoacoustic":
        kw.update(f_ref=F_REF, q_band=(10.0, 80.0))
    host = FORWARDS[physics](*m, 10.0, 2e-4, amp, src, rec, **kw)
    dev = FORWARDS[physics](*on_device(m), 10.0, 2e-4, amp, src, rec, **kw)
    names = ("vx", "vz", "pressure") + (("vy",) if ndim == 3 else ())
    limit = 0.0 if DEVICE == "cpu" else 1e-5
    for name in names:
        ref, got = getattr(host, name), getattr(dev, name)
        assert isinstance(ref, np.ndarray) and isinstance(got, wp.array) and got.device == wp.get_device(DEVICE), name
        assert np.abs(ref).max() > 0 and np.abs(got.numpy() - ref).max() <= limit * np.abs(ref).max(), name


def test_acoustic_vd_gradient_of_device_models_stays_there():
    # the 2D hand-written gradient's side of that convention: Warp models give the vp and rho gradients and the
    # synthetic data as Warp arrays on their device, equal to the NumPy models' (the "l2" misfit formed on the device
    # in both) to float32 rounding on the CPU (the models' gradients meet in other orders) and atomic adds' on a GPU
    m = [np.asarray(a, dtype=np.float32).astype(float) for a in models("acoustic_vd", (24, 20))]
    t = np.arange(60) * 2e-4
    amp = ((1 - 2 * (np.pi * 25 * (t - 0.04)) ** 2) * np.exp(-((np.pi * 25 * (t - 0.04)) ** 2)))[None, None]
    src, rec = np.full((1, 1, 2), 40.0), np.array([[[30.0, 50.0], [60.0, 70.0]]])
    kw = dict(pml_width=4, pml_velocity=4600.0, pml_frequency=25.0, device=DEVICE)
    obs = {"pressure": 0.5 * np.asarray(acoustic_vd.forward_acoustic_vd(*m, 10.0, 2e-4, amp, src, rec, **kw).pressure, dtype=float)}
    host = acoustic_vd.gradient_acoustic_vd(*m, 10.0, 2e-4, amp, src, rec, obs, **kw)
    dev = acoustic_vd.gradient_acoustic_vd(*on_device(m), 10.0, 2e-4, amp, src, rec, obs, **kw)
    limit = 1e-6 if DEVICE == "cpu" else 1e-5
    assert dev.loss == pytest.approx(host.loss, rel=limit)
    for name in ("vp", "rho"):
        ref, got = getattr(host, name), getattr(dev, name)
        assert isinstance(ref, np.ndarray) and isinstance(got, wp.array) and got.device == wp.get_device(DEVICE), name
        assert np.abs(ref).max() > 0 and np.abs(got.numpy() - ref).max() <= limit * np.abs(ref).max(), name
    ref, got = host.synthetic["pressure"], dev.synthetic["pressure"]
    assert isinstance(got, wp.array) and np.abs(got.numpy() - ref).max() <= limit * np.abs(ref).max()
