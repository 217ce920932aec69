"""Scaling a matrix to max |entry| 1, exactly where it matters: the Triton
twin of csrc/kernel/unit_scale.h (the maximiser of tr(R^T M) is unchanged and
no product of a step or of the derivative can over- or underflow)."""
from __future__ import annotations

import triton
import triton.language as tl

from torchrot.triton.lanes import constant, div

__all__ = ["outside_normal_range", "unit_scale"]


@triton.jit
def outside_normal_range(max_abs, TINY: tl.constexpr):
    """(below_normal, above_reciprocal): the lanes whose largest |entry|
    ``max_abs`` has no normal reciprocal, which unit_scale lifts or drops:
    below TINY, the smallest normal number (M = 0 included), or above 1 / TINY."""
    return max_abs < TINY, max_abs > 1.0 / TINY


@triton.jit
def unit_scale(M, max_abs, TINY: tl.constexpr, LIFT: tl.constexpr):
    """(A, lift, inv): A = (M lift) inv, M scaled to max |entry| 1 (0 for
    M = 0). A maximum outside the normal range (below TINY, the smallest
    normal number, or above 1 / TINY), whose reciprocal is not a normal
    number, is first lifted by LIFT = 2^digits or dropped by 2^-digits
    (exact); elsewhere lift is 1, which gives M inv bit for bit."""
    zero = max_abs == 0
    below_normal, above_reciprocal = outside_normal_range(max_abs, TINY)
    lift = tl.where(below_normal, LIFT, tl.where(above_reciprocal, 1.0 / LIFT, constant(max_abs, 1.0)))
    inv = tl.where(zero, 0.0, div(constant(max_abs, 1.0), max_abs * lift))
    A = ((M[0] * lift) * inv, (M[1] * lift) * inv, (M[2] * lift) * inv,
         (M[3] * lift) * inv, (M[4] * lift) * inv, (M[5] * lift) * inv,
         (M[6] * lift) * inv, (M[7] * lift) * inv, (M[8] * lift) * inv)
    return A, lift, inv
