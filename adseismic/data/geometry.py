"""Where observed data sit: the local Cartesian frame of stations and events (:class:`Reference`,
:func:`project`, :func:`unproject`) and the checks of data and geometry before a run
(:func:`check_samples`, :func:`check_inside`).

Conventions as in :mod:`adseismic.data.traces`: metres, coordinate arrays in axis order
(z, [y,] x) with z = depth, positive down (:data:`AXES`); problems raise
:class:`adseismic.data.traces.TraceError`. No ObsPy needed; pyproj only for :func:`project`,
:func:`unproject` and :func:`offline_distance` (a one-line TraceError with the pip command when missing).

Local projection (:func:`project`)
----------------------------------
Ellipsoidal **azimuthal equidistant** projection on WGS84 about the reference point
(lat0, lon0), computed by PROJ through pyproj (``+proj=aeqd +datum=WGS84``; pyproj is the optional
extra ``adseismic[geo]``, imported on first use): a point at geodesic distance ``s`` and azimuth
``alpha`` (clockwise from north) from the reference maps to east = s sin(alpha), north = s cos(alpha).
PROJ's geodesics are Karney's (accurate to nanometres), so

* distances and azimuths *from the reference point* are the WGS84 geodesic ones (the hand-written
  Vincenty formulae used before agree to < 0.001 mm out to 100 km; tests/test_geodesy.py);
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
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from adseismic.data.traces import TraceError

__all__ = ["AXES", "Reference", "as_reference", "project", "unproject", "offline_distance", "check_samples", "check_inside",
           "check_offline"]

log = logging.getLogger(__name__)

AXES = {2: "zx", 3: "zyx"}  # coordinate axis letters by dimension, slowest first


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


def as_reference(ref, key: str = "reference") -> Reference:
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

GEO_EXTRA = "pip install 'adseismic[geo]'  (or: pip install pyproj)"


def _pyproj():
    """pyproj, imported on first use (an optional dependency: the extra ``adseismic[geo]``)."""
    try:
        import pyproj
    except ImportError:
        raise TraceError(f"station coordinates in latitude / longitude need pyproj (PROJ) for the local projection, "
                         f"which is not installed; {GEO_EXTRA}") from None
    return pyproj


@lru_cache(maxsize=32)
def _aeqd(lat0: float, lon0: float):
    """The pyproj Transformer (lon, lat degrees WGS84) -> (east, north) m of the ellipsoidal azimuthal equidistant
    projection about (lat0, lon0) on WGS84 (PROJ's ``aeqd``: geodesic distance and azimuth from the centre, Karney's
    algorithms)."""
    pyproj = _pyproj()
    lon0 = (lon0 + 180.0) % 360.0 - 180.0  # PROJ does not wrap lon_0 itself
    crs = pyproj.CRS.from_proj4(f"+proj=aeqd +lat_0={lat0!r} +lon_0={lon0!r} +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs")
    return pyproj.Transformer.from_crs(pyproj.CRS.from_epsg(4326), crs, always_xy=True)


def _east_north(ref: Reference, lat, lon):
    """(east, north) m of geographic points in the azimuthal equidistant frame about ``ref``."""
    east, north = _aeqd(ref.latitude, ref.longitude).transform(np.asarray(lon, float), np.asarray(lat, float),
                                                              errcheck=True)
    return np.asarray(east, float), np.asarray(north, float)


def project(lat, lon, elevation, reference, *, ndim: int = 3) -> np.ndarray:
    """Geographic coordinates -> local Cartesian metres about ``reference``.

    lat, lon: degrees (WGS84), any broadcastable shapes; elevation: m above the datum surface
    (sea level), positive up; reference: a :class:`Reference` or (lat0, lon0[, datum[, azimuth]]).
    Returns (..., ndim) metres in axis order (z, [y,] x): z = datum - elevation (depth, positive
    down), 3D: y = north, x = east; 2D: x along the line of azimuth ``reference.azimuth``.
    Azimuthal equidistant projection on WGS84 (see the module docstring for its accuracy).
    """
    ref = as_reference(reference)
    if ndim not in (2, 3):
        raise TraceError(f"ndim: {ndim!r} is not 2 or 3")
    lat, lon, elev = np.broadcast_arrays(np.asarray(lat, float), np.asarray(lon, float),
                                         np.asarray(elevation, float))
    bad = ~(np.isfinite(lat) & np.isfinite(lon) & np.isfinite(elev) & (np.abs(lat) <= 90))
    if bad.any():
        i = np.unravel_index(int(np.argmax(bad)), bad.shape)
        raise TraceError(f"project: point {i} (lat {lat[i]}, lon {lon[i]}, elevation {elev[i]}) "
                         f"is not a valid position; latitude in [-90, 90] degrees, all finite")
    east, north = _east_north(ref, lat, lon)
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


def offline_distance(lat, lon, reference) -> np.ndarray:
    """Distance (m) of geographic points from the 2D line through ``reference`` with azimuth
    ``reference.azimuth`` (in the azimuthal equidistant frame of :func:`project`): what the 2D projection
    drops."""
    ref = as_reference(reference)
    east, north = _east_north(ref, lat, lon)
    az = math.radians(ref.azimuth)
    return np.abs(-east * math.cos(az) + north * math.sin(az))


OFFLINE_REFUSE = 0.5  # fraction of the 2D model's length: stations farther off its line are refused
OFFLINE_WARN = 0.05  # fraction of the length above which an off-line distance gets a warning


def check_offline(offline, names, model, key: str = "traces.reference") -> None:
    """2D: refuse (TraceError naming the stations and distances) stations farther off the model's line than
    OFFLINE_REFUSE x the model's x length, which a 2D model cannot place (their distances to an event would be
    wrong by about the off-line distance); warn (log) above OFFLINE_WARN x the length. ``offline`` (n,) m or None."""
    if offline is None or model.ndim != 2:
        return
    off = np.asarray(offline, float)
    lo, hi = model.extent[-1]
    length = max(hi - lo, min(model.spacing))
    far = np.flatnonzero(off > OFFLINE_REFUSE * length)
    if far.size:
        order = far[np.argsort(-off[far])]
        listed = ", ".join(f"{names[i]} ({off[i] / 1e3:,.3f} km)" for i in order[:6])
        more = f" and {far.size - 6} more" if far.size > 6 else ""
        raise TraceError(f"{key}: {far.size} of {off.size} stations lie far off the 2D model's line: {listed}{more}, more "
                         f"than {OFFLINE_REFUSE:g} x the model's {length:g} m length; a 2D model cannot place them (the "
                         f"distance dropped would be ignored): set the line's azimuth ({key}: {{latitude, longitude, "
                         f"azimuth}}) along the stations, check the station coordinates and the reference, use a 3D "
                         f"model, or drop those stations")
    warn = np.flatnonzero(off > OFFLINE_WARN * length)
    if warn.size:
        i = int(warn[np.argmax(off[warn])])
        log.warning("%d of %d stations lie more than %.3g m (%g x the model's length) off the 2D line, up to %.4g m (%s); "
                    "their distances to the event are taken along the line only", warn.size, off.size,
                    OFFLINE_WARN * length, OFFLINE_WARN, off[i], names[i])


def unproject(points, reference):
    """Inverse of :func:`project`: local points (..., ndim) metres, axis order (z,[y,]x) ->
    (lat, lon, elevation) arrays of shape (...) in degrees, degrees, metres (elevation =
    datum - z; a QuakeML depth below sea level is -elevation). 2D points are placed on the line
    of azimuth ``reference.azimuth``. Exact inverse to < 1e-6 m within a few hundred km."""
    ref = as_reference(reference)
    p = np.asarray(points, dtype=float)
    if p.ndim < 1 or p.shape[-1] not in (2, 3) or not np.all(np.isfinite(p)):
        raise TraceError(f"unproject: points of shape {p.shape} are not finite (..., 2) or "
                         f"(..., 3) arrays in axis order (z,[y,]x), metres")
    if p.shape[-1] == 3:
        z, north, east = p[..., 0], p[..., 1], p[..., 2]
    else:
        az = math.radians(ref.azimuth)
        z, east, north = p[..., 0], p[..., 1] * math.sin(az), p[..., 1] * math.cos(az)
    lon, lat = _aeqd(ref.latitude, ref.longitude).transform(east, north, direction="INVERSE", errcheck=True)
    lon, lat = np.asarray(lon, float), np.asarray(lat, float)
    at_ref = (east == 0) & (north == 0)
    lon = np.where(at_ref, ref.longitude, lon)
    lat = np.where(at_ref, ref.latitude, lat)
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
    if not (hasattr(names, "__len__") and hasattr(names, "__getitem__")):
        names = list(names)
    if len(names) != rows.shape[0]:
        raise TraceError(f"names: {len(names)} names for {rows.shape[0]} traces of data shape "
                         f"{a.shape}; give one name per trace")
    if rows.shape[-1] == 0:
        return
    # in blocks of about 2^20 samples: no temporary the size of the data
    step = max(1, 2 ** 20 // rows.shape[-1])
    amax = np.empty(rows.shape[0])
    n_at_max = np.empty(rows.shape[0], dtype=np.int64)
    for r0 in range(0, rows.shape[0], step):
        block = rows[r0:r0 + step]
        bad = ~np.isfinite(block)
        if bad.any():
            _non_finite(rows, names, step)
        mag = np.abs(block)
        amax[r0:r0 + step] = mag.max(axis=1)
        n_at_max[r0:r0 + step] = (mag == amax[r0:r0 + step, None]).sum(axis=1)
    for i in np.flatnonzero(amax == 0):
        log.warning("%s: all samples are zero (dead trace)", names[i])
    for i in np.flatnonzero((amax > 0) & (n_at_max >= min_clip_run)):
        at_max = np.abs(rows[i]) == amax[i]
        edges = np.diff(np.concatenate([[0], at_max.astype(np.int8), [0]]))
        runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
        if runs.max() >= min_clip_run:
            log.warning("%s: looks clipped: %d consecutive samples at max |value| %g (%d runs)",
                        names[i], int(runs.max()), float(amax[i]), int((runs >= min_clip_run).sum()))


def _non_finite(rows, names, step):
    """Raise the TraceError of check_samples for the non-finite samples in ``rows``."""
    rows_bad = np.concatenate([r0 + np.flatnonzero((~np.isfinite(rows[r0:r0 + step])).any(axis=1))
                               for r0 in range(0, rows.shape[0], step)])
    i = int(rows_bad[0])
    bad = ~np.isfinite(rows[i])
    k = int(np.argmax(bad))
    raise TraceError(f"{names[i]}: sample {k} is {rows[i, k]} ({int(bad.sum())} non-finite "
                     f"samples; {len(rows_bad)} traces affected, e.g. "
                     f"{', '.join(str(names[j]) for j in rows_bad[:5])}); remove the traces or "
                     f"replace the bad samples before use")


def check_inside(points, model, what: str, *, names=None) -> None:
    """Raise TraceError if any point (..., ndim) (world metres, axis order (z,[y,]x)) lies outside
    ``model`` (an :class:`adseismic.data.models.Model`). The message names the ``what`` (e.g.
    "station", "receiver") with its index (and name, if ``names`` gives one per point) and
    coordinates, and the model's extent."""
    p = np.asarray(points, dtype=float)
    if p.ndim < 1 or p.shape[-1] != model.ndim:
        raise TraceError(f"{what}: coordinates of shape {p.shape} do not end in {model.ndim} "
                         f"values ({AXES[model.ndim]}) for the {model.ndim}D model; use "
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
    coords = ", ".join(f"{a}={v:.3f}" for a, v in zip(AXES[model.ndim], p[idx]))
    extent = ", ".join(f"{a} {lo:g}..{hi:g}" for a, (lo, hi) in zip(AXES[model.ndim], model.extent))
    raise TraceError(f"{label}: at ({coords}) m is outside the model ({extent} m); "
                     f"{len(outside)} of {inside.size} {what} positions are outside; extend the "
                     f"model or its origin, or drop those {what}s")
