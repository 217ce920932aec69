"""Sphinx configuration of torchrot's documentation site.

Build (warnings are errors, as .ci/docs runs it):

    python -m sphinx -W --keep-going -b html docs build/docs/html

The pages are Markdown (MyST-Parser); the API reference is generated from the
docstrings (autodoc + napoleon, Google style); ``-b doctest`` runs the ``>>>``
examples of the documented docstrings (sphinx.ext.doctest, with
``doctest_global_setup`` below). Requirements: ``pip install -e ".[docs]"``
(the ``docs`` group of pyproject.toml) and a built torchrot (autodoc imports it).
"""
from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "_ext"))

import torchrot  # noqa: E402  (autodoc documents the installed, compiled package)

project = "torchrot"
author = "torchrot contributors"
copyright = "torchrot contributors"
release = torchrot.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.doctest",
    "sphinx.ext.mathjax",
    "myst_parser",
    "torchrot_docs",  # docs/_ext: operator schemas and constants, read from the installed torchrot
]

source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "_ext", "Thumbs.db", ".DS_Store"]
templates_path: list[str] = []

# -- MyST ----------------------------------------------------------------------
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3  # [text](page.md#a-heading) links to headings down to ###
myst_dmath_double_inline = True

# -- autodoc / napoleon ----------------------------------------------------------
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_preserve_defaults = False  # signatures show the values (variant="conservative"), not the names of constants
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False

# -- doctest (python -m sphinx -b doctest docs ...) --------------------------------
# Every ">>>" example of a docstring that the API pages document is a test. The
# examples of one page run in order in one namespace (the doctest builder's
# "default" group), which starts with these imports; keep examples small.
doctest_global_setup = """
import torch
import torchrot
torch.manual_seed(0)
"""
doctest_test_doctest_blocks = "default"  # plain ">>>" blocks (docstring examples) are tests
import doctest as _doctest  # noqa: E402

doctest_default_flags = (_doctest.ELLIPSIS | _doctest.IGNORE_EXCEPTION_DETAIL | _doctest.DONT_ACCEPT_TRUE_FOR_1
                         | _doctest.NORMALIZE_WHITESPACE)

# -- HTML -------------------------------------------------------------------------
html_theme = "furo"
html_title = f"torchrot {release}"
html_static_path: list[str] = []
html_show_sourcelink = False
pygments_style = "sphinx"

