"""An earthquake location with its covariance, written as QuakeML through ObsPy (and read back).

The locator works in the local Cartesian frame of :func:`adseismic.data.geometry.project`: metres,
axis order (z, [y,] x), z = depth = datum - elevation (positive down), 3D y = north, x = east,
2D x along the line of azimuth ``Reference.azimuth``. :func:`write_quakeml` turns a position,
an origin time and their joint covariance into a QuakeML ``Origin``.

Conventions
-----------
* **covariance** (``write_quakeml``): (ndim+1, ndim+1) 1-sigma covariance over
  (position..., origin time), i.e. (z, x, t) in 2D and (z, y, x, t) in 3D, in m^2, m*s, s^2.
  It must be symmetric (to 1e-8 relative) and positive definite.
* **confidence**: every ellipse / ellipsoid axis is a semi-axis of the region
  ``d^T C^-1 d <= k^2`` holding ``confidence`` of the Gaussian, ``k = confidence_scale(dof,
  confidence) = sqrt(chi2.ppf(confidence, dof))`` with dof = the dimension of the region
  (1 for a single coordinate, 2 for an ellipse, 3 for an ellipsoid). So at 68 %: 1 dof
  k = 0.9945, 2 dof k = 1.5096, 3 dof k = 1.8724. The scalar errors (``latitude_errors`` ...
  ``time_errors``) are plain 1-sigma values, not scaled.
* **horizontal ellipse** (:func:`ellipse`): the 2x2 covariance is over (north, east) = local
  (y, x) in 3D, i.e. ``cov[1:3, 1:3]`` of a (z, y, x) covariance. Its azimuth is the direction
  of the major axis in degrees clockwise from north, folded into [0, 180) (an axis has no sign).
* **section ellipse** (:func:`ellipse_2d`): 2x2 covariance over local (z, x) of a 2D section;
  the angle of the major axis is measured from +x toward +z (down), degrees in (-90, 90]:
  positive = the axis dips downward along +x.
* **QuakeML ConfidenceEllipsoid** (3D): the QuakeML Tait-Bryan definition, taken literally.
  Fixed frame x = north, y = east, z = down (right-handed); the ellipsoid frame (X, Y, Z) =
  (major, minor, intermediate axis) is obtained by the intrinsic rotations Z (heading psi =
  ``major_axis_azimuth``), then Y (elevation phi = ``major_axis_plunge``), then X (bank theta
  = ``major_axis_rotation``): ``R = Rz(psi) Ry(phi) Rx(theta)``, the columns of R are the
  major, minor and intermediate unit axes in (north, east, down) and
  ``C_ned * k3^2 = R diag(major^2, minor^2, intermediate^2) R^T``. With right-handed Tait-Bryan
  angles a positive phi tilts the +X end of the major axis *upward*; of the two ends of the
  axis the one pointing up (or, for a horizontal axis, the one with azimuth in [0, 180)) is
  reported, so phi is in [0, 90], psi in [0, 360), theta in (-90, 90]. In geological terms the
  major axis plunges phi degrees **downward toward azimuth psi + 180**.
  :func:`ellipsoid_covariance` rebuilds the covariance from these numbers (and is tested to).
  The 3D origin also carries the horizontal ellipse (min/max_horizontal_uncertainty,
  azimuth_max_horizontal_uncertainty, 2 dof) and ``horizontal_uncertainty`` = its semi-major.
* **2D sections**: only the coordinate along the line is constrained. ``horizontal_uncertainty``
  and ``max_horizontal_uncertainty`` = the along-line semi-axis (1-sigma times the 1-dof k),
  ``azimuth_max_horizontal_uncertainty`` = the line azimuth folded into [0, 180);
  ``min_horizontal_uncertainty`` (off-line) is left unset, because the 2D model does not
  constrain the off-line position at all (the event is placed on the line).
* latitude / longitude errors: degrees, 1 sigma, from the local covariance mapped through the
  Jacobian of :func:`adseismic.data.geometry.unproject` at the event (central differences, 10 m);
  depth in m below sea level (= -elevation = z - datum), depth error m, time error s.
* nothing is lost: a comment (id ``.../adseismic-local``) holds JSON with the local position,
  the reference, the axis order and the full covariance (and ``extra``);
  :func:`read_quakeml_origin` returns it as ``"local"``.

Files are written atomically (``<name>.part`` renamed into place; removed on any error).
ObsPy and SciPy are imported inside the functions.
"""
from __future__ import annotations

