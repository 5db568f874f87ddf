"""What elastic receivers record: particle-velocity and pressure components, and DAS strain rate along a fibre.

Conventions (as adseismic.solve.elastic): 2D, locations in metres (z, x), z depth positive down; recorded traces
(n_shots, n_locations, nt): vx, vz (m/s) sampled at t = (n - 1/2) dt, pressure (Pa) at t = n dt.

DAS (distributed acoustic sensing) measures the strain rate along the fibre averaged over a gauge length L. With
the fibre's unit direction d = (d_z, d_x), the channel centred at r records

    e_dot(r, t) = [d . v(r + L d / 2, t) - d . v(r - L d / 2, t)] / L        (1/s),

the gauge-length average of d_i d_j dv_i/dx_j: a linear map from vx, vz recorded at the gauges' two ends
(:meth:`DasOperator.gauge_ends`) to strain rate, whose exact adjoint (:meth:`DasOperator.adjoint`) spreads a
strain-rate residual back onto those ends (what a gradient's adjoint source needs). For a plane wave of angular
frequency w and apparent slowness p along the fibre the gauge average is the point strain rate times
sin(w p L / 2) / (w p L / 2) (tests/test_elastic_config.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SAMPLE_TIMES", "UNITS", "DasOperator", "Recording"]

UNITS = {"vx": "m/s", "vy": "m/s", "vz": "m/s", "pressure": "Pa", "das": "1/s"}  # each recorded quantity's unit (vy: 3D)
SAMPLE_TIMES = {"vx": "(n - 1/2) dt", "vy": "(n - 1/2) dt", "vz": "(n - 1/2) dt", "pressure": "n dt", "das": "(n - 1/2) dt"}


@dataclass(frozen=True)
class DasOperator:
    """Strain rate along a straight fibre of unit direction (dz, dx) over gauge_length (m) (module docstring)."""

    gauge_length: float
    direction: tuple

    def __post_init__(self):
        d = np.asarray(self.direction, dtype=float)
        if d.shape != (2,) or not np.isclose(np.hypot(*d), 1.0):
            raise ValueError(f"direction {self.direction!r} is not a unit vector (dz, dx)")
        if not self.gauge_length > 0:
            raise ValueError(f"gauge_length {self.gauge_length!r} is not a positive length in metres")

    def gauge_ends(self, centres) -> np.ndarray:
        """The gauges' ends (2 n, 2) metres (z, x) for channel centres (n, 2): the n starts (centre - L d / 2), then
        the n ends (centre + L d / 2)."""
        c = np.asarray(centres, dtype=float)
        half = 0.5 * self.gauge_length * np.asarray(self.direction, dtype=float)
        return np.concatenate([c - half, c + half])

    def forward(self, vx, vz) -> np.ndarray:
        """Strain rate (..., n, nt) in 1/s from vx, vz (..., 2 n, nt) in m/s recorded at gauge_ends' locations."""
        dz, dx = self.direction
        n = np.shape(vx)[-2] // 2
        along = dz * np.asarray(vz) + dx * np.asarray(vx)
        return (along[..., n:, :] - along[..., :n, :]) / self.gauge_length

    def adjoint(self, strain_rate) -> tuple[np.ndarray, np.ndarray]:
        """The exact transpose of :meth:`forward`: (vx, vz) (..., 2 n, nt) from strain rate (..., n, nt)."""
        dz, dx = self.direction
        e = np.asarray(strain_rate) / self.gauge_length
        ends = np.concatenate([-e, e], axis=-2)
        return dx * ends, dz * ends


@dataclass(frozen=True)
class Recording:
    """What an elastic receiver spread records at its n points: ``components`` (any of vx, vz, pressure; vy in 3D) at
    the points and, with ``das`` (2D only), the strain rate of a gauge centred on each point. The solver records vx, vz and pressure at
    :meth:`locations`; :meth:`data` turns those into the named traces and :meth:`adjoint` is its exact transpose."""

    components: tuple
    das: DasOperator | None = None

    @property
    def names(self) -> tuple:
        """The recorded quantities: the components, then "das" (UNITS gives each one's unit)."""
        return tuple(self.components) + (("das",) if self.das is not None else ())

    def locations(self, receivers) -> np.ndarray:
        """(m, 2) metres (z, x) the solver records at for the n receiver points (n, 2): the points (when components
        are recorded), then the DAS gauges' starts and ends (2 n, with das)."""
        r = np.asarray(receivers, dtype=float)
        parts = ([r] if self.components else []) + ([self.das.gauge_ends(r)] if self.das is not None else [])
        return np.concatenate(parts)

    def data(self, recorded: dict, n: int) -> dict:
        """{name: (n_shots, n, nt)} from the solver's {"vx", "vz", "pressure": (n_shots, m, nt)} at locations()."""
        k = n if self.components else 0
        out = {c: np.asarray(recorded[c])[:, :n] for c in self.components}
        if self.das is not None:
            out["das"] = self.das.forward(np.asarray(recorded["vx"])[:, k:], np.asarray(recorded["vz"])[:, k:])
        return out

    def adjoint(self, residuals: dict, n: int) -> dict:
        """The transpose of :meth:`data`: {"vx", "vz", "pressure": (n_shots, m, nt)} from {name: (n_shots, n, nt)}."""
        first = np.asarray(residuals[self.names[0]])
        shape = (first.shape[0], (n if self.components else 0) + (2 * n if self.das is not None else 0), first.shape[-1])
        out = {c: np.zeros(shape, dtype=first.dtype) for c in ("vx", "vz", "pressure")}
        for c in self.components:
            out[c][:, :n] += residuals[c]
        if self.das is not None:
            k = n if self.components else 0
            vx, vz = self.das.adjoint(residuals["das"])
            out["vx"][:, k:] += vx
            out["vz"][:, k:] += vz
        return out
