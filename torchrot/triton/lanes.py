"""Lane operations: the Triton twin of what csrc/kernel/lanes.h adds to
torch's vector types. In Triton a tensor of BLOCK values is the lane vector
(one matrix per lane), comparisons give boolean masks and ``tl.where`` is the
blend; what is left to spell out is below.

Division and square roots: Triton's float32 ``/`` and ``tl.sqrt`` are
approximate on CUDA (``div.full.f32``, ``sqrt.approx.f32``), so the kernels
divide and take roots through :func:`div` and :func:`sqrt`, correctly
rounded in both dtypes, as IEEE arithmetic on the CPU is.
"""
from __future__ import annotations

import triton
import triton.language as tl

__all__ = ["constant", "div", "sqrt", "is_finite", "any", "select", "max_abs_entry"]


@triton.jit
def constant(like, value):
    """``value`` in every lane, in ``like``'s dtype (V(value))."""
    return tl.full(like.shape, value, like.dtype)


@triton.jit
def div(a, b):
    """a / b, correctly rounded (float32: ``div_rn``; float64's ``/`` is)."""
    if a.dtype == tl.float32:
        return tl.math.div_rn(a, b)
    else:
        return a / b


@triton.jit
def sqrt(x):
    """sqrt(x), correctly rounded (float32: ``sqrt_rn``; float64's is)."""
    if x.dtype == tl.float32:
        return tl.sqrt_rn(x)
    else:
        return tl.sqrt(x)


@triton.jit
def is_finite(x):
    """L::is_finite: |x| < inf (false for NaN)."""
    return tl.abs(x) < float("inf")


@triton.jit
def any(mask):
    """L::any: whether some lane of the block is set (a block-wide reduction)."""
    return tl.max(mask.to(tl.int32), 0) > 0


@triton.jit
def select(mask, if_true, if_false):
    """select<L> of a Mat3 (9-tuple): each entry blended per lane."""
    return (
        tl.where(mask, if_true[0], if_false[0]), tl.where(mask, if_true[1], if_false[1]),
        tl.where(mask, if_true[2], if_false[2]), tl.where(mask, if_true[3], if_false[3]),
        tl.where(mask, if_true[4], if_false[4]), tl.where(mask, if_true[5], if_false[5]),
        tl.where(mask, if_true[6], if_false[6]), tl.where(mask, if_true[7], if_false[7]),
        tl.where(mask, if_true[8], if_false[8]),
    )


@triton.jit
def _unordered(a, b):
    return (a != a) | (b != b)


@triton.jit
def max_abs_entry(A):
    """max |A_ij| over a matrix's entries, NaN where one is NaN: a tree of
    maxima with the NaN test apart, in lanes.h's order."""
    a0, a1, a2 = tl.abs(A[0]), tl.abs(A[1]), tl.abs(A[2])
    a3, a4, a5 = tl.abs(A[3]), tl.abs(A[4]), tl.abs(A[5])
    a6, a7, a8 = tl.abs(A[6]), tl.abs(A[7]), tl.abs(A[8])
    top = tl.maximum(tl.maximum(tl.maximum(a0, a1), tl.maximum(a2, a3)),
                     tl.maximum(tl.maximum(a4, a5), tl.maximum(a6, a7)))
    nan = (_unordered(a0, a1) | _unordered(a2, a3)) | ((_unordered(a4, a5) | _unordered(a6, a7)) | _unordered(a8, a8))
    return tl.where(nan, float("nan"), tl.maximum(top, a8))