import json
import math
import re

import numpy as np

from adseismic.data.atomic import atomic_write
from adseismic.data.geometry import Reference, as_reference, unproject

__all__ = [
    "confidence_scale",
    "ellipse",
    "ellipse_2d",
    "ellipsoid",
    "ellipsoid_covariance",
    "write_quakeml",
    "read_quakeml_origin",
    "read_quakeml_focal_mechanism",
]

_LOCAL_TAG = "adseismic-local"
_AXES = {2: ["z", "x"], 3: ["z", "y", "x"]}


# ------------------------------------------------------------------------------- helpers

def confidence_scale(dof: int, confidence: float = 0.68) -> float:
    """Scale k such that the region ``x^T C^-1 x <= k^2`` holds ``confidence`` of a Gaussian in
    ``dof`` dimensions: ``k = sqrt(chi2.ppf(confidence, dof))``. A semi-axis of the confidence
    ellipse / ellipsoid is k times the square root of the covariance eigenvalue.

    At 68 %: 1 dof -> 0.9945, 2 dof -> 1.5096, 3 dof -> 1.8724; at 95 %: 1.960, 2.448, 2.796.
    """
    from scipy.stats import chi2

    if isinstance(dof, bool) or int(dof) != dof or int(dof) < 1:
        raise ValueError(f"dof: {dof!r} is not a positive integer (number of dimensions)")
    _check_confidence(confidence)
    return float(math.sqrt(chi2.ppf(float(confidence), int(dof))))


def _check_confidence(confidence) -> float:
    try:
        c = float(confidence)
    except (TypeError, ValueError):
        c = math.nan
    if not 0.0 < c < 1.0:
        raise ValueError(f"confidence: {confidence!r} must be a probability in (0, 1), e.g. 0.68 "
                         f"or 0.95 (not a percentage)")
    return c


