"""adseismic.quakeml: confidence scales, ellipse / ellipsoid conventions, QuakeML round trips
through ObsPy, bad input and atomic writing."""
import json
import math

import numpy as np
import pytest

from adseismic.data import geometry as G
from adseismic.location import quakeml as Q

obspy = pytest.importorskip("obspy")
scipy_stats = pytest.importorskip("scipy.stats")
from obspy import UTCDateTime  # noqa: E402

REF3 = G.Reference(46.5, 7.25, 450.0)
REF2 = G.Reference(-33.2, 151.1, 0.0, 60.0)
T0 = UTCDateTime("2024-03-05T12:34:56.123456Z")


def _rot2(deg):
    """Columns: unit vectors (north, east) at azimuth deg and deg + 90 (clockwise from north)."""
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def _cov3(seed=0):
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((4, 4)) * np.array([200.0, 150.0, 300.0, 0.05])
    return a @ a.T + np.diag([400.0, 300.0, 500.0, 1e-4])


# ------------------------------------------------------------------------------- scales

@pytest.mark.parametrize("dof", [1, 2, 3, 5])
@pytest.mark.parametrize("conf", [0.5, 0.68, 0.9, 0.95, 0.99])
def test_confidence_scale_matches_chi2(dof, conf):
    k = Q.confidence_scale(dof, conf)
    assert k == pytest.approx(math.sqrt(scipy_stats.chi2.ppf(conf, dof)), rel=1e-12)
    # the region |x| <= k of a standard Gaussian in dof dimensions holds `conf`
    assert scipy_stats.chi2.cdf(k * k, dof) == pytest.approx(conf, rel=1e-10)


def test_confidence_scale_documented_values():
    assert Q.confidence_scale(1, 0.68) == pytest.approx(0.9945, abs=1e-4)
    assert Q.confidence_scale(2, 0.68) == pytest.approx(1.5096, abs=1e-4)
    assert Q.confidence_scale(3, 0.68) == pytest.approx(1.8724, abs=1e-4)
    assert Q.confidence_scale(1, 0.95) == pytest.approx(1.960, abs=5e-4)


@pytest.mark.parametrize("dof, conf, key", [(0, 0.68, "dof"), (1.5, 0.68, "dof"),
                                            (2, 68, "confidence"), (2, 0.0, "confidence"),
                                            (2, 1.0, "confidence")])
def test_confidence_scale_bad_input(dof, conf, key):
    with pytest.raises(ValueError, match=key):
        Q.confidence_scale(dof, conf)


# ------------------------------------------------------------------------------- ellipses

@pytest.mark.parametrize("azimuth", [30.0, 210.0])
def test_ellipse_rotated_covariance(azimuth):
    r = _rot2(azimuth)
    cov = r @ np.diag([100.0 ** 2, 40.0 ** 2]) @ r.T  # over (north, east)
    k = Q.confidence_scale(2, 0.68)
    smaj, smin, az = Q.ellipse(cov)
    assert smaj == pytest.approx(k * 100.0, rel=1e-12)
    assert smin == pytest.approx(k * 40.0, rel=1e-12)
    assert az == pytest.approx(30.0, abs=1e-9)  # 210 folds to 30


def test_ellipse_axis_order_is_north_east():
    # large east variance -> major axis east (90); large north -> 0
    assert Q.ellipse(np.diag([1.0, 9.0]))[2] == pytest.approx(90.0)
    assert Q.ellipse(np.diag([9.0, 1.0]))[2] == pytest.approx(0.0)
    # azimuth 150 (SE-NW axis): north and east anti-correlated
    r = _rot2(150.0)
    az = Q.ellipse(r @ np.diag([4.0, 1.0]) @ r.T)[2]
    assert az == pytest.approx(150.0, abs=1e-9)
    assert 0.0 <= Q.ellipse(np.diag([9.0, 1.0]))[2] < 180.0


def test_ellipse_confidence_95():
    smaj, smin, _ = Q.ellipse(np.diag([25.0, 4.0]), confidence=0.95)
    assert smaj == pytest.approx(5.0 * math.sqrt(scipy_stats.chi2.ppf(0.95, 2)))
    assert smin == pytest.approx(2.0 * math.sqrt(scipy_stats.chi2.ppf(0.95, 2)))


