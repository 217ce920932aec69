"""Fixed-size 3x3 matrix arithmetic on lanes: the Triton twin of
csrc/kernel/mat3.h. A matrix is a tuple of 9 lane tensors, row-major (entry
(r, c) is ``A[3 * r + c]``); sums of three products and differences of two
are evaluated in the kernel's one order.
"""
from __future__ import annotations

import triton
import triton.language as tl

from torchrot.triton.mul_add import mul_add

__all__ = ["dot3", "diff_of_products", "transpose_times", "times", "gram", "reorthonormalize"]


@triton.jit
def dot3(a0, b0, a1, b1, a2, b2):
    """a0 b0 + a1 b1 + a2 b2, the kernel's one evaluation order for it."""
    return mul_add(a0, b0, mul_add(a1, b1, a2 * b2))


@triton.jit
def diff_of_products(a, b, c, d):
    """a b - c d: only c d is rounded before the fused step."""
    return mul_add(a, b, -(c * d))


@triton.jit
def _transpose_times_entry(A, B, r: tl.constexpr, c: tl.constexpr):
    return dot3(A[r], B[c], A[3 + r], B[3 + c], A[6 + r], B[6 + c])


@triton.jit
def transpose_times(A, B):
    """A^T B."""
    return (
        _transpose_times_entry(A, B, 0, 0), _transpose_times_entry(A, B, 0, 1), _transpose_times_entry(A, B, 0, 2),
        _transpose_times_entry(A, B, 1, 0), _transpose_times_entry(A, B, 1, 1), _transpose_times_entry(A, B, 1, 2),
        _transpose_times_entry(A, B, 2, 0), _transpose_times_entry(A, B, 2, 1), _transpose_times_entry(A, B, 2, 2),
    )


@triton.jit
def _times_entry(A, B, r: tl.constexpr, c: tl.constexpr):
    return dot3(A[3 * r], B[c], A[3 * r + 1], B[3 + c], A[3 * r + 2], B[6 + c])


@triton.jit
def times(A, B):
    """A B."""
    return (
        _times_entry(A, B, 0, 0), _times_entry(A, B, 0, 1), _times_entry(A, B, 0, 2),
        _times_entry(A, B, 1, 0), _times_entry(A, B, 1, 1), _times_entry(A, B, 1, 2),
        _times_entry(A, B, 2, 0), _times_entry(A, B, 2, 1), _times_entry(A, B, 2, 2),
    )


@triton.jit
def gram(R):
    """R^T R, computed once per symmetric pair."""
    g00 = _transpose_times_entry(R, R, 0, 0)
    g01 = _transpose_times_entry(R, R, 0, 1)
    g02 = _transpose_times_entry(R, R, 0, 2)
    g11 = _transpose_times_entry(R, R, 1, 1)
    g12 = _transpose_times_entry(R, R, 1, 2)
    g22 = _transpose_times_entry(R, R, 2, 2)
    return (g00, g01, g02, g01, g11, g12, g02, g12, g22)


@triton.jit
def reorthonormalize(R, G):
    """One Newton-Schulz step towards the orthonormal polar factor,
    R (3 I - R^T R) / 2, for G = R^T R (see gram)."""
    H = (
        mul_add(-0.5, G[0], 1.5), mul_add(-0.5, G[1], 0.0), mul_add(-0.5, G[2], 0.0),
        mul_add(-0.5, G[3], 0.0), mul_add(-0.5, G[4], 1.5), mul_add(-0.5, G[5], 0.0),
        mul_add(-0.5, G[6], 0.0), mul_add(-0.5, G[7], 0.0), mul_add(-0.5, G[8], 1.5),
    )
    return times(R, H)
