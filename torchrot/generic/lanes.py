"""Lane operations: the Python twin of what csrc/kernel/lanes.h adds to the
vector types. Here a tensor of n values is the lane vector (one matrix per
lane), so only the matrix-wide pieces are spelled out.
"""
from __future__ import annotations

import torch

__all__ = ["select", "max_abs_entry"]


def select(mask, X, Y):
    """X on the lanes of ``mask``, Y elsewhere, entry by entry (select<L> on a Mat3)."""
    return [torch.where(mask, x, y) for x, y in zip(X, Y)]


def max_abs_entry(M):
    """max |M_ij| per lane, NaN where an entry is NaN (torch.maximum propagates it)."""
    max_abs = M[0].abs()
    for x in M[1:]:
        max_abs = torch.maximum(max_abs, x.abs())
    return max_abs
