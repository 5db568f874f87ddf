"""Tests for adseismic.models (Model, load_model, resample) and the synthetic generators."""
from pathlib import Path

import numpy as np
import pytest

from adseismic.data.model import Model, ModelError
from adseismic.data.models import load_model
from adseismic.data_synthetic import constant, gaussian_anomaly, layered, write_example_files

DATA = Path(__file__).resolve().parents[1] / "data" / "marmousi2"  # the clone holds Marmousi2
OVERTHRUST = Path(__file__).resolve().parents[1] / "data" / "overthrust"  # shipped in the clone (data/README.md)


# ------------------------------------------------------------------------------- generators

def test_layered_values_at_known_depths():
    m = layered([6, 3], 10.0, [1500, 2000, 3000], [20.0, 45.0], origin=[5.0, 0.0])
    # node depths 5, 15, 25, 35, 45, 55: a node on an interface (45) belongs to the layer below
    np.testing.assert_array_equal(m.values[:, 1], [1500, 1500, 2000, 2000, 3000, 3000])
    assert m.shape == (6, 3) and m.spacing == (10.0, 10.0) and m.origin == (5.0, 0.0)
    assert m.extent == ((5.0, 55.0), (0.0, 20.0))
    assert (m.vmin, m.vmax) == (1500.0, 3000.0)


def test_constant_and_gaussian_anomaly_3d():
    c = constant([2, 3, 4], [1.0, 2.0, 3.0], 2500.0)
    assert c.ndim == 3 and c.shape == (2, 3, 4) and np.all(c.values == 2500.0)
    g = gaussian_anomaly([11, 11, 11], 10.0, 3000.0, -500.0, [50.0, 50.0, 40.0], 20.0)
    assert g.values[5, 5, 4] == pytest.approx(2500.0)  # centre
    # one radius away along x (node x=60 is 20 m = 1 sigma from 40)
    assert g.values[5, 5, 6] == pytest.approx(3000.0 - 500.0 * np.exp(-0.5))
    assert g.values.max() < 3000.0 and g.vmin == pytest.approx(2500.0)


def test_model_is_read_only_float64_and_contains():
    m = Model.from_array(np.full((3, 4), 2000, dtype=np.float32), [10.0, 5.0], origin=[0, -5])
    assert m.values.dtype == np.float64 and not m.values.flags.writeable
    pts = np.array([[0.0, -5.0], [20.0, 10.0], [20.0001, 0.0], [10.0, -5.1]])
    np.testing.assert_array_equal(m.contains(pts), [True, True, False, False])
    assert m.contains(np.zeros((2, 5, 2))).shape == (2, 5)


# ------------------------------------------------------------------------------- file loaders

def test_example_files_round_trip(tmp_path):
    specs = write_example_files(tmp_path)
    ref = load_model(specs["layered"])
    assert set(specs) == {"layered", "raw", "npy", "hdf5", "segy"}
    for kind in ("raw", "npy", "hdf5", "segy"):
        m = load_model(specs[kind], base_dir=tmp_path)
        assert m.shape == ref.shape and m.spacing == ref.spacing and m.origin == ref.origin, kind
        np.testing.assert_allclose(m.values, ref.values, rtol=1e-6, err_msg=kind)


@pytest.mark.parametrize("units, stored", [
    ("m/s", 2000.0), ("km/s", 2.0), ("s/m", 1 / 2000.0), ("s2/km2", 0.25), ("s2/m2", 2.5e-7)])
def test_units_conversion(tmp_path, units, stored):
    np.save(tmp_path / "a.npy", np.full((2, 3), stored))
    m = load_model({"kind": "npy", "path": "a.npy", "units": units, "spacing": 1}, tmp_path)
    np.testing.assert_allclose(m.values, 2000.0, rtol=1e-12)


def test_axes_transpose_and_big_endian_raw(tmp_path):
    v = np.arange(1, 25, dtype=float).reshape(2, 3, 4)  # (z, y, x)
    np.transpose(v, (2, 0, 1)).astype(">f8").tofile(tmp_path / "m.bin")  # stored (x, z, y)
    m = load_model({"kind": "raw", "path": "m.bin", "shape": [4, 2, 3], "axes": "xzy",
                    "dtype": "float64", "endian": "big", "spacing": [1, 2, 3]}, tmp_path)
    np.testing.assert_array_equal(m.values, v)
    assert m.spacing == (1.0, 2.0, 3.0) and m.name == "m"


# ------------------------------------------------------------------------------- resampling

def test_resample_refinement_reproduces_linear_slowness():
    z = 10.0 * np.arange(11)
    slow = 1 / 1500 + 1e-6 * z  # slowness linear in depth (s/m)
    m = Model.from_array(np.broadcast_to(1 / slow[:, None], (11, 6)), 10.0)
    r = m.resample(2.5, (0.0, 0.0), (41, 21))
    z_new = 2.5 * np.arange(41)
    np.testing.assert_allclose(1 / r.values, np.broadcast_to((1 / 1500 + 1e-6 * z_new)[:, None],
                                                             (41, 21)), rtol=1e-13)
    assert r.spacing == (2.5, 2.5)


def test_resample_constant_stays_constant_when_coarsening():
    m = constant([40, 30, 20], [2.0, 3.0, 5.0], 3100.0)
    r = m.resample(8.0, (1.0, 1.0, 1.0), (8, 10, 12))
    np.testing.assert_allclose(r.values, 3100.0, rtol=1e-14)


def test_resample_outside_extent_takes_edge_value():
    v = np.random.default_rng(0).uniform(1500, 4500, (10, 5))
    m = Model.from_array(v, 10.0)
    r = m.resample(10.0, (-30.0, -50.0), (17, 15))  # 30 m above / 40 m below, 50 m each side
    np.testing.assert_allclose(r.values, np.pad(v, ((3, 4), (5, 5)), mode="edge"), rtol=1e-14)


