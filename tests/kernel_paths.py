"""The operators' kernel paths on CPU tensors, for the tests that run on each
of them: the C++ kernel (``"cpu"``), the device-generic kernels
(``"generic"``, torchrot.testing.generic_kernel: what MPS tensors run) and
torchrot's Triton kernels under Triton's interpreter (``"triton"``,
torchrot.testing.triton_kernel: what CUDA and XPU tensors run; marked
``triton``, which the default run leaves out, and skipped where Triton cannot
run)."""
from __future__ import annotations

import contextlib

import pytest

from torchrot.testing import generic_kernel, triton_interpreter_unavailable, triton_kernel

__all__ = ["KERNEL_PATHS", "TRITON_MARKS", "kernel_path_params"]

#: path name -> the context that runs torch.ops.torchrot.* on CPU tensors there.
KERNEL_PATHS = {"cpu": contextlib.nullcontext, "generic": generic_kernel, "triton": triton_kernel}

_TRITON_UNAVAILABLE = triton_interpreter_unavailable()
#: The marks of every test of the Triton kernels.
TRITON_MARKS = (pytest.mark.triton,
                pytest.mark.skipif(_TRITON_UNAVAILABLE is not None, reason=str(_TRITON_UNAVAILABLE)))


def kernel_path_params(*names: str) -> list:
    """pytest parameters for the paths ``names`` (default: all), the Triton
    path with TRITON_MARKS."""
    return [pytest.param(name, marks=TRITON_MARKS if name == "triton" else ()) for name in names or KERNEL_PATHS]
