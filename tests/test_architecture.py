"""The house plan: a layer never imports a layer above it (module-level imports).

Layers, bottom first: base helpers; plants and signals; metrics (and the plant zoo, a
test helper independent of the trace code it measures); filters;
ident; update (and validation); trace; workflow; top (plotting, I/O, CLI,
reproduction of the paper). Lazy imports inside ``.plot()`` methods, which
delegate to the plotting module as STYLE.md asks, are function-level and
not counted. Only plotting may import matplotlib, and only lazily.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "greybox"

LAYER = {
    "exceptions": 0, "_validation": 0, "_lti": 0, "_blas": 0, "progress": 0,
    "system": 1, "signals": 1, "plants": 1, "nonlinear": 1,
    "metrics": 2, "zoo": 2,
    "filters": 3,
    "ident": 4,
    "update": 5, "validate": 5,
    "trace": 6,
    "workflow": 7, "workflow_nonlinear": 7, "nominal_refit": 7,
    "reproduce": 8, "plotting": 8, "io": 8, "model_io": 8, "cli": 8, "__main__": 8,
    "__init__": 9,
}


def _module_key(path: Path) -> str:
    rel = path.relative_to(PKG).with_suffix("")
    return rel.parts[0] if len(rel.parts) > 1 else rel.name


def _imported_keys(path: Path):
    """(key, lineno) of greybox modules imported at module level by ``path``."""
    tree = ast.parse(path.read_text())
    pkg_parts = path.relative_to(PKG).parent.parts
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.level:
            base = list(pkg_parts[:len(pkg_parts) - (node.level - 1)])
            target = base + (node.module.split(".") if node.module else [])
            if target:
                yield target[0], node.lineno
            else:  # "from . import x"
                for alias in node.names:
                    yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom) and node.module and \
                node.module.startswith("greybox."):
            yield node.module.split(".")[1], node.lineno


FILES = sorted(p for p in PKG.rglob("*.py"))


@pytest.mark.parametrize("path", FILES, ids=[str(p.relative_to(PKG)) for p in FILES])
def test_no_upward_imports(path):
    me = _module_key(path)
    assert me in LAYER, f"{me} has no layer in the house plan; add it to LAYER"
    for key, line in _imported_keys(path):
        if key == me:
            continue
        assert key in LAYER, f"{path.name}:{line} imports unknown module {key}"
        assert LAYER[key] <= LAYER[me], (
            f"{path.relative_to(PKG)}:{line} ({me}, layer {LAYER[me]}) imports {key} "
            f"(layer {LAYER[key]}), a layer above it")


@pytest.mark.parametrize("path", FILES, ids=[str(p.relative_to(PKG)) for p in FILES])
def test_matplotlib_only_lazily_in_plotting(path):
    tree = ast.parse(path.read_text())
    for node in tree.body:  # module level only
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module]
        assert not any(n.split(".")[0] == "matplotlib" for n in names), \
            f"{path.relative_to(PKG)} imports matplotlib at module level"