def _check_cov(cov, n: int, key: str) -> np.ndarray:
    """Symmetric positive definite (n, n) float array, else ValueError naming ``key``."""
    try:
        c = np.array(cov, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{key}: {cov!r} is not a numeric ({n}, {n}) matrix") from None
    if c.shape != (n, n):
        raise ValueError(f"{key}: shape {c.shape} is not ({n}, {n})")
    if not np.all(np.isfinite(c)):
        raise ValueError(f"{key}: contains non-finite values (NaN / inf)")
    scale = float(np.max(np.abs(c))) if c.size else 0.0
    if not np.allclose(c, c.T, rtol=0.0, atol=1e-8 * scale):
        raise ValueError(f"{key}: matrix is not symmetric (largest |C - C^T| = "
                         f"{float(np.max(np.abs(c - c.T))):g}); a covariance must be symmetric")
    c = 0.5 * (c + c.T)
    try:
        np.linalg.cholesky(c)
        ok = True
    except np.linalg.LinAlgError:
        ok = False
    if not ok or scale == 0.0:
        eig = np.linalg.eigvalsh(c)
        raise ValueError(f"{key}: matrix is not positive definite (eigenvalues {eig.tolist()}); "
                         f"a covariance needs all variances > 0 and |correlations| < 1")
    return c


def _eig_desc(c):
    w, v = np.linalg.eigh(c)
    order = np.argsort(w)[::-1]
    return w[order], v[:, order]


def ellipse(cov2, confidence: float = 0.68) -> tuple[float, float, float]:
    """Horizontal confidence ellipse of a 2x2 covariance over **(north, east)** (= local (y, x)
    in 3D, ``cov[1:3, 1:3]`` of a (z, y, x) covariance), m^2.

    Returns (semi_major m, semi_minor m, azimuth of the major axis in degrees clockwise from
    north, in [0, 180)); semi-axes = ``confidence_scale(2, confidence) * sqrt(eigenvalues)``.
    """
    c = _check_cov(cov2, 2, "cov2")
    k = confidence_scale(2, confidence)
    w, v = _eig_desc(c)
    north, east = v[0, 0], v[1, 0]
    az = math.degrees(math.atan2(east, north)) % 180.0
    if az >= 180.0 - 1e-12:
        az = 0.0
    return k * math.sqrt(w[0]), k * math.sqrt(w[1]), az


def ellipse_2d(cov_zx, confidence: float = 0.68) -> tuple[float, float, float]:
    """Confidence ellipse of a 2D section: 2x2 covariance over local **(z, x)**, m^2.

    Returns (semi_major m, semi_minor m, angle of the major axis in degrees measured from +x
    toward +z (downward), in (-90, 90]); semi-axes scaled by ``confidence_scale(2, confidence)``.
    """
    c = _check_cov(cov_zx, 2, "cov_zx")
    k = confidence_scale(2, confidence)
    w, v = _eig_desc(c)
    dz, dx = v[0, 0], v[1, 0]
    ang = math.degrees(math.atan2(dz, dx))
    ang = (ang + 90.0) % 180.0 - 90.0  # [-90, 90)
    if ang <= -90.0 + 1e-12:
        ang = 90.0
    return k * math.sqrt(w[0]), k * math.sqrt(w[1]), ang


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _tait_bryan(azimuth, plunge, rotation) -> np.ndarray:
    """R = Rz(psi) Ry(phi) Rx(theta) (degrees); columns = major, minor, intermediate in NED."""
    return _rz(math.radians(azimuth)) @ _ry(math.radians(plunge)) @ _rx(math.radians(rotation))


def ellipsoid(cov_zyx, confidence: float = 0.68) -> dict:
    """QuakeML confidence ellipsoid of a 3x3 position covariance over local **(z, y, x)** =
    (down, north, east), m^2, scaled by ``confidence_scale(3, confidence)``.

    Returns a dict with the ConfidenceEllipsoid fields: semi_major_axis_length,
    semi_minor_axis_length, semi_intermediate_axis_length (m), major_axis_azimuth (psi, [0, 360)),
    major_axis_plunge (phi, elevation of the reported end, [0, 90]) and major_axis_rotation
    (theta, (-90, 90]), degrees, in the Tait-Bryan convention of the module docstring.
    """
    c = _check_cov(cov_zyx, 3, "covariance")
    k = confidence_scale(3, confidence)
    ned = c[np.ix_([1, 2, 0], [1, 2, 0])]
    w, v = _eig_desc(ned)  # major, intermediate, minor
    major, minor = v[:, 0], v[:, 2]  # the intermediate axis is X x Y (right-handed frame)
    tol = 1e-9
    if major[2] > tol or (abs(major[2]) <= tol and not _in_half_plane(major)):
        major = -major  # report the upward end (or, horizontal, the one with azimuth in [0, 180))
    psi = math.degrees(math.atan2(major[1], major[0])) % 360.0
    phi = math.degrees(math.asin(min(1.0, max(-1.0, -major[2])))) + 0.0
    if phi > 90.0 - 1e-9:  # vertical major axis: psi is free; pick it so that theta = 0
        phi = 90.0
        psi = (math.degrees(math.atan2(minor[1], minor[0])) - 90.0) % 180.0
    if psi >= 360.0 - 1e-12:
        psi = 0.0
    r0 = _rz(math.radians(psi)) @ _ry(math.radians(phi))
    y0, z0 = r0[:, 1], r0[:, 2]
    theta = math.degrees(math.atan2(float(minor @ z0), float(minor @ y0))) + 0.0
    if theta <= -90.0 or theta > 90.0:
        theta = (theta + 90.0) % 180.0 - 90.0  # minor -> -minor
        if theta <= -90.0 + 1e-12:
            theta = 90.0
    if abs(theta) < 1e-9:
        theta = 0.0
    return {
        "semi_major_axis_length": k * math.sqrt(w[0]),
        "semi_minor_axis_length": k * math.sqrt(w[2]),
        "semi_intermediate_axis_length": k * math.sqrt(w[1]),
        "major_axis_azimuth": psi,
        "major_axis_plunge": phi,
        "major_axis_rotation": theta,
    }


def _in_half_plane(d) -> bool:
    az = math.degrees(math.atan2(d[1], d[0])) % 360.0
    return az < 180.0 - 1e-9


def ellipsoid_covariance(ell, confidence: float = 0.68) -> np.ndarray:
    """Inverse of :func:`ellipsoid`: the 3x3 1-sigma covariance over local (z, y, x) from a dict
    (or an ObsPy ConfidenceEllipsoid) of QuakeML ellipsoid fields at ``confidence``."""
    get = (ell.get if isinstance(ell, dict) else lambda key: getattr(ell, key))
    k = confidence_scale(3, confidence)
    r = _tait_bryan(get("major_axis_azimuth"), get("major_axis_plunge"), get("major_axis_rotation"))
    lengths = np.array([get("semi_major_axis_length"), get("semi_minor_axis_length"),
                        get("semi_intermediate_axis_length")], dtype=float) / k
    ned = r @ np.diag(lengths ** 2) @ r.T
    zyx = [2, 0, 1]
    return ned[np.ix_(zyx, zyx)]


def _slug(text: str) -> str:
    s = re.sub(r"[^\w\-.]+", "_", str(text)).strip("_")
    return s or "method"


def _latlon_jacobian(position, ref: Reference, h: float = 10.0) -> np.ndarray:
    """d(lat, lon)/d(horizontal local coordinates), degrees per metre, shape (2, ndim-1):
    columns (y, x) in 3D, (x,) in 2D."""
    p = np.asarray(position, float)
    cols = []
    for i in range(1, p.size):
        e = np.zeros_like(p)
        e[i] = h
        lat_p, lon_p, _ = unproject(p + e, ref)
        lat_m, lon_m, _ = unproject(p - e, ref)
        dlon = (float(lon_p) - float(lon_m) + 180.0) % 360.0 - 180.0
        cols.append([(float(lat_p) - float(lat_m)) / (2 * h), dlon / (2 * h)])
    return np.array(cols).T


# ------------------------------------------------------------------------------- writing

def write_quakeml(path, *, position, origin_time, covariance, reference, ndim: int,
                  confidence: float = 0.68, method: str = "adseismic waveform inversion",
                  creation_info="adseismic", extra=None, focal_mechanism=None) -> None:
    """Write one located event as QuakeML (Catalog -> Event -> Origin) to ``path``, atomically.

    position: (ndim,) local metres, axis order (z,[y,]x) (see :func:`adseismic.data.geometry.project`);
    origin_time: obspy UTCDateTime (or anything UTCDateTime accepts);
    covariance: (ndim+1, ndim+1) 1-sigma covariance over (position..., origin time), m^2, m*s, s^2;
    reference: the :class:`adseismic.data.geometry.Reference` (or tuple) of the local frame (required);
    ndim: 2 (section along ``reference.azimuth``) or 3;
    confidence: probability (0, 1) of the confidence regions (stored as confidence_level in %);
    method: free text, stored as the origin's method_id ``smi:local/adseismic/method/<slug>``;
    creation_info: author string or an obspy CreationInfo;
    extra: JSON-serialisable dict stored in the local-coordinates comment;
    focal_mechanism: a moment tensor as :func:`adseismic.location.moment_tensor.describe` returns it, written as
    a FocalMechanism (MomentTensor with its Tensor in USE and 1-sigma errors, the scalar moment, the nodal
    planes; a comment names the components 2D does not resolve, carried as 0) derived from the origin.

    Raises ValueError naming the argument for bad input (e.g. a covariance that is not positive
    definite); nothing is left at ``path`` or ``path.part`` on error.
    See the module docstring for every convention.
    """
    from obspy import UTCDateTime
    from obspy.core.event import (
        Catalog,
        Comment,
        ConfidenceEllipsoid,
        CreationInfo,
        Event,
        Origin,
        OriginUncertainty,
        QuantityError,
        ResourceIdentifier,
    )

    if ndim not in (2, 3) or isinstance(ndim, bool):
        raise ValueError(f"ndim: {ndim!r} is not 2 or 3")
    if reference is None:
        raise ValueError("reference: required (QuakeML needs latitude / longitude); pass the "
                         "adseismic.data.geometry.Reference the local coordinates were projected about")
    ref = as_reference(reference)
    conf = _check_confidence(confidence)
    try:
        pos = np.array(position, dtype=float)
    except (TypeError, ValueError):
        pos = np.array([np.nan])
    if pos.shape != (ndim,) or not np.all(np.isfinite(pos)):
        raise ValueError(f"position: {position!r} is not {ndim} finite values in axis order "
                         f"({','.join(_AXES[ndim])}), metres")
    cov = _check_cov(covariance, ndim + 1, "covariance")
    try:
        t0 = origin_time if isinstance(origin_time, UTCDateTime) else UTCDateTime(origin_time)
    except Exception as exc:  # noqa: BLE001 - obspy raises many kinds
        raise ValueError(f"origin_time: {origin_time!r} is not a time ({exc})") from None
    if extra is not None:
        try:
            extra_json = json.loads(json.dumps(extra))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"extra: not JSON-serialisable ({exc})") from None
    else:
        extra_json = None

    lat, lon, elev = (float(v) for v in unproject(pos, ref))
    depth = -elev
    jac = _latlon_jacobian(pos, ref)
    cov_ll = jac @ cov[1:ndim, 1:ndim] @ jac.T
    lat_err, lon_err = (float(math.sqrt(max(v, 0.0))) for v in np.diag(cov_ll))
    depth_err = math.sqrt(cov[0, 0])
    time_err = math.sqrt(cov[ndim, ndim])

    unc = OriginUncertainty(confidence_level=100.0 * conf)
    if ndim == 3:
        ell = ellipsoid(cov[:3, :3], conf)
        unc.confidence_ellipsoid = ConfidenceEllipsoid(**ell)
        smaj, smin, az = ellipse(cov[1:3, 1:3], conf)
        unc.horizontal_uncertainty = smaj
        unc.max_horizontal_uncertainty = smaj
        unc.min_horizontal_uncertainty = smin
        unc.azimuth_max_horizontal_uncertainty = az
        unc.preferred_description = "confidence ellipsoid"
    else:
        along = confidence_scale(1, conf) * math.sqrt(cov[1, 1])
        unc.horizontal_uncertainty = along
        unc.max_horizontal_uncertainty = along
        unc.azimuth_max_horizontal_uncertainty = ref.azimuth % 180.0
        unc.preferred_description = "uncertainty ellipse"

    if isinstance(creation_info, CreationInfo):
        cinfo = creation_info
    else:
        cinfo = CreationInfo(author=str(creation_info), creation_time=UTCDateTime())

    event = Event(event_type="earthquake", creation_info=cinfo)
    origin = Origin(
        resource_id=ResourceIdentifier(prefix="smi:local/adseismic/origin"),
        time=t0, latitude=lat, longitude=lon, depth=depth,
        time_errors=QuantityError(uncertainty=time_err),
        latitude_errors=QuantityError(uncertainty=lat_err),
        longitude_errors=QuantityError(uncertainty=lon_err),
        depth_errors=QuantityError(uncertainty=depth_err),
        depth_type="from location", origin_uncertainty=unc,
        method_id=ResourceIdentifier(f"smi:local/adseismic/method/{_slug(method)}"),
        evaluation_mode="automatic", evaluation_status="preliminary", creation_info=cinfo)
    local = {
        "ndim": ndim,
        "axes": ",".join(_AXES[ndim]),
        "position_m": pos.tolist(),
        "covariance_order": ",".join(_AXES[ndim] + ["t"]),
        "covariance_units": "m^2, m*s, s^2 (1 sigma)",
        "covariance": cov.tolist(),
        "origin_time": str(t0),
        "reference": {"latitude": ref.latitude, "longitude": ref.longitude, "datum": ref.datum,
                      "azimuth": ref.azimuth},
        "frame": "adseismic.data.geometry.project: z = datum - elevation (down); 3D y = north, x = east; "
                 "2D x along reference.azimuth",
        "confidence": conf,
        "method": str(method),
    }
    if extra_json is not None:
        local["extra"] = extra_json
    origin.comments.append(Comment(
        text=json.dumps(local), resource_id=ResourceIdentifier(f"{origin.resource_id}/{_LOCAL_TAG}")))
    origin.comments.append(Comment(text=f"method: {method}"))
    event.origins.append(origin)
    event.preferred_origin_id = origin.resource_id
    if focal_mechanism is not None:
        fm = _focal_mechanism(focal_mechanism, origin, cinfo)
        event.focal_mechanisms.append(fm)
        event.preferred_focal_mechanism_id = fm.resource_id
    catalog = Catalog(events=[event], creation_info=cinfo)

    with atomic_write(path) as part:
        catalog.write(str(part), format="QUAKEML")


