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

import inspect
import os
import re
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

# -- docstring clean-ups (autodoc-process-docstring, connected in setup below) -----
# torchrot's docstrings are written to be read as plain text too; these make
# the few plain-text habits valid reST, and do nothing to docstrings without them.


def _drop_type_docstrings(app, what, name, obj, options, lines):
    """A documented constant (``autodata``) without a ``#:`` comment of its
    own would show its type's docstring (float's, dict's): dropped, the page
    gives the description."""
    doc = type(obj).__doc__
    if what in ("data", "attribute") and doc and "\n".join(lines).strip() == inspect.cleandoc(doc).strip():
        lines[:] = []


def _namedtuple_fields(app, what, name, obj, options, lines):
    """A NamedTuple's docstring (FitInfo, RigidTransform) lists its fields as
    ``name: text`` lines, continued by indented lines: made a definition list
    (the field's name as the term), which reST reads with its continuations."""
    fields = getattr(obj, "_fields", None)
    if what != "class" or not fields:
        return
    out = []
    for line in lines:
        head, _, rest = line.partition(":")
        if head in fields and rest:
            if out and out[-1].strip():
                out.append("")
            out += [f"``{head}``", "    " + rest.strip()]
        else:
            out.append(line)
    lines[:] = out


_EXCEPTION_ENTRY = re.compile(r"^[A-Za-z_][\w.]*(\s*\([^)]*\))?\s*:(\s|$)")


def _free_text_raises(app, what, name, obj, options, lines):
    """Runs before napoleon. napoleon reads a ``Raises:`` section as
    ``ExceptionType: description`` entries; one written as prose ("TypeError
    for ..., ValueError for ...") would come out as a list of garbled
    entries, so it is kept as a paragraph led by "Raises:"."""
    i = 0
    while i < len(lines):
        line = lines[i]
        indent = len(line) - len(line.lstrip())
        if line.strip() != "Raises:":
            i += 1
            continue
        end = i + 1
        while end < len(lines) and (not lines[end].strip() or len(lines[end]) - len(lines[end].lstrip()) > indent):
            end += 1
        body = [text.strip() for text in lines[i + 1:end]]
        first = next((text for text in body if text), "")
        if first and not _EXCEPTION_ENTRY.match(first):
            lines[i:end] = [" " * indent + "**Raises:** " + " ".join(text for text in body if text), ""]
        i += 1


_INLINE_LITERAL = re.compile(r"(``.+?``)")


def _escape_bars(app, what, name, obj, options, lines):
    """torchrot's docstrings write norms in plain text, ``|M|_F``, ``|R^T R - I|``;
    reST would read ``|...|`` as a substitution reference (an error). Every
    ``|`` of running text is escaped, none in inline literals, ``>>>``
    examples (up to the blank line that ends them), literal blocks (after
    ``::``), grid tables or line blocks (``| `` at the start of a line)."""
    in_example = in_table = False
    literal_indent = None  # the indentation of the paragraph that ended in "::"
    for i, line in enumerate(lines):
        stripped = line.lstrip()
        indent = len(line) - len(stripped)
        if not stripped:
            in_example = in_table = False
            continue
        if literal_indent is not None:
            if indent > literal_indent:
                continue
            literal_indent = None
        if stripped.startswith(">>>"):
            in_example = True
        if stripped.startswith(("+-", "+=")):
            in_table = True
        if in_example or in_table or stripped.startswith("| "):
            continue
        parts = _INLINE_LITERAL.split(line)
        lines[i] = "".join(part if part.startswith("``") else part.replace("|", "\\|") for part in parts)
        if stripped.endswith("::"):
            literal_indent = indent


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


def setup(app):
    app.connect("autodoc-process-docstring", _free_text_raises, priority=100)  # before napoleon (500)
    app.connect("autodoc-process-docstring", _drop_type_docstrings)
    app.connect("autodoc-process-docstring", _escape_bars)
    app.connect("autodoc-process-docstring", _namedtuple_fields)
