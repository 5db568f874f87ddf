"""CPU and CUDA run the same kernels: traces and gradients agree (skipped where no GPU is present)."""

import numpy as np
import pytest
import warp as wp

from adseismic.solve.acoustic import forward, gradient
from adseismic.solve.common import init_warp
from adseismic.wavelets import ricker

init_warp()
pytestmark = pytest.mark.skipif(not wp.get_cuda_device_count(), reason="no CUDA device")


# float32: the source-position gradient sums ~10^4 atomic contributions whose order and rounding
# (sin, exp on each device) differ; measured 2.0e-5 of the largest component (H200 vs CPU), and
# the float32 dot-product target is 1e-4.
@pytest.mark.parametrize("precision, tol", [("float64", 1e-12), ("float32", 1e-4)])
@pytest.mark.parametrize("free_surface", [False, True])
def test_cpu_and_cuda_agree(precision, tol, free_surface):
    rng = np.random.default_rng(0)
    v = 2000 + 300 * rng.random((40, 50))
    nt = 300
    s = ricker(15.0, nt, 1e-3)[None, None].repeat(2, axis=0)
    src = np.array([[[55.3, 101.7]], [[150.2, 300.9]]])
    rec = np.array([[[20.0, x] for x in np.linspace(10.0, 480.0, 7)]] * 2)
    obs = np.zeros((2, 7, nt))
    runs = {}
    for dev in ("cpu", "cuda:0"):
        kw = dict(precision=precision, free_surface=free_surface, device=dev, pml_width=10)
        d = forward(v, 10.0, 1e-3, s, src, rec, **kw).receiver_amplitudes
        g = gradient(v, 10.0, 1e-3, s, src, rec, obs, wrt=("velocity", "source_locations"), **kw)
        runs[dev] = (d, g.velocity, g.source_locations)
    for a, b in zip(runs["cpu"], runs["cuda:0"]):
        assert np.abs(a - b).max() <= tol * np.abs(a).max()


@pytest.mark.parametrize("n", [1, 3, 4, 1027, 1_000_003])
def test_gpu_reductions_equal_numpy(n):
    # the blow-up monitor and value_range read 4-vectors and the remainder separately: every length must
    # give NumPy's extrema and count of non-finite values, wherever the largest value and the NaNs fall
    from adseismic.accel.reductions import field_stats, value_range

    rng = np.random.default_rng(n)
    a = rng.standard_normal(n).astype(np.float32)
    a[-1] = 7.5  # the largest |value|, in the remainder when n % 4 != 0
    lo, hi, bad = value_range(wp.array(a, device="cuda:0"))
    assert (lo, hi, bad) == (float(a.min()), float(a.max()), 0)
    a[0] = np.nan
    a[n // 2] = -np.inf if n > 1 else np.nan
    stats = wp.zeros(2, dtype=wp.float32, device="cuda:0")
    field_stats([wp.array(a, device="cuda:0")], stats)
    finite = a[np.isfinite(a)]
    assert stats.numpy().tolist() == [float(np.abs(finite).max(initial=0.0)), float(n - finite.size)]
