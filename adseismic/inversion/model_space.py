"""The model space of an inversion: the map from the optimiser's vector x to the physics' parameters, with its
exact chain rule (one layer for every physics, parameterisation and representation).

x -> m -> q -> physical, arrays (nz, [ny,] nx) on the simulation grid:

- representation (x -> m): "pixels" (m = x, one block of cells per inverted quantity, in the order of `names`; with
  transform "sigmoid" instead m = (lo + (hi - lo) sigmoid(x)) / REFERENCE inside each quantity's bounds, x free:
  Deepwave's FWI recipe, which scales a cell's update by (q - lo)(hi - q) / (hi - lo), so quantities near a bound,
  such as water near v_min, move little) or
  "nn" (m = v(theta) / V_REF, v the MLP of inversion.parameterization, x = theta; its chain rule is Warp's tape
  of the same kernel, so no hand-written derivative);
- scaling (m -> q): q = m x REFERENCE[name]. Every quantity is made dimensionless by a fixed reference of its
  unit (1000 m/s for speeds, 1000 kg/m^3 for density, 1 GPa for the Lame moduli), so that the optimiser's
  numbers are O(1) whatever the unit: L-BFGS's first step, its curvature pairs and the bounds then mean the same
  for m/s, kg/m^3 and Pa (a raw vector mixing 2000 m/s and 8e9 Pa would make the Hessian's diagonal span 1e13
  and L-BFGS would move only the Pa entries). Fixed references, not the start model's means, keep the acoustic
  path's x = v / 1000 m/s (and its regularisation weights) exactly as before;
- parameterisation (q -> physical): "vp-vs-rho" (identity), "lambda-mu-rho" (vp = sqrt((lambda + 2 mu) / rho),
  vs = sqrt(mu / rho)) or, for acoustic_vd (a fluid, vs = 0 throughout), "ip-rho" (vp = ip / rho, the acoustic
  impedance ip = rho vp); physics viscoacoustic (vp, q, rho) and vti (vp, epsilon, delta, rho) invert their solver's
  parameters themselves; quantities not inverted stay at the start model's values. VTI is stable for epsilon >= delta
  only: a delta above epsilon is clamped to epsilon (with the clamp's exact (sub)gradient, as vs below). The elastic solver needs
  vs <= vp / sqrt(2) (lambda >= 0): in vp-vs-rho a box on vp and vs cannot say that, so vs is clamped to
  vp / sqrt(2) (1 - 1e-9) with the clamp's exact (sub)gradient; the nn representation clips v into its bounds
  (the plan's velocity range, so every model is stable), with zero gradient outside.

Gradients travel back the same way: dJ/dphysical (the solver's) -> dJ/dm per cell (`cells_gradient`, where the
inversion conditions and regularises it) -> dJ/dx (`x_gradient`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

V_REF = 1000.0  # m/s
# The dimensionless quantities get references of their own scale, so that L-BFGS sees O(1) numbers for them too: the
# quality factor q 100 (rock Q 30-1000: x = q / 100 is 0.3-10), Thomsen's epsilon and delta 1 (they are O(0.1) already;
# a reference of 1 keeps x = epsilon, and a 0.1 change of epsilon moves the qP speed as much as ~10% of vp does).
REFERENCE = {"vp": V_REF, "vs": V_REF, "rho": 1000.0, "lambda": 1e9, "mu": 1e9, "ip": 1e6, "q": 100.0, "epsilon": 1.0,
             "delta": 1.0}  # m/s, m/s, kg/m^3, Pa, Pa, kg/(m^2 s), dimensionless x 3
UNITS = {"vp": "m/s", "vs": "m/s", "rho": "kg/m^3", "lambda": "Pa", "mu": "Pa", "ip": "kg/(m^2 s)", "q": "(dimensionless)",
         "epsilon": "(dimensionless)", "delta": "(dimensionless)"}
# the solver's parameters per physics (acoustic_vd's vs is 0 and never inverted: kept for the elastic layout)
PHYSICS_PARAMETERS = {"acoustic": ("vp",), "elastic": ("vp", "vs", "rho"), "acoustic_vd": ("vp", "vs", "rho"),
                      "viscoacoustic": ("vp", "q", "rho"), "vti": ("vp", "epsilon", "delta", "rho")}
OWN_QUANTITIES = ("viscoacoustic", "vti")  # physics whose quantities are their solver's parameters (no parameterisation)
PARAMETERIZATIONS = {"vp-vs-rho": ("vp", "vs", "rho"), "lambda-mu-rho": ("lambda", "mu", "rho"), "ip-rho": ("ip", "rho")}
_VS_MAX = (1.0 - 1e-9) / math.sqrt(2.0)  # vs <= vp / sqrt(2): lambda >= 0 (the elastic solver's check)


def quantities_of(physical: dict, parameterization: str) -> dict:
    """The parameterisation's quantities {name: array} of physical {vp, [vs, rho]} (m/s, kg/m^3) (viscoacoustic {vp, q,
    rho} and vti {vp, epsilon, delta, rho} are their own quantities: vp-vs-rho, the identity)."""
    if parameterization == "ip-rho":
        vp, rho = (np.asarray(physical[k], float) for k in ("vp", "rho"))
        return {"ip": rho * vp, "rho": rho}
    if parameterization != "lambda-mu-rho":
        return {k: np.asarray(v, float) for k, v in physical.items()}
    vp, vs, rho = (np.asarray(physical[k], float) for k in ("vp", "vs", "rho"))
    return {"lambda": rho * (vp**2 - 2 * vs**2), "mu": rho * vs**2, "rho": rho}


@dataclass
class Point:
    """One x decoded: m {inverted name: dimensionless cells}, q {every quantity: array in its unit}, physical
    {vp, [vs, rho]} as the solver gets them, and the masks of the clamps (for the chain rule)."""

    m: dict
    q: dict
    physical: dict
    vs_clamped: np.ndarray | None = None
    clipped: np.ndarray | None = None
    delta_clamped: np.ndarray | None = None  # vti: where delta > epsilon was clamped to epsilon


class ModelSpace:
    """The inverted part of a model and its map to the physics (module docstring).

    physics "acoustic" | "elastic" | "acoustic_vd" | "viscoacoustic" | "vti"; start {vp, [vs, rho]} (nz, [ny,] nx) m/s,
    kg/m^3 (viscoacoustic {vp, q, rho}, vti {vp, epsilon, delta, rho}); names: the inverted quantities (of
    PARAMETERIZATIONS[parameterization], of PHYSICS_PARAMETERS[physics] for viscoacoustic and vti, or ("vp",) for
    acoustic); bounds {name: (min, max)} in
    the quantity's unit (each inverted name has one); network: an inversion.parameterization.MLP (acoustic vp only)
    or None for pixels."""

    def __init__(self, physics: str, start: dict, names, parameterization: str = "vp-vs-rho", bounds=None, network=None,
                 transform: str = "linear"):
        self.physics, self.parameterization, self.names = physics, parameterization, tuple(names)
        self.transform = transform
        self.shape = np.shape(start["vp"])
        self.fixed = quantities_of(start, parameterization)
        self.bounds = {k: tuple(map(float, v)) for k, v in (bounds or {}).items()}
        self.network = network
        if network is not None and (physics != "acoustic" or self.names != ("vp",)):
            raise ValueError("an nn model represents the acoustic velocity only")

    def around(self, start: dict) -> "ModelSpace":
        """The same space (physics, inverted names, parameterisation, bounds, transform; pixels) around another start
        model, e.g. on another grid; its x0() is that model's x."""
        return ModelSpace(self.physics, start, self.names, self.parameterization, self.bounds, None, self.transform)

    # ---------------------------------------------------------------- x <-> m
    @property
    def size(self) -> int:
        return self.network.parameters.size if self.network is not None else len(self.names) * math.prod(self.shape)

    def x0(self) -> np.ndarray:
        """The start x: the network's initial weights, or the start model's quantities / REFERENCE."""
        if self.network is not None:
            return np.asarray(self.network.parameters, float).ravel().copy()
        if self.transform == "sigmoid":  # logit of the start inside its box (1e-6 from a bound)
            u = {k: np.clip((self.fixed[k] - self.bounds[k][0]) / (self.bounds[k][1] - self.bounds[k][0]), 1e-6, 1 - 1e-6) for k in self.names}
            return np.concatenate([np.log(u[k] / (1 - u[k])).ravel() for k in self.names])
        return np.concatenate([(self.fixed[k] / REFERENCE[k]).ravel() for k in self.names])

    def x_bounds(self):
        """(lower, upper) arrays of x for the optimiser (pixels), or None (the network's weights are free)."""
        if self.network is not None or self.transform == "sigmoid":
            return None
        n = math.prod(self.shape)
        lo = np.concatenate([np.full(n, self.bounds[k][0] / REFERENCE[k]) for k in self.names])
        hi = np.concatenate([np.full(n, self.bounds[k][1] / REFERENCE[k]) for k in self.names])
        return lo, hi

    def _cells(self, name: str, xk):
        """m of one quantity's block of x: x itself, or its sigmoid into the bounds / REFERENCE."""
        if self.transform != "sigmoid":
            return xk
        lo, hi = self.bounds[name]
        return (lo + (hi - lo) / (1 + np.exp(-xk))) / REFERENCE[name]

    def _cells_slope(self, name: str, xk):
        """dm/dx per cell of one quantity's block."""
        if self.transform != "sigmoid":
            return 1.0
        lo, hi = self.bounds[name]
        sg = 1 / (1 + np.exp(-xk))
        return (hi - lo) * sg * (1 - sg) / REFERENCE[name]

    def _network_velocity(self, x, tape=None):
        import warp as wp

        wp.init()
        theta = wp.array(np.asarray(x, float), dtype=wp.float64, device="cpu", requires_grad=tape is not None)
        if tape is None:
            return self.network.velocity(theta, wp.float64, "cpu").numpy().reshape(self.shape), None
        with tape:
            v = self.network.velocity(theta, wp.float64, "cpu")
        return v, theta

    def point(self, x) -> Point:
        """Decode x (module docstring)."""
        x = np.asarray(x, float)
        if self.network is not None:
            v, _ = self._network_velocity(x)
            lo, hi = self.bounds["vp"]
            clipped = (v < lo) | (v > hi)
            m = {"vp": v / V_REF}
            return Point(m, {"vp": np.clip(v, lo, hi)}, {"vp": np.clip(v, lo, hi)}, clipped=clipped)
        n = math.prod(self.shape)
        m = {k: self._cells(k, x[i * n:(i + 1) * n].reshape(self.shape)) for i, k in enumerate(self.names)}
        q = dict(self.fixed)
        q.update({k: m[k] * REFERENCE[k] for k in self.names})
        if self.physics == "acoustic":
            return Point(m, q, {"vp": q["vp"]})
        if self.physics == "viscoacoustic":
            return Point(m, q, {k: q[k] for k in PHYSICS_PARAMETERS["viscoacoustic"]})
        if self.physics == "vti":  # the solver is stable for epsilon >= delta only: a delta above epsilon is clamped to it
            clamped = q["delta"] > q["epsilon"]
            return Point(m, q, {"vp": q["vp"], "epsilon": q["epsilon"], "delta": np.where(clamped, q["epsilon"], q["delta"]),
                                "rho": q["rho"]}, delta_clamped=clamped)  # fmt: skip
        if self.parameterization == "lambda-mu-rho":
            lam, mu, rho = q["lambda"], q["mu"], q["rho"]
            return Point(m, q, {"vp": np.sqrt((lam + 2 * mu) / rho), "vs": np.sqrt(mu / rho), "rho": rho})
        if self.parameterization == "ip-rho":  # a fluid: vs = 0
            return Point(m, q, {"vp": q["ip"] / q["rho"], "vs": np.zeros(self.shape), "rho": q["rho"]})
        clamped = q["vs"] > _VS_MAX * q["vp"]
        return Point(m, q, {"vp": q["vp"], "vs": np.where(clamped, _VS_MAX * q["vp"], q["vs"]), "rho": q["rho"]}, vs_clamped=clamped)

    # ---------------------------------------------------------------- chain rule
    def cells_gradient(self, pt: Point, g: dict) -> dict:
        """dJ/dm {inverted name: (nz, [ny,] nx)} from the solver's dJ/dphysical g {vp, [vs, rho]} (per m/s, per
        kg/m^3) at the point pt: the exact chain rule of the parameterisation and the clamps."""
        if self.physics == "acoustic":
            gq = {"vp": g["vp"] if pt.clipped is None else np.where(pt.clipped, 0.0, g["vp"])}
        elif self.physics == "viscoacoustic":
            gq = g
        elif self.physics == "vti":  # delta = min(delta, epsilon): the clamped cells' delta gradient belongs to epsilon
            c = pt.delta_clamped
            gq = {"vp": g["vp"], "epsilon": g["epsilon"] + np.where(c, g["delta"], 0.0), "delta": np.where(c, 0.0, g["delta"]),
                  "rho": g["rho"]}  # fmt: skip
        elif self.parameterization == "lambda-mu-rho":
            vp, vs, rho = pt.physical["vp"], pt.physical["vs"], pt.physical["rho"]
            gvp, gvs = g["vp"] / (2 * rho * vp), g["vs"] / (2 * rho * vs)  # dJ/dvp dvp/d(lambda + 2 mu), dJ/dvs dvs/dmu
            gq = {"lambda": gvp, "mu": 2 * gvp + gvs, "rho": g["rho"] - gvp * vp**2 - gvs * vs**2}
        elif self.parameterization == "ip-rho":  # vp = ip / rho
            rho = pt.physical["rho"]
            gq = {"ip": g["vp"] / rho, "rho": g["rho"] - g["vp"] * pt.physical["vp"] / rho}
        else:
            c = pt.vs_clamped
            gq = {"vp": g["vp"] + np.where(c, _VS_MAX * g["vs"], 0.0), "vs": np.where(c, 0.0, g["vs"]), "rho": g["rho"]}
        return {k: gq[k] * REFERENCE[k] for k in self.names}

    def x_gradient(self, x, gm: dict) -> np.ndarray:
        """dJ/dx (x's shape) from dJ/dm {name: cells}: the blocks in order (pixels) or the network's pullback (Warp's
        tape of the MLP kernel, float64 on the CPU)."""
        if self.network is None:
            n = math.prod(self.shape)
            return np.concatenate([(np.asarray(gm[k], float) * self._cells_slope(k, np.asarray(x, float)[i * n:(i + 1) * n].reshape(self.shape))).ravel()
                                   for i, k in enumerate(self.names)])  # fmt: skip
        import warp as wp

        tape = wp.Tape()
        v, theta = self._network_velocity(x, tape)
        v.grad = wp.array(np.asarray(gm["vp"], float).reshape(v.shape) / V_REF, dtype=wp.float64, device="cpu")
        tape.backward()
        return theta.grad.numpy().copy()

    def physical_ranges(self) -> dict:
        """{vp: (min, max), [vs: (min, max)]} (m/s) that every model the optimiser may visit stays within: what the
        plan (grid, time step) is made for. viscoacoustic and vti: the range of each of their parameters ({vp, q, rho},
        {vp, epsilon, delta, rho}; the wave speeds follow from them: inversion.fwi.wave_speed_range)."""
        lo = {k: float(np.min(v)) for k, v in self.fixed.items()}
        hi = {k: float(np.max(v)) for k, v in self.fixed.items()}
        for k in self.names:  # an inverted quantity stays in its box (pixels: the optimiser's bounds; nn: clipped)
            lo[k], hi[k] = self.bounds[k]
        if self.physics == "acoustic":
            return {"vp": (lo["vp"], hi["vp"])}
        if self.physics in OWN_QUANTITIES:
            return {k: (lo[k], hi[k]) for k in PHYSICS_PARAMETERS[self.physics]}
        if self.parameterization == "lambda-mu-rho":
            vp = (math.sqrt((lo["lambda"] + 2 * lo["mu"]) / hi["rho"]), math.sqrt((hi["lambda"] + 2 * hi["mu"]) / lo["rho"]))
            return {"vp": vp, "vs": (math.sqrt(lo["mu"] / hi["rho"]), math.sqrt(hi["mu"] / lo["rho"]))}
        if self.parameterization == "ip-rho":
            return {"vp": (lo["ip"] / hi["rho"], hi["ip"] / lo["rho"]), "vs": (0.0, 0.0)}
        return {"vp": (lo["vp"], hi["vp"]), "vs": (lo["vs"], min(hi["vs"], _VS_MAX * hi["vp"]))}
