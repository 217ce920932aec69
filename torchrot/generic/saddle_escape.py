"""Escape from a saddle point of the objective (a fixed point of Algorithm 1
that is not the maximum) on structure-of-arrays lanes: the Python twin of
csrc/kernel/saddle_escape.h (saddle_escape_rotation), whose comment has the
derivation: the half-turn 2 v v^T / v.v - I about the top eigenvector v of
sym(S), found by repeated squaring of sym(S) shifted by its Gershgorin lower
bound.
"""
from __future__ import annotations

import torch

from torchrot.generic.mat3 import times

__all__ = ["saddle_escape_rotation"]


def saddle_escape_rotation(S, squarings=4):
    """The half-turn that takes the saddle S = R^T M (nearly) to the maximum
    (``squarings``: the kernel's kEscapeSquarings)."""
    B = [0.5 * (S[3 * r + c] + S[3 * c + r]) for r in range(3) for c in range(3)]
    lower = B[0]
    for r in range(3):
        radius = sum(B[3 * r + c].abs() for c in range(3) if c != r)
        bound = B[4 * r] - radius
        lower = torch.where(bound < lower, bound, lower)
    B = [b - lower if i % 4 == 0 else b for i, b in enumerate(B)]
    for _ in range(squarings):
        inv_trace = 1 / (B[0] + B[4] + B[8])
        B = [b * inv_trace for b in B]
        B = times(B, B)
    v = [B[0], B[3], B[6]]
    vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    for c in (1, 2):
        norm = B[c] * B[c] + B[3 + c] * B[3 + c] + B[6 + c] * B[6 + c]
        larger = norm > vv
        v = [torch.where(larger, B[3 * r + c], v[r]) for r in range(3)]
        vv = torch.where(larger, norm, vv)
    k = 2 / vv
    return [k * v[r] * v[c] - (1 if r == c else 0) for r in range(3) for c in range(3)]
