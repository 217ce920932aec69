"""The cold start, the best of the 24 rotations of the cube for tr(P^T A), on
structure-of-arrays lanes: the Python twin of csrc/kernel/cold_start.h
(best_start_rotation), whose comment explains the choice.
"""
from __future__ import annotations

import torch

from torchrot.generic.control_flow import _INT

__all__ = ["_START_PERMS", "best_start_rotation"]

#: cold_start.h's kStartPerm: row i's entry of permutation p is in column
#: _START_PERMS[p][i]; the first three are even.
_START_PERMS = ((0, 1, 2), (1, 2, 0), (2, 0, 1), (0, 2, 1), (2, 1, 0), (1, 0, 2))


def best_start_rotation(A):
    """The best of the 24 rotations of the cube (signed permutation matrices
    of det +1) for tr(P^T A), the first of equals (cold_start.h, step by
    step: each permutation with the signs of its entries, the smallest one
    flipped where det would be -1; the winner's entries and columns kept),
    and its objective."""
    best = odd_perm = None
    entry, column = [None] * 3, [None] * 3
    for p, col in enumerate(_START_PERMS):
        xyz = (A[col[0]], A[3 + col[1]], A[6 + col[2]])
        a, b, c = (v.abs() for v in xyz)
        product = (xyz[0] * xyz[1]) * xyz[2]
        flip = product < 0 if p < 3 else product > 0
        total = (a + b) + c
        value = torch.where(flip, total - 2 * torch.minimum(torch.minimum(a, b), c), total)
        if p == 0:
            best, odd_perm = value, torch.zeros_like(flip)
            entry = list(xyz)
            column = [torch.full(value.shape, col[i], dtype=_INT, device=value.device) for i in range(3)]
            continue
        better = value > best  # strict: the first of equals wins, as in the kernel
        best = torch.where(better, value, best)
        odd_perm = torch.where(better, p >= 3, odd_perm)
        entry = [torch.where(better, xyz[i], entry[i]) for i in range(3)]
        column = [torch.where(better, col[i], column[i]) for i in range(3)]
    size = [e.abs() for e in entry]
    flip = odd_perm ^ (entry[0] < 0) ^ (entry[1] < 0) ^ (entry[2] < 0)
    smallest0 = ~(size[0] > size[1]) & ~(size[0] > size[2])
    smallest1 = ~smallest0 & ~(size[1] > size[2])
    smallest = (smallest0, smallest1, ~(smallest0 | smallest1))
    R = []
    for i in range(3):
        sign = torch.where(entry[i] < 0, -1.0, 1.0).to(A[0].dtype)
        s = torch.where(flip & smallest[i], -sign, sign)
        R += [torch.where(column[i] == j, s, 0.0).to(A[0].dtype) for j in range(3)]
    return R, best
