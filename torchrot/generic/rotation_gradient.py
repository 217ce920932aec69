"""The derivative of the fitted rotation, from the optimality condition, on
structure-of-arrays lanes: the Python twin of csrc/kernel/rotation_gradient.h
(rotation_tangent), whose comment has the derivation.
"""
from __future__ import annotations

import math

import torch

from torchrot.generic.cayley import skew_vector, trace
from torchrot.generic.lanes import max_abs_entry
from torchrot.generic.mat3 import transpose_times
from torchrot.generic.unit_scale import unit_scale

__all__ = ["skew_axial", "times_cross", "rotation_tangent"]


def skew_axial(R, X):
    """vex(B - B^T) for B = R^T X."""
    return skew_vector(transpose_times(R, X))


def times_cross(R, u):
    """R [u]x, [u]x = [[0, -z, y], [z, 0, -x], [-y, x, 0]]."""
    T = []
    for r in range(3):
        R0, R1, R2 = R[3 * r], R[3 * r + 1], R[3 * r + 2]
        T += [R1 * u[2] - R2 * u[1], R2 * u[0] - R0 * u[2], R0 * u[1] - R1 * u[0]]
    return T


def rotation_tangent(X, R, M, damping):
    """csrc/kernel/rotation_gradient.h's rotation_tangent on SoA lists:
    R [u]x with u = Re (K + i lambda I)^-1 g (no K^2: float32 keeps its digits)."""
    dtype = R[0].dtype
    finfo = torch.finfo(dtype)
    max_abs = max_abs_entry(M)
    zero = max_abs == 0
    A, lift, inv_max = unit_scale(M, max_abs)
    frob2 = sum(a * a for a in A)
    frob = torch.where(zero, 1.0, torch.sqrt(frob2))
    S = transpose_times(R, A)
    inv_frob = 1 / frob
    scaled_trace = trace(S) * inv_frob
    half_inv = 0.5 * inv_frob
    k00, k11, k22 = scaled_trace - S[0] * inv_frob, scaled_trace - S[4] * inv_frob, scaled_trace - S[8] * inv_frob
    k01, k02, k12 = -(S[1] + S[3]) * half_inv, -(S[2] + S[6]) * half_inv, -(S[5] + S[7]) * half_inv
    x_max = X[0].abs()
    for x in X[1:]:
        x_max = torch.maximum(x_max, x.abs())
    half_range = (int(math.log2(finfo.max)) + 1) // 2  # max_exponent / 2
    x_huge = x_max > 2.0**half_range
    x_down = torch.where(x_huge, torch.full_like(x_max, 2.0**-half_range), torch.ones_like(x_max))
    Xs = [x * x_down for x in X]
    g = skew_axial(R, Xs)
    c00, c01, c02 = k11 * k22 - k12 * k12, k02 * k12 - k01 * k22, k01 * k12 - k02 * k11
    c11, c12, c22 = k00 * k22 - k02 * k02, k01 * k02 - k00 * k12, k00 * k11 - k01 * k01
    det_k = k00 * c00 + k01 * c01 + k02 * c02
    trace_k = k00 + k11 + k22
    lam, lam2 = float(damping), float(damping) * float(damping)
    a = det_k - lam2 * trace_k
    b = lam * (c00 + c11 + c22 - lam2)
    adj_g = (c00 * g[0] + c01 * g[1] + c02 * g[2], c01 * g[0] + c11 * g[1] + c12 * g[2],
             c02 * g[0] + c12 * g[1] + c22 * g[2])
    shift_g = (trace_k * g[0] - (k00 * g[0] + k01 * g[1] + k02 * g[2]),
               trace_k * g[1] - (k01 * g[0] + k11 * g[1] + k12 * g[2]),
               trace_k * g[2] - (k02 * g[0] + k12 * g[1] + k22 * g[2]))
    ab_max = torch.maximum(a.abs(), b.abs())
    solvable = ab_max > finfo.tiny
    inv_ab = torch.where(solvable, 1 / torch.where(solvable, ab_max, 1.0), 0.0)
    as_, bs = a * inv_ab, b * inv_ab
    norm2 = torch.where(solvable, as_ * as_ + bs * bs, 1.0)
    w_adj = as_ * inv_ab / norm2
    w_shift = bs * inv_ab / norm2 * lam
    huge = finfo.max
    sat = lambda v: v.clamp(-huge, huge)
    u = [sat(sat(w_adj * (adj_g[i] - lam2 * g[i])) + sat(w_shift * shift_g[i])) for i in range(3)]
    scale = torch.clamp(lift * inv_max * inv_frob, max=huge)
    x_up = torch.where(x_huge, torch.full_like(x_max, 2.0**half_range), torch.ones_like(x_max))
    return [sat(sat(t * scale) * x_up) for t in times_cross(R, u)]