def test_ellipse_2d_angle_from_x_toward_z():
    k = Q.confidence_scale(2, 0.68)
    for ang in (0.0, 25.0, -40.0, 89.0):
        a = math.radians(ang)
        major = np.array([math.sin(a), math.cos(a)])  # (z, x): from +x toward +z (down)
        minor = np.array([math.cos(a), -math.sin(a)])
        cov = 300.0 ** 2 * np.outer(major, major) + 70.0 ** 2 * np.outer(minor, minor)
        smaj, smin, got = Q.ellipse_2d(cov)
        assert smaj == pytest.approx(k * 300.0, rel=1e-12)
        assert smin == pytest.approx(k * 70.0, rel=1e-12)
        assert got == pytest.approx(ang, abs=1e-9)
    assert Q.ellipse_2d(np.diag([9.0, 1.0]))[2] == pytest.approx(90.0)  # vertical major axis


def test_ellipsoid_diagonal():
    k = Q.confidence_scale(3, 0.68)
    # (z, y, x) = (down, north, east): sigma 120, 50, 300 -> major east, minor north, intermediate down
    ell = Q.ellipsoid(np.diag([120.0 ** 2, 50.0 ** 2, 300.0 ** 2]))
    assert ell["semi_major_axis_length"] == pytest.approx(k * 300.0)
    assert ell["semi_intermediate_axis_length"] == pytest.approx(k * 120.0)
    assert ell["semi_minor_axis_length"] == pytest.approx(k * 50.0)
    assert ell["major_axis_azimuth"] == pytest.approx(90.0)
    assert ell["major_axis_plunge"] == pytest.approx(0.0, abs=1e-9)
    assert ell["major_axis_rotation"] == pytest.approx(0.0, abs=1e-9)
    # major north, minor down -> rotation 90 (the minor axis is turned from east to vertical)
    ell = Q.ellipsoid(np.diag([50.0 ** 2, 300.0 ** 2, 120.0 ** 2]))
    assert (ell["major_axis_azimuth"], ell["major_axis_plunge"]) == pytest.approx((0.0, 0.0), abs=1e-9)
    assert abs(ell["major_axis_rotation"]) == pytest.approx(90.0)
    # major vertical -> plunge 90
    ell = Q.ellipsoid(np.diag([300.0 ** 2, 50.0 ** 2, 120.0 ** 2]))
    assert ell["major_axis_plunge"] == pytest.approx(90.0)
    assert ell["semi_major_axis_length"] == pytest.approx(k * 300.0)


def test_ellipsoid_tilted_major_axis_direction():
    # major axis dipping 30 deg below the horizontal toward the east (down-dip end at azimuth 90)
    a = math.radians(30.0)
    d = np.array([math.sin(a), 0.0, math.cos(a)])  # (z, y, x)
    cov = 500.0 ** 2 * np.outer(d, d) + np.diag([1.0, 1.0, 1.0]) * 1e-6
    cov += 20.0 ** 2 * np.outer([0, 1, 0], [0, 1, 0])
    e = np.cross(d, [0, 1, 0])
    cov += 10.0 ** 2 * np.outer(e, e)
    ell = Q.ellipsoid(cov)
    # reported end points up: elevation 30 toward azimuth 270 (= plunging 30 down toward 90)
    assert ell["major_axis_azimuth"] == pytest.approx(270.0, abs=1e-6)
    assert ell["major_axis_plunge"] == pytest.approx(30.0, abs=1e-6)
    r = Q._tait_bryan(ell["major_axis_azimuth"], ell["major_axis_plunge"], ell["major_axis_rotation"])
    x_ned = r[:, 0]  # (north, east, down)
    assert abs(x_ned @ np.array([0.0, math.cos(a), math.sin(a)])) == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("seed", range(20))
def test_ellipsoid_rebuilds_covariance(seed):
    cov = _cov3(seed)[:3, :3]
    for conf in (0.68, 0.95):
        ell = Q.ellipsoid(cov, conf)
        assert 0.0 <= ell["major_axis_azimuth"] < 360.0
        assert 0.0 <= ell["major_axis_plunge"] <= 90.0
        assert -90.0 < ell["major_axis_rotation"] <= 90.0
        assert (ell["semi_major_axis_length"] >= ell["semi_intermediate_axis_length"]
                >= ell["semi_minor_axis_length"] > 0)
        np.testing.assert_allclose(Q.ellipsoid_covariance(ell, conf), cov, rtol=1e-9,
                                   atol=1e-9 * np.abs(cov).max())


@pytest.mark.parametrize("fn, n", [(Q.ellipse, 2), (Q.ellipse_2d, 2), (Q.ellipsoid, 3)])
def test_ellipse_not_positive_definite(fn, n):
    bad = np.eye(n)
    bad[0, 0] = -1.0
    with pytest.raises(ValueError, match="not positive definite"):
        fn(bad)
    with pytest.raises(ValueError, match="symmetric"):
        fn(np.eye(n) + np.triu(np.ones((n, n)), 1))


# ------------------------------------------------------------------------------- QuakeML

