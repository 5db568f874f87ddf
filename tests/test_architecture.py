"""The package's layers, read from the source: every module of the installed package is parsed with ast (none is
imported) and its imports of adseismic modules are collected (absolute and relative, at module level and inside
functions); then

- no import cycle between modules;
- adseismic.kernels imports neither adseismic.accel, adseismic.solve nor a workflow (WORKFLOWS);
- adseismic.accel imports neither adseismic.solve nor a workflow;
- only adseismic.cli imports adseismic.cli; only adseismic.cli and adseismic.bench import adseismic.bench.

An import is an edge from the importing module to the module it names: `import adseismic.x.y` names adseismic.x.y;
`from adseismic.x import y` names adseismic.x.y where that is a module or a subpackage, else adseismic.x (y is one of
its attributes); relative imports are resolved from the importing module's package. A package is its __init__ (the
module named by the package). Imports by name at run time (adseismic/__init__.py's lazy attributes through
importlib.import_module) are not edges.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import pkgutil
from functools import lru_cache

WORKFLOWS = ("adseismic.inversion", "adseismic.location", "adseismic.imaging", "adseismic.cli", "adseismic.bench", "adseismic.config")
# Subpackages kept outside adseismic/ in the repository (pyproject's package-dir); an editable install maps them by
# name, so a walk of adseismic's __path__ does not reach them and they are walked as roots of their own.
ROOTS = ("adseismic", "adseismic.kernels", "adseismic.data_synthetic")


def walk(name: str, paths) -> dict:
    """{module name: source file} of the package `name` (directories `paths`) and everything under it, as
    pkgutil.walk_packages lists them but without importing the subpackages to find their __path__."""
    found = {}
    for path in paths:
        init = os.path.join(path, "__init__.py")
        if os.path.isfile(init):
            found.setdefault(name, init)
        for info in pkgutil.iter_modules([path], name + "."):
            leaf = info.name.rpartition(".")[2]
            if info.ispkg:
                found.update({k: v for k, v in walk(info.name, [os.path.join(path, leaf)]).items() if k not in found})
            elif os.path.isfile(os.path.join(path, leaf + ".py")):  # (an extension module has no source to read)
                found.setdefault(info.name, os.path.join(path, leaf + ".py"))
    return found


@lru_cache(maxsize=None)
def modules() -> dict:
    """{module name: source file} of every module of the installed package (a package is its __init__.py)."""
    found = {}
    for root in ROOTS:
        # find_spec imports no module but the root's parent package (adseismic/__init__.py, which imports nothing else)
        spec = importlib.util.find_spec(root)
        assert spec is not None and spec.submodule_search_locations, f"{root} is not an installed package"
        found.update({k: v for k, v in walk(root, list(spec.submodule_search_locations)).items() if k not in found})
    return found


def resolve(name: str, known) -> str | None:
    """The module `name` names, or its closest enclosing known module (an attribute of a package or module:
    `from adseismic import gradient` imports adseismic's __init__); None outside adseismic."""
    while name and name not in known:
        name = name.rpartition(".")[0]
    return name or None


@lru_cache(maxsize=None)
def graph() -> dict:
    """{module: {imported adseismic module: line of the first such import}} of the installed package."""
    return imports(modules())


def imports(mods: dict) -> dict:
    """{module: {imported adseismic module: line of the first such import}} of the modules `mods` ({name: file})."""
    edges = {}
    for name, path in mods.items():
        with open(path, encoding="utf-8") as f:
            tree = ast.parse(f.read(), filename=path)
        package = name if os.path.basename(path) == "__init__.py" else name.rpartition(".")[0]
        out = {}

        def add(target, line):
            t = resolve(target, mods)
            if t is not None and t != name:
                out.setdefault(t, line)

        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name == "adseismic" or alias.name.startswith("adseismic."):
                        add(alias.name, node.lineno)
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative: from the module's package, up level - 1 packages
                    base = package.split(".")
                    base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                    base = ".".join(base + ([node.module] if node.module else []))
                else:
                    base = node.module or ""
                if base != "adseismic" and not base.startswith("adseismic."):
                    continue
                for alias in node.names:  # `from x import y`: x.y where that is a module, else x
                    sub = f"{base}.{alias.name}"
                    add(sub if sub in mods else base, node.lineno)
        edges[name] = out
    return edges


def under(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def offending(importers, forbidden) -> list:
    """'a -> b (file:line)' for every edge from a module a for which importers(a) holds to a module b under one of
    the packages `forbidden`."""
    mods = modules()
    return [f"{a} -> {b} ({os.path.relpath(mods[a])}:{line})" for a, out in sorted(graph().items()) if importers(a)
            for b, line in sorted(out.items()) if any(under(b, p) for p in forbidden)]  # fmt: skip


def cycles(g: dict) -> list:
    """Every strongly connected component of more than one module of the import graph g, each as one cycle through
    its modules ['a', 'b', ..., 'a'] (Tarjan's algorithm, then a shortest way back to its first module)."""
    index, low, stack, on, comps = {}, {}, [], set(), []

    def connect(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in g.get(v, ()):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            connect(v)
    found = []
    for comp in comps:  # breadth-first from the component's first module back to itself, inside the component
        start, inside = comp[0], set(comp)
        prev, frontier = {}, [start]
        while frontier and start not in prev:
            nxt = []
            for v in frontier:
                for w in sorted(g[v]):
                    if w in inside and w not in prev:
                        prev[w] = v
                        nxt.append(w)
            frontier = nxt
        path, v = [start], prev[start]
        while v != start:
            path.append(v)
            v = prev[v]
        found.append([start, *reversed(path[1:]), start])
    return sorted(found)


# --- the walk itself ----------------------------------------------------------------------------------------------


def test_walk_finds_every_layer():
    # the walk reaches the subpackages installed from outside adseismic/ and the modules of every layer, and edges
    # come out of absolute, relative and function-level imports (guards against a walk that silently finds nothing)
    mods, g = modules(), graph()
    for name in ("adseismic.kernels.acoustic", "adseismic.kernels.elastic", "adseismic.data_synthetic.generators",
                 "adseismic.accel.graphs", "adseismic.solve.acoustic", "adseismic.solve.elastic", "adseismic.cli",
                 "adseismic.bench"):  # fmt: skip
        assert name in mods, name
    assert any(under(b, "adseismic.kernels") for b in g["adseismic.solve.elastic"])
    assert sum(len(out) for out in g.values()) > 2 * len(mods) // 3


def test_resolution_of_import_forms(tmp_path):
    # `from x import y` is x.y where that is a module, else x; relative imports count from the module's package;
    # imports inside functions count; a package is its __init__
    pkg = tmp_path / "adseismic"
    (pkg / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "a.py": "from adseismic import sub\nfrom adseismic.sub import b, CONSTANT\n",
        "sub/__init__.py": "from .b import f\n",
        "sub/b.py": "def f():\n    from ..a import thing\n    import adseismic.c\n",
        "c.py": "from .sub import nothing_there\n",
    }
    for rel, text in files.items():
        (pkg / rel).write_text(text)
    found = walk("adseismic", [str(pkg)])
    assert sorted(found) == ["adseismic", "adseismic.a", "adseismic.c", "adseismic.sub", "adseismic.sub.b"]
    assert {k: sorted(v) for k, v in imports(found).items()} == {
        "adseismic": [],
        "adseismic.a": ["adseismic.sub", "adseismic.sub.b"],
        "adseismic.sub": ["adseismic.sub.b"],
        "adseismic.sub.b": ["adseismic.a", "adseismic.c"],
        "adseismic.c": ["adseismic.sub"],
    }
    # one strongly connected component {a, c, sub, sub.b}, reported as a cycle through its first module
    assert cycles(imports(found)) == [["adseismic.a", "adseismic.sub.b", "adseismic.a"]]
    assert cycles({"x": {"y": 1}, "y": {"z": 1}, "z": {"y": 1}}) == [["y", "z", "y"]]


# --- the rules ----------------------------------------------------------------------------------------------------


def test_no_import_cycles():
    found = cycles(graph())
    assert not found, "import cycles:\n" + "\n".join(" -> ".join(c) for c in found)


def test_kernels_import_no_solver_accel_or_workflow():
    bad = offending(lambda m: under(m, "adseismic.kernels"), ("adseismic.accel", "adseismic.solve", *WORKFLOWS))
    assert not bad, "kernels import a higher layer:\n" + "\n".join(bad)


def test_accel_imports_no_solver_or_workflow():
    bad = offending(lambda m: under(m, "adseismic.accel"), ("adseismic.solve", *WORKFLOWS))
    assert not bad, "accel imports a higher layer:\n" + "\n".join(bad)


def test_only_cli_imports_cli():
    bad = offending(lambda m: not under(m, "adseismic.cli"), ("adseismic.cli",))
    assert not bad, "adseismic.cli imported from outside it:\n" + "\n".join(bad)


def test_only_cli_and_bench_import_bench():
    bad = offending(lambda m: not (under(m, "adseismic.cli") or under(m, "adseismic.bench")), ("adseismic.bench",))
    assert not bad, "adseismic.bench imported from outside cli and bench:\n" + "\n".join(bad)
