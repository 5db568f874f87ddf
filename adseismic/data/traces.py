"""Observed data from files, through ObsPy, onto the simulation's time axis.

Two kinds of observed data feed the inversions:

* **shot gathers** (full-waveform inversion): SEG-Y or Seismic Unix (SU) files, one trace per
  source-receiver pair, coordinates in the trace headers -> :class:`ShotGathers`
  (:func:`read_shot_gathers`, written for tests and docs by :func:`write_shot_gathers_su`);
* **station traces** (earthquake location): MiniSEED + StationXML, SAC, or anything else ObsPy
  reads, station coordinates in latitude / longitude / elevation -> :class:`StationTraces`
  (:func:`read_station_traces`, written by :func:`write_station_traces`), mapped to local metres
  by :func:`project` (inverse :func:`unproject`).

:func:`preprocess` puts any of them onto the simulation's time axis (detrend, taper, band-pass,
anti-aliased resampling, trim / pad); :func:`check_samples` and :func:`check_inside` check data
and geometry before a run.

Conventions (as everywhere in adseismic): metres, seconds, Hz; coordinate arrays in axis order
(z, [y,] x) with z = depth, positive down. Every problem with the input raises
:class:`TraceError` (a ``ValueError``) naming the file / trace / station / shot, the offending
value and the fix. Files are written atomically (``<name>.part`` renamed into place). ObsPy is
imported inside the functions only, so the simulation path imports without it. Every
preprocessing step is logged on the ``adseismic.traces`` logger.

Local projection (:func:`project`)
----------------------------------
Ellipsoidal **azimuthal equidistant** projection on WGS84 about the reference point
(lat0, lon0): a point at geodesic distance ``s`` and azimuth ``alpha`` (clockwise from north)
from the reference maps to east = s sin(alpha), north = s cos(alpha). The geodesic is computed
with Vincenty's formulae (the same ones ``obspy.geodetics.gps2dist_azimuth`` falls back to
without geographiclib; direct and inverse problem, iterated to 1e-13 rad), so

* distances and azimuths *from the reference point* are the WGS84 geodesic ones (Vincenty's
  error: < 0.5 mm at any distance);
* :func:`unproject` inverts :func:`project` to < 1e-6 m horizontally (tested < 1 mm within
  100 km); elevation round-trips to floating-point rounding (z = datum - elevation);
* distances between two points that are not the reference are distorted by the transverse scale
  factor of the projection, ~ 1 + (r/R)^2 / 6 at distance r from the reference (R = 6371 km):
  4e-6 relative at 30 km, 4e-5 (4 m per 100 km) at 100 km, 1e-3 at 500 km. Place the reference
  near the centre of the network / model.
* the vertical is **flat-earth**: z = datum - elevation (elevation in m above the ellipsoid /
  sea level as given by the metadata, minus any sensor burial depth); Earth curvature is ignored
  (the surface drops ~ r^2 / (2R) below the tangent plane: 8 m at 10 km, 785 m at 100 km), as is
  usual for local earthquake location in a Cartesian model.

2D (ndim=2): x is the coordinate along a straight line through the reference with azimuth
``Reference.azimuth`` (degrees clockwise from north; default 90, so x = east):
x = east sin(azimuth) + north cos(azimuth). The perpendicular (off-line) offset is dropped and
its largest value logged; :func:`unproject` places 2D points on the line. 3D: x = east,
y = north; arrays (z, y, x).
"""
from __future__ import annotations

import logging
import math
import os
import pathlib
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from adseismic.data.store import atomic_path

__all__ = [
    "ShotGathers",
    "StationTraces",
    "Reference",
    "TraceError",
    "read_shot_gathers",
    "read_station_traces",
    "project",
    "unproject",
    "preprocess",
    "check_inside",
    "check_samples",
    "write_shot_gathers_su",
    "write_station_traces",
]

log = logging.getLogger(__name__)

