"""The CPU demos in configs/ run as their headers say: each header states "wall time: ~N s on 2 CPU cores"
(a first run on a fresh machine: an empty Warp kernel cache, so kernel compilation included) and this
test runs the demo's own command in a fresh process and cache and holds that figure to within 50%
(issue 28). Slow pass only (.ci/run); on a machine without exactly 2 cores only the run is checked."""

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DEMOS = {"example_2d": "forward", "example_3d": "forward", "fwi_demo": "fwi", "locate_demo": "locate",
         "elastic_forward": "forward", "das_forward": "forward", "elastic_fwi": "fwi", "nn_fwi": "fwi",
         "locate_mt_demo": "locate", "image_marmousi": "image", "image_elastic": "image", "acoustic_vd_forward": "forward"}


def stated_seconds(path: Path) -> float:
    m = re.search(r"wall time: ~(\d+(?:\.\d+)?) s on 2 CPU cores", path.read_text())
    assert m, f"{path.name}: its header states no 'wall time: ~N s on 2 CPU cores'"
    return float(m.group(1))


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(DEMOS))
def test_demo_runs_in_its_stated_time(name, tmp_path):
    config = ROOT / "configs" / f"{name}.yaml"
    stated = stated_seconds(config)
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "warp-cache"))
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "adseismic.cli", DEMOS[name], str(config), "-o", str(tmp_path / "out"), "-q"],
                       cwd=ROOT, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.splitlines()[-1].startswith("wrote ")
    print(f"{name}: {seconds:.0f} s (stated ~{stated:.0f} s)")
    if os.cpu_count() == 2:
        assert 0.5 * stated <= seconds <= 1.5 * stated, f"{name}: {seconds:.0f} s against the stated ~{stated:.0f} s; update its header"


def test_every_cpu_demo_states_its_time():
    for name in DEMOS:
        assert stated_seconds(ROOT / "configs" / f"{name}.yaml") > 0