def test_write_read_3d_round_trip(tmp_path):
    pos = np.array([8123.456, -15321.25, 22890.75])  # (z, y, x)
    cov = _cov3(3)
    path = tmp_path / "event.xml"
    Q.write_quakeml(path, position=pos, origin_time=T0, covariance=cov, reference=REF3, ndim=3,
                    extra={"misfit": 0.25})
    assert path.exists() and not (tmp_path / "event.xml.part").exists()

    from obspy.io.quakeml.core import _validate
    assert _validate(str(path))  # valid against the QuakeML 1.2 schema

    cat = obspy.read_events(str(path))
    assert len(cat) == 1
    ev = cat[0]
    org = ev.preferred_origin()
    assert org is not None and org.resource_id == ev.preferred_origin_id
    assert org.evaluation_mode == "automatic" and org.evaluation_status == "preliminary"
    assert "adseismic" in str(org.method_id)
    assert abs(org.time - T0) < 1e-6
    back = G.project(org.latitude, org.longitude, -org.depth, REF3, ndim=3)
    np.testing.assert_allclose(back, pos, atol=1e-3)

    # scalar errors: 1 sigma
    assert org.depth_errors.uncertainty == pytest.approx(math.sqrt(cov[0, 0]))
    assert org.time_errors.uncertainty == pytest.approx(math.sqrt(cov[3, 3]))
    m_per_deg_lat = 111_132.0  # roughly, at 46.5 N
    assert org.latitude_errors.uncertainty * m_per_deg_lat == pytest.approx(math.sqrt(cov[1, 1]), rel=0.02)
    m_per_deg_lon = 111_320.0 * math.cos(math.radians(46.5))
    assert org.longitude_errors.uncertainty * m_per_deg_lon == pytest.approx(math.sqrt(cov[2, 2]), rel=0.02)

    unc = org.origin_uncertainty
    assert unc.preferred_description == "confidence ellipsoid"
    assert unc.confidence_level == pytest.approx(68.0)
    ell = Q.ellipsoid(cov[:3, :3])
    for key, val in ell.items():
        assert getattr(unc.confidence_ellipsoid, key) == pytest.approx(val, rel=1e-9, abs=1e-9)
    smaj, smin, az = Q.ellipse(cov[1:3, 1:3])
    assert unc.max_horizontal_uncertainty == pytest.approx(smaj)
    assert unc.min_horizontal_uncertainty == pytest.approx(smin)
    assert unc.azimuth_max_horizontal_uncertainty == pytest.approx(az)

    got = Q.read_quakeml_origin(path)
    assert got["latitude"] == org.latitude and got["depth"] == org.depth
    assert abs(got["time"] - T0) < 1e-6
    assert got["ellipsoid"] == pytest.approx(ell, rel=1e-9, abs=1e-9)
    np.testing.assert_allclose(Q.ellipsoid_covariance(got["ellipsoid"], got["confidence_level"] / 100),
                               cov[:3, :3], rtol=1e-8, atol=1e-8 * np.abs(cov).max())
    local = got["local"]
    np.testing.assert_array_equal(local["position_m"], pos)
    np.testing.assert_array_equal(local["covariance"], cov)
    assert local["reference"] == REF3 and local["axes"] == "z,y,x" and local["ndim"] == 3
    assert local["extra"] == {"misfit": 0.25}


def test_latlon_errors_match_jacobian(tmp_path):
    # a pure-north and a pure-east uncertainty map to latitude / longitude errors alone
    pos = np.array([5000.0, 0.0, 0.0])
    cov = np.diag([100.0 ** 2, 1000.0 ** 2, 1e-6, 0.01])
    path = tmp_path / "n.xml"
    Q.write_quakeml(path, position=pos, origin_time=T0, covariance=cov, reference=REF3, ndim=3)
    got = Q.read_quakeml_origin(path)
    lat_p, _, _ = G.unproject(pos + [0, 1000.0, 0], REF3)
    assert got["latitude_error"] == pytest.approx(float(lat_p) - REF3.latitude, rel=1e-4)
    assert got["longitude_error"] < 1e-7  # east sigma 1 mm