def _focal_mechanism(mt: dict, origin, cinfo):
    """ObsPy FocalMechanism of a moment_tensor.describe() dict."""
    from obspy.core.event import Comment, FocalMechanism, MomentTensor, NodalPlane, NodalPlanes, QuantityError, ResourceIdentifier, Tensor

    use, err = mt["use"], mt["use_error_1sigma"]
    tensor = Tensor(**{k: use[k] for k in use}, **{f"{k}_errors": QuantityError(uncertainty=err[k]) for k in use})
    planes = [NodalPlane(strike=p["strike"], dip=p["dip"], rake=p["rake"]) for p in mt["nodal_planes"]]
    mom = MomentTensor(resource_id=ResourceIdentifier(prefix="smi:local/adseismic/momenttensor"), derived_origin_id=origin.resource_id,
                       scalar_moment=mt["scalar_moment"], tensor=tensor, method_id=ResourceIdentifier("smi:local/adseismic/method/waveform-moment-tensor"),
                       inversion_type="zero trace" if mt["constraint"] == "deviatoric" else ("double couple" if mt["constraint"] == "double_couple" else "general"),
                       creation_info=cinfo)  # fmt: skip
    mom.comments.append(Comment(text=f"2D P-SV moment tensor ({mt['constraint']}); units {mt['units']}; unresolved components "
                                     f"(carried as 0): {', '.join(mt['unresolved'])}; local (x along the line, y, z down): "
                                     f"{json.dumps(mt['local_xyz'])}"))  # fmt: skip
    fm = FocalMechanism(resource_id=ResourceIdentifier(prefix="smi:local/adseismic/focalmechanism"), triggering_origin_id=origin.resource_id,
                        nodal_planes=NodalPlanes(nodal_plane_1=planes[0], nodal_plane_2=planes[1]), moment_tensor=mom,
                        evaluation_mode="automatic", evaluation_status="preliminary", creation_info=cinfo)  # fmt: skip
    return fm


