"""The Born operator and the two images made with it: reverse-time migration and least-squares RTM.

The Born operator B of a background velocity v0 maps a velocity perturbation dm (nz, [ny,] nx) m/s to the
linearised receiver data B dm (n_shots, n_receivers, nt): the exact derivative of the simulated data along dm
(adseismic.solve.acoustic.born). Its adjoint B^T d is the gradient of <F(v0), d> with respect to the velocity
(adseismic.solve.acoustic.gradient with the misfit d(syn) -> (<syn, d>, d)), so that <B dm, d> = <dm, B^T d> holds to
the rounding of the simulation's precision (tests/test_imaging.py checks it in float64).

- RTM: image = B^T r with r = d_obs - F(v0), the observed data less the data simulated in the background (the
  direct wave and whatever the smooth background sends back), optionally filtered by -laplacian and divided by the
  source illumination I = sum over time and shots of u0^2 plus epsilon x max(I);
- LSRTM: dm minimising ||B dm - r||^2 by conjugate gradients on the normal equations (CGLS, Hestenes-Stiefel /
  Paige-Saunders form), with the right preconditioner W = mask / sqrt(I / max(I) + epsilon): B W x = r is solved for
  x and dm = W x; CGLS lowers ||B dm - r|| at every iteration (in exact arithmetic).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import laplace

from adseismic.solve.acoustic import born, gradient

log = logging.getLogger(__name__)


@dataclass
class BornOperator:
    """The Born operator of the acoustic wave equation about a background model.

    background: v0 (nz, [ny,] nx) m/s on a grid of spacing dx (m), axis order (z, [y,] x); dt (s);
    source_amplitudes (n_shots, n_src, nt); source_locations, receiver_locations (n_shots, n, ndim) m relative to
    grid node 0; options: the keyword arguments of adseismic.solve.acoustic.forward (order, pml_width,
    pml_reflection, free_surface, device, precision, ...)."""

    background: np.ndarray
    dx: float
    dt: float
    source_amplitudes: np.ndarray
    source_locations: np.ndarray
    receiver_locations: np.ndarray
    options: dict = field(default_factory=dict)

    def _args(self):
        return (self.dx, self.dt, self.source_amplitudes, self.source_locations, self.receiver_locations)

    def apply(self, dm: np.ndarray) -> np.ndarray:
        """B dm: the linearised data (n_shots, n_receivers, nt) of the perturbation dm (model shape, m/s)."""
        return born(self.background, dm, *self._args(), **self.options)

    def adjoint(self, data: np.ndarray, illumination: bool = False):
        """B^T data for data (n_shots, n_receivers, nt): (image (model shape), illumination or None)."""
        return self._adjoint(lambda syn: np.asarray(data, float), illumination)[:2]

    def migrate(self, observed: np.ndarray, illumination: bool = False):
        """(B^T r, illumination or None, r) for the reflection data r = observed - F(v0) (n_shots, n_receivers,
        nt), F(v0) simulated in the same run as the adjoint."""
        observed = np.asarray(observed, float)
        return self._adjoint(lambda syn: observed - syn, illumination)

    def _adjoint(self, data_of: Callable, illumination: bool):
        """B^T d with d = data_of(background synthetics): the gradient of <F(v), d> at v0 (d held fixed)."""
        kept = {}

        def misfit(syn):
            kept["d"] = data_of(syn)
            return float(np.vdot(syn, kept["d"])), kept["d"]

        g = gradient(self.background, *self._args(), misfit=misfit, illumination=illumination, **self.options)
        return np.asarray(g.velocity, float), g.illumination, kept["d"]


@dataclass
class ImageResult:
    """An image on the background's grid (nz, [ny,] nx), axis order (z, [y,] x).

    image: rtm: B^T r after the optional -laplacian and illumination division (relative amplitudes: (data
    units)^2 per (m/s), per m^2 more with the Laplacian); lsrtm: the velocity perturbation dm (m/s) that best explains
    the reflection data. raw: B^T r before any filter (rtm) or the first CG direction's image (lsrtm).
    illumination: sum over time and shots of the background wavefield squared (source illumination; units of
    u^2), or None. residual_norms: ||r_k|| of the data residual (data units), k = 0 before any update (rtm: only
    ||r_0||). residual: the reflection data r_0 = d_obs - F(v0) (n_shots, n_receivers, nt)."""

    method: str
    image: np.ndarray
    raw: np.ndarray
    illumination: np.ndarray | None
    residual_norms: list
    residual: np.ndarray | None


def stabilised(illumination: np.ndarray, epsilon: float) -> np.ndarray:
    """I / max(I) + epsilon: the illumination normalised by its maximum, kept >= epsilon."""
    return illumination / illumination.max() + epsilon


def rtm(op: BornOperator, observed: np.ndarray, *, mask: np.ndarray | None = None, illumination: bool = True,
        epsilon: float = 0.001, laplacian: bool = False) -> ImageResult:
    """Reverse-time migration of the observed data (n_shots, n_receivers, nt) in op's background: one background
    forward and adjoint simulation of every shot. mask (model shape, weights in [0, 1]) multiplies the image;
    illumination: divide by I / max(I) + epsilon; laplacian: apply -laplacian (per m^2) first."""
    raw, illum, r = op.migrate(observed, illumination=illumination)
    image = rtm_filter(raw, op.dx, mask=mask, illumination=illum if illumination else None, epsilon=epsilon,
                       laplacian=laplacian)
    return ImageResult("rtm", image, raw, illum, [float(np.linalg.norm(r))], r)


def rtm_filter(raw: np.ndarray, dx: float, *, mask=None, illumination=None, epsilon: float = 0.001,
               laplacian: bool = False) -> np.ndarray:
    """The RTM image from B^T r (model shape; grid spacing dx m): -laplacian (per m^2) when laplacian, divided by
    I / max(I) + epsilon when the illumination I (model shape) is given, times the mask (weights in [0, 1])."""
    image = -laplace(raw, mode="nearest") / dx**2 if laplacian else raw.copy()
    if illumination is not None:
        image /= stabilised(illumination, epsilon)
    return image if mask is None else image * mask


def lsrtm(op: BornOperator, observed: np.ndarray, iterations: int, *, mask: np.ndarray | None = None,
          illumination: bool = True, epsilon: float = 0.001, callback: Callable | None = None) -> ImageResult:
    """Least-squares RTM: the perturbation dm (m/s) minimising ||B dm - r||^2, r = observed - F(v0), by
    `iterations` of CGLS on B W (W: the mask over sqrt(I / max(I) + epsilon) when illumination, else the mask).
    callback(k, residual_norm) after each iteration k = 1..iterations. Costs 1 + iterations adjoint and iterations
    Born simulations of every shot."""
    g, illum, r = op.migrate(observed, illumination=illumination)
    r0 = r
    w = np.ones_like(g) if mask is None else np.asarray(mask, float)
    if illumination:
        w = w / np.sqrt(stabilised(illum, epsilon))
    x = np.zeros_like(g)
    s = w * g  # (B W)^T r
    p = s.copy()
    gamma = float(np.vdot(s, s))
    norms = [float(np.linalg.norm(r))]
    log.info("lsrtm iteration 0: |r| = %.6g (the reflection data)", norms[0])
    for k in range(1, iterations + 1):
        if gamma == 0.0:  # the residual is orthogonal to the range: nothing left to fit
            log.info("lsrtm: the normal-equation residual is zero after %d iterations; stopping", k - 1)
            break
        q = op.apply(w * p)
        alpha = gamma / float(np.vdot(q, q))
        x += alpha * p
        r = r - alpha * q
        norms.append(float(np.linalg.norm(r)))
        log.info("lsrtm iteration %d: |r| = %.6g (%.4g of the start)", k, norms[-1], norms[-1] / norms[0])
        if callback is not None:
            callback(k, norms[-1])
        if k == iterations:
            break
        s = w * op.adjoint(r)[0]
        gamma, gamma_old = float(np.vdot(s, s)), gamma
        p = s + (gamma / gamma_old) * p
    return ImageResult("lsrtm", w * x, w * g, illum, norms, r0)
