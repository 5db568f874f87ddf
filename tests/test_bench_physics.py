"""``adseismic bench --physics`` (issue 26 item 8): the physics family's rows at their tiny CPU sizes with Deepwave
absent, the selection (the default output unchanged), the on-node geometry and the conventions' arithmetic of
bench/physics.py. Deepwave itself cannot run here (no torch): its side was checked by hand (docs/benchmarks.md)."""
import argparse
import json

import numpy as np
import pytest
import warp as wp

from adseismic import bench, cli
from adseismic.bench import SCENES, physics

from .conftest import DEVICE


@pytest.fixture(scope="module")
def physics_run(tmp_path_factory):
    """The four tiny physics scenes on the CPU, 10 steps, in this process, Deepwave absent (~15 s)."""
    out = tmp_path_factory.mktemp("physics") / "out"
    mp = pytest.MonkeyPatch()
    mp.setattr(bench, "deepwave_available", lambda: False)
    try:
        code = cli.main(["bench", "--physics", "--steps", "10", "--in-process", "-o", str(out), "-q"])
    finally:
        mp.undo()
    return code, out


def test_physics_rows_run_and_say_reference_not_installed(physics_run):
    code, out = physics_run
    assert code == 0  # a missing reference is not our failure
    rows = [bench.row_from_dict(r) for r in json.loads((out / "bench.json").read_text())["rows"]]
    assert [r.scene for r in rows if r.engine == "adseismic"] == ["VD40"] * 2 + ["Q40"] * 2 + ["VTI40"] * 2 + ["E3D16"] * 2
    for r in rows:
        if r.engine == "adseismic":
            assert r.ok and r.nt == 10 and r.nt_reference == 30 and r.rate == pytest.approx(r.cell_updates / r.seconds)
            assert r.rate > 0 and r.padded_cells == bench.padded_cells(SCENES[r.scene], 4)
        else:
            assert r.status == "reference failed: not installed" and not bench.is_our_failure(r)
    e3d = next(r for r in rows if r.scene == "E3D16" and r.mode == "gradient")
    assert e3d.padded_cells == 60**3 and e3d.peak_estimate_bytes > 0 and "x" in e3d.segments
    md = (out / "bench.md").read_text()
    line = next(ln for ln in md.splitlines() if ln.startswith("| VTI40 | cpu | gradient | 10 (of 30) |"))
    assert "reference failed: not installed" in line
    assert "| E3D16 | elastic3d | cpu | vz |  |  | reference failed: not installed |" in md  # the accuracy table


def test_default_selection_is_unchanged():
    standard = ["S600", "S600x4", "S600x16", "S4000", "S3D400", "E2000", "E600x16"]
    assert bench._family("standard", "cuda") == standard and bench._family("standard", "cpu") == ["S600", "S600x4"]
    assert bench._family("physics", "cuda") == ["VD1000", "Q1000", "VTI1000", "E3D200"]
    assert bench._family("physics", "cpu") == ["VD40", "Q40", "VTI40", "E3D16"]
    parser = argparse.ArgumentParser()
    bench.register(parser)

    def scenes(*argv):
        args = parser.parse_args([*argv, "--steps", "4", "--no-deepwave", "-o", "unused"])
        return [j.scene for j in bench._check_args(args)[1]["cpu"]]

    assert scenes("--scenes", "all") == standard  # `--scenes all`: the standard scenes only
    assert scenes() == ["S600", "S600x4"] and scenes("--physics") == ["VD40", "Q40", "VTI40", "E3D16"]
    assert bench.physics_accuracy_lines([]) == []  # no physics rows: bench.md as before


def test_physics_with_scenes_is_refused(tmp_path, capsys):
    assert cli.main(["bench", "--physics", "--scenes", "VD40", "-o", str(tmp_path / "o"), "-q"]) == 2
    assert "--physics: give it or --scenes VD40, not both" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("kind, shape", [("acoustic_vd", (40, 40)), ("viscoacoustic", (40, 40)), ("vti", (40, 40)),
                                         ("elastic3d", (16, 16, 16))])  # fmt: skip