def read_quakeml_focal_mechanism(path) -> dict:
    """The preferred (else first) focal mechanism of the first event: {"use": {m_rr..m_tp}, "use_error_1sigma",
    "scalar_moment", "nodal_planes": [{strike, dip, rake}, ...], "comment"}."""
    import obspy

    event = obspy.read_events(str(path))[0]
    fm = event.preferred_focal_mechanism() or (event.focal_mechanisms[0] if event.focal_mechanisms else None)
    if fm is None:
        raise ValueError(f"{path}: the event has no focal mechanism")
    t = fm.moment_tensor.tensor
    keys = ("m_rr", "m_tt", "m_pp", "m_rt", "m_rp", "m_tp")
    planes = [fm.nodal_planes.nodal_plane_1, fm.nodal_planes.nodal_plane_2]
    return {"use": {k: getattr(t, k) for k in keys}, "use_error_1sigma": {k: getattr(t, f"{k}_errors").uncertainty for k in keys},
            "scalar_moment": fm.moment_tensor.scalar_moment, "nodal_planes": [{"strike": p.strike, "dip": p.dip, "rake": p.rake} for p in planes],
            "comment": fm.moment_tensor.comments[0].text if fm.moment_tensor.comments else ""}  # fmt: skip


# ------------------------------------------------------------------------------- reading

