"""The maximal objective max_R tr(R^T A) over rotations, per lane: the
largest eigenvalue of Horn's K by Laguerre's method on its characteristic
quartic, from above. The Triton twin of csrc/kernel/maximal_objective.h,
whose header derives the polynomial and the start."""
from __future__ import annotations

import triton
import triton.language as tl

from torchrot.triton.cayley import cayley_step, skew_vector, trace
from torchrot.triton.lanes import any, constant, div, sqrt
from torchrot.triton.mat3 import dot3
from torchrot.triton.mul_add import mul_add
from torchrot.triton.optimality import determinant

__all__ = ["maximal_objective"]


@triton.jit
def maximal_objective(A, lower, tol, MAX_STEPS: tl.constexpr):
    """lambda for each lane of A, from above: a lane stops once its
    correction falls below tol x, would take x below ``lower`` (an objective
    attained), or after MAX_STEPS steps. A = 0 gives 0; NaN entries give NaN."""
    t = trace(A)
    m = skew_vector(A)
    system = cayley_step(A, constant(t, 0.0))  # H for c = 0 is T: its step gives det T and adj(T) m
    p0 = mul_add(t, system[3], -dot3(m[0], system[0], m[1], system[1], m[2], system[2]))  # det K
    norm2 = constant(t, 0.0)
    for k in tl.static_range(9):
        norm2 = mul_add(A[k], A[k], norm2)
    p2 = -2.0 * norm2
    p1 = -8.0 * determinant(A)
    x = sqrt(3.0 * norm2)
    active = x > 0.0
    two_p2 = 2.0 * p2
    k = 0
    while (k < MAX_STEPS) & any(active):
        x2 = x * x
        p = mul_add(mul_add(x2 + p2, x, p1), x, p0)
        dp = mul_add(mul_add(4.0, x2, two_p2), x, p1)
        ddp = mul_add(12.0, x2, two_p2)
        # (L::max: IEEE maximum, NaN propagates)
        root = sqrt(tl.maximum(mul_add(9.0 * dp, dp, -12.0 * (p * ddp)), 0.0, propagate_nan=tl.PropagateNan.ALL))
        next_x = x - div(4.0 * p, dp + root)
        move = active & (next_x < x) & ~(next_x < lower)
        active = move & (x - next_x > tol * next_x)
        x = tl.where(move, next_x, x)
        k += 1
    return x
