"""2D isotropic elastic physics, velocity-stress on a staggered grid (Virieux 1986; Levander 1988).

Fields vx, vz (m/s), sxx, szz, sxz (Pa); parameters vp, vs (m/s) and rho (kg/m^3); force, moment-tensor
and explosive sources; stress-imaging free surface. The kernels, their layouts and launch helper are in
propagator.py; DESCRIPTION is what the solver and the planner read.
"""

from adseismic.kernels.common import Description
from adseismic.kernels.elastic.propagator import (
    ADJOINT_LAYOUT,
    ADJOINT_LAYOUTS,
    CORE_LAYOUT,
    LAYOUTS,
    MATERIALS,
    PSI,
    AdjointLayout,
    Elastic,
    Layout,
    State,
    build,
    shear_ratio,
)
from adseismic.kernels.numerics import ORDERS, STAGGERED_DERIVATIVE, staggered_cfl_limit, staggered_dispersion_error

DESCRIPTION = Description(
    name="elastic",
    fields={"vx": "m/s", "vz": "m/s", "sxx": "Pa", "szz": "Pa", "sxz": "Pa"},
    parameters={"vp": "m/s", "vs": "m/s", "rho": "kg/m^3"},
    ndims=(2,),
    orders=ORDERS,
    stencil=STAGGERED_DERIVATIVE,
    injection="Kaiser-windowed sinc (Hicks 2002) at each field's staggered position, folded across a free surface",
    courant_speed="vp",
    cfl_limit=staggered_cfl_limit,
    dispersion_error=staggered_dispersion_error,
)

__all__ = ["DESCRIPTION", "ADJOINT_LAYOUT", "ADJOINT_LAYOUTS", "CORE_LAYOUT", "LAYOUTS", "MATERIALS", "PSI", "AdjointLayout",
           "Elastic", "Layout", "State", "build", "shear_ratio"]
