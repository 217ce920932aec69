"""The layout of the operators' fresh results, as the C++ CPU kernels choose
it (csrc/ops/layout.cpp): the fake kernels and the device-generic kernels
give the same strides, so every path returns what the CPU kernel returns."""
from __future__ import annotations

import torch

from torchrot._torch_private import is_non_overlapping_and_dense

__all__ = ["empty_result", "has_soa_layout", "in_result_layout"]


def has_soa_layout(t: torch.Tensor) -> bool:
    """Whether ``t`` is in structure-of-arrays layout (csrc/ops/layout.cpp's
    has_soa_layout): dense, the matrix index of stride 1 across all its batch
    dimensions (e.g. ``S.permute(2, 0, 1)`` of a (3, 3, N) S) or within tiles
    (``torchrot.testing.tiled_view``): its trailing batch dimensions flatten
    to one of stride 1 and more than one matrix, its leading ones to one stride."""
    if t.dim() < 3:
        return False
    batch = [(t.shape[d], t.stride(d)) for d in range(t.dim() - 2) if t.shape[d] != 1]
    leading, run = len(batch), 1
    while leading > 0 and batch[leading - 1][1] == run:
        leading -= 1
        run *= batch[leading][0]
    if run == 1:
        return False
    if any(batch[d][1] != batch[d + 1][1] * batch[d + 1][0] for d in range(leading - 1)):
        return False
    return is_non_overlapping_and_dense(t)


def empty_result(M: torch.Tensor) -> torch.Tensor:
    """A new result of M's shape, laid out as the C++ kernels lay it out
    (new_result in csrc/ops/layout.cpp): M's layout if structure of arrays, else contiguous."""
    if has_soa_layout(M):
        return torch.empty_strided(M.shape, M.stride(), dtype=M.dtype, device=M.device)
    return torch.empty(M.shape, dtype=M.dtype, device=M.device)


def in_result_layout(like: torch.Tensor, result: torch.Tensor) -> torch.Tensor:
    """``result`` laid out as the C++ kernel lays out a result for ``like``."""
    if has_soa_layout(like) or not result.is_contiguous():
        return empty_result(like).copy_(result)
    return result
