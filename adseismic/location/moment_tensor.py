"""Moment tensors of 2D (P-SV) sources: the constraints the locator fits under, the full 3D tensor with what
2D cannot see marked, and the nodal planes (strike, dip, rake) of its double couple.

Frames. The 2D section is the plane (x, z) of the model: x along the line of azimuth ``azimuth`` (degrees
clockwise from north, the traces' reference azimuth), z down; y = z cross x completes a right-handed frame
(y points to azimuth + 90 degrees). Components are in N m (per metre of line in 2D), Aki & Richards' sign
convention (the equivalent body force is -div(M delta); an explosion has M = M0 I). QuakeML's Tensor is in
USE (r up, t south, p east).

What 2D P-SV resolves. A line source in the (x, z) plane radiates P-SV waves through Mxx, Mzz and Mxz only;
Mxy and Myz radiate SH (not simulated, not recorded by vx, vz) and Myy radiates nothing in-plane (its body
force acts along y, and d/dy = 0). So:

* ``none``: the three in-plane components are free; Myy, Mxy, Myz are unresolved (reported as such; the
  QuakeML tensor carries 0 for them, with a comment).
* ``deviatoric``: trace M = 0, i.e. Myy = -(Mxx + Mzz). The in-plane fit is the same as ``none`` (Myy is
  unseen), but Myy is then determined by the constraint; Mxy, Myz remain unresolved.
* ``double_couple``: a pure shear dislocation on a fault that strikes along the section's normal (y), with
  dip-slip (rake +-90): the only double couples with no SH part. Then Myy = Mxy = Myz = 0 and the in-plane
  tensor is trace-free: (Mxx, Mzz, Mxz) = M0 (-sin 2d, sin 2d, cos 2d) for a fault dipping d toward +x (a
  negative M0 flips the slip: normal <-> reverse). Two free coefficients, linear: a = Mzz = -Mxx, b = Mxz;
  M0 = sqrt(a^2 + b^2), the dip from atan2(a, b) (and 90 - dip for the auxiliary plane).

Nothing here imports ObsPy (the simulation path stays importable without it); the beachball does, lazily.
"""

from __future__ import annotations

import math

import numpy as np

