"""Geodesy through pyproj (issue 27): the local frame of :mod:`adseismic.data.geometry` (PROJ's WGS84 aeqd) agrees with
the hand-written Vincenty geodesic it replaced to 1 mm out to 100 km, keeps its axis conventions (x along the line
azimuth, z down, datum), and a missing pyproj is a one-line error with the pip command.

The old formulas live here only, as the reference (copied verbatim from adseismic/data/geometry.py before the change).
"""
import math
import sys

import numpy as np
import pytest

from adseismic.data.geometry import Reference, offline_distance, project, unproject
from adseismic.data.traces import TraceError

pytest.importorskip("pyproj")

# ----------------------------------------------------------------- the old implementation (reference only)

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
        raise RuntimeError("Vincenty's inverse formula did not converge")
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



def _old_east_north(lat0, lon0, lat, lon):
    s, alpha = _vincenty_inverse(lat0, lon0, lat, lon)
    return s * np.sin(alpha), s * np.cos(alpha)


# ----------------------------------------------------------------- agreement

REFS = [(46.5, 8.2), (0.0, 0.0), (-33.9, 151.2), (64.1, -21.9), (79.0, 15.0), (-77.8, 166.7), (35.7, 179.9),
        (38.3, 350.0)]
MM = 1e-3


def _points(lat0, lon0, n=4000, s_max=100e3, seed=0):
    """n points at geodesic distances up to s_max from (lat0, lon0), uniform in distance and azimuth (old direct)."""
    rng = np.random.default_rng(seed)
    s = np.concatenate([[0.0, 1.0, s_max], rng.uniform(0, s_max, n)])
    alpha = np.concatenate([[0.3, -2.0, 1.1], rng.uniform(-np.pi, np.pi, n)])
    lat, lon = _vincenty_direct(lat0, lon0, s, alpha)
    return lat, lon, s, alpha


@pytest.mark.parametrize("lat0, lon0", REFS)
def test_projection_agrees_with_the_old_vincenty_to_1mm_out_to_100km(lat0, lon0):
    lat, lon, s, alpha = _points(lat0, lon0)
    elev = np.linspace(-3000, 4000, lat.size)
    ref = Reference(lat0, lon0, datum=120.0)
    new = project(lat, lon, elev, ref, ndim=3)
    e_old, n_old = _old_east_north(lat0, lon0, lat, lon)
    err = np.hypot(new[:, 2] - e_old, new[:, 1] - n_old)
    assert err.max() < 1 * MM, f"max difference {err.max() / MM:.4f} mm"
    # and both equal the (distance, azimuth) the points were built from
    assert np.hypot(new[:, 2] - s * np.sin(alpha), new[:, 1] - s * np.cos(alpha)).max() < 1 * MM
    np.testing.assert_array_equal(new[:, 0], 120.0 - elev)  # z = datum - elevation, down


@pytest.mark.parametrize("azimuth", [90.0, 0.0, 37.5, 200.0])
def test_2d_line_and_offline_distance_agree_with_the_old_formulas(azimuth):
    lat0, lon0 = 46.5, 8.2
    lat, lon, _, _ = _points(lat0, lon0, n=1000, seed=1)
    ref = Reference(lat0, lon0, 0.0, azimuth)
    e, n = _old_east_north(lat0, lon0, lat, lon)
    az = math.radians(azimuth)
    x_old = e * math.sin(az) + n * math.cos(az)
    off_old = np.abs(-e * math.cos(az) + n * math.sin(az))
    p = project(lat, lon, np.zeros_like(lat), ref, ndim=2)
    assert p.shape == (lat.size, 2)
    assert np.abs(p[:, 1] - x_old).max() < 1 * MM
    assert np.abs(offline_distance(lat, lon, ref) - off_old).max() < 1 * MM


@pytest.mark.parametrize("lat0, lon0", REFS)
def test_unproject_agrees_with_the_old_direct_formula_and_inverts_project(lat0, lon0):
    rng = np.random.default_rng(2)
    east, north = rng.uniform(-70e3, 70e3, (2, 2000))
    z = rng.uniform(-2000, 30000, 2000)
    ref = Reference(lat0, lon0, datum=50.0)
    lat, lon, elev = unproject(np.stack([z, north, east], axis=-1), ref)
    lat_old, lon_old = _vincenty_direct(lat0, lon0, np.hypot(east, north), np.arctan2(east, north))
    # compare on the ground: old and new points' separation in metres (old inverse distance between them)
    d, _ = _vincenty_inverse(lat_old[0], lon_old[0], lat[:1], lon[:1])
    assert d.max() < 1 * MM
    e2, n2 = _old_east_north(lat0, lon0, lat, lon)
    assert np.hypot(e2 - east, n2 - north).max() < 1 * MM
    back = project(lat, lon, elev, ref, ndim=3)
    assert np.abs(back - np.stack([z, north, east], axis=-1)).max() < 1e-6 * 1e3  # 1 mm, in practice ~1e-9 m
    np.testing.assert_allclose(elev, 50.0 - z, atol=1e-9)
    # the reference itself maps to (lat0, lon0) exactly
    lat_r, lon_r, el_r = unproject(np.array([[0.0, 0.0, 0.0]]), ref)
    assert (lat_r[0], lon_r[0], el_r[0]) == (lat0, lon0, 50.0)


def test_2d_unproject_places_points_on_the_line():
    ref = Reference(46.5, 8.2, 0.0, 30.0)
    x = np.linspace(-50e3, 50e3, 11)
    lat, lon, _ = unproject(np.stack([np.zeros_like(x), x], axis=-1), ref)
    p = project(lat, lon, 0.0, ref, ndim=2)
    np.testing.assert_allclose(p[:, 1], x, atol=1e-6)
    assert offline_distance(lat, lon, ref).max() < 1e-6


def test_missing_pyproj_is_a_one_line_error_with_the_pip_command(monkeypatch):
    import adseismic.data.geometry as g

    monkeypatch.setitem(sys.modules, "pyproj", None)  # import pyproj -> ImportError
    g._aeqd.cache_clear()
    try:
        with pytest.raises(TraceError) as e:
            project([46.6], [8.3], [0.0], Reference(46.51, 8.21))
    finally:
        g._aeqd.cache_clear()
    msg = str(e.value)
    assert "\n" not in msg and "pip install 'adseismic[geo]'" in msg and "pyproj" in msg
