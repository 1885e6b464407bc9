"""The house plan: a layer never imports a layer above it; no import circle.

Layers, bottom first: base helpers; plants and signals; metrics (and the plant zoo,
a test helper independent of the trace code it measures); filters; ident; update
(and validation); trace; workflow (its records first); top (plotting, I/O, CLI,
reproduction of the paper). Imports inside functions count as much as those at
module level, with one exception: the lazy import of :mod:`greybox.plotting` inside
``.plot()`` methods, which delegate to the plotting module as STYLE.md asks. Only
plotting may import matplotlib, and only lazily. No function over ``MAX_LINES``
lines (from ``def`` to the end of its body, docstring included), except the debts
listed in ``LONG_FUNCTIONS`` (which may only shrink); imports of another
sub-package's ``_private`` names may only become fewer.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "greybox"

LAYER = {
    "exceptions": 0, "_validation": 0, "_lti": 0, "_blas": 0, "progress": 0, "_jit": 0,
    "system": 1, "signals": 1, "plants": 1, "nonlinear": 1, "hold": 1,
    "metrics": 2, "zoo": 2, "terms": 2, "lawsim": 2,
    "filters": 3,
    "ident": 4,
    "update": 5, "validate": 5,
    "trace": 6,
    "records": 7, "recommend": 7, "plant_adapter": 7, "workflow": 7, "workflow_nonlinear": 7,
    "nominal_refit": 7,
    "reproduce": 8, "plotting": 8, "io": 8, "model_io": 8, "cli": 8, "__main__": 8,
    "fleet": 8,
    "__init__": 9,
}


def _module_key(path: Path) -> str:
    rel = path.relative_to(PKG).with_suffix("")
    return rel.parts[0] if len(rel.parts) > 1 else rel.name


def _is_plot_delegation(node, tree) -> bool:
    """A function-level ``from ..plotting import ...`` (a ``.plot()`` delegating)."""
    return (node not in tree.body and isinstance(node, ast.ImportFrom)
            and (node.module or "").split(".")[-1] == "plotting")


def _imported_keys(path: Path):
    """(key, lineno) of greybox modules imported by ``path`` (functions included)."""
    tree = ast.parse(path.read_text())
    pkg_parts = path.relative_to(PKG).parent.parts
    for node in ast.walk(tree):
        if _is_plot_delegation(node, tree):
            continue
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


# ------------------------------------------------------------------ import circles
def _dotted(path: Path) -> str:
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_dotted(p): p for p in FILES}


def _targets(path: Path, node: ast.ImportFrom) -> list[str]:
    """greybox modules an ImportFrom names (the module, and names that are submodules)."""
    me = _dotted(path).split(".")
    package = me if path.name == "__init__.py" else me[:-1]
    if node.level:
        base = package[:len(package) - (node.level - 1)]
        mod = ".".join(base + (node.module.split(".") if node.module else []))
    elif (node.module or "").startswith("greybox"):
        mod = node.module
    else:
        return []
    out = [mod] if mod in MODULES else []
    out += [f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in MODULES]
    return out


def _graph() -> dict[str, dict[str, int]]:
    """module -> {imported module: line}, imports inside functions included."""
    edges = {}
    for name, path in MODULES.items():
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and not _is_plot_delegation(node, tree):
                for t in _targets(path, node):
                    if t != name and not name.startswith(t + "."):  # a package's own parent
                        edges.setdefault(name, {})[t] = node.lineno
    return edges


def _cycles(edges) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative enough)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, {}):
            if w not in index:
                visit(w)
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
                out.append(sorted(comp))

    for v in sorted(set(edges) | {w for ws in edges.values() for w in ws}):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle():
    edges = _graph()
    cycles = _cycles(edges)
    detail = [f"{a} -> {b} (line {edges[a][b]})" for c in cycles for a in c
              for b in edges.get(a, {}) if b in c]
    assert not cycles, f"import circles: {cycles}; edges: {detail}"


def test_the_circle_check_can_fail():
    """The detector finds a planted circle (a test that cannot fail is a defect)."""
    assert _cycles({"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b": 1}, "b": {}}) == []


# ------------------------------------------------------------------ function length
MAX_LINES = 120
# The debts: functions over MAX_LINES today, with their length (lines from ``def`` to
# the last line of the body, the docstring included); an entry may only shrink or go.
# The pipeline rebuild (named stages, linear and nonlinear) paid the last of them by the
# old count (docstring left out); the split of the long public functions into named steps
# (their derivations moved to the module docstrings) paid those of the full count.
LONG_FUNCTIONS: dict[str, int] = {}


def _code_lines(fn) -> int:
    """Lines from ``def`` to the end of the body, the docstring included: a numpydoc
    docstring is long by design (Parameters, Returns, Examples), so a function that
    needs one has that much less room for code; long derivations go to the module
    docstring."""
    return fn.end_lineno - fn.lineno + 1


def _long_functions() -> dict[str, int]:
    found = {}
    for path in FILES:
        tree = ast.parse(path.read_text())

        def walk(node, prefix):
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    name = f"{prefix}{child.name}"
                    if not isinstance(child, ast.ClassDef):
                        length = _code_lines(child)
                        if length > MAX_LINES:
                            found[f"{path.relative_to(PKG)}:{name}"] = length
                    walk(child, name + ".")

        walk(tree, "")
    return found


def test_no_function_over_the_limit_but_the_listed_debts():
    found = _long_functions()
    new = {k: v for k, v in found.items() if k not in LONG_FUNCTIONS}
    grown = {k: (v, LONG_FUNCTIONS[k]) for k, v in found.items()
             if k in LONG_FUNCTIONS and v > LONG_FUNCTIONS[k]}
    paid = sorted(k for k in LONG_FUNCTIONS if k not in found)
    assert not new, f"functions over {MAX_LINES} lines: {new}; split them into named steps"
    assert not grown, f"listed long functions grew (now, listed): {grown}"
    assert not paid, f"these are no longer over {MAX_LINES} lines: remove them from " \
                     f"LONG_FUNCTIONS: {paid}"


# ------------------------------------------------------------------ private imports
# Imports of another sub-package's ``_private`` name: none (the last fourteen, such as
# ``from ..trace.laws import _fit_static`` in workflow_nonlinear.py, are public names now).
MAX_PRIVATE_IMPORTS = 0


def _private_imports() -> list[str]:
    out = []
    for path in FILES:
        tree = ast.parse(path.read_text())
        me = _dotted(path).split(".")
        for node in ast.walk(tree):
            if not isinstance(node, ast.ImportFrom):
                continue
            for t in _targets(path, node) or []:
                if t not in MODULES or t.split(".")[:2] == me[:2]:
                    continue  # the same sub-package (or module) may share its privates
                out += [f"{path.relative_to(PKG)}:{node.lineno} {t}.{a.name}"
                        for a in node.names if a.name.startswith("_")
                        and not a.name.startswith("__")]
    return out


def test_private_imports_across_subpackages_only_become_fewer():
    found = _private_imports()
    assert len(found) <= MAX_PRIVATE_IMPORTS, (
        f"{len(found)} imports of another sub-package's private names (at most "
        f"{MAX_PRIVATE_IMPORTS}); make the name public or move the helper: " + "; ".join(found))
