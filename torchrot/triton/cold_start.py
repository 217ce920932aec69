"""Cold start: the best of the 24 rotations of the cube (signed permutation
matrices of det +1), per lane: the Triton twin of csrc/kernel/cold_start.h,
which says why and how they are ranked."""
from __future__ import annotations

import triton
import triton.language as tl

from torchrot.triton.lanes import constant
from torchrot.triton.mul_add import mul_add

__all__ = ["best_start_rotation"]


@triton.jit
def _consider(best, odd_perm, e0, e1, e2, k0, k1, k2, x, y, z, j0: tl.constexpr, j1: tl.constexpr,
              j2: tl.constexpr, EVEN: tl.constexpr, FIRST: tl.constexpr):
    """One permutation of kStartPerm (row i's entry in column j_i; EVEN: of
    det +1), with its entries x, y, z: the running best updated (the first of
    equals wins)."""
    a, b, c = tl.abs(x), tl.abs(y), tl.abs(z)
    product = (x * y) * z
    if EVEN:
        flip = product < 0.0
    else:
        flip = product > 0.0
    total = (a + b) + c
    value = tl.where(flip, mul_add(-2.0, tl.minimum(tl.minimum(a, b), c), total), total)
    if EVEN:
        parity = 0.0
    else:
        parity = 1.0
    if FIRST:  # the first candidate is the best so far
        best, odd_perm, e0, e1, e2 = value, constant(value, parity), x, y, z
        k0, k1, k2 = tl.full(k0.shape, j0, tl.int32), tl.full(k1.shape, j1, tl.int32), tl.full(k2.shape, j2, tl.int32)
    else:
        better = value > best
        best = tl.where(better, value, best)
        odd_perm = tl.where(better, parity, odd_perm)
        e0, e1, e2 = tl.where(better, x, e0), tl.where(better, y, e1), tl.where(better, z, e2)
        k0, k1, k2 = tl.where(better, j0, k0), tl.where(better, j1, k1), tl.where(better, j2, k2)
    return best, odd_perm, e0, e1, e2, k0, k1, k2


@triton.jit
def _row(entry, column, flip, smallest):
    """Row i of the start: the sign of its entry (flipped in the row of the
    smallest entry where det would be -1) in its column."""
    sign = tl.where(entry < 0.0, -1.0, 1.0).to(entry.dtype)
    s = tl.where(flip & smallest, 0.0 - sign, sign)
    return tl.where(column == 0, s, 0.0), tl.where(column == 1, s, 0.0), tl.where(column == 2, s, 0.0)


@triton.jit
def best_start_rotation(A):
    """(R, objective): the best of the 24 candidates per lane and its
    objective (up to rounding). kStartPerm's order, even permutations first:
    (0 1 2), (1 2 0), (2 0 1), (0 2 1), (2 1 0), (1 0 2)."""
    zero = constant(A[0], 0.0)
    k = tl.zeros(A[0].shape, tl.int32)
    best, odd, e0, e1, e2, k0, k1, k2 = _consider(zero, zero, zero, zero, zero, k, k, k, A[0], A[4], A[8], 0, 1, 2,
                                                  True, True)
    best, odd, e0, e1, e2, k0, k1, k2 = _consider(best, odd, e0, e1, e2, k0, k1, k2, A[1], A[5], A[6], 1, 2, 0,
                                                  True, False)
    best, odd, e0, e1, e2, k0, k1, k2 = _consider(best, odd, e0, e1, e2, k0, k1, k2, A[2], A[3], A[7], 2, 0, 1,
                                                  True, False)
    best, odd, e0, e1, e2, k0, k1, k2 = _consider(best, odd, e0, e1, e2, k0, k1, k2, A[0], A[5], A[7], 0, 2, 1,
                                                  False, False)
    best, odd, e0, e1, e2, k0, k1, k2 = _consider(best, odd, e0, e1, e2, k0, k1, k2, A[2], A[4], A[6], 2, 1, 0,
                                                  False, False)
    best, odd, e0, e1, e2, k0, k1, k2 = _consider(best, odd, e0, e1, e2, k0, k1, k2, A[1], A[3], A[8], 1, 0, 2,
                                                  False, False)
    # Flip where the negatives' parity differs from the permutation's.
    flip = (odd > 0.0) ^ (e0 < 0.0) ^ (e1 < 0.0) ^ (e2 < 0.0)
    s0, s1, s2 = tl.abs(e0), tl.abs(e1), tl.abs(e2)
    smallest0 = ~(s0 > s1) & ~(s0 > s2)
    smallest1 = ~smallest0 & ~(s1 > s2)
    smallest2 = ~(smallest0 | smallest1)
    r00, r01, r02 = _row(e0, k0, flip, smallest0)
    r10, r11, r12 = _row(e1, k1, flip, smallest1)
    r20, r21, r22 = _row(e2, k2, flip, smallest2)
    return (r00, r01, r02, r10, r11, r12, r20, r21, r22), best
