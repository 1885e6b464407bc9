"""Meta-tests: every public callable documents each of its parameters; doctests run."""

from __future__ import annotations

import doctest
import importlib
import inspect

import pytest

import greybox as gb

PUBLIC = [name for name in gb.__all__ if callable(getattr(gb, name))
          and not inspect.isclass(getattr(gb, name))]


@pytest.mark.parametrize("name", PUBLIC)
def test_every_parameter_is_documented(name):
    func = getattr(gb, name)
    doc = inspect.getdoc(func) or ""
    assert doc, f"{name} has no docstring"
    params = [p for p in inspect.signature(func).parameters.values()
              if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
    if not params:
        return
    assert "Parameters" in doc, f"{name}: no Parameters section"
    section = doc.split("Parameters", 1)[1].split("Returns", 1)[0]
    missing = [p.name for p in params
               if not any(line.split(":")[0].strip().split(",").__contains__(p.name)
                          or p.name in [s.strip() for s in line.split(":")[0].split(",")]
                          for line in section.splitlines() if ":" in line)]
    assert not missing, f"{name}: parameters not documented: {missing}"


@pytest.mark.parametrize("module", ["greybox.filters.uikf", "greybox.filters.kernels", "greybox.ident.n4sid",
                                    "greybox.ident.closedloop", "greybox.metrics"])
def test_doctests(module):
    mod = importlib.import_module(module)
    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.failed == 0
