"""The derivative of the fitted rotation, from the optimality condition
(R^T M symmetric): the Triton twin of csrc/kernel/rotation_gradient.h, whose
header derives (G1)/(G2) and the damping."""
from __future__ import annotations

import triton
import triton.language as tl

from torchrot.triton.lanes import any, constant, div, max_abs_entry, sqrt
from torchrot.triton.mat3 import diff_of_products, dot3, transpose_times
from torchrot.triton.mul_add import mul_add
from torchrot.triton.unit_scale import unit_scale

__all__ = ["skew_axial", "times_cross", "rotation_tangent"]


@triton.jit
def skew_axial(R, X):
    """vex(B - B^T) for B = R^T X."""
    B = transpose_times(R, X)
    return B[7] - B[5], B[2] - B[6], B[3] - B[1]


@triton.jit
def times_cross(R, u):
    """R [u]x, [u]x = [[0, -z, y], [z, 0, -x], [-y, x, 0]]."""
    x, y, z = u[0], u[1], u[2]
    return (diff_of_products(R[1], z, R[2], y), diff_of_products(R[2], x, R[0], z), diff_of_products(R[0], y, R[1], x),
            diff_of_products(R[4], z, R[5], y), diff_of_products(R[5], x, R[3], z), diff_of_products(R[3], y, R[4], x),
            diff_of_products(R[7], z, R[8], y), diff_of_products(R[8], x, R[6], z), diff_of_products(R[6], y, R[7], x))


@triton.jit
def _saturate(x, huge):
    # L::clamp(x, -huge, huge): NaN stays NaN
    return tl.minimum(tl.maximum(x, -huge, propagate_nan=tl.PropagateNan.ALL), huge, propagate_nan=tl.PropagateNan.ALL)


@triton.jit
def _solve(weight_adj, weight_shift, lambda2, adj, gi, shift, huge):
    # Each term saturates on its own: a sum of two overflows is +-inf, never NaN.
    return _saturate(_saturate(weight_adj * (adj - lambda2 * gi), huge) + _saturate(weight_shift * shift, huge), huge)


