"""Loads the compiled extension, torchrot._C, after checking that it was built
against the running torch.

A C++ extension is compiled against one torch's headers and libraries; loaded
under another minor release it fails to link or, worse, links and crashes
later. setup.py records the torch it compiled against in
torchrot/_build_info.py; here that release is compared with the running one
before the extension is loaded, and a mismatch is an ImportError that names
both and the command that rebuilds torchrot. Patch releases of one minor
release share its C++ ABI, as the wheel's requirement (torch==X.Y.*) assumes.
"""
from __future__ import annotations

import importlib
import os
from types import ModuleType

import torch

__all__ = ["load_extension", "torch_release", "check_torch_release"]

_PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__))


def torch_release(version: str) -> tuple[int, int]:
    """(major, minor) of a torch version string: ``(2, 13)`` for ``"2.13.0+cpu"``."""
    major, minor = version.split("+")[0].split(".")[:2]
    return int(major), int(minor)


def rebuild_command() -> str:
    """How to rebuild torchrot against the installed torch: in its source tree
    where it runs from one (an editable install), else from a source checkout."""
    root = os.path.dirname(_PACKAGE_DIR)
    if os.path.isfile(os.path.join(root, "setup.py")):
        return f"pip install --no-build-isolation -e {root}"
    return "pip install --no-build-isolation --force-reinstall --no-deps <a torchrot source checkout or sdist>"


def check_torch_release(built: str | None, running: str) -> None:
    """Raises ImportError unless torch ``built`` (None: never built) and
    ``running`` are the same minor release."""
    if built is None:
        raise ImportError(
            f"torchrot's C++ extension (torchrot._C) has not been built in {_PACKAGE_DIR}; build it against the "
            f"installed torch {running}: {rebuild_command()}"
        )
    if torch_release(built) != torch_release(running):
        raise ImportError(
            f"torchrot's C++ extension was built against torch {built}, but torch {running} is installed; a C++ "
            f"extension only runs with the torch release it was compiled for. Rebuild torchrot for this torch: "
            f"{rebuild_command()}"
        )


def load_extension() -> ModuleType:
    """torchrot._C, loaded once its torch release is checked (see the module docstring)."""
    try:
        from torchrot._build_info import TORCH_VERSION as built
    except ImportError:
        built = None
    check_torch_release(built, torch.__version__)
    return importlib.import_module("torchrot._C")