def test_resample_smooths_when_coarsening():
    m = layered([41, 3], 1.0, [1500, 3000], [20.0])
    sharp = m.resample(1.0, (0, 0), (41, 3)).values[:, 0]
    coarse = m.resample(4.0, (0, 0), (11, 3)).values[:, 0]
    np.testing.assert_allclose(sharp, m.values[:, 0])  # same grid: unchanged
    assert 1500 < coarse[5] < 3000 and 1500 < coarse[4] < 3000  # interface blurred over >1 cell


# ------------------------------------------------------------------------------- real data

def test_marmousi_raw_kms():
    m = load_model({"kind": "raw", "path": "marmousi2_resampled_1601x401_7.5m_kms.f32", "shape": [1601, 401], "axes": "xz",
                    "units": "km/s", "spacing": 7.5}, DATA)
    assert m.shape == (401, 1601) and m.spacing == (7.5, 7.5)
    assert m.vmin == pytest.approx(1028, abs=0.5) and m.vmax == pytest.approx(4700, abs=0.5)
    np.testing.assert_allclose(m.values[:27], 1500.0, rtol=1e-6)  # water layer
    assert m.values[27:].mean() > 2000


def test_overthrust_hdf5_squared_slowness():
    path = OVERTHRUST / "overthrust_model.h5"
    assert path.is_file(), f"{path}: shipped in the clone (data/README.md)"
    # Julia wrote n = [nx, nz] = [401, 121] column-major, so h5py sees (121, 401) = (z, x).
    m = load_model({"kind": "hdf5", "path": path.name, "dataset": "m", "spacing_dataset": "d",
                    "units": "s2/km2", "axes": "zx"}, OVERTHRUST)
    assert m.shape == (121, 401) and m.spacing == (25.0, 25.0)
    assert m.vmin == pytest.approx(1500, abs=0.1) and m.vmax == pytest.approx(5500, abs=0.1)
    np.testing.assert_allclose(m.values[0], 1500.0, rtol=1e-6)  # water at the surface
    row_mean = m.values.mean(axis=1)
    assert np.corrcoef(np.arange(121), row_mean)[0, 1] > 0.8  # velocity increases with depth
    assert row_mean[-10:].mean() > row_mean[:30].mean() + 1500


# ------------------------------------------------------------------------------- bad input

@pytest.fixture
def examples(tmp_path):
    return tmp_path, write_example_files(tmp_path)


def _bad(spec, base_dir=None):
    with pytest.raises(ModelError) as info:
        load_model(spec, base_dir)
    return str(info.value)


def test_bad_units_axes_kind_and_unknown_key(examples):
    d, specs = examples
    msg = _bad({**specs["npy"], "units": "kph"}, d)
    assert "model.units" in msg and "'kph'" in msg and "km/s" in msg
    assert "model.axes" in _bad({**specs["npy"], "axes": "zz"}, d)
    assert "model.axes" in _bad({**specs["npy"], "axes": "zyx"}, d)
    assert "model.kind" in _bad({**specs["npy"], "kind": "vtk"}, d)
    assert "model.unit" in _bad({**specs["npy"], "unit": "km/s"}, d)


def test_bad_path_size_dtype_and_dataset(examples):
    d, specs = examples
    msg = _bad({**specs["raw"], "path": "nope.f32"}, d)
    assert "model.path" in msg and "nope.f32" in msg
    msg = _bad({**specs["raw"], "shape": [20, 13]}, d)
    assert "model.shape" in msg and "240" in msg and "260" in msg
    assert "model.dtype" in _bad({**specs["raw"], "dtype": "float99"}, d)
    assert "model.endian" in _bad({**specs["raw"], "endian": "middle"}, d)
    assert "model.dataset" in _bad({**specs["hdf5"], "dataset": "vp"}, d)
    no_spacing = {k: v for k, v in specs["npy"].items() if k != "spacing"}
    assert "model.spacing" in _bad(no_spacing, d)
    assert "model.spacing" in _bad({**specs["npy"], "spacing": [1, 2, 3]}, d)
    assert "model.spacing" in _bad({**specs["npy"], "spacing": -1}, d)


def test_bad_velocities_in_file(tmp_path):
    v = np.full((3, 4), 2.0)
    v[1, 2], v[2, 0] = np.nan, -1.0
    np.save(tmp_path / "bad.npy", v)
    msg = _bad({"kind": "npy", "path": "bad.npy", "units": "km/s", "spacing": 1}, tmp_path)
    assert "model.path" in msg and "2 of 12" in msg and "z=1, x=2" in msg


def test_bad_generator_parameters():
    base = {"kind": "layered", "shape": [10, 10], "spacing": 5.0}
    assert "model.interfaces" in _bad({**base, "velocities": [1500, 2000], "interfaces": []})
    assert "model.interfaces" in _bad({**base, "velocities": [1, 2, 3], "interfaces": [9, 3]})
    assert "model.velocities" in _bad({**base, "velocities": [1500, -5], "interfaces": [10]})
    assert "model.velocities" in _bad({**base, "interfaces": [10]})  # missing
    assert "model.shape" in _bad({**base, "shape": [10], "kind": "constant", "velocity": 1500})
    assert "model.velocity" in _bad({**base, "kind": "constant", "velocity": "fast"})
    ga = {**base, "kind": "gaussian_anomaly", "background": 2000, "center": [0, 0], "radius": 5}
    assert "model.perturbation" in _bad({**ga, "perturbation": -2500})
    assert "model.radius" in _bad({**ga, "perturbation": 100, "radius": 0})
    assert "model.center" in _bad({**ga, "perturbation": 100, "center": [0, 0, 0]})
