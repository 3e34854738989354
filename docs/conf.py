"""Sphinx configuration: the user guide (MyST Markdown), the API reference (autodoc, numpy-style
docstrings through napoleon) and the gallery of examples/ (sphinx-gallery, which runs them).
``make docs`` builds it with warnings as errors into docs/_build/html."""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
os.environ.setdefault("MPLBACKEND", "Agg")

import rtfem  # noqa: E402

project = "rtfem"
author = "the rtfem developers"
copyright = "2026, the rtfem developers"
release = version = rtfem.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "auto_examples/*.ipynb", "auto_examples/*.py", "auto_examples/*.zip",
                    "auto_examples/*.md5", "auto_examples/*.json"]
myst_heading_anchors = 3

autosummary_generate = True
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_typehints = "none"  # the docstrings say what each parameter is
autodoc_mock_imports = ["cupy", "pypardiso"]
napoleon_numpy_docstring = True
napoleon_google_docstring = False
napoleon_use_rtype = False

html_theme = "pydata_sphinx_theme"
html_title = "rtfem"
html_static_path: list[str] = []
templates_path = ["_templates"]
html_theme_options = {"navigation_with_keys": False, "show_toc_level": 2}

sphinx_gallery_conf = {
    "examples_dirs": str(ROOT / "examples"),
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"/\d\d_",  # every numbered example runs
    "download_all_examples": False,
    "remove_config_comments": True,
    "within_subsection_order": "FileNameSortKey",
}


def _plain_pipes(app, what, name, obj, options, lines):
    """The docstrings write norms as |x| in plain text (``|A w - b| <= tol |b|``); reStructuredText
    would read |...| as a substitution, so the bars are escaped before parsing."""
    for i, line in enumerate(lines):
        row = line.strip()
        if "|" in line and not (row.startswith("+-") or (row.startswith("|") and row.endswith("|"))):  # not a table
            lines[i] = line.replace("\\|", "|").replace("|", "\\|")


def setup(app):
    app.connect("autodoc-process-docstring", _plain_pipes)