_AXES = {2: "zx", 3: "zyx"}


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
    three rows. reference: the :class:`Reference` the positions were projected about (None when
    every position came from ``local_coordinates``); pass it to :func:`unproject`.
    """

    data: np.ndarray
    dt: float
    starttime: object
    positions: np.ndarray
    names: list
    noise_std: np.ndarray | None = None
    reference: "Reference | None" = None

    @property
    def nt(self) -> int:
        return int(self.data.shape[-1])

    @property
    def ndim(self) -> int:
        return int(self.positions.shape[-1])


@dataclass(frozen=True)
class Reference:
    """Origin of the local frame of :func:`project`.

    latitude, longitude: degrees (WGS84) of the point mapped to x = 0 (and y = 0);
    datum: elevation (m) mapped to z = 0, so z = datum - elevation (default 0: sea level);
    azimuth: 2D only, direction of the +x line, degrees clockwise from north (default 90: east).
    Accepted wherever a reference is asked for: a Reference, a tuple
    (lat, lon[, datum[, azimuth]]) or a dict with keys latitude/lat, longitude/lon, datum, azimuth.
    """

    latitude: float
    longitude: float
    datum: float = 0.0
    azimuth: float = 90.0


def _as_reference(ref, key: str = "reference") -> Reference:
    if isinstance(ref, Reference):
        out = ref
    elif isinstance(ref, dict):
        d = dict(ref)
        lat = d.pop("latitude", d.pop("lat", None))
        lon = d.pop("longitude", d.pop("lon", None))
        extra = sorted(set(d) - {"datum", "azimuth"})
        if lat is None or lon is None or extra:
            raise TraceError(f"{key}: {ref!r} needs keys latitude and longitude (degrees) and "
                             f"optionally datum (m) and azimuth (degrees){'; unknown ' + ', '.join(extra) if extra else ''}")
        out = Reference(lat, lon, d.get("datum", 0.0), d.get("azimuth", 90.0))
    elif isinstance(ref, (tuple, list, np.ndarray)) and 2 <= len(ref) <= 4:
        out = Reference(*ref)
    else:
        raise TraceError(f"{key}: {ref!r} is not a reference point; give (latitude, longitude"
                         f"[, datum, azimuth]) in degrees / metres / degrees or a Reference")
    try:
        vals = [float(v) for v in (out.latitude, out.longitude, out.datum, out.azimuth)]
    except (TypeError, ValueError):
        vals = [math.nan]
    if not all(math.isfinite(v) for v in vals) or abs(vals[0]) > 90 or not -180 <= vals[1] <= 360:
        raise TraceError(f"{key}: {ref!r} is not a valid reference; latitude must be in "
                         f"[-90, 90], longitude in [-180, 360] degrees, datum and azimuth finite")
    return Reference(*vals)


# ------------------------------------------------------------------------------- projection

_A = 6378137.0                 # WGS84 semi-major axis (m)
_F = 1 / 298.257223563         # WGS84 flattening
_B = _A * (1 - _F)


def _series(cos2_alpha):
    u2 = cos2_alpha * (_A ** 2 - _B ** 2) / _B ** 2
    big_a = 1 + u2 / 16384 * (4096 + u2 * (-768 + u2 * (320 - 175 * u2)))
    big_b = u2 / 1024 * (256 + u2 * (-128 + u2 * (74 - 47 * u2)))
    return big_a, big_b


def _delta_sigma(big_b, sin_s, cos_s, cos2sm):
    return big_b * sin_s * (cos2sm + big_b / 4 * (cos_s * (-1 + 2 * cos2sm ** 2)
                                                   - big_b / 6 * cos2sm * (-3 + 4 * sin_s ** 2)
                                                   * (-3 + 4 * cos2sm ** 2)))


def _vincenty_inverse(lat1, lon1, lat2, lon2):
    """Geodesic distance (m) and forward azimuth (rad) from (lat1, lon1) to (lat2, lon2), degrees."""
    lat2, lon2 = np.broadcast_arrays(np.asarray(lat2, float), np.asarray(lon2, float))
    u1 = np.arctan((1 - _F) * np.tan(np.radians(lat1)))
    u2 = np.arctan((1 - _F) * np.tan(np.radians(lat2)))
    big_l = np.radians((lon2 - lon1 + 180.0) % 360.0 - 180.0)
    su1, cu1, su2, cu2 = np.sin(u1), np.cos(u1), np.sin(u2), np.cos(u2)
    lam = big_l.copy()
    for _ in range(200):
        sl, cl = np.sin(lam), np.cos(lam)
        sin_s = np.hypot(cu2 * sl, cu1 * su2 - su1 * cu2 * cl)
        cos_s = su1 * su2 + cu1 * cu2 * cl
        sigma = np.arctan2(sin_s, cos_s)
        safe = np.where(sin_s == 0, 1.0, sin_s)
        sin_a = np.where(sin_s == 0, 0.0, cu1 * cu2 * sl / safe)
        cos2a = 1 - sin_a ** 2
        cos2sm = np.where(cos2a == 0, 0.0, cos_s - 2 * su1 * su2 / np.where(cos2a == 0, 1, cos2a))
        c = _F / 16 * cos2a * (4 + _F * (4 - 3 * cos2a))
        new = big_l + (1 - c) * _F * sin_a * (
            sigma + c * sin_s * (cos2sm + c * cos_s * (-1 + 2 * cos2sm ** 2)))
        done = np.all(np.abs(new - lam) < 1e-13)
        lam = new
        if done:
            break
    else:
        raise TraceError("project: Vincenty's inverse formula did not converge (nearly antipodal "
                         "points); choose a reference point near the stations")
    big_a, big_b = _series(cos2a)
    s = _B * big_a * (sigma - _delta_sigma(big_b, sin_s, cos_s, cos2sm))
    sl, cl = np.sin(lam), np.cos(lam)
    alpha = np.arctan2(cu2 * sl, cu1 * su2 - su1 * cu2 * cl)
    return np.where(sin_s == 0, 0.0, s), np.where(sin_s == 0, 0.0, alpha)


def _vincenty_direct(lat1, lon1, s, alpha1):
    """Point (lat, lon degrees) at geodesic distance s (m) and azimuth alpha1 (rad) from (lat1, lon1)."""
    s, alpha1 = np.broadcast_arrays(np.asarray(s, float), np.asarray(alpha1, float))
    u1 = np.arctan((1 - _F) * np.tan(np.radians(lat1)))
    su1, cu1 = np.sin(u1), np.cos(u1)
    sa1, ca1 = np.sin(alpha1), np.cos(alpha1)
    sigma1 = np.arctan2(np.tan(u1), ca1)
    sin_a = cu1 * sa1
    cos2a = 1 - sin_a ** 2
    big_a, big_b = _series(cos2a)
    sigma = s / (_B * big_a)
    for _ in range(200):
        cos2sm = np.cos(2 * sigma1 + sigma)
        new = s / (_B * big_a) + _delta_sigma(big_b, np.sin(sigma), np.cos(sigma), cos2sm)
        done = np.all(np.abs(new - sigma) < 1e-13)
        sigma = new
        if done:
            break
    sin_s, cos_s = np.sin(sigma), np.cos(sigma)
    cos2sm = np.cos(2 * sigma1 + sigma)
    lat2 = np.arctan2(su1 * cos_s + cu1 * sin_s * ca1,
                      (1 - _F) * np.hypot(sin_a, su1 * sin_s - cu1 * cos_s * ca1))
    lam = np.arctan2(sin_s * sa1, cu1 * cos_s - su1 * sin_s * ca1)
    c = _F / 16 * cos2a * (4 + _F * (4 - 3 * cos2a))
    big_l = lam - (1 - c) * _F * sin_a * (
        sigma + c * sin_s * (cos2sm + c * cos_s * (-1 + 2 * cos2sm ** 2)))
    lon2 = (lon1 + np.degrees(big_l) + 180.0) % 360.0 - 180.0
    return np.degrees(lat2), lon2


def project(lat, lon, elevation, reference, *, ndim: int = 3) -> np.ndarray:
    """Geographic coordinates -> local Cartesian metres about ``reference``.

    lat, lon: degrees (WGS84), any broadcastable shapes; elevation: m above the datum surface
    (sea level), positive up; reference: a :class:`Reference` or (lat0, lon0[, datum[, azimuth]]).
    Returns (..., ndim) metres in axis order (z, [y,] x): z = datum - elevation (depth, positive
    down), 3D: y = north, x = east; 2D: x along the line of azimuth ``reference.azimuth``.
    Azimuthal equidistant projection on WGS84 (see the module docstring for its accuracy).
    """
    ref = _as_reference(reference)
    if ndim not in (2, 3):
        raise TraceError(f"ndim: {ndim!r} is not 2 or 3")
    lat, lon, elev = np.broadcast_arrays(np.asarray(lat, float), np.asarray(lon, float),
                                         np.asarray(elevation, float))
    bad = ~(np.isfinite(lat) & np.isfinite(lon) & np.isfinite(elev) & (np.abs(lat) <= 90))
    if bad.any():
        i = np.unravel_index(int(np.argmax(bad)), bad.shape)
        raise TraceError(f"project: point {i} (lat {lat[i]}, lon {lon[i]}, elevation {elev[i]}) "
                         f"is not a valid position; latitude in [-90, 90] degrees, all finite")
    s, alpha = _vincenty_inverse(ref.latitude, ref.longitude, lat, lon)
    east, north = s * np.sin(alpha), s * np.cos(alpha)
    z = ref.datum - elev
    if ndim == 3:
        return np.stack([z, north, east], axis=-1)
    az = math.radians(ref.azimuth)
    x = east * math.sin(az) + north * math.cos(az)
    off = -east * math.cos(az) + north * math.sin(az)
    if off.size:
        log.info("project (2D, line azimuth %g deg): largest off-line distance %.1f m dropped",
                 ref.azimuth, float(np.max(np.abs(off))))
    return np.stack([z, x], axis=-1)


def unproject(points, reference):
    """Inverse of :func:`project`: local points (..., ndim) metres, axis order (z,[y,]x) ->
    (lat, lon, elevation) arrays of shape (...) in degrees, degrees, metres (elevation =
    datum - z; a QuakeML depth below sea level is -elevation). 2D points are placed on the line
    of azimuth ``reference.azimuth``. Exact inverse to < 1e-6 m within a few hundred km."""
    ref = _as_reference(reference)
    p = np.asarray(points, dtype=float)
    if p.ndim < 1 or p.shape[-1] not in (2, 3) or not np.all(np.isfinite(p)):
        raise TraceError(f"unproject: points of shape {p.shape} are not finite (..., 2) or "
                         f"(..., 3) arrays in axis order (z,[y,]x), metres")
    if p.shape[-1] == 3:
        z, north, east = p[..., 0], p[..., 1], p[..., 2]
    else:
        az = math.radians(ref.azimuth)
        z, east, north = p[..., 0], p[..., 1] * math.sin(az), p[..., 1] * math.cos(az)
    s, alpha = np.hypot(east, north), np.arctan2(east, north)
    lat, lon = _vincenty_direct(ref.latitude, ref.longitude, s, alpha)
    lon = np.where(s == 0, ref.longitude, lon)
    lat = np.where(s == 0, ref.latitude, lat)
    return lat, lon, ref.datum - z


# ------------------------------------------------------------------------------- checks

def check_samples(data, names, *, min_clip_run: int = 3) -> None:
    """Raise TraceError if any sample is NaN or inf; log a warning for clipped traces.

    data: (..., nt) array, one trace per row of data.reshape(-1, nt); names: one name per trace
    (same flattened order). A trace counts as clipped when ``min_clip_run`` or more consecutive
    samples sit exactly at its maximum |value| (a digitizer / recorder limit); an all-zero trace
    is reported as dead (warning).
    """
    a = np.asarray(data)
    rows = a.reshape(-1, a.shape[-1]) if a.ndim else a.reshape(1, 1)
    names = list(names)
    if len(names) != rows.shape[0]:
        raise TraceError(f"names: {len(names)} names for {rows.shape[0]} traces of data shape "
                         f"{a.shape}; give one name per trace")
    bad = ~np.isfinite(rows)
    if bad.any():
        rows_bad = np.flatnonzero(bad.any(axis=1))
        i = int(rows_bad[0])
        k = int(np.argmax(bad[i]))
        raise TraceError(f"{names[i]}: sample {k} is {rows[i, k]} ({int(bad[i].sum())} non-finite "
                         f"samples; {len(rows_bad)} traces affected, e.g. "
                         f"{', '.join(str(names[j]) for j in rows_bad[:5])}); remove the traces or "
                         f"replace the bad samples before use")
    if rows.shape[-1] == 0:
        return
    amax = np.max(np.abs(rows), axis=1)
    for i in np.flatnonzero(amax == 0):
        log.warning("%s: all samples are zero (dead trace)", names[i])
    for i in np.flatnonzero(amax > 0):
        at_max = np.abs(rows[i]) == amax[i]
        if at_max.sum() < min_clip_run:
            continue
        edges = np.diff(np.concatenate([[0], at_max.astype(np.int8), [0]]))
        runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
        if runs.max() >= min_clip_run:
            log.warning("%s: looks clipped: %d consecutive samples at max |value| %g (%d runs)",
                        names[i], int(runs.max()), float(amax[i]), int((runs >= min_clip_run).sum()))


def check_inside(points, model, what: str, *, names=None) -> None:
    """Raise TraceError if any point (..., ndim) (world metres, axis order (z,[y,]x)) lies outside
    ``model`` (an :class:`adseismic.models.Model`). The message names the ``what`` (e.g.
    "station", "receiver") with its index (and name, if ``names`` gives one per point) and
    coordinates, and the model's extent."""
    p = np.asarray(points, dtype=float)
    if p.ndim < 1 or p.shape[-1] != model.ndim:
        raise TraceError(f"{what}: coordinates of shape {p.shape} do not end in {model.ndim} "
                         f"values ({_AXES[model.ndim]}) for the {model.ndim}D model; use "
                         f"ndim={model.ndim} when reading")
    inside = model.contains(p)
    if inside.all():
        return
    outside = np.argwhere(~inside)
    idx = tuple(int(i) for i in outside[0])
    flat = int(np.ravel_multi_index(idx, inside.shape)) if inside.ndim else 0
    label = f"{what} {idx[0] if len(idx) == 1 else idx}"
    if names is not None:
        label += f" ({list(names)[flat]})"
    coords = ", ".join(f"{a}={v:.3f}" for a, v in zip(_AXES[model.ndim], p[idx]))
    extent = ", ".join(f"{a} {lo:g}..{hi:g}" for a, (lo, hi) in zip(_AXES[model.ndim], model.extent))
    raise TraceError(f"{label}: at ({coords}) m is outside the model ({extent} m); "
                     f"{len(outside)} of {inside.size} {what} positions are outside; extend the "
                     f"model or its origin, or drop those {what}s")


