"""Sphinx configuration of the rayaccel documentation.

Build with ``make docs`` (installs the ``docs`` extra into ``.venv`` first); the HTML
lands in ``docs/_build/html``. The gallery runs every ``examples/plot_*.py`` script.
"""

from __future__ import annotations

import os
import re

# Before anything imports matplotlib: no display on a build machine.
os.environ.setdefault("MPLBACKEND", "Agg")

import rayaccel

project = "rayaccel"
author = "rayaccel developers"
copyright = "rayaccel developers (MIT licence)"
version = release = rayaccel.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "numpydoc",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
templates_path = ["_templates"]
exclude_patterns = ["_build", "auto_examples/*.ipynb", "auto_examples/*.py", "**/*.codeobj.json"]

# -- API reference ----------------------------------------------------------------------------
# One generated page per public module (api.rst lists them); members come from each
# module's ``__all__`` where it has one, otherwise from what the module defines.
autosummary_generate = True
autosummary_imported_members = False
autodoc_default_options = {"members": True}
autodoc_member_order = "bysource"
autodoc_typehints = "none"  # numpydoc's Parameters sections carry the types and shapes
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

# A bare ``name_`` in reST is a hyperlink reference; in our numpydoc docstrings it is
# always meant literally ("no build_/traverse_ module"), so escape a word-final
# underscore outside inline literals and literal blocks before docutils sees it.
_BARE_REFERENCE = re.compile(r"(?<![\w`])([A-Za-z]\w*[A-Za-z0-9])_(?=[\s/,;:.)]|$)")


def _escape_bare_references(app, what, name, obj, options, lines):
    literal_indent = None
    for i, line in enumerate(lines):
        indent = len(line) - len(line.lstrip())
        if literal_indent is not None and (not line.strip() or indent > literal_indent):
            continue
        literal_indent = indent if line.rstrip().endswith("::") else None
        parts = line.split("``")
        parts[::2] = [_BARE_REFERENCE.sub(r"\1\\_", part) for part in parts[::2]]
        lines[i] = "``".join(parts)


def setup(app):
    app.connect("autodoc-process-docstring", _escape_bare_references)


# -- Markdown pages ---------------------------------------------------------------------------
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3

# -- Gallery ----------------------------------------------------------------------------------
sphinx_gallery_conf = {
    "examples_dirs": "../examples",
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"/plot_",
    "download_all_examples": False,
    "remove_config_comments": True,
    "matplotlib_animations": False,
    "within_subsection_order": "FileNameSortKey",
}

# -- HTML -------------------------------------------------------------------------------------
html_theme = "pydata_sphinx_theme"
html_title = f"rayaccel {release}"
html_theme_options = {
    "show_toc_level": 2,
    "navigation_with_keys": False,
    "secondary_sidebar_items": ["page-toc"],
    "footer_start": ["copyright"],
    "footer_end": ["sphinx-version"],
}
# The narrative pages have no sub-pages: no left sidebar there (more room for tables).
NARRATIVE_PAGES = ("quickstart", "algorithms", "architecture", "performance", "contributing")
html_sidebars = {"**": ["sidebar-nav-bs"], **{page: [] for page in NARRATIVE_PAGES}}
html_show_sourcelink = False
html_static_path = ["_static"]
html_css_files = ["custom.css"]
