"""Tests for the adseismic command line (plan, forward), io.py and plotting.py."""
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from adseismic import cli
from adseismic.data.store import read_forward, write_forward
from adseismic.kernels.numerics import cfl_limit

ROOT = Path(__file__).resolve().parents[1]

TINY = {  # 60 x 80 cells, 2 shots, order 4: a few seconds on a CPU
    "model": {"kind": "layered", "shape": [60, 80], "spacing": 10.0,
              "velocities": [1500, 2500], "interfaces": [300]},
    "geometry": {
        "sources": {"points": [{"x": 200, "z": 20}, {"x": 600, "z": 20}]},
        "receivers": {"line": {"start": {"x": 0, "z": 10}, "end": {"x": 790, "z": 10},
                               "count": 40}},
    },
    "wavelet": {"kind": "ricker", "peak_frequency": 12.0},
    "simulation": {"order": 4, "dx": 10.0, "duration": 0.4, "device": "cpu",
                   "domain": "model", "pml_width": 10},
    "output": {"snapshot_interval": 0.1},
}


def write_config(tmp_path, raw=TINY, name="tiny.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def test_plan_example_2d_subprocess():
    r = subprocess.run([sys.executable, "-m", "adseismic.cli", "plan",
                        str(ROOT / "configs" / "example_2d.yaml")],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "dx = " in r.stdout and "dt " in r.stdout and "nt " in r.stdout
    assert "Traceback" not in r.stderr


def test_plan_bad_config_exits_2_without_traceback(tmp_path, capsys):
    raw = {**TINY, "simulation": {**TINY["simulation"], "oder": 4}}
    assert cli.main(["plan", str(write_config(tmp_path, raw))]) == 2
    err = capsys.readouterr().err
    assert "simulation.oder: unknown key; allowed: order" in err
    assert "Traceback" not in err


def test_no_command_and_help(capsys):
    assert cli.main([]) == 2
    with pytest.raises(SystemExit) as e:
        cli.main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "plan" in out and "forward" in out


@pytest.fixture(scope="module")
def forward_run(tmp_path_factory):
    """One forward run of TINY, shared by the tests that inspect its outputs."""
    tmp = tmp_path_factory.mktemp("fwd")
    config = write_config(tmp)
    out = tmp / "out"
    code = cli.main(["forward", str(config), "-o", str(out), "--quiet"])
    return code, config, out


def test_forward_writes_data_and_figures(forward_run):
    code, config, out = forward_run
    assert code == 0
    names = {p.name for p in out.iterdir()}
    assert {"data.h5", "config.yaml", "forward.log", "model.png", "gather_shot0.png",
            "gather_shot1.png", "snapshots_shot0.png"} <= names
    assert not [n for n in names if n.endswith(".part")]
    for png in ("model.png", "gather_shot0.png", "snapshots_shot0.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "config.yaml").read_text() == config.read_text()
    assert "simulated in" in (out / "forward.log").read_text()


def test_forward_hdf5_layout(forward_run):
    _, config, out = forward_run
    with h5py.File(out / "data.h5", "r") as f:
        nt = int(f.attrs["nt"])
        assert f["receiver_data"].shape == (2, 40, nt)
        assert f["receiver_data"].attrs["axes"] == "shot,receiver,time"
        assert "units" in f["receiver_data"].attrs
        assert f["source_wavelet"].shape == (nt,)
        assert f["time"].shape == (nt,)
        np.testing.assert_allclose(f["time"][1] - f["time"][0], f.attrs["dt"])
        # world coordinates, axis order z, x
        np.testing.assert_allclose(f["source_coordinates"][()], [[20, 200], [20, 600]])
        assert f["receiver_coordinates"].shape == (40, 2)
        np.testing.assert_allclose(f["receiver_coordinates"][-1], [10, 790])
        for name in ("source_coordinates", "receiver_coordinates"):
            assert f[name].attrs["axes"] == "z,x" and f[name].attrs["units"] == "m"
        v = f["velocity"]
        assert v.ndim == 2 and v.attrs["spacing"] == pytest.approx(f.attrs["dx"])
        assert len(v.attrs["origin"]) == 2
        assert 1499 < v[()].min() and v[()].max() < 2501
        snaps, times = f["snapshots"], f["snapshot_times"][()]
        assert snaps.shape == (len(times), 2, *v.shape)
        assert times[0] == 0 and np.all(np.diff(times) > 0)
        for key in ("dx", "dt", "nt", "order", "precision", "device", "free_surface",
                    "pml_width", "adseismic_version", "created_utc", "config_yaml", "plan"):
            assert key in f.attrs, key
        assert f.attrs["order"] == 4 and f.attrs["device"] == "cpu"
        assert f.attrs["pml_width"] == 10 and not f.attrs["free_surface"]
        assert f.attrs["config_yaml"] == config.read_text()
        assert "dx = " in f.attrs["plan"]
        assert f.attrs["created_utc"].endswith("+00:00")
        data = f["receiver_data"][()]
    assert np.all(np.isfinite(data)) and np.abs(data).max() > 0
    # reading back through io.read_forward gives the same arrays
    d = read_forward(out / "data.h5")
    np.testing.assert_array_equal(d.receiver_data, data)
    assert d.ndim == 2 and d.attrs["order"] == 4 and d.dt == pytest.approx(d.attrs["dt"])


def test_forward_snapshots_change_with_time(forward_run):
    _, _, out = forward_run
    d = read_forward(out / "data.h5")
    assert np.abs(d.snapshots[0]).max() == 0  # t = 0: nothing injected yet
    assert not np.array_equal(d.snapshots[1], d.snapshots[2])


def test_forward_unstable_dt_is_refused_before_outputs(tmp_path, capsys):
    raw = {**TINY, "simulation": {**TINY["simulation"], "dt": 0.01}}  # Courant 2.5
    out = tmp_path / "out"
    code = cli.main(["forward", str(write_config(tmp_path, raw)), "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 2
    assert "limit" in err and f"{cfl_limit(4, 2):.3f}" in err and "Traceback" not in err
    assert not out.exists()


def test_forward_blowup_exits_3_without_data(tmp_path, capsys, monkeypatch):
    from adseismic import scene
    from adseismic.solve.common import PropagationError

    def explode(*args, **kwargs):
        raise PropagationError("wavefield blew up at step 7")

    monkeypatch.setattr(scene, "run_forward", explode)
    out = tmp_path / "out"
    code = cli.main(["forward", str(write_config(tmp_path)), "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 3 and "blew up at step 7" in err
    assert not (out / "data.h5").exists()
    assert not list(out.glob("*.part"))
    assert "blew up" in (out / "forward.log").read_text()


def test_write_forward_is_atomic_on_error(tmp_path):
    path = tmp_path / "data.h5"
    common = dict(source_wavelet=np.zeros(5), dt=0.1, source_coordinates=np.zeros((1, 2)),
                  receiver_coordinates=np.zeros((2, 2)), velocity=np.ones((3, 4)),
                  spacing=10.0, origin=(0.0, 0.0))
    with pytest.raises(ValueError, match="source_wavelet"):
        write_forward(path, receiver_data=np.zeros((1, 2, 6)), **common)
    with pytest.raises(TypeError):  # fails while writing: an attribute h5py cannot store
        write_forward(path, receiver_data=np.zeros((1, 2, 5)), attrs={"bad": object()},
                      **common)
    assert not path.exists() and not list(tmp_path.glob("*.part"))
    write_forward(path, receiver_data=np.ones((1, 2, 5)), attrs={"note": None}, **common)
    d = read_forward(path)
    assert d.receiver_data.shape == (1, 2, 5) and d.attrs["note"] == "none"
    assert d.snapshots is None and d.spacing == 10.0


def test_plotting_3d_slices(tmp_path):
    from adseismic import plotting

    v = np.full((5, 6, 7), 2000.0)
    src = np.array([[10.0, 20.0, 30.0]])
    rec = np.array([[0.0, 20.0, x] for x in range(0, 70, 10)])
    plotting.plot_model(tmp_path / "m.png", v, 10.0, (0, 0, 0), src, rec)
    snaps = np.random.default_rng(0).normal(size=(3, 5, 6, 7))
    plotting.plot_snapshots(tmp_path / "s.png", snaps, [0, 0.1, 0.2], 10.0, (0, 0, 0), src)
    plotting.plot_gather(tmp_path / "g.png", np.zeros((7, 20)), 0.01, rec[:, -1])
    for name in ("m.png", "s.png", "g.png"):
        assert (tmp_path / name).stat().st_size > 1000
    assert not list(tmp_path.glob("*.part"))
