"""Writes docs/api.md from adseismic.__all__ and the names' docstrings."""
import inspect

import adseismic

out = ["# Public API", "",
       "`import adseismic` gives these names (`adseismic.__all__`); each is imported on first use. Units are SI:",
       "metres, seconds, m/s, kg/m^3, Hz. Arrays follow the model's axis order (z, [y,] x), z depth positive down:",
       "models (nz, [ny,] nx); locations (n_shots, n_per_shot, ndim) metres; source samples and receiver data",
       "(n_shots, n, nt) at t = k dt. Everything else is reachable in its layer (docs/architecture.md). This page is",
       "generated from the docstrings (`python docs/gen_api.py`); tests/test_architecture.py checks that it lists `__all__`.", ""]
for name in adseismic.__all__:
    obj = getattr(adseismic, name)
    kind = "class" if inspect.isclass(obj) else "function"
    try:
        sig = str(inspect.signature(obj)) if kind == "function" else ""
    except (TypeError, ValueError):
        sig = ""
    out += [f"## `{name}`", "", f"{kind} in `{obj.__module__}`" + (f": `{name}{sig}`" if sig else ""), "", "```", inspect.getdoc(obj) or "", "```", ""]
open("docs/api.md", "w").write("\n".join(out))
