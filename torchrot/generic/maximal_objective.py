"""The maximal objective max_R tr(R^T A) over rotations, per lane: the largest
eigenvalue of Horn's K, by Laguerre's method on K's characteristic polynomial
from above, on structure-of-arrays lanes: the Python twin of
csrc/kernel/maximal_objective.h, whose comment has the polynomial and the
method. A cold start's first Cayley step takes it as c (exact: one step
lands on the maximum).
"""
from __future__ import annotations

import torch

from torchrot._constants import OBJECTIVE_LAGUERRE_STEPS, UNDAMPED, dtype_name
from torchrot.generic.cayley import cayley_step, skew_vector, trace
from torchrot.generic.control_flow import _any, _compiling
from torchrot.generic.optimality import determinant

__all__ = ["maximal_objective"]


def maximal_objective(A, lower):
    """max_R tr(R^T A), K's largest eigenvalue, by Laguerre's method on K's
    characteristic polynomial from above (maximal_objective.h, step by step,
    with kernel::Tolerances' sqrt(eps) and step cap); ``lower``: an attained
    objective (the cube start's)."""
    tol = UNDAMPED[dtype_name(A[0].dtype)]
    t = trace(A)
    m = skew_vector(A)
    w, d, _, _, _ = cayley_step(A, t, m, 0)  # T = A + A^T - t I is Algorithm 2's H for c = 0
    p0 = t * d - (m[0] * w[0] + m[1] * w[1] + m[2] * w[2])  # det K
    norm2 = sum(a * a for a in A)
    p2, p1 = -2 * norm2, -8 * determinant(A)
    x = torch.sqrt(3 * norm2)
    active = x > 0
    for _ in range(OBJECTIVE_LAGUERRE_STEPS):
        if not _compiling() and not _any(active):
            break
        x2 = x * x
        p = ((x2 + p2) * x + p1) * x + p0
        dp = (4 * x2 + 2 * p2) * x + p1
        ddp = 12 * x2 + 2 * p2
        root = torch.sqrt(torch.clamp(9 * dp * dp - 12 * (p * ddp), min=0))
        nxt = x - 4 * p / (dp + root)
        move = active & (nxt < x) & ~(nxt < lower)
        active = move & (x - nxt > tol * nxt)
        x = torch.where(move, nxt, x)
        if x.device.type == "meta":  # one step gives the shape and dtype
            break
    return x
