"""Sphinx configuration: the user guide (Markdown, via MyST) and the API reference
(autodoc + autosummary from the numpydoc docstrings, read by napoleon).

Build: ``python3 -m sphinx -W -b html docs docs/_build/html`` (``pip install -e ".[docs]"``).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import greybox  # noqa: E402

project = "greybox"
author = "the greybox developers"
copyright = "the greybox developers"
release = version = greybox.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "myst_parser",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
templates_path = ["_templates"]

# MyST: anchors for "page.md#heading" links; $...$ maths left as written.
myst_heading_anchors = 3
myst_enable_extensions = ["colon_fence"]

# API reference: one page per public name, documented as ``greybox.<name>``
# (where users import it from), whatever module defines it.
autosummary_generate = True
autosummary_imported_members = True
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_format = "short"
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_ivar = True          # "Attributes" as a field list: no duplicate entries
napoleon_use_rtype = False
nitpicky = False

html_theme = "alabaster"
html_static_path: list[str] = []
html_title = f"greybox {release}"


def _check_api_covers_all(app):
    """Every name in ``greybox.__all__`` is listed on the API page (a warning otherwise,
    which ``-W`` turns into a failed build)."""
    text = (Path(app.srcdir) / "api.rst").read_text()
    listed = set(re.findall(r"^\s{3}(\w+)\s*$", text, flags=re.M))
    missing = sorted(set(greybox.__all__) - listed)
    if missing:
        from sphinx.util import logging

        logging.getLogger(__name__).warning(
            "docs/api.rst does not list these public names of greybox.__all__: %s",
            ", ".join(missing))


_DATA_MODULES = ("greybox.plants.tape_drive", "greybox.plants.motor_pump")
_LITERAL = re.compile(r"(``.*?``|`[^`]*`)")
_BARS = re.compile(r"(?<![\\\w|])\|([^|\s`][^|`]{0,15}?)\|(?![\w_|])")


def _docstrings(app, what, name, obj, options, lines):
    """Two fixes made while reading, so that ``greybox/`` stays as it is:

    * a public constant (``TAPE_DRIVE_Q``, ...) is an ndarray or a float, whose
      own docstring autodoc would show; use the string literal after its
      assignment in the module that defines it;
    * ``|x|`` in running text (an absolute value) reads as an RST substitution:
      escape it outside inline literals, in docstrings without maths.
    """
    if what == "data":
        from sphinx.pycode import ModuleAnalyzer

        short = name.rsplit(".", 1)[-1]
        for mod in _DATA_MODULES:
            doc = ModuleAnalyzer.for_module(mod).find_attr_docs().get(("", short))
            if doc:
                lines[:] = list(doc)
                return
        lines[:] = []
        return
    if any(".. math::" in ln or ":math:" in ln for ln in lines):
        return
    for i, ln in enumerate(lines):
        parts = _LITERAL.split(ln)
        lines[i] = "".join(p if j % 2 else _BARS.sub(r"\\|\1\\|", p)
                           for j, p in enumerate(parts))


def setup(app):
    app.connect("builder-inited", _check_api_covers_all)
    app.connect("autodoc-process-docstring", _docstrings)
