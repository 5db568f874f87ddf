"""A kernel is identified by everything its code is generated from (issue 29).

Warp evaluates wp.static(A[m + 1]) in `for m in range(...)` only when it generates the code, but hashes and names a
kernel of module="unique" when it is declared, before the Warp funcs it calls are generated: a weight read so in a func
was left out of the module's hash, and a second build with other weights, in the same process or in another one sharing
the kernel cache (WARP_CACHE_PATH), was given the kernel compiled for the first weights. Here the acoustic
helper is built twice, once with numerics' second-derivative weights of order 8 and once with one weight changed by 1%
(the same builder, a patched table), and one step of a unit impulse must give each table's own stencil, in one process
and in two processes sharing one cache directory.
"""

import functools
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import warp as wp

from adseismic.kernels.acoustic import propagator
from adseismic.kernels.elastic import propagator as elastic
from adseismic.kernels.numerics import SECOND_DERIVATIVE, STAGGERED_DERIVATIVE

ORDER, N, COURANT2 = 8, 9, 0.01  # grid of N x N cells, (v dt / dx)^2


def weights(scale: float) -> tuple:
    """numerics' order-8 second-derivative weights with a_2 times `scale`."""
    a = list(SECOND_DERIVATIVE[ORDER])
    a[2] *= scale
    return tuple(a)


