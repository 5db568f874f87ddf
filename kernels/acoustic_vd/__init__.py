"""Variable-density acoustic physics in 2D and 3D: pressure-velocity on the standard staggered grid, CPML, optional
pressure-release free surface, explosive (pressure) sources.

Fields vx, [vy,] vz (m/s), p (Pa); parameters vp (m/s), rho (kg/m^3), arrays (nz, [ny,] nx). The kernels and their
launch helper are in propagator.py; DESCRIPTION is what the solver and the planner read. The CFL limit is the
staggered scheme's, 1 / (sqrt(ndim) sum |c_m|): 0.707 / 0.606 / 0.548 in 2D, 0.577 / 0.495 / 0.448 in 3D for orders
2 / 4 / 8.
"""

from adseismic.kernels.acoustic_vd.propagator import MATERIALS, PSI, VELOCITIES, AcousticVD, Materials, State, build
from adseismic.kernels.common import Description
from adseismic.kernels.numerics import ORDERS, STAGGERED_DERIVATIVE, staggered_cfl_limit, staggered_dispersion_error

DESCRIPTION = Description(
    name="acoustic_vd",
    fields={"vx": "m/s", "vy": "m/s (3D)", "vz": "m/s", "p": "Pa"},
    parameters={"vp": "m/s", "rho": "kg/m^3"},
    ndims=(2, 3),
    orders=ORDERS,
    stencil=STAGGERED_DERIVATIVE,
    injection="Kaiser-windowed sinc (Hicks 2002) at each field's staggered position, folded across a free surface",
    courant_speed="vp",
    cfl_limit=staggered_cfl_limit,
    dispersion_error=staggered_dispersion_error,
)

__all__ = ["DESCRIPTION", "MATERIALS", "PSI", "VELOCITIES", "AcousticVD", "Materials", "State", "build"]
