"""2D visco-acoustic physics: pressure-velocity on a staggered grid with L standard linear solids (constant Q over
a band; memory variables), variable density, CPML, optional pressure-release free surface.

Fields vx, vz (m/s), p (Pa); parameters vp (m/s, the phase velocity at a reference frequency), q (quality factor)
and rho (kg/m^3); explosive (pressure) sources. The kernels and their launch helper are in propagator.py, the
mechanisms' fit in relaxation.py; DESCRIPTION is what the solver and the planner read. The CFL limit is the
staggered scheme's for the unrelaxed (fastest, w -> infinity) velocity sqrt(M_U / rho) = vp sqrt(1 + sum y_l)
Re(m(w_ref)^(-1/2)): 1.5% above vp at Q = 50, 7.4% at Q = 10 (band 3-25 Hz, f_ref 10 Hz).
"""

from adseismic.kernels.common import Description
from adseismic.kernels.numerics import ORDERS, STAGGERED_DERIVATIVE, staggered_cfl_limit, staggered_dispersion_error
from adseismic.kernels.viscoacoustic.propagator import MATERIALS, PSI, State, Viscoacoustic, build
from adseismic.kernels.viscoacoustic.relaxation import Mechanisms, fit_mechanisms

DESCRIPTION = Description(
    name="viscoacoustic",
    fields={"vx": "m/s", "vz": "m/s", "p": "Pa", "r": "Pa/s (one per mechanism)"},
    parameters={"vp": "m/s (phase velocity at f_ref)", "q": "1 (quality factor)", "rho": "kg/m^3"},
    ndims=(2,),
    orders=ORDERS,
    stencil=STAGGERED_DERIVATIVE,
    injection="Kaiser-windowed sinc (Hicks 2002) at each field's staggered position, folded across a free surface",
    courant_speed="unrelaxed vp",
    cfl_limit=staggered_cfl_limit,
    dispersion_error=staggered_dispersion_error,
)

__all__ = ["DESCRIPTION", "MATERIALS", "PSI", "Mechanisms", "State", "Viscoacoustic", "build", "fit_mechanisms"]
