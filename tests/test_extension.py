"""Loading the compiled extension (torchrot/_extension.py): under a torch
release other than the one it was built against, or where it was never
built, ``import torchrot`` raises an ImportError that names both releases and
the command that rebuilds torchrot, before loading anything."""
from __future__ import annotations

import subprocess
import sys

import pytest
import torch

import torchrot
from torchrot._extension import check_torch_release, torch_release


def test_release_of_a_version_string():
    assert torch_release("2.13.0+cpu") == (2, 13)
    assert torch_release("2.15.0") == (2, 15)
    assert torch_release("2.12.1+cu130") == (2, 12)


def test_same_minor_release_loads():
    check_torch_release(torch.__version__, torch.__version__)
    check_torch_release("2.13.0+cpu", "2.13.1")  # patch releases share the C++ ABI


@pytest.mark.parametrize("built", ["2.11.0", "2.14.1+cu128", "3.0.0"])
def test_another_release_is_a_clear_import_error(built):
    running = "2.13.0+cpu" if not built.startswith("2.13") else "2.14.0"
    with pytest.raises(ImportError) as error:
        check_torch_release(built, running)
    message = str(error.value)
    assert f"built against torch {built}" in message and f"torch {running} is installed" in message
    assert "pip install --no-build-isolation" in message


def test_never_built_is_a_clear_import_error():
    with pytest.raises(ImportError, match=r"has not been built in .*pip install --no-build-isolation"):
        check_torch_release(None, torch.__version__)


def test_import_under_another_torch_fails_before_loading():
    """A fresh interpreter whose build record names another torch: the
    import stops with the message, and the extension is never loaded (loading
    it under another torch can fail to link, or crash)."""
    code = (
        "import sys, types\n"
        "record = types.ModuleType('torchrot._build_info'); record.TORCH_VERSION = '2.10.0+cpu'\n"
        "sys.modules['torchrot._build_info'] = record\n"
        "try:\n"
        "    import torchrot\n"
        "except ImportError as error:\n"
        "    print('ImportError:', error)\n"
        "print('loaded' if 'torchrot._C' in sys.modules else 'not loaded')\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert f"built against torch 2.10.0+cpu, but torch {torch.__version__} is installed" in result.stdout
    assert "pip install --no-build-isolation" in result.stdout
    assert result.stdout.strip().endswith("not loaded")


def test_version_is_the_package_metadata():
    from importlib.metadata import version

    assert torchrot.__version__ == version("torchrot")
