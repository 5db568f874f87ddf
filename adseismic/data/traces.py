"""Observed data as plain objects, and the error raised for every problem with them.

Two kinds of observed data feed the inversions:

* **shot gathers** (full-waveform inversion): SEG-Y or Seismic Unix (SU) files, one trace per
  source-receiver pair, coordinates in the trace headers -> :class:`ShotGathers`
  (:func:`adseismic.data.read.read_shot_gathers`, written for tests and docs by
  :func:`adseismic.data.write.write_shot_gathers_su`);
* **station traces** (earthquake location): MiniSEED + StationXML, SAC, or anything else ObsPy
  reads, station coordinates in latitude / longitude / elevation -> :class:`StationTraces`
  (:func:`adseismic.data.read.read_station_traces`, written by
  :func:`adseismic.data.write.write_station_traces`), mapped to local metres by
  :func:`adseismic.data.geometry.project` (inverse :func:`adseismic.data.geometry.unproject`).

:func:`adseismic.data.preprocess.preprocess` puts any of them onto the simulation's time axis
(detrend, taper, band-pass, anti-aliased resampling, trim / pad);
:func:`adseismic.data.geometry.check_samples` and :func:`adseismic.data.geometry.check_inside`
check data and geometry before a run.

Conventions (as everywhere in adseismic): metres, seconds, Hz; coordinate arrays in axis order
(z, [y,] x) with z = depth, positive down. Every problem with the input raises
:class:`TraceError` (a ``ValueError``) naming the file / trace / station / shot, the offending
value and the fix. ObsPy is imported inside the functions of :mod:`adseismic.data.read` and
:mod:`adseismic.data.write` only, so this module, :mod:`adseismic.data.geometry`,
:mod:`adseismic.data.preprocess` and the simulation path import without it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TraceError", "ShotGathers", "StationTraces"]


class TraceError(ValueError):
    """Invalid observed data or metadata; the message names the file / trace / station / shot,
    the offending value and the fix."""


# ------------------------------------------------------------------------------- containers

@dataclass
class ShotGathers:
    """Observed shot gathers. data (n_shots, n_receivers, nt) on time axis t = t0 + k*dt;
    sources (n_shots, ndim) and receivers (n_shots, n_receivers, ndim) in world metres, axis order (z,[y,]x).

    dt: sample interval (s); t0: time of the first sample relative to the shot time (s; the
    SEG-Y "delay recording time"). data keeps the file's sample type (float32 for SEG-Y / SU).
    z is depth = -elevation (m, positive down).
    """

    data: np.ndarray
    dt: float
    t0: float
    sources: np.ndarray
    receivers: np.ndarray

    @property
    def n_shots(self) -> int:
        return int(self.data.shape[0])

    @property
    def n_receivers(self) -> int:
        return int(self.data.shape[1])

    @property
    def nt(self) -> int:
        return int(self.data.shape[2])

    @property
    def ndim(self) -> int:
        return int(self.sources.shape[-1])

    @property
    def time(self) -> np.ndarray:
        """(nt,) sample times t0 + k dt (s)."""
        return self.t0 + self.dt * np.arange(self.nt)


@dataclass
class StationTraces:
    """Event traces: data (n_stations, nt) at t = starttime + k*dt (starttime an obspy UTCDateTime or float s);
    positions (n_stations, ndim) local metres, axis order (z,[y,]x) with z = depth = -elevation (+ optional datum);
    names list[str] 'NET.STA.LOC.CHA'; noise_std (n_stations,) from a pre-event window if requested.

    dt: sample interval (s). One row per trace (channel), so a three-component station gives
    three rows. reference: the :class:`adseismic.data.geometry.Reference` the positions were
    projected about (None when every position came from ``local_coordinates``); pass it to
    :func:`adseismic.data.geometry.unproject`. offline: 2D only, the distance (m) of each station from
    the model's line (:func:`adseismic.data.geometry.offline_distance`; 0 for local coordinates), which
    the projection drops; :func:`adseismic.data.geometry.check_offline` refuses stations far off it.
    """

    data: np.ndarray
    dt: float
    starttime: object
    positions: np.ndarray
    names: list
    noise_std: np.ndarray | None = None
    reference: object = None  # adseismic.data.geometry.Reference
    offline: np.ndarray | None = None  # 2D: (n_stations,) m each station lies off the line (dropped by project)

    @property
    def nt(self) -> int:
        return int(self.data.shape[-1])

    @property
    def ndim(self) -> int:
        return int(self.positions.shape[-1])
