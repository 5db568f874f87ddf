"""Constant-density acoustic physics, 2D and 3D: (1/v^2) d2u/dt2 - laplacian(u) = s(t) delta(x - x_s).

Second order in time (leapfrog), order 2, 4 or 8 in space, convolutional PML on every absorbing side,
optional pressure-release free surface at z = 0. The kernels and their launch helper are in
propagator.py; DESCRIPTION is what the solver and the planner read.
"""

from adseismic.kernels.acoustic.propagator import Acoustic, State, build, cpml_profile
from adseismic.kernels.common import Description
from adseismic.kernels.numerics import ORDERS, SECOND_DERIVATIVE, cfl_limit, dispersion_error

DESCRIPTION = Description(
    name="acoustic",
    fields={"u": "source units (2D) or source units x m (3D)"},
    parameters={"velocity": "m/s"},
    ndims=(2, 3),
    orders=ORDERS,
    stencil=SECOND_DERIVATIVE,
    injection="Kaiser-windowed sinc (Hicks 2002), half-width HICKS_RADIUS cells per axis; the same operator records",
    courant_speed="velocity",
    cfl_limit=cfl_limit,
    dispersion_error=dispersion_error,
)

__all__ = ["DESCRIPTION", "Acoustic", "State", "build", "cpml_profile"]
