"""Fake (meta) kernels of the operators: output shapes, dtypes and strides
for torch.compile, FakeTensor and meta tensors, after the same argument
checks as the C++ operator (torchrot/_checks.py)."""
from __future__ import annotations

import torch

from torchrot._checks import check_all, check_backward, check_gradient_eps, check_out
from torchrot._constants import DEFAULT_VARIANT, GRADIENT_EPS
from torchrot._layout import empty_result

__all__: list[str] = []  # registers the kernels; nothing to import


@torch.library.register_fake("torchrot::fit_rotation")
def _fit_rotation_fake(M, init=None, max_iter=None, variant=DEFAULT_VARIANT, gradient_eps=GRADIENT_EPS):
    check_all(M, init, max_iter, variant)
    check_gradient_eps(gradient_eps)
    return empty_result(M)


@torch.library.register_fake("torchrot::fit_rotation_out")
def _fit_rotation_out_fake(M, init, max_iter, variant, out):
    check_all(M, init, max_iter, variant)
    check_out(M, out)


@torch.library.register_fake("torchrot::fit_rotation_backward")
def _fit_rotation_backward_fake(grad, R, M, gradient_eps=GRADIENT_EPS):
    check_backward(grad, R, M, gradient_eps)
    return empty_result(R)


@torch.library.register_fake("torchrot::fit_rotation_info")
def _fit_rotation_info_fake(M, init=None, max_iter=None, variant=DEFAULT_VARIANT):
    check_all(M, init, max_iter, variant)
    batch = M.shape[:-2]
    return (
        empty_result(M),
        torch.empty(batch, dtype=torch.int32, device=M.device),
        torch.empty(batch, dtype=torch.uint8, device=M.device),
    )
