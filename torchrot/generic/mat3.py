"""3x3 matrix algebra on structure-of-arrays lanes: the Python twin of
csrc/kernel/mat3.h.

A matrix is a list of 9 tensors, its entries row-major (entry (r, c) is
``A[3 * r + c]``), each holding that entry of every lane (matrix) of the
batch. The kernel's fused a * b + c (csrc/kernel/mul_add.h) has no
counterpart here: torch's ops round each product and sum.
"""
from __future__ import annotations

import torch

__all__ = ["dot3", "diff_of_products", "transpose_times", "times", "gram", "reorthonormalize"]


def dot3(a0, b0, a1, b1, a2, b2):
    """a0 b0 + a1 b1 + a2 b2 in three ops (addcmul: eager makes one pass per op)."""
    return torch.addcmul(torch.addcmul(a0 * b0, a1, b1), a2, b2)


def diff_of_products(a, b, c, d):
    """a b - c d (cofactors, cross products; each product rounded here)."""
    return a * b - c * d


def transpose_times(R, A):
    """R^T A (transpose_times)."""
    return [dot3(R[r], A[c], R[3 + r], A[3 + c], R[6 + r], A[6 + c]) for r in range(3) for c in range(3)]


def times(A, B):
    """A B (times)."""
    return [dot3(A[3 * r], B[c], A[3 * r + 1], B[3 + c], A[3 * r + 2], B[6 + c]) for r in range(3) for c in range(3)]



def gram(R):
    """R^T R (gram), each off-diagonal entry computed once."""
    G = [None] * 9
    for r in range(3):
        for c in range(r, 3):
            G[3 * r + c] = R[r] * R[c] + R[3 + r] * R[3 + c] + R[6 + r] * R[6 + c]
            G[3 * c + r] = G[3 * r + c]
    return G


def reorthonormalize(R, G=None):
    """One Newton-Schulz step R (3 I - R^T R) / 2 (reorthonormalize); ``G``:
    R's Gram matrix if the caller has it."""
    G = gram(R) if G is None else G
    H = [(1.5 - 0.5 * g) if i % 4 == 0 else (-0.5 * g) for i, g in enumerate(G)]
    return times(R, H)
