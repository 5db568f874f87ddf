"""The public API: a small __all__, every name documented with its units, and docs/api.md in step with it."""

import inspect
import pathlib
import re
import subprocess
import sys

import adseismic

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_all_is_small_and_every_name_resolves_with_a_docstring():
    assert 10 <= len(adseismic.__all__) <= 22
    assert sorted(adseismic.__all__) == sorted(adseismic._WHERE)  # every exported name is importable, and only those
    for name in adseismic.__all__:
        doc = inspect.getdoc(getattr(adseismic, name)) or ""
        assert len(doc) >= 60, f"adseismic.{name} needs a docstring that states units and shapes"


def test_simulation_entry_points_state_units_and_shapes():
    for name in ("forward", "gradient", "born", "forward_elastic", "gradient_elastic", "ForwardResult", "GradientResult",
                 "ElasticResult", "ElasticGradient", "Model", "ricker"):
        doc = inspect.getdoc(getattr(adseismic, name))
        assert re.search(r"\(n_shots|\(nz|\(nt|nt\)", doc), f"{name}: no array shape in its docstring"
        assert re.search(r"m/s|\bs\b|Hz|metres|\(s\)", doc), f"{name}: no unit in its docstring"


def test_docs_api_lists_exactly_the_public_names():
    text = (ROOT / "docs" / "api.md").read_text()
    assert sorted(re.findall(r"^## `(\w+)`", text, flags=re.M)) == sorted(adseismic.__all__)


def test_importing_the_package_loads_no_simulation_code():
    code = "import sys, adseismic; print(any(m.startswith(('warp', 'adseismic.solve')) for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
