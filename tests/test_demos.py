"""The CPU demos in configs/ run as their headers say: each header states "wall time: ~N s on 2 CPU cores"
(a first run on a fresh machine: an empty Warp kernel cache, so kernel compilation included) and this
test runs the demo's own command in a fresh process and cache and holds that figure, scaled by this machine's speed
(CALIBRATION below), to within 50% (issue 28). Slow pass only (.ci/run); on a machine without exactly 2 cores only the run is checked."""

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
         "locate_mt_demo": "locate", "image_marmousi": "image", "image_elastic": "image", "acoustic_vd_forward": "forward",
         "vti_forward": "forward", "viscoacoustic_forward": "forward"}


def stated_seconds(path: Path) -> float:
    m = re.search(r"wall time: ~(\d+(?:\.\d+)?) s on 2 CPU cores", path.read_text())
    assert m, f"{path.name}: its header states no 'wall time: ~N s on 2 CPU cores'"
    return float(m.group(1))


# The calibration's seconds on the machine the headers' times were measured on (a 2-core VM like CI's). 2-core VMs
# differ in speed from day to day: on 2026-11-27 one ran every demo 1.6-1.9x (median 1.8x) slower than its header
# and this calibration in 8.5 s, hence 8.5 / 1.8 = 4.7 s. A demo is held to its stated time times this machine's
# slowness, measured by the calibration: a cold-cache compile and a small run of the acoustic kernels, the work that
# dominates the demos.
CALIBRATION_SECONDS = 4.7
# The bounds: 0.5x to 1.5x the stated time x the slowness (the calibration tracks a 2-core VM's speed to about +-30%),
# plus START_SECONDS above: a demo's fixed cost (a Python start, imports, cold-cache kernel builds, ~3-8 s) varies by
# several seconds from run to run on a shared VM whatever its speed (vti_forward: 4.0-8.7 s scaled over one day;
# example_2d: 15.5 s in one CI run against ~8 s x 1.27, the ratio's bound 15.3 s), which a ratio alone holds against
# short demos only.
START_SECONDS = 10.0
CALIBRATION = """
import time
t0 = time.perf_counter()
import numpy as np
from adseismic.solve.acoustic import forward
amp = np.zeros((1, 1, 400))
amp[0, 0, 5] = 1.0
forward(np.full((120, 120), 2000.0), 10.0, 1e-3, amp, np.array([[[600.3, 600.7]]]), np.array([[[100.2, 900.1]]]), order=4,
        pml_width=10)
print(time.perf_counter() - t0)
"""


@pytest.fixture(scope="module")
def machine_slowness(tmp_path_factory) -> float:
    """This machine's time for the calibration over CALIBRATION_SECONDS (1 on the headers' machine, 2 when twice as
    slow); the best of two runs, each in a fresh process and kernel cache."""
    runs = []
    for i in range(2):
        env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path_factory.mktemp(f"calibration{i}")))
        r = subprocess.run([sys.executable, "-c", CALIBRATION], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
        runs.append(float(r.stdout.split()[-1]))
    return min(runs) / CALIBRATION_SECONDS


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(DEMOS))
def test_demo_runs_in_its_stated_time(name, tmp_path, machine_slowness):
    config = ROOT / "configs" / f"{name}.yaml"
    stated = stated_seconds(config)
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "warp-cache"))
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "adseismic.cli", DEMOS[name], str(config), "-o", str(tmp_path / "out"), "-q"],
                       cwd=ROOT, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.splitlines()[-1].startswith("wrote ")
    expected = stated * machine_slowness
    print(f"{name}: {seconds:.0f} s (stated ~{stated:.0f} s; this machine {machine_slowness:.2f}x the headers': ~{expected:.0f} s)")
    if os.cpu_count() == 2:
        assert 0.5 * expected <= seconds <= 1.5 * expected + START_SECONDS, (
            f"{name}: {seconds:.0f} s against the stated ~{stated:.0f} s x this machine's {machine_slowness:.2f} = {expected:.0f} s; "
            f"update its header")


def test_every_cpu_demo_states_its_time():
    for name in DEMOS:
        assert stated_seconds(ROOT / "configs" / f"{name}.yaml") > 0
