"""Layers (issue 26, must have 5): bus/ imports nothing from build, nodes, scenario or run;
physics/ and control/ know nothing of CAN (no canbrake.bus, canbrake.nodes, can, cantools).
Every import statement counts, at module level or inside a function."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "canbrake"


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in a Python or Cython file (a .pyx's ``cimport`` and
    ``cdef`` lines are not Python: they are checked as text, its Python lines by ast)."""
    text = path.read_text()
    if path.suffix == ".pyx":
        out = []
        for i, ln in enumerate(text.splitlines(), 1):
            words = ln.split()
            if len(words) >= 2 and words[0] in ("import", "cimport"):
                out += [(i, w.strip(",")) for w in words[1:] if w not in ("as",)][:1]
            elif len(words) >= 4 and words[0] == "from" and words[2] in ("import", "cimport"):
                out.append((i, words[1]))
        return out
    out = []
    pkg = ".".join(path.relative_to(PKG.parent).with_suffix("").parts[:-1])
    for node in ast.walk(ast.parse(text, str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the package
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # ``from canbrake import build`` imports canbrake.build: name the module imported
            out.append((node.lineno, mod if mod != "canbrake" else f"{mod}.{node.names[0].name}"))
            if mod == "canbrake":
                out += [(node.lineno, f"{mod}.{a.name}") for a in node.names[1:]]
    return out


def _violations(layer: str, forbidden: tuple[str, ...]) -> list[str]:
    bad = []
    for path in sorted((PKG / layer).rglob("*.py")) + sorted((PKG / layer).rglob("*.pyx")):
        for line, mod in _imports(path):
            if any(mod == f or mod.startswith(f + ".") for f in forbidden):
                bad.append(f"{path.relative_to(PKG.parent)}:{line}: imports {mod}")
    return sorted(set(bad))


@pytest.mark.parametrize("layer, forbidden", [
    ("bus", ("canbrake.build", "canbrake.nodes", "canbrake.scenario", "canbrake.run")),
    ("physics", ("canbrake.bus", "canbrake.nodes", "can", "cantools")),
    ("control", ("canbrake.bus", "canbrake.nodes", "can", "cantools")),
])
def test_layer_imports_nothing_from_the_layers_above_it(layer, forbidden):
    assert (PKG / layer).is_dir()
    assert _violations(layer, forbidden) == []


def test_the_layer_check_sees_imports_inside_functions_and_relative_ones(tmp_path, monkeypatch):
    """The check itself can fail: a function-level and a relative import of a forbidden module."""
    pkg = tmp_path / "canbrake"
    (pkg / "bus").mkdir(parents=True)
    (pkg / "bus" / "x.py").write_text("def f():\n    from canbrake.build import bus_layout\n")
    (pkg / "bus" / "y.py").write_text("from ..nodes.recorder import error_frame\nfrom .. import scenario\n")
    (pkg / "bus" / "z.pyx").write_text("from canbrake.run import memory_yield\ncimport cython\n")
    monkeypatch.setattr(__import__(__name__), "PKG", pkg)
    assert _violations("bus", ("canbrake.build", "canbrake.nodes", "canbrake.scenario", "canbrake.run")) == [
        "canbrake/bus/x.py:2: imports canbrake.build",
        "canbrake/bus/y.py:1: imports canbrake.nodes.recorder",
        "canbrake/bus/y.py:2: imports canbrake.scenario",
        "canbrake/bus/z.pyx:1: imports canbrake.run",
    ]
