"""Scaling a matrix to max |entry| 1, exactly where it matters: the Python
twin of csrc/kernel/unit_scale.h (the maximiser of tr(R^T M) is unchanged,
and no product of a step or of the derivative can over- or underflow)."""
from __future__ import annotations

import math

import torch

__all__ = ["outside_normal_range", "unit_scale"]


def outside_normal_range(max_abs):
    """(below_normal, above_reciprocal): the lanes whose largest |entry|
    ``max_abs`` has no normal reciprocal, which unit_scale lifts or drops:
    below the smallest normal number (M = 0 included) or above its reciprocal."""
    tiny = torch.finfo(max_abs.dtype).tiny
    return max_abs < tiny, max_abs > 1 / tiny


def unit_scale(M, max_abs):
    """(A, lift, inv) with A = (M lift) inv, M scaled to max |entry| 1 (0 for
    M = 0), ``max_abs`` its largest |entry| (lanes.max_abs_entry). A maximum
    outside the normal range, whose reciprocal is not a normal number, is
    first lifted by 2^digits (subnormal) or dropped by 2^-digits (above
    1 / tiny); elsewhere lift is 1."""
    finfo = torch.finfo(M[0].dtype)
    digits = round(-math.log2(finfo.eps)) + 1
    ones = torch.ones_like(max_abs)
    below_normal, above_reciprocal = outside_normal_range(max_abs)
    lift = torch.where(below_normal, float(2**digits), torch.where(above_reciprocal, float(2**-digits), ones))
    zero = max_abs == 0
    inv = torch.where(zero, 0.0, 1 / torch.where(zero, 1.0, max_abs * lift))
    return [(x * lift) * inv for x in M], lift, inv
