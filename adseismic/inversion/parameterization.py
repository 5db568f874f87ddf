"""Model parameterisations for gradient(): velocity as a differentiable function of parameters theta.

Each class has `parameters` (numpy array theta), `initial_velocity()` (velocity for theta, numpy,
(nz, [ny,] nx) m/s) and `velocity(theta, dtype, device)` that launches Warp kernels
(kernels/parameterization.py) producing the (nz, ny, nx) velocity; gradient() records it on its tape,
so dJ/dtheta comes out of the same reverse sweep.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from adseismic.inversion import parameterization_kernels as K


def _shape3(shape):
    return tuple(shape) if len(shape) == 3 else (shape[0], 1, shape[1])


def _launch(kernel_index, shape, dtype, device, *inputs, **build_kw):
    v = wp.zeros(_shape3(shape), dtype=dtype, device=device, requires_grad=True)
    wp.launch(K.build(dtype, **build_kw)[kernel_index], dim=v.shape, inputs=[*inputs[:1], v, *inputs[1:]], device=device)
    return v


def _on_cpu(param):
    """Evaluate a parameterisation for its own parameters, in float64 on the CPU (numpy result)."""
    wp.init()
    return param.velocity(wp.array(param.parameters, dtype=wp.float64, device="cpu"), wp.float64, "cpu").numpy().reshape(param.shape)


class _Elementwise:
    kernel_index = None

    def __init__(self, velocity):
        self.shape = np.shape(velocity)
        self.parameters = self.encode(np.asarray(velocity, dtype=float))

    def _3d(self, x):
        return x[:, None, :] if x.ndim == 2 else x

    def initial_velocity(self):
        return self.decode(self.parameters)

    def velocity(self, theta, dtype, device):
        return _launch(self.kernel_index, self.shape, dtype, device, theta)

    def encode(self, v):
        return self._3d(self.to_theta(v))

    def decode(self, theta):
        return self.to_v(np.asarray(theta)).reshape(self.shape)


class Slowness(_Elementwise):
    """theta = 1 / v (s/m), shape of the velocity model (with a singleton y axis in 2D)."""

    kernel_index = 0
    to_theta = staticmethod(lambda v: 1.0 / v)
    to_v = staticmethod(lambda p: 1.0 / p)


class LogVelocity(_Elementwise):
    """theta = ln(v / (1 m/s)): scale-free, and keeps v > 0 under any update."""

    kernel_index = 1
    to_theta = staticmethod(np.log)
    to_v = staticmethod(np.exp)


class SmoothBasis:
    """Velocity = multilinear interpolation of a coarse node grid (coarse_shape nodes spanning the
    model); theta: coarse node velocities (m/s), (cz, cy, cx) with cy = 1 in 2D."""

    def __init__(self, shape, coarse_shape, initial):
        self.shape = tuple(shape)
        self.parameters = np.broadcast_to(np.asarray(initial, float), _shape3(coarse_shape)).copy()

    def velocity(self, theta, dtype, device):
        return _launch(2, self.shape, dtype, device, theta)

    def initial_velocity(self):
        return _on_cpu(self)


class MLP:
    """A small neural network v(x) = v0 + scale * f_theta(x) over scaled cell coordinates, two tanh
    layers of `hidden` units; theta: all weights and biases, flat (random init, seed). zero_output: the output
    layer's weights and bias start at 0, so that the start model is the constant v0 (FWI's start model)."""

    def __init__(self, shape, v0: float, scale: float, hidden: int = 8, seed: int = 0, zero_output: bool = False):
        self.shape, self.v0, self.scale, self.hidden = tuple(shape), float(v0), float(scale), int(hidden)
        d, h = 3, self.hidden
        rng = np.random.default_rng(seed)
        sizes = [h * d, h, h * h, h, h, 1]
        self.parameters = np.concatenate([rng.standard_normal(n) / np.sqrt(max(n // h, 1)) for n in sizes])
        if zero_output:
            self.parameters[-(h + 1):] = 0.0

    def velocity(self, theta, dtype, device):
        return _launch(3, self.shape, dtype, device, theta, dtype(self.v0), dtype(self.scale), mlp_hidden=self.hidden)

    def initial_velocity(self):
        return _on_cpu(self)
