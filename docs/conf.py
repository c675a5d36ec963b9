"""Sphinx configuration of the slicersim documentation (``make docs``)."""
import os
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(DOCS / "_ext"))
sys.path.insert(0, str(ROOT))
# the gallery and autodoc import slicersim: keep its progress bars and Dask dashboards quiet
os.environ.setdefault("MPLBACKEND", "Agg")

import slicersim  # noqa: E402

project = "slicersim"
author = "the slicersim developers"
copyright = "the slicersim developers"
release = version = slicersim.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx_gallery.gen_gallery",
    "cli_reference",        # docs/_ext: the CLI reference from argparse
    "benchmark_pages",      # docs/_ext: one page per benchmark family from benchmarks/results
    "api_pages",            # docs/_ext: the API reference pages of slicersim.__all__
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "examples", "Thumbs.db", ".DS_Store"]

myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

# numpydoc docstrings: Parameters / Returns sections, "name : type" then an indented description
# with its [unit]; every docstring renders through napoleon (tests/docs/test_api_docstrings.py)
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False
autodoc_member_order = "bysource"
autodoc_typehints = "none"
autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": True}

# -- cross-references: every one must resolve (``-n``) ----------------------------------------------
# Not ignored: any reference to slicersim itself (a broken one is a bug in a docstring).  Ignored, and
# only these: what cannot resolve in an offline build, and the words of numpydoc type fields.
nitpicky = True
nitpick_ignore_regex = [
    # other packages' objects: the build has no network, so intersphinx cannot fetch their inventories
    (r"py:.*", r"(numpy|astropy|matplotlib|h5py|sncosmo|distributed|dask|scipy|pyopencl|os|pathlib|io"
               r"|contextlib|collections|typing)(\..+)?"),
    # numpydoc type vocabulary ("array_like of shape (n,), optional"): words, not objects
    (r"py:class", r"optional|default|array_like|sequence|iterable|callable|path-like|file object|scalar"),
    # sizes and dimension names of "of shape (nλ, ny, nx)", "(S, J, M, 4)", "(S, J−1, M−1)"
    (r"py:class", r"\d+|[A-Za-z]|h|w|ny|nx|nλ|nλ\+1|nλ_in|ny_in|nx_in|rows|cols|n_rows|n_cols|nints"
                  r"|ngroups|nramps|[A-Z][−-]1"),
    # literal values of type fields ({"rest", "obs"}, "narrow")
    (r"py:class", r"""[{"'].*|.*["'}]"""),
    # base classes outside the public API, shown by ``show-inheritance``
    (r"py:class", r"slicersim\.versioning\.Versioned|slicersim\.targets\.detector\.DetectorProducts"
                  r"|slicersim\.targets\.observation\.ObservationMixin|slicersim\.snr\.spectrum\.SpectrumSNRMixin"
                  r"|slicersim\.instrument\.mapper_projection\.ProjectionMixin"
                  r"|slicersim\.[\w.]*\._\w+"),
]

sphinx_gallery_conf = {
    "examples_dirs": "examples",
    "gallery_dirs": "_generated/gallery",
    "filename_pattern": r"/plot_",
    "download_all_examples": False,
    "remove_config_comments": True,
    "within_subsection_order": "FileNameSortKey",
    "matplotlib_animations": False,
    "image_scrapers": ("matplotlib",),
    "abort_on_example_error": True,
    "show_memory": False,
}

html_theme = "alabaster"
html_title = f"slicersim {release}"
html_theme_options = {"description": "Image-slicer IFS simulator (Lazuli)", "fixed_sidebar": True,
                      "page_width": "1100px", "sidebar_width": "230px"}
html_static_path = []


#: attribute, property and module-data docstrings, kept from napoleon (see ``_keep_sentences``)
_SENTENCES = {}


def _hold_sentences(app, what, name, obj, options, lines):
    """The package's attribute, property and module-data docstrings are reST sentences ("pixels a
    cell owns per native bin: its slit image"), not napoleon's inline "type: description", which
    would read the words before the first colon as a type: hold them before napoleon (priority
    500) ..."""
    if what in ("attribute", "property", "data"):
        _SENTENCES[(what, name)] = list(lines)


def _keep_sentences(app, what, name, obj, options, lines):
    """... and put them back after it (rendered as written)."""
    held = _SENTENCES.pop((what, name), None)
    if held is not None:
        lines[:] = held


def setup(app):
    app.connect("autodoc-process-docstring", _hold_sentences, priority=400)
    app.connect("autodoc-process-docstring", _keep_sentences, priority=600)