def impulse_step(scale: float) -> np.ndarray:
    """u after one CPU step of the acoustic helper (built afresh with weights(scale), no PML, v = 1, dt / dx = 0.1) from
    a unit impulse at the centre of an N x N grid (u_prev = 0): the (z, x) padded field."""
    table = {**SECOND_DERIVATIVE, ORDER: weights(scale)}
    saved = propagator.SECOND_DERIVATIVE, propagator.build
    propagator.SECOND_DERIVATIVE, propagator.build = table, functools.lru_cache(maxsize=None)(propagator.build.__wrapped__)
    try:
        p = propagator.Acoustic((N, N), 1.0, 0.1, ORDER, 1, 0, 1e-3, 10.0, 1.0, dtype=wp.float32, device="cpu")
    finally:
        propagator.SECOND_DERIVATIVE, propagator.build = saved
    st = p.new_state()
    u = st.u.numpy()
    u[0, p.padded[0] // 2, 0, p.padded[2] // 2] = 1.0
    st.u.assign(u)
    out = p.step(st, wp.array(np.ones(p.padded), dtype=wp.float32, device="cpu"))
    return out.u.numpy()[0, :, 0, :]


def expected(scale: float) -> np.ndarray:
    """The stencil of weights(scale) around the centre: 2 u - u_prev + C^2 (a_0 + a_0) at the centre, C^2 a_k at k cells
    from it along z and x."""
    a = weights(scale)
    R = ORDER // 2
    e = np.zeros((N + 2 * R, N + 2 * R))
    c = e.shape[0] // 2
    e[c, c] = 2.0 + 2.0 * COURANT2 * a[0]
    for k in range(1, R + 1):
        e[c + k, c] = e[c - k, c] = e[c, c + k] = e[c, c - k] = COURANT2 * a[k]
    return e


def check(u_real: np.ndarray, u_patched: np.ndarray):
    np.testing.assert_allclose(u_real, expected(1.0), rtol=1e-5, atol=1e-9)
    assert not np.allclose(u_patched, u_real, rtol=1e-5, atol=1e-9), "the kernel built for the patched weights is the one built for the real ones"
    np.testing.assert_allclose(u_patched, expected(1.01), rtol=1e-5, atol=1e-9)


def test_patched_weights_give_their_own_kernel_in_one_process():
    check(impulse_step(1.0), impulse_step(1.01))


@pytest.mark.slow
def test_patched_weights_give_their_own_kernel_in_a_process_sharing_the_cache(tmp_path):
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "kernel-cache"))

    def run(scale):
        done = subprocess.run([sys.executable, __file__, str(scale)], env=env, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr[-3000:]
        return np.array(json.loads(done.stdout.strip().splitlines()[-1]))

    u_real = run(1.0)  # compiles into the empty cache
    u_patched = run(1.01)  # another process, the cache now warm
    check(u_real, u_patched)


@pytest.mark.parametrize("order, dtype", [(8, wp.float32), (8, wp.float64), (4, wp.float64)])
def test_elastic_kernels_are_named_by_their_weights(order, dtype):
    """An elastic kernel changes its name, and so its Warp module, when a staggered weight it reads changes, also one of
    the order-6 weights that serve order 8 next to a free surface, and also by less than float32's resolution (Warp
    hashes float constants as float32); the kernels that read no weight keep theirs, and the same weights give the same
    names, under which the kernel cache serves them. Declaring kernels compiles nothing."""

    def names(table):
        saved = elastic.STAGGERED_DERIVATIVE
        elastic.STAGGERED_DERIVATIVE = table
        try:
            k = elastic.build.__wrapped__(order, dtype, True)
        finally:
            elastic.STAGGERED_DERIVATIVE = saved
        tiled = dict(zip(("velocity_update", "stress_update"), k.updates(2, 2, False)))
        return {n: v.key for n, v in (vars(k) | tiled).items() if isinstance(v, wp.Kernel)}

    real = names(STAGGERED_DERIVATIVE)
    assert len(real) > 10 and real == names(dict(STAGGERED_DERIVATIVE))
    stress = {"stress", "stress_adjoint", "stress_update"}  # their z-derivatives next to the surface: orders 2, 4, 6
    updates = stress | {"stress_transpose", "velocity", "velocity_adjoint", "velocity_transpose", "velocity_update"}
    for m in (order, 6):
        for factor in (1.01, 1.0 + 1e-12):
            c = list(STAGGERED_DERIVATIVE[m])
            c[-1] *= factor
            other = names({**STAGGERED_DERIVATIVE, m: tuple(c)})
            changed = {n for n in real if other[n] != real[n]}
            if m == order:
                assert changed == updates, (m, factor)
            elif order == 8:
                assert changed == stress, (m, factor)
            else:  # order 4 never generates the order-6 stencil; a name may still change (a spare compile, never a stale one)
                assert changed <= stress, (m, factor)


def module_hashes(compile_first: bool) -> dict:
    """{kernel: its module's hash} of the 2D acoustic helper's GPU-layout kernels on the CPU, after compiling the step's
    module (compile_first) or compiling nothing."""
    p = propagator.Acoustic((12, 16), 10.0, 1e-3, 4, 1, 4, 1e-3, 10.0, 2000.0, dtype=wp.float32, device="cpu")
    core = p.core_kernel()
    if compile_first:
        wp.load_module(core.module, device="cpu")
    kernels = {"step_core": core, "pre_step": p.k.pre_step, "adjoint_core": p.adjoint_kernel(), "post_adjoint": p.k.post_adjoint}
    return {n: f"{k.module.name} {k.module.hash_module().hex()}" for n, k in kernels.items()}


@pytest.mark.slow
def test_a_module_is_named_and_hashed_alike_whatever_this_process_compiled_before(tmp_path):
    """The adjoint's module calls Warp funcs that the step's module calls too. Warp hashes a func with the wp.static()
    values it evaluated while generating code for it, so compiling the step (into an empty cache) used to change the
    adjoint's module name and hash: the next run, which compiles nothing, looked for another module and compiled the
    adjoint again (a warm cache that was not: 2-4 s on a GPU, issue 22). Two processes, one compiling the step first
    into an empty cache, the other nothing, must name and hash every module alike."""
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "kernel-cache"))

    def run(mode):
        done = subprocess.run([sys.executable, __file__, mode], env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-3000:]
        return json.loads(done.stdout.strip().splitlines()[-1])

    compiled, declared = run("compile"), run("declare")
    assert compiled == declared


if __name__ == "__main__":  # the second process of the tests above: prints impulse_step(scale) or module_hashes as JSON
    wp.config.quiet = True
    mode = sys.argv[1]
    print(json.dumps(module_hashes(mode == "compile") if mode in ("compile", "declare") else impulse_step(float(mode)).tolist()))