def test_write_read_2d_round_trip(tmp_path):
    pos = np.array([3456.789, -12345.678])  # (z, x along azimuth 60)
    cov = np.array([[250.0 ** 2, 0.3 * 250 * 400, 2.0],
                    [0.3 * 250 * 400, 400.0 ** 2, -3.0],
                    [2.0, -3.0, 0.04 ** 2]])
    path = tmp_path / "section.xml"
    Q.write_quakeml(path, position=pos, origin_time=T0, covariance=cov, reference=REF2, ndim=2,
                    confidence=0.9, method="my method / v2")
    from obspy.io.quakeml.core import _validate
    assert _validate(str(path))
    org = obspy.read_events(str(path))[0].preferred_origin()
    back = G.project(org.latitude, org.longitude, -org.depth, REF2, ndim=2)
    np.testing.assert_allclose(back, pos, atol=1e-3)
    assert abs(org.time - T0) < 1e-6
    unc = org.origin_uncertainty
    assert unc.preferred_description == "uncertainty ellipse"
    assert unc.confidence_level == pytest.approx(90.0)
    k1 = math.sqrt(scipy_stats.chi2.ppf(0.9, 1))
    assert unc.horizontal_uncertainty == pytest.approx(k1 * 400.0)
    assert unc.max_horizontal_uncertainty == pytest.approx(k1 * 400.0)
    assert unc.min_horizontal_uncertainty is None  # off-line position is not constrained in 2D
    assert unc.azimuth_max_horizontal_uncertainty == pytest.approx(60.0)
    assert unc.confidence_ellipsoid is None or unc.confidence_ellipsoid.semi_major_axis_length is None
    assert org.depth_errors.uncertainty == pytest.approx(250.0)
    assert org.time_errors.uncertainty == pytest.approx(0.04)
    # along-line sigma 400 m at azimuth 60: latitude part 400 cos 60, longitude part 400 sin 60
    assert org.latitude_errors.uncertainty * 110_900 == pytest.approx(200.0, rel=0.01)
    lon_m = 111_320.0 * math.cos(math.radians(org.latitude))
    assert org.longitude_errors.uncertainty * lon_m == pytest.approx(400 * math.sin(math.radians(60)), rel=0.01)
    got = Q.read_quakeml_origin(path)
    assert got["local"]["axes"] == "z,x"
    np.testing.assert_array_equal(got["local"]["covariance"], cov)
    assert got["local"]["method"] == "my method / v2"


def test_comment_is_json(tmp_path):
    path = tmp_path / "c.xml"
    Q.write_quakeml(path, position=[1000.0, 2.0, 3.0], origin_time=T0, covariance=np.eye(4),
                    reference=REF3, ndim=3)
    org = obspy.read_events(str(path))[0].origins[0]
    texts = [c.text for c in org.comments if str(c.resource_id).endswith("adseismic-local")]
    assert len(texts) == 1
    data = json.loads(texts[0])
    assert data["covariance_order"] == "z,y,x,t"


@pytest.mark.parametrize("cov, match", [
    (np.diag([1.0, -1.0, 1.0, 1.0]), "covariance.*positive definite"),
    (np.ones((4, 4)), "covariance.*positive definite"),
    (np.eye(3), "covariance.*shape"),
    (np.diag([1.0, np.nan, 1.0, 1.0]), "covariance.*non-finite"),
])
def test_bad_covariance_raises_and_leaves_nothing(tmp_path, cov, match):
    path = tmp_path / "bad.xml"
    with pytest.raises(ValueError, match=match):
        Q.write_quakeml(path, position=[1.0, 2.0, 3.0], origin_time=T0, covariance=cov,
                        reference=REF3, ndim=3)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kwargs, match", [
    ({"reference": None}, "reference"),
    ({"position": [1.0, 2.0]}, "position"),
    ({"ndim": 4}, "ndim"),
    ({"confidence": 68}, "confidence"),
    ({"extra": {"x": object()}}, "extra"),
])
def test_bad_arguments(tmp_path, kwargs, match):
    args = dict(position=[1.0, 2.0, 3.0], origin_time=T0, covariance=np.eye(4), reference=REF3,
                ndim=3)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Q.write_quakeml(tmp_path / "x.xml", **args)
    assert list(tmp_path.iterdir()) == []


def test_error_during_write_leaves_nothing(tmp_path, monkeypatch):
    from obspy.core.event import Catalog

    def broken_write(self, filename, format, **kwargs):
        with open(filename, "w") as f:
            f.write("<half")
        raise OSError("disk full")

    monkeypatch.setattr(Catalog, "write", broken_write)
    path = tmp_path / "event.xml"
    with pytest.raises(OSError, match="disk full"):
        Q.write_quakeml(path, position=[1.0, 2.0, 3.0], origin_time=T0, covariance=np.eye(4),
                        reference=REF3, ndim=3)
    assert list(tmp_path.iterdir()) == []


def test_overwrite_replaces_existing(tmp_path):
    path = tmp_path / "event.xml"
    path.write_text("old")
    Q.write_quakeml(path, position=[1.0, 2.0, 3.0], origin_time=T0, covariance=np.eye(4),
                    reference=REF3, ndim=3)
    lat = obspy.read_events(str(path))[0].origins[0].latitude
    assert lat == pytest.approx(REF3.latitude, abs=1e-3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["event.xml"]