CONSTRAINTS = ("none", "deviatoric", "double_couple")
#: coefficients -> in-plane (Mxx, Mzz, Mxz): m = a @ BASIS[constraint]
BASIS = {"none": np.eye(3), "deviatoric": np.eye(3), "double_couple": np.array([[-1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])}
COMPONENTS_LOCAL = ("Mxx", "Myy", "Mzz", "Mxy", "Mxz", "Myz")
COMPONENTS_USE = ("m_rr", "m_tt", "m_pp", "m_rt", "m_rp", "m_tp")


def unresolved(constraint: str) -> tuple:
    """The local components a 2D P-SV fit under `constraint` does not determine."""
    return ("Myy", "Mxy", "Myz") if constraint == "none" else ("Mxy", "Myz")


def tensor_local(m_inplane, constraint: str) -> np.ndarray:
    """(3, 3) tensor over (x, y, z) from the in-plane (Mxx, Mzz, Mxz): Myy = -(Mxx + Mzz) (deviatoric), 0
    otherwise (double couple: 0 by the constraint; none: unresolved, put at 0); Mxy = Myz = 0 (unresolved)."""
    mxx, mzz, mxz = (float(v) for v in m_inplane)
    myy = -(mxx + mzz) if constraint == "deviatoric" else 0.0
    return np.array([[mxx, 0.0, mxz], [0.0, myy, 0.0], [mxz, 0.0, mzz]])


def section_rotation(azimuth: float) -> np.ndarray:
    """(3, 3) columns: the local x, y, z unit vectors in (north, east, down) for a line of azimuth (degrees)."""
    a = math.radians(azimuth)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def to_ned(m_local, azimuth: float) -> np.ndarray:
    """(3, 3) local (x, y, z) tensor -> (north, east, down)."""
    R = section_rotation(azimuth)
    return R @ np.asarray(m_local, float) @ R.T


def ned_to_use(m_ned) -> dict:
    """{m_rr, m_tt, m_pp, m_rt, m_rp, m_tp} (r up, t south, p east) of a (north, east, down) tensor."""
    m = np.asarray(m_ned, float)
    return {"m_rr": m[2, 2], "m_tt": m[0, 0], "m_pp": m[1, 1], "m_rt": m[0, 2], "m_rp": -m[1, 2], "m_tp": -m[0, 1]}


def local_covariance_to_use(cov_inplane, azimuth: float) -> dict:
    """1-sigma errors of the USE components from the covariance (3, 3) of (Mxx, Mzz, Mxz) (linear map)."""
    J = np.empty((6, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1.0
        J[:, k] = list(ned_to_use(to_ned(tensor_local(e, "none"), azimuth)).values())
    c = J @ np.asarray(cov_inplane, float) @ J.T
    return dict(zip(COMPONENTS_USE, np.sqrt(np.maximum(np.diag(c), 0.0))))


def scalar_moment(m) -> float:
    """M0 = sqrt(sum M_ij^2 / 2) of a (3, 3) tensor (N m; per metre of line in 2D)."""
    m = np.asarray(m, float)
    return float(np.sqrt(np.sum(m * m) / 2.0))


def _plane(n, s) -> tuple[float, float, float]:
    """(strike, dip, rake) degrees of the plane with normal n and slip s in (north, east, down) (Aki & Richards)."""
    if n[2] > 0:  # the normal of the hanging wall points up
        n, s = -n, -s
    dip = math.degrees(math.acos(min(1.0, max(-1.0, -n[2]))))
    strike = math.degrees(math.atan2(-n[0], n[1])) % 360.0
    phi, d = math.radians(strike), math.radians(dip)
    sin_r = -s[2] / max(math.sin(d), 1e-12)
    cos_r = s[0] * math.cos(phi) + s[1] * math.sin(phi)
    return strike, dip, math.degrees(math.atan2(sin_r, cos_r))


def nodal_planes(m_ned) -> list:
    """The two nodal planes [(strike, dip, rake), (strike, dip, rake)] (degrees; strike in [0, 360), dip in
    [0, 90], rake in (-180, 180]) of the double couple of a (north, east, down) tensor: from its T (largest
    eigenvalue) and P (smallest) axes, normal and slip (T +- P) / sqrt(2)."""
    _, v = np.linalg.eigh(np.asarray(m_ned, float))  # eigenvalues ascending
    t, p = v[:, 2], v[:, 0]
    n1, s1 = (t + p) / math.sqrt(2), (t - p) / math.sqrt(2)
    return [_plane(n1, s1), _plane(s1, n1)]


def double_couple_dip(m_inplane) -> tuple[float, float]:
    """(M0, dip) of an in-plane double couple (Mxx, Mzz, Mxz) = M0 (-sin 2d, sin 2d, cos 2d), dip in [0, 90) degrees
    toward +x, M0 signed; the trace-free part of a general in-plane tensor is used."""
    mxx, mzz, mxz = (float(v) for v in m_inplane)
    a, b = 0.5 * (mzz - mxx), mxz
    m0 = math.hypot(a, b)
    two_d = math.degrees(math.atan2(a, b))  # (-180, 180]
    d = (0.5 * two_d) % 180.0
    if d >= 90.0:  # the same plane dipping the other way is (d - 90) with -M0
        d, m0 = d - 90.0, -m0
    return m0, d


def in_plane_double_couple(m0: float, dip: float) -> np.ndarray:
    """(Mxx, Mzz, Mxz) of a fault of dip `dip` degrees toward +x, striking along y, dip-slip with moment m0 (> 0:
    reverse, the hanging wall moves up-dip; < 0: normal)."""
    d = math.radians(2 * dip)
    return m0 * np.array([-math.sin(d), math.sin(d), math.cos(d)])


def describe(m_inplane, cov_inplane, constraint: str, azimuth: float) -> dict:
    """The numbers of a located moment tensor for summary.json and QuakeML: local components (unresolved ones
    None), 1-sigma errors, normalised in-plane components, USE components and errors, scalar moment, the nodal
    planes of the double couple, and what 2D resolves."""
    m_loc = tensor_local(m_inplane, constraint)
    names = dict(zip(COMPONENTS_LOCAL, (m_loc[0, 0], m_loc[1, 1], m_loc[2, 2], m_loc[0, 1], m_loc[0, 2], m_loc[1, 2])))
    sd = np.sqrt(np.maximum(np.diag(cov_inplane), 0.0))
    err = {"Mxx": sd[0], "Mzz": sd[1], "Mxz": sd[2]}
    if constraint == "deviatoric":
        e = np.array([1.0, 1.0, 0.0])
        err["Myy"] = float(np.sqrt(max(e @ np.asarray(cov_inplane) @ e, 0.0)))
    elif constraint == "double_couple":
        err["Myy"] = 0.0
    un = unresolved(constraint)
    m_ned = to_ned(m_loc, azimuth)
    m = np.asarray(m_inplane, float)
    norm = float(np.sqrt(m[0] ** 2 + m[1] ** 2 + 2 * m[2] ** 2))
    out = {
        "constraint": constraint,
        "units": "N m per metre of line (2D)",
        "local_xyz": {k: (None if k in un else float(v)) for k, v in names.items()},
        "local_xyz_error_1sigma": {k: float(v) for k, v in err.items()},
        "unresolved": list(un),
        "normalised_inplane": dict(zip(("Mxx", "Mzz", "Mxz"), (m / (norm or 1.0)).tolist())),
        "use": {k: float(v) for k, v in ned_to_use(m_ned).items()},
        "use_error_1sigma": {k: float(v) for k, v in local_covariance_to_use(cov_inplane, azimuth).items()},
        "scalar_moment": scalar_moment(m_loc),
        "nodal_planes": [dict(zip(("strike", "dip", "rake"), p)) for p in nodal_planes(m_ned)],
        "note": "2D P-SV resolves Mxx, Mzz, Mxz only; Mxy, Myz (SH) are never seen and Myy only through the constraint",
    }
    if constraint == "double_couple":
        m0, dip = double_couple_dip(m_inplane)
        out["dip_toward_x_deg"], out["signed_scalar_moment"] = dip, m0
    return out


def plot_beachball(path, m_ned, title: str = ""):
    """The focal sphere (lower hemisphere) of a (north, east, down) tensor as a PNG, through ObsPy's beachball."""
    from obspy.imaging.beachball import beach

    from adseismic.plotting import _figure, save_figure

    use = ned_to_use(m_ned)
    fig = _figure(4.0, 4.3)
    ax = fig.add_subplot()
    ax.add_collection(beach([use[k] for k in COMPONENTS_USE], xy=(0, 0), width=1.9, linewidth=1, facecolor="tab:red"))
    ax.set_xlim(-1.05, 1.05)
    ax.set_ylim(-1.05, 1.05)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(title, fontsize=9)
    return save_figure(fig, path)
