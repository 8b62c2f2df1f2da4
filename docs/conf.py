"""Sphinx configuration of febed's documentation (`make docs`: HTML in docs/_build/html, warnings are errors)."""

from __future__ import annotations

import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS / "_ext"))
sys.path.insert(0, str(DOCS.parent))

import febed  # noqa: E402  (after the path set-up: the documented package is the one in this tree)

project = "febed"
author = "The febed developers"
copyright = "The febed developers, MIT licence"
release = febed.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "febed_params",
    "febed_docstrings",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "_ext", "**/out", "Thumbs.db", ".DS_Store"]

# Markdown: $...$ and $$...$$ math, ::: fences, definition lists; anchors for ## and ### headings so that
# pages and code comments can point at `theory.md#drag-closures`.
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

# API reference from the docstrings (Google style).
autodoc_member_order = "bysource"
autodoc_typehints = "none"  # the signature line keeps the names; types are in the Args text
autodoc_default_options = {"members": True}
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_use_ivar = True  # Attributes sections as fields, not a second description of each attribute
default_role = "literal"  # `name` in a docstring is code

html_theme = "alabaster"
html_title = f"febed {release}"
html_static_path: list[str] = []
html_theme_options = {
    "description": "CFD-DEM for gas-solid fluidized beds",
    "page_width": "1180px",
    "sidebar_width": "240px",
    "fixed_sidebar": True,
}
html_sidebars = {"**": ["about.html", "navigation.html", "searchbox.html"]}


def _check_api_page(app) -> None:
    """Warn (an error under -W) when a febed module is missing from api.md, so the API reference stays whole."""
    import pkgutil
    import re

    from sphinx.util import logging

    listed = set(re.findall(r"automodule:: (\S+)", (DOCS / "api.md").read_text(encoding="utf-8")))
    modules = {"febed"} | {m.name for m in pkgutil.walk_packages(febed.__path__, "febed.")}
    missing = sorted(m for m in modules - listed if not m.endswith("__main__"))
    if missing:
        logging.getLogger(__name__).warning("docs/api.md does not document: %s", ", ".join(missing))


def setup(app):
    """Connect the API-page check."""
    app.connect("builder-inited", _check_api_page)
