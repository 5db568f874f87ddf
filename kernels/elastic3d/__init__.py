"""3D isotropic elastic physics: velocity-stress on the standard staggered grid (Virieux 1986; Graves 1996), CPML on
every face, optional stress-imaging free surface at z = 0, force, moment-tensor and explosive sources.

Fields vx, vy, vz (m/s), sxx, syy, szz, sxy, sxz, syz (Pa); parameters vp, vs (m/s), rho (kg/m^3), arrays (nz, ny, nx).
The kernels and their launch helper are in propagator.py; DESCRIPTION is what the solver and the planner read. The
CFL limit is the staggered scheme's in 3D, 1 / (sqrt(3) sum |c_m|): 0.577 / 0.495 / 0.448 for orders 2 / 4 / 8.
"""

from adseismic.kernels.common import Description
from adseismic.kernels.elastic3d.propagator import FIELDS, MATERIALS, POINTS, PSI, Elastic3D, State, build
from adseismic.kernels.numerics import ORDERS, STAGGERED_DERIVATIVE, staggered_cfl_limit, staggered_dispersion_error

DESCRIPTION = Description(
    name="elastic3d",
    fields={"vx": "m/s", "vy": "m/s", "vz": "m/s", "sxx": "Pa", "syy": "Pa", "szz": "Pa", "sxy": "Pa", "sxz": "Pa", "syz": "Pa"},
    parameters={"vp": "m/s", "vs": "m/s", "rho": "kg/m^3"},
    ndims=(3,),
    orders=ORDERS,
    stencil=STAGGERED_DERIVATIVE,
    injection="Kaiser-windowed sinc (Hicks 2002) at each field's staggered position, folded across a free surface",
    courant_speed="vp",
    cfl_limit=staggered_cfl_limit,
    dispersion_error=staggered_dispersion_error,
)

__all__ = ["DESCRIPTION", "FIELDS", "MATERIALS", "POINTS", "PSI", "Elastic3D", "State", "build"]
