"""The operators' kernels on every device without a C++ one. CUDA (NVIDIA and
AMD ROCm, which torch calls "cuda") and XPU tensors run torchrot's Triton
kernels (torchrot.triton) where Triton has a backend for the device; MPS
tensors, and CUDA and XPU tensors where Triton is missing, run the
device-generic pure-PyTorch algorithm (torchrot.generic, through
torchrot.reference) eagerly. Each after the C++ operator's argument checks,
with its results laid out as the C++ kernel lays them out.

Which of the two runs on a device type is decided at its first call (that
is also when Triton is imported) and kept for the process:
:func:`kernels_for`.
"""
from __future__ import annotations

import importlib.util

import torch

from torchrot._checks import check_all, check_gradient_eps, check_out
from torchrot._constants import DEFAULT_VARIANT, GRADIENT_EPS
from torchrot._layout import in_result_layout
from torchrot.reference import fit_rotation_backward_reference, fit_rotation_reference

__all__ = ["GENERIC_KERNELS", "OPERATOR_NAMES", "TRITON_BACKENDS", "kernels_for", "triton_runs_on"]


def _fit_rotation_other(M, init=None, max_iter=None, variant=DEFAULT_VARIANT, gradient_eps=GRADIENT_EPS):
    check_all(M, init, max_iter, variant)  # in the C++ operator's order
    check_gradient_eps(gradient_eps)
    return in_result_layout(M, fit_rotation_reference(M, init, max_iter=max_iter, variant=variant))


def _fit_rotation_out_other(M, init, max_iter, variant, out):
    check_all(M, init, max_iter, variant)
    check_out(M, out)
    # Computed before out is written: out may overlap M or init in any way,
    # and a call that raises leaves it as it was.
    out.copy_(fit_rotation_reference(M, init, max_iter=max_iter, variant=variant))


def _fit_rotation_backward_other(grad, R, M, gradient_eps=GRADIENT_EPS):
    return in_result_layout(R, fit_rotation_backward_reference(grad, R, M, gradient_eps))


def _fit_rotation_info_other(M, init=None, max_iter=None, variant=DEFAULT_VARIANT):
    R, iterations, status = fit_rotation_reference(M, init, max_iter=max_iter, variant=variant, return_info=True)
    return in_result_layout(M, R), iterations, status


#: operator name -> its device-generic kernel (torchrot.testing.generic_kernel
#: also runs them on CPU tensors).
GENERIC_KERNELS = {
    "fit_rotation": _fit_rotation_other,
    "fit_rotation_out": _fit_rotation_out_other,
    "fit_rotation_backward": _fit_rotation_backward_other,
    "fit_rotation_info": _fit_rotation_info_other,
}
OPERATOR_NAMES = tuple(GENERIC_KERNELS)

#: torch device type -> the Triton backends (triton.backends) that compile for it.
TRITON_BACKENDS = {"cuda": ("nvidia", "amd"), "xpu": ("intel",)}
_chosen: dict = {}  # device type -> its kernels (kernels_for)


def triton_runs_on(device_type: str) -> bool:
    """Whether Triton is installed with a backend for ``device_type``."""
    if device_type not in TRITON_BACKENDS or importlib.util.find_spec("triton") is None:
        return False
    from triton.backends import backends

    return any(name in backends for name in TRITON_BACKENDS[device_type])


def kernels_for(device_type: str) -> dict:
    """operator name -> the kernel that tensors of ``device_type`` run: the
    Triton kernels where :func:`triton_runs_on` it, else the device-generic ones."""
    if device_type not in _chosen:
        if triton_runs_on(device_type):
            from torchrot.triton.operators import TRITON_KERNELS

            _chosen[device_type] = TRITON_KERNELS
        else:
            _chosen[device_type] = GENERIC_KERNELS
    return _chosen[device_type]


def _device_kernel(name: str, device_type: str):
    def kernel(*args, **kwargs):
        return kernels_for(device_type)[name](*args, **kwargs)

    kernel.__name__ = kernel.__qualname__ = f"_{name}_{device_type}"
    return kernel


for _name in OPERATOR_NAMES:
    for _device_type in (*TRITON_BACKENDS, "mps"):
        torch.library.register_kernel(f"torchrot::{_name}", _device_type, _device_kernel(_name, _device_type))
