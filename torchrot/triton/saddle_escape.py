"""Escape from a saddle point of the objective: the half-turn about the top
eigenvector of sym(S) (Sec. 3, Eq. 18). The Triton twin of
csrc/kernel/saddle_escape.h, which explains the repeated squaring."""
from __future__ import annotations

import triton
import triton.language as tl

from torchrot.triton.lanes import constant, div
from torchrot.triton.mat3 import times

__all__ = ["ESCAPE_SQUARINGS", "saddle_escape_rotation"]

ESCAPE_SQUARINGS = tl.constexpr(4)  # kEscapeSquarings: B^16, eigenvalue ratios to the 16th power


@triton.jit
def _gershgorin_bound(B, r: tl.constexpr, c1: tl.constexpr, c2: tl.constexpr):
    return B[4 * r] - ((0.0 + tl.abs(B[3 * r + c1])) + tl.abs(B[3 * r + c2]))


@triton.jit
def _column_norm2(B, c: tl.constexpr):
    return B[c] * B[c] + B[3 + c] * B[3 + c] + B[6 + c] * B[6 + c]


@triton.jit
def saddle_escape_rotation(S):
    """The half-turn 2 v v^T / v.v - I about (an approximation of) the
    eigenvector v of sym(S)'s largest eigenvalue."""
    b00, b11, b22 = 0.5 * (S[0] + S[0]), 0.5 * (S[4] + S[4]), 0.5 * (S[8] + S[8])
    b01, b02, b12 = 0.5 * (S[1] + S[3]), 0.5 * (S[2] + S[6]), 0.5 * (S[5] + S[7])
    b10, b20, b21 = 0.5 * (S[3] + S[1]), 0.5 * (S[6] + S[2]), 0.5 * (S[7] + S[5])
    B = (b00, b01, b02, b10, b11, b12, b20, b21, b22)
    lower = B[0]
    bound = _gershgorin_bound(B, 0, 1, 2)  # Gershgorin lower bound of the spectrum
    lower = tl.where(bound < lower, bound, lower)
    bound = _gershgorin_bound(B, 1, 0, 2)
    lower = tl.where(bound < lower, bound, lower)
    bound = _gershgorin_bound(B, 2, 0, 1)
    lower = tl.where(bound < lower, bound, lower)
    B = (B[0] - lower, B[1], B[2], B[3], B[4] - lower, B[5], B[6], B[7], B[8] - lower)
    for _ in tl.static_range(ESCAPE_SQUARINGS):
        inv_trace = div(constant(lower, 1.0), B[0] + B[4] + B[8])
        B = (B[0] * inv_trace, B[1] * inv_trace, B[2] * inv_trace, B[3] * inv_trace, B[4] * inv_trace,
             B[5] * inv_trace, B[6] * inv_trace, B[7] * inv_trace, B[8] * inv_trace)
        B = times(B, B)
    v0, v1, v2 = B[0], B[3], B[6]  # the column of largest norm
    vv = v0 * v0 + v1 * v1 + v2 * v2
    norm = _column_norm2(B, 1)
    larger = norm > vv
    v0, v1, v2 = tl.where(larger, B[1], v0), tl.where(larger, B[4], v1), tl.where(larger, B[7], v2)
    vv = tl.where(larger, norm, vv)
    norm = _column_norm2(B, 2)
    larger = norm > vv
    v0, v1, v2 = tl.where(larger, B[2], v0), tl.where(larger, B[5], v1), tl.where(larger, B[8], v2)
    vv = tl.where(larger, norm, vv)
    two_over_vv = div(constant(vv, 2.0), vv)
    return ((two_over_vv * v0) * v0 - 1.0, (two_over_vv * v0) * v1 - 0.0, (two_over_vv * v0) * v2 - 0.0,
            (two_over_vv * v1) * v0 - 0.0, (two_over_vv * v1) * v1 - 1.0, (two_over_vv * v1) * v2 - 0.0,
            (two_over_vv * v2) * v0 - 0.0, (two_over_vv * v2) * v1 - 0.0, (two_over_vv * v2) * v2 - 1.0)
