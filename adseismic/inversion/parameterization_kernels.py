"""Warp kernels mapping model parameters to velocity (m/s); differentiated by wp.Tape with the
wave-equation kernels, so the chain rule of a parameterisation costs no hand-written code.

Velocity arrays are (nz, ny, nx) (ny = 1 in 2D), as in kernels/acoustic/.
"""

import functools

import warp as wp


@functools.lru_cache(maxsize=None)
def build(dtype, mlp_inputs: int = 3, mlp_hidden: int = 8):
    """Kernels for one dtype: reciprocal, exponential, multilinear interpolation and a small MLP."""
    arr3 = wp.array3d(dtype=dtype)
    H, D = mlp_hidden, mlp_inputs

    @wp.kernel(module="unique")
    def reciprocal(p: arr3, v: arr3):
        # v = 1 / p (slowness -> velocity)
        i, j, k = wp.tid()
        v[i, j, k] = dtype(1.0) / p[i, j, k]

    @wp.kernel(module="unique")
    def exponential(m: arr3, v: arr3):
        # v = exp(m) (log-velocity -> velocity)
        i, j, k = wp.tid()
        v[i, j, k] = wp.exp(m[i, j, k])

    @wp.func
    def frac(i: int, n_fine: int, n_coarse: int) -> dtype:
        return dtype(i) * dtype(n_coarse - 1) / dtype(wp.max(n_fine - 1, 1))

    @wp.kernel(module="unique")
    def trilinear(c: arr3, v: arr3):
        # v = multilinear interpolation of a coarse node grid spanning the same extent (smooth basis)
        i, j, k = wp.tid()
        fz = frac(i, v.shape[0], c.shape[0])
        fy = frac(j, v.shape[1], c.shape[1])
        fx = frac(k, v.shape[2], c.shape[2])
        z0 = wp.min(int(fz), c.shape[0] - 1)
        y0 = wp.min(int(fy), c.shape[1] - 1)
        x0 = wp.min(int(fx), c.shape[2] - 1)
        z1 = wp.min(z0 + 1, c.shape[0] - 1)
        y1 = wp.min(y0 + 1, c.shape[1] - 1)
        x1 = wp.min(x0 + 1, c.shape[2] - 1)
        az = fz - dtype(z0)
        ay = fy - dtype(y0)
        ax = fx - dtype(x0)
        one = dtype(1.0)
        c0 = (c[z0, y0, x0] * (one - ax) + c[z0, y0, x1] * ax) * (one - ay) + (c[z0, y1, x0] * (one - ax) + c[z0, y1, x1] * ax) * ay
        c1 = (c[z1, y0, x0] * (one - ax) + c[z1, y0, x1] * ax) * (one - ay) + (c[z1, y1, x0] * (one - ax) + c[z1, y1, x1] * ax) * ay
        v[i, j, k] = c0 * (one - az) + c1 * az

    @wp.kernel(module="unique")
    def mlp(theta: wp.array(dtype=dtype), v: arr3, v0: dtype, scale: dtype):
        # v = v0 + scale * w2 . tanh(W1 tanh(W0 x + b0) + b1) + b2, x = (z, x, y) scaled to [-1, 1];
        # theta = [W0 (H x D), b0 (H), W1 (H x H), b1 (H), w2 (H), b2 (1)]
        i, j, k = wp.tid()
        x = wp.vector(length=3, dtype=dtype)
        x[0] = dtype(2.0) * frac(i, v.shape[0], 2) - dtype(1.0)
        x[1] = dtype(2.0) * frac(k, v.shape[2], 2) - dtype(1.0)
        x[2] = dtype(2.0) * frac(j, v.shape[1], 2) - dtype(1.0)
        h0 = wp.vector(length=H, dtype=dtype)
        for a in range(wp.static(H)):
            acc = theta[wp.static(H * D) + a]
            for b in range(wp.static(D)):
                acc += theta[a * wp.static(D) + b] * x[b]
            h0[a] = wp.tanh(acc)
        out = theta[wp.static(H * D + H + H * H + H + H)]
        for a in range(wp.static(H)):
            acc = theta[wp.static(H * D + H + H * H) + a]
            for b in range(wp.static(H)):
                acc += theta[wp.static(H * D + H) + a * wp.static(H) + b] * h0[b]
            out += theta[wp.static(H * D + H + H * H + H) + a] * wp.tanh(acc)
        v[i, j, k] = v0 + scale * out

    return reciprocal, exponential, trilinear, mlp