def read_quakeml_origin(path) -> dict:
    """Read the preferred origin (else the first) of the first event of a QuakeML file.

    Returns a dict: latitude, longitude (deg), depth (m below sea level), time (UTCDateTime),
    latitude_error, longitude_error (deg), depth_error (m), time_error (s) (1 sigma, None if
    absent), confidence_level (%), preferred_description, horizontal_uncertainty,
    min_horizontal_uncertainty, max_horizontal_uncertainty (m),
    azimuth_max_horizontal_uncertainty (deg), ellipsoid (dict of the ConfidenceEllipsoid fields
    or None), method_id (str or None), evaluation_mode, evaluation_status, and local (the
    adseismic comment decoded from JSON, with "covariance" as an array and "reference" as a
    adseismic.data.geometry.Reference; None for files written elsewhere).
    """
    import obspy

    cat = obspy.read_events(str(path))
    if not len(cat):
        raise ValueError(f"{path}: no events in the QuakeML file")
    event = cat[0]
    origin = event.preferred_origin() or (event.origins[0] if event.origins else None)
    if origin is None:
        raise ValueError(f"{path}: event {event.resource_id} has no origin")

    def err(q):
        return None if q is None or q.uncertainty is None else float(q.uncertainty)

    out = {
        "latitude": origin.latitude, "longitude": origin.longitude, "depth": origin.depth,
        "time": origin.time,
        "latitude_error": err(origin.latitude_errors),
        "longitude_error": err(origin.longitude_errors),
        "depth_error": err(origin.depth_errors), "time_error": err(origin.time_errors),
        "method_id": str(origin.method_id) if origin.method_id is not None else None,
        "evaluation_mode": origin.evaluation_mode, "evaluation_status": origin.evaluation_status,
        "confidence_level": None, "preferred_description": None, "horizontal_uncertainty": None,
        "min_horizontal_uncertainty": None, "max_horizontal_uncertainty": None,
        "azimuth_max_horizontal_uncertainty": None, "ellipsoid": None, "local": None,
    }
    unc = origin.origin_uncertainty
    if unc is not None:
        for key in ("confidence_level", "preferred_description", "horizontal_uncertainty",
                    "min_horizontal_uncertainty", "max_horizontal_uncertainty",
                    "azimuth_max_horizontal_uncertainty"):
            out[key] = getattr(unc, key)
        if unc.preferred_description is not None:
            out["preferred_description"] = str(unc.preferred_description)
        ce = unc.confidence_ellipsoid
        if ce is not None and ce.semi_major_axis_length is not None:
            out["ellipsoid"] = {key: getattr(ce, key) for key in (
                "semi_major_axis_length", "semi_minor_axis_length", "semi_intermediate_axis_length",
                "major_axis_azimuth", "major_axis_plunge", "major_axis_rotation")}
    for c in origin.comments:
        if c.resource_id is not None and str(c.resource_id).endswith("/" + _LOCAL_TAG):
            try:
                local = json.loads(c.text)
            except (TypeError, ValueError):
                break
            local["covariance"] = np.asarray(local["covariance"], dtype=float)
            local["position_m"] = np.asarray(local["position_m"], dtype=float)
            local["reference"] = Reference(**local["reference"])
            out["local"] = local
            break
    return out
