"""Problems shared by several test modules (not collected: no test_ prefix)."""

import functools

import numpy as np
from scipy.ndimage import gaussian_filter

import adseismic.solve.elastic as E
from adseismic.wavelets import ricker

from .conftest import DEVICE

DX, DT, NT = 10.0, 1e-3, 200
P_SCALE = 1e-6  # pressure (Pa) scaled to be commensurate with velocities (m/s) in an elastic misfit


@functools.lru_cache(maxsize=None)
def elastic_problem(free_surface: bool, source_type: str):
    """A smooth random 24 x 30 elastic model, one source, six receivers, float64: (parameters {vp, vs, rho,
    source_amplitudes, source_components, source_locations}, receiver locations, the observed ElasticResult of a
    model 3% off in vp and vs, the keyword arguments of forward_elastic / gradient_elastic)."""
    rng = np.random.default_rng(0)
    shape = (24, 30)
    vp = gaussian_filter(2400 + 300 * rng.random(shape), 2)
    vs = gaussian_filter(1200 + 200 * rng.random(shape), 2)
    rho = gaussian_filter(2000 + 300 * rng.random(shape), 2)
    s = ricker(15.0, NT, DT)[None, None]
    src = np.array([[[75.3, 141.7]]])
    rec = np.array([[[5.0 if free_surface else 30.0, x] for x in np.linspace(20.0, 270.0, 6)]])
    comp = np.array([[[0.7, -0.4]]]) if source_type == "force" else np.array([[[1.0, 0.5, -0.3]]])
    kw = dict(precision="float64", pml_velocity=2800.0, pml_frequency=15.0, pml_width=6, free_surface=free_surface,
              source_type=source_type, device=DEVICE)  # fmt: skip
    observed = E.forward_elastic(vp * 1.03, vs * 0.97, rho, DX, DT, s, src, rec, source_components=comp, **kw)
    base = dict(vp=vp, vs=vs, rho=rho, source_amplitudes=s, source_components=comp, source_locations=src)
    return base, rec, observed, kw
