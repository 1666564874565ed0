"""Sphinx configuration of the clsas site: the guide (MyST Markdown), the API reference (numpydoc
docstrings through autosummary), the gallery (sphinx-gallery, from examples/) and the benchmark
pages (generated from bench/results/ by _ext/benchpages.py).

Build offline, warnings as errors (what CI runs):

    python -m sphinx -W --keep-going docs docs/_build/html
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path[:0] = [str(ROOT), str(HERE / "_ext")]
os.environ.setdefault("MPLBACKEND", "Agg")

from gallery_args import ARGS as GALLERY_ARGS  # noqa: E402

import clsas  # noqa: E402

project = "clsas"
author = "the clsas authors"
copyright = "2026, the clsas authors"
release = version = clsas.__version__ if hasattr(clsas, "__version__") else "0.1.0"

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "numpydoc",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
    "benchpages",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "**/GALLERY_HEADER.rst",
                    "api/examples", "auto_examples/*.ipynb", "auto_examples/*.py", "auto_examples/*.zip"]
templates_path = ["_templates"]
suppress_warnings = ["myst.header"]

# MyST: $...$ maths, {doc} and {func} roles, heading anchors for links into sections
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

# API reference: one page per public name
autosummary_generate = True
autosummary_imported_members = True
autodoc_typehints = "none"
autodoc_default_options = {"inherited-members": False}
# examples shown on an API page in addition to the docstring's, for functions whose docstring has no
# room for one (the 80-line limit counts docstrings) or is being changed on another branch:
# docs/api/examples/<full name>.rst, doctest format
autosummary_context = {"api_examples": {p.stem: p.read_text(encoding="utf-8")
                                        for p in sorted((HERE / "api" / "examples").glob("*.rst"))}}
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

# gallery: the examples with an entry in _ext/gallery_args.py's ARGS are executed, at the small sizes
# given there (about a minute in all on 2 cores); an example without one is shown with its code, not
# executed (add it, with a size that takes seconds)
sphinx_gallery_conf = {
    "examples_dirs": str(ROOT / "examples"),
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"[\\/](" + "|".join(GALLERY_ARGS) + r")\.py$",
    "ignore_pattern": r"__init__\.py|/out/",
    "reset_argv": "gallery_args.reset_argv",
    "image_scrapers": ("gallery_args.png_scraper",),
    "download_all_examples": False,
    "remove_config_comments": True,
    "plot_gallery": "True",
    "abort_on_example_error": True,
    "only_warn_on_example_error": False,
    "show_memory": False,
    "capture_repr": (),
    "matplotlib_animations": False,
    "within_subsection_order": "FileNameSortKey",
}

html_theme = "pydata_sphinx_theme"
html_title = "clsas"
html_theme_options = {
    "navigation_with_keys": False,
    "show_toc_level": 2,
    "secondary_sidebar_items": ["page-toc"],
}
html_static_path: list[str] = []
html_show_sourcelink = False