@triton.jit
def rotation_tangent(X, R, M, damping, TINY: tl.constexpr, LIFT: tl.constexpr, HUGE: tl.constexpr,
                     HALF_RANGE: tl.constexpr):
    """R [u]x with u the damped solution of A u = vex(R^T X - X^T R),
    A = tr(S) I - sym(S), S = R^T M, for X = dL/dR (the backward) or dM (the
    forward-mode derivative); ``damping`` is eps (a scalar of the compute dtype). HUGE: the largest finite
    number; HALF_RANGE: 2^(max_exponent / 2)."""
    max_abs = max_abs_entry(M)
    zero = max_abs == 0.0
    A, lift, inv_max = unit_scale(M, max_abs, TINY, LIFT)
    frob2 = constant(max_abs, 0.0)
    for k in tl.static_range(9):
        frob2 = mul_add(A[k], A[k], frob2)
    frob = tl.where(zero, 1.0, sqrt(frob2))  # |A|_F in [1, 3]
    S = transpose_times(R, A)
    inv_frob = div(constant(frob, 1.0), frob)
    trace = (S[0] + S[4] + S[8]) * inv_frob
    half_inv = 0.5 * inv_frob
    k00, k11, k22 = trace - S[0] * inv_frob, trace - S[4] * inv_frob, trace - S[8] * inv_frob
    k01 = -(S[1] + S[3]) * half_inv
    k02 = -(S[2] + S[6]) * half_inv
    k12 = -(S[5] + S[7]) * half_inv
    # An X with entries above 2^(max_exponent / 2) is scaled down by that power of two (exact).
    x_huge = ((tl.abs(X[0]) > HALF_RANGE) | (tl.abs(X[1]) > HALF_RANGE) | (tl.abs(X[2]) > HALF_RANGE)) | \
        ((tl.abs(X[3]) > HALF_RANGE) | (tl.abs(X[4]) > HALF_RANGE) | (tl.abs(X[5]) > HALF_RANGE)) | \
        ((tl.abs(X[6]) > HALF_RANGE) | (tl.abs(X[7]) > HALF_RANGE) | (tl.abs(X[8]) > HALF_RANGE))
    scaled = any(x_huge)
    x_down = tl.where(x_huge, 1.0 / HALF_RANGE, constant(max_abs, 1.0))
    if scaled:
        X = (X[0] * x_down, X[1] * x_down, X[2] * x_down, X[3] * x_down, X[4] * x_down, X[5] * x_down,
             X[6] * x_down, X[7] * x_down, X[8] * x_down)
    g = skew_axial(R, X)
    c00, c01 = diff_of_products(k11, k22, k12, k12), diff_of_products(k02, k12, k01, k22)
    c02, c11 = diff_of_products(k01, k12, k02, k11), diff_of_products(k00, k22, k02, k02)
    c12, c22 = diff_of_products(k01, k02, k00, k12), diff_of_products(k00, k11, k01, k01)
    det_k = dot3(k00, c00, k01, c01, k02, c02)
    trace_k = k00 + k11 + k22
    lam = constant(max_abs, 0.0) + damping
    lambda2 = lam * lam
    a = det_k - lambda2 * trace_k
    b = lam * (c00 + c11 + c22 - lambda2)
    adj_g0 = dot3(c00, g[0], c01, g[1], c02, g[2])
    adj_g1 = dot3(c01, g[0], c11, g[1], c12, g[2])
    adj_g2 = dot3(c02, g[0], c12, g[1], c22, g[2])
    shift_g0 = mul_add(trace_k, g[0], -dot3(k00, g[0], k01, g[1], k02, g[2]))
    shift_g1 = mul_add(trace_k, g[1], -dot3(k01, g[0], k11, g[1], k12, g[2]))
    shift_g2 = mul_add(trace_k, g[2], -dot3(k02, g[0], k12, g[1], k22, g[2]))
    # Divide by a^2 + b^2 after scaling a, b by 1 / max(|a|, |b|) (L::max: NaN propagates).
    ab_max = tl.maximum(tl.abs(a), tl.abs(b), propagate_nan=tl.PropagateNan.ALL)
    solvable = ab_max > TINY
    inv_ab_max = tl.where(solvable, div(constant(ab_max, 1.0), ab_max), 0.0)
    a_s, b_s = a * inv_ab_max, b * inv_ab_max
    norm2 = tl.where(solvable, mul_add(a_s, a_s, b_s * b_s), 1.0)
    weight_adj = div(a_s * inv_ab_max, norm2)
    weight_shift = div(b_s * inv_ab_max, norm2) * lam
    u = (_solve(weight_adj, weight_shift, lambda2, adj_g0, g[0], shift_g0, HUGE),
         _solve(weight_adj, weight_shift, lambda2, adj_g1, g[1], shift_g1, HUGE),
         _solve(weight_adj, weight_shift, lambda2, adj_g2, g[2], shift_g2, HUGE))
    # Undo the scaling by 1 / |M|_F = inv_frob / max |M_ij|, saturating.
    scale = _saturate((lift * inv_max) * inv_frob, HUGE)
    T = times_cross(R, u)
    T = (_saturate(T[0] * scale, HUGE), _saturate(T[1] * scale, HUGE), _saturate(T[2] * scale, HUGE),
         _saturate(T[3] * scale, HUGE), _saturate(T[4] * scale, HUGE), _saturate(T[5] * scale, HUGE),
         _saturate(T[6] * scale, HUGE), _saturate(T[7] * scale, HUGE), _saturate(T[8] * scale, HUGE))
    if scaled:
        x_up = tl.where(x_huge, HALF_RANGE, constant(max_abs, 1.0))
        T = (_saturate(T[0] * x_up, HUGE), _saturate(T[1] * x_up, HUGE), _saturate(T[2] * x_up, HUGE),
             _saturate(T[3] * x_up, HUGE), _saturate(T[4] * x_up, HUGE), _saturate(T[5] * x_up, HUGE),
             _saturate(T[6] * x_up, HUGE), _saturate(T[7] * x_up, HUGE), _saturate(T[8] * x_up, HUGE))
    return T