# ------------------------------------------------------------------------------- preprocessing

def _butter(kind, freqs, fs, order):
    from scipy import signal

    return signal.butter(order, freqs, btype=kind, fs=fs, output="sos")


def _fir(up: int, down: int) -> np.ndarray:
    """Low-pass FIR for resample_poly: cutoff at the lower Nyquist, long Kaiser (beta 8) window."""
    from scipy import signal

    m = max(up, down)
    return signal.firwin(2 * 24 * m + 1, 1.0 / m, window=("kaiser", 8.0))


def preprocess(data, dt_in, *, dt, nt, t_shift=0.0, detrend=True, taper=0.05, band=None, order=4,
               fmax_required=None, antialias=0.8, name="data") -> np.ndarray:
    """Put traces onto the simulation's time axis: (..., nt_in) sampled at ``dt_in`` (s) ->
    float64 (..., nt) sampled at ``dt`` (s), output sample j at time t_shift + j*dt relative to
    the input's first sample (samples outside the input are zero).

    Steps, each logged (on the whole record, before trimming, so filters see no cut edges):

    1. ``detrend``: remove the least-squares straight line of each trace;
    2. ``taper``: cosine (Tukey) taper over this fraction of the record at EACH end (0: none);
    3. ``band`` = (fmin or None, fmax or None) Hz: zero-phase Butterworth (sosfiltfilt, so the
       amplitude response is squared: 2*``order`` poles in effect) band-pass, high-pass (fmax
       None) or low-pass (fmin None); fmax must be below the input Nyquist 1/(2 dt_in);
    4. anti-aliasing, when dt > dt_in: zero-phase Butterworth low-pass at ``antialias`` times the
       new Nyquist 1/(2 dt);
    5. resampling to ``dt``: ``scipy.signal.resample_poly`` (Kaiser-windowed FIR) when dt_in/dt is
       a ratio of integers <= 64 and t_shift a whole number of output samples; otherwise band-
       limited interpolation: resample_poly up by an integer factor to >= 32 samples per period
       of the highest frequency left, then a cubic spline at the exact output times;
    6. trim / zero-pad to ``nt`` samples starting at ``t_shift`` (s; may be negative).

    fmax_required (Hz): the simulation's highest frequency; TraceError if it is not below the
    input Nyquist 1/(2 dt_in) (the data cannot constrain it), a warning above 0.8 of it (typical
    digitizer anti-alias corner). ``name`` labels messages.
    """
    from scipy import signal

    x = np.array(data, dtype=np.float64)
    if x.ndim < 1 or x.shape[-1] < 2:
        raise TraceError(f"{name}: shape {x.shape} has fewer than 2 samples along its last "
                         f"(time) axis; pass (..., nt_in) traces")
    for key, val in (("dt_in", dt_in), ("dt", dt)):
        if not (isinstance(val, (int, float, np.floating)) and math.isfinite(val) and val > 0):
            raise TraceError(f"{key}: {val!r} is not a positive sample interval in seconds")
    if not (isinstance(nt, (int, np.integer)) and nt >= 1):
        raise TraceError(f"nt: {nt!r} is not a positive number of samples")
    if not math.isfinite(float(t_shift)):
        raise TraceError(f"t_shift: {t_shift!r} is not a finite time in seconds")
    if not 0 <= float(taper) <= 0.5:
        raise TraceError(f"taper: {taper!r} is not a fraction in [0, 0.5] of the record "
                         f"tapered at each end")
    dt_in, dt, t_shift = float(dt_in), float(dt), float(t_shift)
    nyq_in, nyq_out = 0.5 / dt_in, 0.5 / dt
    n_in = x.shape[-1]
    if not np.all(np.isfinite(x)):
        raise TraceError(f"{name}: contains NaN or inf samples; run check_samples to find the "
                         f"traces and remove or repair them")
    if fmax_required is not None:
        if not float(fmax_required) < nyq_in:
            raise TraceError(f"{name}: sampled at dt_in = {dt_in:g} s (Nyquist {nyq_in:g} Hz), too "
                             f"coarse for the simulation's maximum frequency fmax_required = "
                             f"{float(fmax_required):g} Hz; use data sampled at dt_in < "
                             f"{0.5 / float(fmax_required):g} s or lower the simulation's fmax "
                             f"(e.g. a lower-frequency wavelet)")
        if float(fmax_required) > 0.8 * nyq_in:
            log.warning("%s: fmax_required %g Hz is above 0.8 x the input Nyquist (%g Hz), where "
                        "recorders' anti-alias filters usually cut", name, fmax_required, nyq_in)
    if detrend:
        x = signal.detrend(x, axis=-1, type="linear")
        log.info("%s: removed linear trend", name)
    if taper > 0:
        x *= signal.windows.tukey(n_in, 2 * float(taper))
        log.info("%s: cosine taper over %.1f%% of the record at each end", name, 100 * taper)
    if band is not None:
        try:
            fmin, fmax = band
        except (TypeError, ValueError):
            raise TraceError(f"band: {band!r} is not a pair (fmin or None, fmax or None) in Hz") from None
        for key, f in (("fmin", fmin), ("fmax", fmax)):
            if f is not None and not (math.isfinite(float(f)) and 0 < float(f) < nyq_in):
                raise TraceError(f"band: {key} = {f!r} Hz is not between 0 and the input Nyquist "
                                 f"{nyq_in:g} Hz (dt_in = {dt_in:g} s)")
        if fmin is not None and fmax is not None and not float(fmin) < float(fmax):
            raise TraceError(f"band: fmin = {fmin} Hz is not below fmax = {fmax} Hz")
        if fmin is None and fmax is None:
            log.info("%s: band (None, None): no band filter", name)
        else:
            if fmin is None:
                sos, what = _butter("lowpass", float(fmax), 1 / dt_in, order), f"low-pass {fmax} Hz"
            elif fmax is None:
                sos, what = _butter("highpass", float(fmin), 1 / dt_in, order), f"high-pass {fmin} Hz"
            else:
                sos = _butter("bandpass", [float(fmin), float(fmax)], 1 / dt_in, order)
                what = f"band-pass {fmin}-{fmax} Hz"
            x = signal.sosfiltfilt(sos, x, axis=-1)
            log.info("%s: zero-phase Butterworth %s, order %d (x2, forward-backward)",
                     name, what, order)
    if dt > dt_in * (1 + 1e-12):
        fc = float(antialias) * nyq_out
        x = signal.sosfiltfilt(_butter("lowpass", fc, 1 / dt_in, 8), x, axis=-1)
        log.info("%s: anti-alias zero-phase Butterworth low-pass %g Hz (%.2f x new Nyquist "
                 "%g Hz)", name, fc, antialias, nyq_out)
    return _resample_trim(x, dt_in, dt, nt, t_shift, name)