def test_scene_locations_sit_on_the_recorded_fields_nodes(kind, shape):
    model, src, rec = physics.scene(kind, shape, 10.0)
    assert all(m.shape == shape for m in model.values()) and src.shape == (1, 1, len(shape))
    assert rec.shape == (1, shape[-1] // 2, len(shape))
    stagger = np.zeros(len(shape))
    stagger[0] = physics.STAGGER.get(kind, 0.0)  # vz at (i + 1/2) dx in z
    for loc in (src, rec):
        cells = loc / 10.0 - stagger
        assert np.array_equal(cells, np.rint(cells))  # on a node: Deepwave's integer index names the same point
    assert np.array_equal(rec[0, :, -1], 20.0 * np.arange(shape[-1] // 2))


def test_conventions_arithmetic():
    s = np.array([[[0.0, 1.0, 3.0, 3.0]]])
    assert np.allclose(physics.source_rate(s, 1e-3, 10.0), [[[10.0, 20.0, 0.0, 0.0]]])  # (S[n+1] - S[n]) / (dt dx^2)
    q = np.array([100.0, 50.0, np.inf])
    v0 = physics.relaxed_velocity(np.full(3, 2000.0), q, 15.0)
    assert v0[2] == pytest.approx(2000.0)  # lossless: one speed at every frequency
    # below the phase velocity at 15 Hz by a drop ~ 1/Q for weak loss (measured 1.6% at Q 50, 0.8% at Q 100): the Q 50
    # drop is twice the Q 100 one within 2% (second-order terms in 1/Q)
    drop = 2000.0 - v0[:2]
    assert 0.005 * 2000 < drop[0] < drop[1] < 0.03 * 2000 and drop[1] / drop[0] == pytest.approx(2.0, rel=0.02)
    r = np.linspace(-1.0, 1.0, 24).reshape(1, 2, 12)
    assert physics.difference(2 * r, r) == (pytest.approx(0.5), pytest.approx(2.0))
    # ours on the device (a GPU run's traces: models passed as Warp arrays) is read back (implicit conversion of a GPU
    # array raises: ADSEISMIC_TEST_DEVICE=cuda:0 checks that)
    assert physics.difference(wp.array(2 * r, dtype=wp.float32, device=DEVICE), r) == (pytest.approx(0.5), pytest.approx(2.0))
    assert physics.difference(np.zeros_like(r), r) == (None, None)
    with pytest.raises(ValueError, match="shapes"):
        physics.difference(r, r[:, :1])


def test_accuracy_table_reads_the_deepwave_forward_row():
    base = dict(scene="VD40", kind="acoustic_vd", device="cpu", device_name="CPU", order=4, shape=(40, 40), shots=1, nt=30,
                nt_reference=30, padded_cells=84**2)  # fmt: skip
    rows = [bench.BenchRow(engine="adseismic", mode="forward", seconds=1.0, rate=1.0, **base),
            bench.BenchRow(engine="deepwave", mode="forward", seconds=1.0, rate=2.0, reference_l2=6.58e-8, reference_scale=1.0, **base)]
    lines = bench.physics_accuracy_lines(rows)
    assert "| VD40 | acoustic_vd | cpu | pressure | 6.58e-08 | 1 |  |" in lines
    line = next(ln for ln in bench.markdown(rows, {"date_utc": "d", "adseismic": "v", "warp": "w", "devices": {"cpu": "CPU"},
                                                   "cpu_model": "x", "cpu_count": 2, "deepwave": "0.1.0"}).splitlines()
                if ln.startswith("| VD40 | cpu | forward |"))  # fmt: skip
    assert "| 2e-09 (live, Deepwave" in line and line.rstrip().endswith("| 0.5 |  |")  # ours / Deepwave
