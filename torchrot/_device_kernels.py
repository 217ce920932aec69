"""The operators' kernels on every device without a native one (CUDA, XPU,
MPS): the device-generic pure-PyTorch algorithm (torchrot.generic, through
torchrot.reference), after the C++ operator's argument checks, its results
laid out as the C++ kernel lays them out."""
from __future__ import annotations

import torch

from torchrot._checks import check_all, check_gradient_eps, check_out
from torchrot._constants import DEFAULT_VARIANT, GRADIENT_EPS
from torchrot._layout import in_result_layout
from torchrot.reference import fit_rotation_backward_reference, fit_rotation_reference

__all__ = ["GENERIC_KERNELS"]

_OTHER_DEVICES = ("cuda", "xpu", "mps")


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
for _name, _kernel in GENERIC_KERNELS.items():
    torch.library.register_kernel(f"torchrot::{_name}", _OTHER_DEVICES, _kernel)