def _resample_trim(x, dt_in, dt, nt, t_shift, name):
    from scipy import signal
    from scipy.interpolate import CubicSpline

    n_in = x.shape[-1]
    ratio = Fraction(dt_in / dt).limit_denominator(64)
    up, down = ratio.numerator, ratio.denominator
    exact = up <= 64 and abs(up * dt - down * dt_in) <= 1e-9 * down * dt_in
    shift = t_shift / dt
    out = np.zeros(x.shape[:-1] + (nt,))
    if exact and abs(shift - round(shift)) <= 1e-6:
        y = x if up == down == 1 else signal.resample_poly(x, up, down, axis=-1, window=_fir(up, down))
        if up != down:
            log.info("%s: resampled dt %g -> %g s with resample_poly (up %d, down %d)",
                     name, dt_in, dt, up, down)
        k0 = int(round(shift))
        lo, hi = max(k0, 0), min(k0 + nt, y.shape[-1])
        if hi > lo:
            out[..., lo - k0:hi - k0] = y[..., lo:hi]
        n_valid = max(hi - lo, 0)
    else:
        n_up = max(1, math.ceil(16 * dt_in / max(dt_in, dt)))
        dt_mid = dt_in / n_up
        times = t_shift + dt * np.arange(nt)
        valid = (times >= -1e-9 * dt_in) & (times <= (n_in - 1) * dt_in + 1e-9 * dt_in)
        rows = x.reshape(-1, n_in)
        flat = out.reshape(-1, nt)
        block = max(1, int(2e7 // (n_in * n_up)))
        for b in range(0, rows.shape[0], block):
            y = rows[b:b + block]
            if n_up > 1:
                y = signal.resample_poly(y, n_up, 1, axis=-1, window=_fir(n_up, 1))
            y = y[:, :(n_in - 1) * n_up + 1]
            spline = CubicSpline(dt_mid * np.arange(y.shape[-1]), y, axis=-1)
            flat[b:b + block, valid] = spline(np.clip(times[valid], 0, (n_in - 1) * dt_in))
        out = flat.reshape(out.shape)
        n_valid = int(valid.sum())
        log.info("%s: resampled dt %g -> %g s, t_shift %g s: resample_poly up %d then cubic spline "
                 "at the exact output times", name, dt_in, dt, t_shift, n_up)
    log.info("%s: output %d samples from t_shift = %g s (%d from the data, %d zero-padded)",
             name, nt, t_shift, n_valid, nt - n_valid)
    return out


# ------------------------------------------------------------------------------- SEG-Y / SU

_EXT_FORMATS = {".su": "SU", ".segy": "SEGY", ".sgy": "SEGY", ".seg-y": "SEGY", ".seg": "SEGY"}


def _scalar(value) -> float:
    """SEG-Y scalar rule: positive multiplies, negative divides, zero means 1."""
    v = int(value)
    return 1.0 if v == 0 else (float(v) if v > 0 else 1.0 / abs(v))


def _read_one(path: pathlib.Path, fmt: str | None):
    import obspy

    if fmt is None:
        fmt = _EXT_FORMATS.get(path.suffix.lower())
        if fmt is None:
            raise TraceError(f"fmt: cannot tell the format of {path} from its extension "
                             f"{path.suffix!r}; pass fmt='SEGY' or fmt='SU'")
    fmt = str(fmt).upper().replace("-", "")
    if fmt not in ("SEGY", "SU"):
        raise TraceError(f"fmt: {fmt!r} is not 'SEGY' or 'SU'")
    if not path.is_file():
        raise TraceError(f"paths: {path} does not exist; give existing SEG-Y / SU files")
    try:
        stream = obspy.read(str(path), format=fmt, unpack_trace_headers=True)
    except Exception as e:  # ObsPy raises assorted types for unreadable files
        raise TraceError(f"{path}: could not be read as {fmt} ({type(e).__name__}: {e}); check "
                         f"the file or the fmt argument") from None
    if len(stream) == 0:
        raise TraceError(f"{path}: holds no traces")
    return stream, fmt


def read_shot_gathers(paths, fmt=None, *, coordinate_scale=None, ndim=2,
                      group_by="source") -> ShotGathers:
    """Read SEG-Y or SU file(s) into :class:`ShotGathers` (see its docstring for shapes / units).

    paths: one path or a list (traces are taken in file order, then trace order); fmt: "SEGY",
    "SU" or None (from the extension: .su -> SU; .segy/.sgy/.seg -> SEGY).
    Trace headers used (ObsPy names, ``obspy.io.segy.header``):

    * source_coordinate_x/y, group_coordinate_x/y times scalar_to_be_applied_to_all_coordinates
      (negative: divide; 0: 1); coordinate_units must be 0/1 (length);
    * receiver_group_elevation, surface_elevation_at_source, source_depth_below_surface times
      scalar_to_be_applied_to_all_elevations_and_depths: receiver z = -elevation, source
      z = depth - surface elevation (z = depth, m, positive down);
    * ``coordinate_scale`` (m per header unit) replaces both header scalars when given (files
      with wrong scalars); SEG-Y binary header measurement_system 2 (feet) converts to metres;
    * sample_interval_in_ms_for_this_trace (microseconds) -> dt; number of samples -> nt;
      delay_recording_time (ms) times scalar_to_be_applied_to_times -> t0;
    * original_field_record_number, trace_number_within_the_original_field_record: labels
      (and the shot key for ``group_by="record"``).

    ndim=2: x from the x coordinates (the y coordinates must all be equal, else TraceError:
    use ndim=3); ndim=3 adds y. Shots are formed by equal source coordinates (to 1 mm;
    ``group_by="source"``) or equal field record number (``group_by="record"``), in order of first
    appearance (record numbers are compared across all files, and the traces of one record must
    share one source position); receivers keep their trace order within a shot. Every trace must share one
    sample interval, length and t0, and every shot the same number of receivers (TraceError).
    """
    if ndim not in (2, 3):
        raise TraceError(f"ndim: {ndim!r} is not 2 or 3")
    if group_by not in ("source", "record"):
        raise TraceError(f"group_by: {group_by!r} is not 'source' or 'record'")
    if coordinate_scale is not None and not (math.isfinite(float(coordinate_scale))
                                             and float(coordinate_scale) > 0):
        raise TraceError(f"coordinate_scale: {coordinate_scale!r} is not a positive number of "
                         f"metres per header unit")
    path_list = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not path_list:
        raise TraceError("paths: no files given")
    labels, samples, src, rec, rec_no, dts, t0s = [], [], [], [], [], [], []
    for p in map(pathlib.Path, path_list):
        stream, f = _read_one(p, fmt)
        unit = 1.0
        if f == "SEGY":
            ms = int(getattr(stream.stats.binary_file_header, "measurement_system", 1) or 1)
            if ms == 2:
                unit = 0.3048
                log.info("%s: binary header measurement_system = 2 (feet): coordinates "
                         "converted to metres", p.name)
        for i, tr in enumerate(stream):
            h = tr.stats.segy.trace_header if f == "SEGY" else tr.stats.su.trace_header
            rec_id = int(h.original_field_record_number)
            label = (f"{p.name} trace {i} (0-based; field record {rec_id}, trace "
                     f"{int(h.trace_number_within_the_original_field_record)})")
            cu = int(h.coordinate_units)
            if cu not in (0, 1) and coordinate_scale is None:
                raise TraceError(f"{label}: coordinate_units = {cu} (2: arc seconds, 3: degrees, "
                                 f"4: DMS) are geographic; convert the coordinates to metres "
                                 f"(e.g. UTM) or pass coordinate_scale to force a length scale")
            if coordinate_scale is None:
                cs = _scalar(h.scalar_to_be_applied_to_all_coordinates) * unit
                es = _scalar(h.scalar_to_be_applied_to_all_elevations_and_depths) * unit
            else:
                cs = es = float(coordinate_scale)
            sx, sy = cs * h.source_coordinate_x, cs * h.source_coordinate_y
            gx, gy = cs * h.group_coordinate_x, cs * h.group_coordinate_y
            sz = es * (h.source_depth_below_surface - h.surface_elevation_at_source)
            gz = -es * h.receiver_group_elevation
            src.append((sz, sy, sx))
            rec.append((gz, gy, gx))
            rec_no.append(rec_id)
            dts.append((int(h.sample_interval_in_ms_for_this_trace), float(tr.stats.delta)))
            t0s.append(1e-3 * int(h.delay_recording_time) * _scalar(h.scalar_to_be_applied_to_times))
            labels.append(label)
            samples.append(tr.data)
    # --- one sampling, one length, one t0
    first = labels[0]
    for i, lab in enumerate(labels):
        if dts[i][1] != dts[0][1] and abs(dts[i][1] - dts[0][1]) > 1e-9 * dts[0][1]:
            raise TraceError(f"{lab}: sample interval {dts[i][1]:g} s differs from "
                             f"{dts[0][1]:g} s of {first}; resample the traces to one interval")
        if len(samples[i]) != len(samples[0]):
            raise TraceError(f"{lab}: {len(samples[i])} samples differ from {len(samples[0])} of "
                             f"{first}; cut or pad the traces to one length")
        if abs(t0s[i] - t0s[0]) > 1e-9:
            raise TraceError(f"{lab}: delay recording time t0 = {t0s[i]:g} s differs from "
                             f"{t0s[0]:g} s of {first}; shift the traces to one start time")
    dt = dts[0][1]
    if not dt > 0:
        raise TraceError(f"{first}: sample interval {dt!r} s is not positive; set "
                         f"sample_interval_in_ms_for_this_trace (microseconds)")
    src, rec = np.array(src, dtype=float), np.array(rec, dtype=float)
    if ndim == 2:
        ys = np.concatenate([src[:, 1], rec[:, 1]])
        if np.ptp(ys) > 1e-3:
            i = int(np.argmax(np.maximum(np.abs(src[:, 1] - ys[0]), np.abs(rec[:, 1] - ys[0]))))
            raise TraceError(f"{labels[i]}: y coordinates vary (source y {src[i, 1]:g} m, receiver "
                             f"y {rec[i, 1]:g} m, first trace y {ys[0]:g} m; range {np.ptp(ys):g} m) "
                             f"but ndim=2 reads x only; pass ndim=3, or rotate the line onto x")
        src, rec = src[:, [0, 2]], rec[:, [0, 2]]
    # --- group into shots
    keys = (np.round(src * 1e3).astype(np.int64).tolist() if group_by == "source" else rec_no)
    order, members = [], {}
    for i, k in enumerate(map(lambda k: tuple(k) if isinstance(k, list) else k, keys)):
        if k not in members:
            members[k] = []
            order.append(k)
        members[k].append(i)
    shots = [members[k] for k in order]
    counts = [len(m) for m in shots]
    for s, m in enumerate(shots):
        if counts[s] != counts[0]:
            where = ", ".join(f"{a}={v:.3f}" for a, v in zip(_AXES[ndim], src[m[0]]))
            raise TraceError(f"shot {s} (source at {where} m; first trace {labels[m[0]]}): "
                             f"{counts[s]} receivers, but shot 0 has {counts[0]}; every shot needs "
                             f"the same number of receivers (pad missing traces with zeros "
                             f"or drop the shot)")
        if group_by == "record" and np.ptp(src[m], axis=0).max() > 1e-3:
            raise TraceError(f"shot {s} (field record {rec_no[m[0]]}): traces have different "
                             f"source coordinates; group_by='source' instead")
    data = np.stack([np.stack([samples[i] for i in m]) for m in shots])
    gathers = ShotGathers(data=data, dt=dt, t0=float(t0s[0]),
                          sources=np.array([src[m[0]] for m in shots]),
                          receivers=np.array([[rec[i] for i in m] for m in shots]))
    check_samples(gathers.data, [labels[i] for m in shots for i in m])
    log.info("read %d shots x %d receivers x %d samples, dt %g s, t0 %g s from %d file(s)",
             gathers.n_shots, gathers.n_receivers, gathers.nt, dt, gathers.t0, len(path_list))
    return gathers


def _fit_scalar(values, what, lo=-(2 ** 31), hi=2 ** 31 - 1, finest=-1000):
    """Finest SEG-Y scalar (-1000, -100, -10, 1, 10, ...) for which all values fit the int range."""
    v = np.asarray(values, dtype=float)
    for sc in (-1000, -100, -10, 1, 10, 100, 1000, 10000):
        if sc < finest:
            continue
        ints = np.round(v * abs(sc) if sc < 0 else v / sc)
        if ints.size == 0 or (ints.min() >= lo and ints.max() <= hi):
            if sc != finest:
                log.warning("%s: stored with scalar %d (precision %g m)", what, sc,
                            1 / abs(sc) if sc < 0 else sc)
            return sc, ints.astype(np.int64)
    raise TraceError(f"{what}: values up to {np.abs(v).max():g} m do not fit a SEG-Y header")


def write_shot_gathers_su(path, gathers: ShotGathers, fmt="SU") -> pathlib.Path:
    """Write ``gathers`` to an SU (fmt="SU") or SEG-Y rev 1 (fmt="SEGY", IEEE float32) file,
    atomically; returns the path. One trace per (shot, receiver), shot-major. Headers:
    coordinates with scalar_to_be_applied_to_all_coordinates = -1000 (mm) and elevations with
    scalar_to_be_applied_to_all_elevations_and_depths = -1000 (coarser only if mm overflow
    int32), receiver_group_elevation = -z, surface_elevation_at_source = -z_source (depth 0),
    coordinate_units = 1, delay_recording_time = t0 in ms (scalar_to_be_applied_to_times when
    t0 is not whole ms), original_field_record_number = shot + 1,
    trace_number_within_the_original_field_record = receiver + 1, offset (whole m).
    dt must be a whole number of microseconds (the header unit). Samples stored as float32."""
    import obspy
    from obspy.core import AttribDict

    path = pathlib.Path(path)
    fmt = str(fmt).upper().replace("-", "")
    if fmt not in ("SU", "SEGY"):
        raise TraceError(f"fmt: {fmt!r} is not 'SU' or 'SEGY'")
    data = np.asarray(gathers.data)
    if data.ndim != 3:
        raise TraceError(f"gathers.data: shape {data.shape} is not (n_shots, n_receivers, nt)")
    n_shots, n_rec, nt = data.shape
    src, rec = np.asarray(gathers.sources, float), np.asarray(gathers.receivers, float)
    nd = src.shape[-1]
    if src.shape != (n_shots, nd) or rec.shape != (n_shots, n_rec, nd) or nd not in (2, 3):
        raise TraceError(f"gathers: sources {src.shape} / receivers {rec.shape} do not match "
                         f"data {data.shape}: need (n_shots, ndim) and (n_shots, n_receivers, ndim)")
    us = int(round(gathers.dt * 1e6))
    if not (1 <= us <= 65535 and abs(us - gathers.dt * 1e6) < 1e-6 * us):
        raise TraceError(f"gathers.dt: {gathers.dt!r} s is not a whole number of microseconds "
                         f"in 1..65535 (the SEG-Y header unit); resample first")
    delta = us * 1e-6
    while int(delta * 1e6) != us:  # ObsPy's SEG-Y writer truncates delta * 1e6
        delta = np.nextafter(delta, 1.0)
    t0_ms = gathers.t0 * 1e3
    for t_sc in (1, -10, -100, -1000, -10000):  # plainest exact scalar (SU tools ignore it)
        t_int = round(t0_ms * (abs(t_sc) if t_sc < 0 else 1))
        if abs(t_int * _scalar(t_sc) - t0_ms) < 1e-9 * max(1.0, abs(t0_ms)) and abs(t_int) < 32768:
            break
    else:
        raise TraceError(f"gathers.t0: {gathers.t0!r} s cannot be stored as the delay recording "
                         f"time (int16 ms with a scalar down to 1e-4 ms); shift the data to a "
                         f"whole 0.1 microsecond within +-32 s")
    xs = np.concatenate([src[:, -1], rec[..., -1].ravel()] +
                        ([src[:, 1], rec[..., 1].ravel()] if nd == 3 else []))
    c_sc, _ = _fit_scalar(xs, "coordinates")
    e_sc, _ = _fit_scalar(np.concatenate([src[:, 0], rec[..., 0].ravel()]), "elevations")

    def ints(v, sc):
        return int(round(v * abs(sc) if sc < 0 else v / sc))

    traces = []
    key = "su" if fmt == "SU" else "segy"
    for s in range(n_shots):
        for r in range(n_rec):
            n = s * n_rec + r + 1
            sy = src[s, 1] if nd == 3 else 0.0
            gy = rec[s, r, 1] if nd == 3 else 0.0
            h = AttribDict(
                trace_sequence_number_within_line=n, trace_sequence_number_within_segy_file=n,
                original_field_record_number=s + 1,
                trace_number_within_the_original_field_record=r + 1,
                energy_source_point_number=s + 1, trace_identification_code=1,
                scalar_to_be_applied_to_all_coordinates=c_sc,
                scalar_to_be_applied_to_all_elevations_and_depths=e_sc,
                source_coordinate_x=ints(src[s, -1], c_sc), source_coordinate_y=ints(sy, c_sc),
                group_coordinate_x=ints(rec[s, r, -1], c_sc), group_coordinate_y=ints(gy, c_sc),
                surface_elevation_at_source=ints(-src[s, 0], e_sc), source_depth_below_surface=0,
                receiver_group_elevation=ints(-rec[s, r, 0], e_sc), coordinate_units=1,
                distance_from_center_of_the_source_point_to_the_center_of_the_receiver_group=int(
                    round(float(np.hypot(rec[s, r, -1] - src[s, -1], gy - sy)))),
                delay_recording_time=int(t_int), scalar_to_be_applied_to_times=t_sc,
            )
            tr = obspy.Trace(np.ascontiguousarray(data[s, r], dtype=np.float32))
            tr.stats.delta = delta
            tr.stats[key] = AttribDict(trace_header=h)
            traces.append(tr)
    stream = obspy.Stream(traces)
    path.parent.mkdir(parents=True, exist_ok=True)
    part = atomic_path(path)
    try:
        if fmt == "SEGY":
            from obspy.io.segy.segy import SEGYBinaryFileHeader

            bh = SEGYBinaryFileHeader()
            bh.measurement_system = 1
            bh.number_of_data_traces_per_ensemble = n_rec
            bh.trace_sorting_code = 1
            stream.stats = AttribDict(textual_file_header=b"C 1 adseismic shot gathers".ljust(3200),
                                      binary_file_header=bh)
            stream.write(str(part), format="SEGY", data_encoding=5, byteorder=">")
        else:
            stream.write(str(part), format="SU", byteorder="<")
        os.replace(part, path)
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    log.info("wrote %d shots x %d receivers x %d samples to %s (%s)", n_shots, n_rec, nt, path, fmt)
    return path


# ------------------------------------------------------------------------------- stations

def _gap_message(gaps) -> str:
    parts = []
    for g in gaps[:5]:
        kind = "overlap" if g[6] < 0 else "gap"
        parts.append(f"{'.'.join(g[:4])}: {kind} from {g[4]} to {g[5]} ({abs(g[6]):g} s)")
    more = f" and {len(gaps) - 5} more" if len(gaps) > 5 else ""
    return "; ".join(parts) + more


def _sac_coordinates(tr):
    sac = tr.stats.get("sac")
    if not sac:
        return None
    vals = [sac.get(k) for k in ("stla", "stlo", "stel", "stdp")]
    if vals[0] is None or vals[1] is None or -12345.0 in (vals[0], vals[1]):
        return None
    elev = 0.0 if vals[2] in (None, -12345.0) else float(vals[2])
    depth = 0.0 if vals[3] in (None, -12345.0) else float(vals[3])
    return float(vals[0]), float(vals[1]), elev - depth


def _local_override(local, tr, ndim):
    """(z,[y,]x) from local_coordinates for this trace, or None."""
    s = tr.stats
    for key in (tr.id, f"{s.network}.{s.station}", s.station):
        if key in local:
            v = local[key]
            if isinstance(v, dict):
                axes = _AXES[ndim]
                missing = [a for a in axes if a not in v]
                if missing:
                    raise TraceError(f"local_coordinates[{key!r}]: {v!r} lacks {missing}; give "
                                     f"{', '.join(axes)} in metres")
                v = [v[a] for a in axes]
            arr = np.asarray(v, dtype=float)
            if arr.shape != (ndim,) or not np.all(np.isfinite(arr)):
                raise TraceError(f"local_coordinates[{key!r}]: {v!r} is not {ndim} finite "
                                 f"numbers in axis order ({','.join(_AXES[ndim])}), metres")
            return arr
    return None


def read_station_traces(paths, *, inventory=None, reference=None, ndim=2, local_coordinates=None,
                        component=None, fill_gaps=None, align=False, noise_window=None,
                        starttime=None, endtime=None) -> StationTraces:
    """Read event traces (MiniSEED, SAC, anything ObsPy reads) into :class:`StationTraces`.

    paths: one path / glob or a list; inventory: an ObsPy Inventory or StationXML path(s)
    (read with obspy.read_inventory). Coordinates per trace, first found wins:
    ``local_coordinates`` (dict keyed 'NET.STA.LOC.CHA', 'NET.STA' or 'STA' -> (z,[y,]x) metres
    in model axis order, or a dict with keys 'x', ['y',] 'z'), then the inventory
    (latitude, longitude, elevation - local_depth of the channel at the trace's start), then SAC
    headers stla / stlo / stel (- stdp; float32 in the file, so ~0.2 m horizontal precision),
    then ``trace.stats.coordinates``. Geographic ones are
    mapped by :func:`project` about ``reference`` (required then; see :class:`Reference`).

    component: keep only this component (e.g. "Z"); fill_gaps: None (default) raises TraceError
    on gaps / overlaps (Stream.get_gaps), a number fills them with it, "interpolate" linearly.
    All traces must share one sampling rate; they are cut to their common time window
    (optionally [starttime, endtime], UTCDateTime). Start times off the first trace's sample grid
    by more than 1% of dt raise TraceError unless ``align=True`` (Lanczos interpolation onto the
    grid). noise_window: (start, end) seconds relative to the common start time (or UTCDateTimes)
    -> noise_std, the standard deviation of each trace there (e.g. the pre-event window).
    """
    import obspy
    from obspy import UTCDateTime

    if ndim not in (2, 3):
        raise TraceError(f"ndim: {ndim!r} is not 2 or 3")
    path_list = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not path_list:
        raise TraceError("paths: no files given")
    stream = obspy.Stream()
    for p in path_list:
        try:
            stream += obspy.read(str(p))
        except Exception as e:
            raise TraceError(f"{p}: could not be read by ObsPy ({type(e).__name__}: {e}); check "
                             f"the path and the format") from None
    if component is not None:
        stream = stream.select(component=component)
        log.info("kept %d traces of component %s", len(stream), component)
    if len(stream) == 0:
        raise TraceError(f"paths: no traces in {[str(p) for p in path_list]}"
                         f"{' with component ' + repr(component) if component else ''}")
    gaps = stream.get_gaps()
    if gaps:
        if fill_gaps is None:
            raise TraceError(f"{_gap_message(gaps)}; traces with gaps or overlaps cannot be used "
                             f"as they are; pass fill_gaps=0.0 (or 'interpolate') to merge them, "
                             f"or remove the traces")
        stream.merge(method=1, fill_value=fill_gaps)
        log.warning("merged %d gaps/overlaps, filled with %r: %s", len(gaps), fill_gaps,
                    _gap_message(gaps))
    else:
        stream.merge(method=1)
    for tr in stream:
        if np.ma.isMaskedArray(tr.data):
            if np.ma.is_masked(tr.data):
                raise TraceError(f"{tr.id}: still has masked samples after merging; fill the "
                                 f"gaps (fill_gaps=0.0) or remove the trace")
            tr.data = tr.data.filled()
    stream.sort(keys=["network", "station", "location", "channel"])
    ids = [tr.id for tr in stream]
    dups = sorted({i for i in ids if ids.count(i) > 1})
    if dups:
        raise TraceError(f"{dups[0]}: {ids.count(dups[0])} separate traces remain after merging; "
                         f"give one continuous record per channel")
    if starttime is not None or endtime is not None:
        stream.trim(None if starttime is None else UTCDateTime(starttime),
                    None if endtime is None else UTCDateTime(endtime))
        log.info("cut to %s .. %s", starttime, endtime)
    # --- one sampling interval
    delta = float(stream[0].stats.delta)
    for tr in stream:
        if abs(tr.stats.delta - delta) > 1e-6 * delta:
            raise TraceError(f"{tr.id}: sampling rate {tr.stats.sampling_rate:g} Hz (dt "
                             f"{tr.stats.delta:g} s) differs from {stream[0].stats.sampling_rate:g}"
                             f" Hz of {stream[0].id}; resample it (obspy Trace.resample) first")
        if tr.stats.npts < 2:
            raise TraceError(f"{tr.id}: {tr.stats.npts} samples in the window; widen the window "
                             f"or drop the trace")
    # --- common sample grid and window
    t_grid = stream[0].stats.starttime
    for tr in stream:
        frac = ((tr.stats.starttime - t_grid) / delta) % 1.0
        off = min(frac, 1 - frac)
        if off > 0.01:
            if not align:
                raise TraceError(f"{tr.id}: starts at {tr.stats.starttime}, {off * delta:g} s "
                                 f"({off:.3f} samples) off the sample grid of {stream[0].id}; pass "
                                 f"align=True to interpolate it onto that grid")
            k = math.ceil((tr.stats.starttime - t_grid) / delta)
            t_new = t_grid + k * delta
            n_new = int(math.floor((tr.stats.endtime - t_new) / delta + 1e-6)) + 1
            tr.interpolate(1.0 / delta, method="lanczos", a=20, starttime=t_new, npts=n_new)
            log.info("%s: interpolated onto the common sample grid (shift %.3f samples)",
                     tr.id, off)
    t_start = max(tr.stats.starttime for tr in stream)
    t_end = min(tr.stats.endtime for tr in stream)
    if t_end - t_start < delta:
        raise TraceError(f"traces share no common time window (latest start {t_start}, earliest "
                         f"end {t_end}); select traces that overlap in time")
    nt = int(math.floor((t_end - t_start) / delta + 1e-6)) + 1
    rows = []
    for tr in stream:
        k0 = int(round((t_start - tr.stats.starttime) / delta))
        rows.append(np.asarray(tr.data[k0:k0 + nt], dtype=np.float64))
        if k0 or len(tr.data) != nt:
            log.info("%s: cut to the common window (%d of %d samples)", tr.id, nt, len(tr.data))
    data = np.stack(rows)
    # --- coordinates
    inv = None
    if inventory is not None:
        if isinstance(inventory, obspy.Inventory):
            inv = inventory
        else:
            inv = obspy.Inventory()
            for ip in ([inventory] if isinstance(inventory, (str, os.PathLike)) else inventory):
                try:
                    inv += obspy.read_inventory(str(ip))
                except Exception as e:
                    raise TraceError(f"inventory: {ip} could not be read ({type(e).__name__}: "
                                     f"{e}); give StationXML (or another ObsPy inventory format)") from None
    local = dict(local_coordinates or {})
    positions = [None] * len(stream)
    geo, missing = {}, []
    for i, tr in enumerate(stream):
        over = _local_override(local, tr, ndim)
        if over is not None:
            positions[i] = over
            continue
        c = None
        if inv is not None:
            try:
                cc = inv.get_coordinates(tr.id, tr.stats.starttime)
                c = (cc["latitude"], cc["longitude"], cc["elevation"] - (cc.get("local_depth") or 0.0))
            except Exception:
                c = None
        if c is None:
            c = _sac_coordinates(tr)
        if c is None and tr.stats.get("coordinates"):
            cc = tr.stats.coordinates
            if cc.get("latitude") is not None and cc.get("longitude") is not None:
                c = (cc.latitude, cc.longitude, cc.get("elevation", 0.0) or 0.0)
        if c is None:
            missing.append(tr.id)
        else:
            geo[i] = c
    if missing:
        raise TraceError(f"{', '.join(missing)}: no coordinates (not in the inventory, no SAC "
                         f"stla/stlo, no stats.coordinates, not in local_coordinates); pass "
                         f"inventory=<StationXML> or local_coordinates={{'{missing[0]}': "
                         f"({', '.join(_AXES[ndim])}) metres}}")
    ref = None
    if geo:
        lat, lon, elev = (np.array([geo[i][k] for i in sorted(geo)], dtype=float) for k in range(3))
        if reference is None:
            raise TraceError(f"reference: needed to map station latitude/longitude to local "
                             f"metres; pass reference=(lat0, lon0) in degrees (the model's "
                             f"x=0{', y=0' if ndim == 3 else ''} point), e.g. the network centre "
                             f"({lat.mean():.4f}, {lon.mean():.4f})")
        ref = _as_reference(reference)
        xyz = project(lat, lon, elev, ref, ndim=ndim)
        for j, i in enumerate(sorted(geo)):
            positions[i] = xyz[j]
        log.info("projected %d stations about (%.6f, %.6f), datum %g m%s", len(geo),
                 ref.latitude, ref.longitude, ref.datum,
                 f", 2D line azimuth {ref.azimuth:g} deg" if ndim == 2 else "")
    names = list(ids)
    check_samples(data, names)
    noise = None
    if noise_window is not None:
        try:
            a, b = (float(w - t_start) if isinstance(w, UTCDateTime) else float(w)
                    for w in noise_window)
        except (TypeError, ValueError):
            raise TraceError(f"noise_window: {noise_window!r} is not (start, end) in seconds "
                             f"relative to the start {t_start}") from None
        i0, i1 = max(int(math.ceil(a / delta - 1e-9)), 0), min(int(math.floor(b / delta + 1e-9)), nt - 1)
        if i1 - i0 + 1 < 2:
            raise TraceError(f"noise_window: ({a:g}, {b:g}) s after {t_start} holds {max(i1 - i0 + 1, 0)} "
                             f"samples of the {nt * delta:g} s record; give a window of at least "
                             f"two samples inside it (before the first arrival)")
        noise = data[:, i0:i1 + 1].std(axis=1)
        log.info("noise std from %g..%g s (%d samples)", i0 * delta, i1 * delta, i1 - i0 + 1)
    log.info("read %d traces x %d samples, dt %g s, from %s", len(names), nt, delta, t_start)
    return StationTraces(data=data, dt=delta, starttime=t_start, positions=np.array(positions, float),
                         names=names, noise_std=noise, reference=ref)


def write_station_traces(directory, traces: StationTraces, latitude=None, longitude=None,
                         elevation=None, reference=None, *, stem="event"):
    """Write ``traces`` as MiniSEED (float64 samples) + StationXML into ``directory``; returns
    (mseed path, stationxml path), both written atomically. Station coordinates: per-trace
    ``latitude``, ``longitude`` (degrees) and ``elevation`` (m), or, when they are None,
    ``unproject(traces.positions, reference or traces.reference)``. Trace names must be
    'NET.STA.LOC.CHA'; starttime a UTCDateTime or float seconds (epoch)."""
    import obspy
    from obspy import UTCDateTime
    from obspy.core.inventory import Channel, Inventory, Network, Station

    directory = pathlib.Path(directory)
    data = np.asarray(traces.data, dtype=np.float64)
    n = data.shape[0]
    if latitude is None or longitude is None or elevation is None:
        ref = reference if reference is not None else traces.reference
        if ref is None:
            raise TraceError("latitude/longitude/elevation: not given and no reference to "
                             "unproject traces.positions with; pass either")
        latitude, longitude, elevation = unproject(traces.positions, ref)
    lat, lon, elev = (np.broadcast_to(np.asarray(v, float), (n,)) for v in (latitude, longitude, elevation))
    start = traces.starttime if isinstance(traces.starttime, UTCDateTime) else UTCDateTime(float(traces.starttime))
    stream, nets = obspy.Stream(), {}
    for i, name in enumerate(traces.names):
        parts = str(name).split(".")
        if len(parts) != 4:
            raise TraceError(f"traces.names[{i}]: {name!r} is not 'NET.STA.LOC.CHA'")
        net, sta, loc, cha = parts
        tr = obspy.Trace(np.ascontiguousarray(data[i]),
                         {"network": net, "station": sta, "location": loc, "channel": cha,
                          "delta": float(traces.dt), "starttime": start})
        stream.append(tr)
        stations = nets.setdefault(net, {})
        st = stations.setdefault(sta, Station(sta, float(lat[i]), float(lon[i]), float(elev[i])))
        st.channels.append(Channel(cha, loc, float(lat[i]), float(lon[i]), float(elev[i]), 0.0,
                                   sample_rate=1.0 / float(traces.dt)))
    inv = Inventory(networks=[Network(code, stations=list(st.values())) for code, st in nets.items()],
                    source="adseismic")
    directory.mkdir(parents=True, exist_ok=True)
    mseed, xml = directory / f"{stem}.mseed", directory / f"{stem}.xml"
    parts = [atomic_path(mseed), atomic_path(xml)]
    try:
        stream.write(str(parts[0]), format="MSEED", encoding="FLOAT64")
        inv.write(str(parts[1]), format="STATIONXML")
        os.replace(parts[0], mseed)
        os.replace(parts[1], xml)
    except BaseException:
        for p in parts:
            p.unlink(missing_ok=True)
        raise
    log.info("wrote %d traces to %s and %s", n, mseed, xml)
    return mseed, xml
