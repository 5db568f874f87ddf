"""2D pseudo-acoustic VTI physics (Duveneck & Bakker 2011), velocity-stress on a staggered grid.

Fields vx, vz (m/s), sH, sV (Pa); parameters vp (vertical P speed, m/s), Thomsen epsilon and delta (dimensionless,
stable iff epsilon >= delta) and rho (kg/m^3); explosive sources; pressure -(sH + sV)/2 and vx, vz receivers; CPML,
optional pressure-release free surface. The kernels and their launch helper are in propagator.py; DESCRIPTION is what
the solver and the planner read: the time step is set by the horizontal P speed vh = vp sqrt(1 + 2 epsilon), the
fastest of the medium (the scheme's limit is the elastic staggered one: docs/vti.md).
"""

from adseismic.kernels.common import Description
from adseismic.kernels.numerics import ORDERS, STAGGERED_DERIVATIVE, staggered_cfl_limit, staggered_dispersion_error
from adseismic.kernels.vti.propagator import MATERIALS, OPERATOR, PSI, VTI, State, build, thomsen_check

DESCRIPTION = Description(
    name="vti",
    fields={"vx": "m/s", "vz": "m/s", "sh": "Pa", "sv": "Pa"},
    parameters={"vp": "m/s", "epsilon": "1", "delta": "1", "rho": "kg/m^3"},
    ndims=(2,),
    orders=ORDERS,
    stencil=STAGGERED_DERIVATIVE,
    injection="Kaiser-windowed sinc (Hicks 2002) at each field's staggered position, folded onto the images above a free surface",
    courant_speed="vh",  # vp sqrt(1 + 2 epsilon), the horizontal P speed
    cfl_limit=staggered_cfl_limit,
    dispersion_error=staggered_dispersion_error,
)

__all__ = ["DESCRIPTION", "MATERIALS", "OPERATOR", "PSI", "VTI", "State", "build", "thomsen_check"]
