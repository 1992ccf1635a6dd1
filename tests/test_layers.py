"""The package's floors (docs/development.md): read with ``ast``, every import of a clcurv
module by another, made at the top or inside a function, points down or sideways within a
floor, never up; no module imports itself back through others (no cycle); and no module
imports another's private (``_name``) names. A planted cycle and a planted private import
are caught (the checker is tested on a copy of the package)."""
import ast
import shutil
from pathlib import Path

import pytest

import clcurv

PACKAGE = Path(clcurv.__file__).resolve().parent

#: floor of each subpackage (and top-level module); an import may go to a lower floor or to
#: the same subpackage, never up or sideways to another subpackage of the same floor
FLOORS = {
    "_shared": 0,
    "runtime": 1, "reference": 1, "io": 1,
    "grid": 2,
    "orient": 3,                  # normals turned: the k-NN graph and spanning forest
    "ops": 4,
    "api": 5,
    "tiles": 6,
    "jobs": 7,
    "render": 8, "data": 0,
    "cli": 9,
    "": 10,                       # clcurv/__init__.py: the public names
}


def modules(root):
    """{dotted name: path} of every module under ``root`` (a package directory)."""
    out = {}
    for path in root.rglob("*.py"):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def imports(root):
    """[(importer, imported module, names)] of every clcurv import under ``root``."""
    mods = modules(root)
    top = root.name
    found = []
    for name, path in mods.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name == top or a.name.startswith(top + "."):
                        found.append((name, a.name, []))
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".") if is_pkg else name.split(".")[:-1]
                    base = base[:len(base) - (node.level - 1)]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                if mod != top and not mod.startswith(top + "."):
                    continue
                for a in node.names:              # a submodule imported by name is an edge
                    sub = f"{mod}.{a.name}"
                    if sub in mods:
                        found.append((name, sub, []))
                    else:
                        found.append((name, mod, [a.name]))
    return found


def cycles(root):
    """The strongly connected groups (more than one module) of the import graph."""
    mods = modules(root)
    edges = {m: set() for m in mods}
    for a, b, _ in imports(root):
        if b in mods and a != b:
            edges[a].add(b)
    index, low, stack, on, groups = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for v in mods:
        if v not in index:
            visit(v)
    return groups


def private_imports(root):
    return sorted((a, b, n) for a, b, names in imports(root) for n in names
                  if n.startswith("_") and not (n.startswith("__") and n.endswith("__")))


def floor(module):
    parts = module.split(".")
    return FLOORS[parts[1] if len(parts) > 1 else ""]


def upward_imports(root):
    """Imports into a higher floor, or into another subpackage of the same floor."""
    bad = []
    for a, b, _ in imports(root):
        pa, pb = a.split(".")[1:2], b.split(".")[1:2]
        if pa == pb:
            continue
        if floor(b) > floor(a) or floor(b) == floor(a):
            bad.append((a, b))
    return sorted(set(bad))


def test_no_import_cycles():
    assert cycles(PACKAGE) == []


def test_no_private_names_across_modules():
    assert private_imports(PACKAGE) == []


def test_imports_point_down():
    assert upward_imports(PACKAGE) == []


def test_every_subpackage_has_a_floor():
    tops = {p.name if p.is_dir() else p.stem for p in PACKAGE.iterdir()
            if p.name != "__pycache__" and (p.is_dir() or p.suffix == ".py")}
    assert tops - {"__init__", "kernels"} <= set(FLOORS), tops - set(FLOORS)
    assert len([p for p in PACKAGE.iterdir() if p.name != "__pycache__"]) <= 14


@pytest.fixture
def copy(tmp_path):
    dst = tmp_path / "clcurv"
    shutil.copytree(PACKAGE, dst, ignore=shutil.ignore_patterns("__pycache__", "kernels",
                                                                "*.ply"))
    return dst


def test_the_checks_catch_a_planted_cycle_and_private_import(copy):
    low = copy / "_shared" / "constants.py"
    low.write_text(low.read_text() + "\n\ndef _late():\n    from clcurv.api import curvature"
                   "  # noqa\n    from clcurv.runtime.device import _cl  # noqa\n")
    assert any("clcurv._shared.constants" in g for g in cycles(copy))
    assert ("clcurv._shared.constants", "clcurv.runtime.device", "_cl") in private_imports(copy)
    assert ("clcurv._shared.constants", "clcurv.api.curvature") in upward_imports(copy)
