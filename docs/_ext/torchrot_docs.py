"""Sphinx helpers that read facts from the installed torchrot at build time,
so that the pages cannot drift from the code:

- ``torchrot-schema`` (directive): the schema of a registered operator, as
  the dispatcher has it (csrc/ops/schemas.cpp defines them)::

      ```{torchrot-schema} fit_rotation
      ```

- ``torchrot-const`` (role): the value of one of torchrot's constants
  (``torchrot._constants``, read from csrc/limits.h), e.g.
  ``{torchrot-const}`CONVERGED_CAP``` renders as the number.
"""
from __future__ import annotations

import re

from docutils import nodes
from sphinx.util.docutils import SphinxDirective

# The dispatcher prints float defaults with 17 significant digits (1e-6 as
# 9.9999999999999995e-07); shown as Python writes them.
_LONG_FLOAT = re.compile(r"(?<==)(-?\d\.\d{12,}e[-+]\d+)")


def schema_text(name: str) -> str:
    import torch

    import torchrot  # noqa: F401  (registers torch.ops.torchrot.*)

    packet = getattr(torch.ops.torchrot, name)
    schema = str(packet.default._schema)
    return _LONG_FLOAT.sub(lambda m: repr(float(m.group(1))), schema)


class SchemaDirective(SphinxDirective):
    required_arguments = 1
    has_content = False

    def run(self) -> list[nodes.Node]:
        text = schema_text(self.arguments[0])
        block = nodes.literal_block(text, text)
        block["language"] = "none"
        return [block]


def constant_text(name: str) -> str:
    from torchrot import _constants

    value = getattr(_constants, name)
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    return str(value)


def constant_role(name, rawtext, text, lineno, inliner, options=None, content=None):
    try:
        value = constant_text(text.strip())
    except AttributeError:
        message = inliner.reporter.error(f"torchrot has no constant {text!r} (torchrot._constants)", line=lineno)
        return [inliner.problematic(rawtext, rawtext, message)], [message]
    return [nodes.Text(value)], []


def setup(app):
    app.add_directive("torchrot-schema", SchemaDirective)
    app.add_role("torchrot-const", constant_role)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
