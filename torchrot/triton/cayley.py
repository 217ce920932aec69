"""The Cayley step of Zhang, Jacobson & Alexa (Algorithm 2) and the Cayley
map back to a rotation (Eq. 10): the Triton twin of csrc/kernel/cayley.h,
whose header derives the formulas for S = R^T M:
  m = vee(S - S^T)                          (Eq. 12)
  t = tr S,   T = S + S^T - t I             (Eq. 36)
  (S + S^T - (t + c) I) z = -m              (Eqs. 24 / 29)
and Q = I + K from z = -w / d               (Eq. 10), applied as R + R K.

A step is kept as the tuple ``(w0, w1, w2, d, ww, dd, mm, hh)`` (the C++
CayleyStep's fields: w = adj(H) m, d = det H, w.w, d^2, m.m, |H|_F^2).
"""
from __future__ import annotations

import triton
import triton.language as tl

from torchrot.triton.lanes import constant, div, sqrt
from torchrot.triton.mat3 import diff_of_products, dot3
from torchrot.triton.mul_add import mul_add

__all__ = ["smaller_than", "singular", "trace", "skew_vector", "objective_estimate", "step_system",
           "frobenius2", "cayley_step", "cayley_increment", "rotate_by"]


@triton.jit
def smaller_than(step, tol):
    """CayleyStep::smaller_than: s = w.w / d^2 < tol (false for a singular H
    or a step that is not finite)."""
    return step[4] < tol * step[5]


@triton.jit
def singular(step, tol):
    """CayleyStep::singular: |m|^2 >= tol |H|_F^2, H singular with the
    gradient in its range (a small step only through 0 / 0)."""
    return ~(step[6] < tol * step[7])


@triton.jit
def trace(S):
    return S[0] + S[4] + S[8]


@triton.jit
def skew_vector(S):  # Eq. 12
    return (S[7] - S[5], S[2] - S[6], S[3] - S[1])


@triton.jit
def objective_estimate(S, VARIANT: tl.constexpr):
    """The estimate c of the maximal objective for VARIANT (Sec. 4.2):
    "newton" (Eq. 21), "conservative" (Eq. 26 with g_S ~ tr S) or
    "gershgorin" (Eq. 27, lambda_2 bounded by Eq. 28)."""
    t = trace(S)
    if VARIANT == "newton":
        return t
    else:
        m = skew_vector(S)
        mm = dot3(m[0], m[0], m[1], m[1], m[2], m[2])
        g_sym = t
        if VARIANT == "gershgorin":
            s01 = tl.abs(S[1] + S[3])
            s02 = tl.abs(S[2] + S[6])
            s12 = tl.abs(S[5] + S[7])
            # (L::max: IEEE maximum, NaN propagates)
            two_lambda2 = tl.maximum(2.0 * S[0] + s01 + s02,
                                     tl.maximum(2.0 * S[4] + s01 + s12, 2.0 * S[8] + s02 + s12,
                                                propagate_nan=tl.PropagateNan.ALL),
                                     propagate_nan=tl.PropagateNan.ALL)
            g_sym = tl.maximum(t, two_lambda2 - t, propagate_nan=tl.PropagateNan.ALL)
        return sqrt(mul_add(g_sym, g_sym, mm))  # Eqs. 26-27


@triton.jit
def step_system(S, c):
    """StepSystem: the symmetric H = S + S^T - (tr S + c) I of Algorithm 2
    as (h00, h11, h22, h01, h02, h12)."""
    shift = trace(S) + c
    return (mul_add(2.0, S[0], -shift), mul_add(2.0, S[4], -shift), mul_add(2.0, S[8], -shift),
            S[1] + S[3], S[2] + S[6], S[5] + S[7])


@triton.jit
def frobenius2(H):
    """StepSystem::frobenius2: |H|_F^2."""
    return mul_add(H[0], H[0], mul_add(H[1], H[1], mul_add(H[2], H[2], 2.0 * dot3(H[3], H[3], H[4], H[4], H[5], H[5]))))


@triton.jit
def cayley_step(S, c):
    """Algorithm 2 for a given c: H z = -m by Cramer's rule (Eqs. 30-33),
    with the symmetric adjugate of H."""
    m = skew_vector(S)
    H = step_system(S, c)
    h00, h11, h22, h01, h02, h12 = H[0], H[1], H[2], H[3], H[4], H[5]
    c00 = diff_of_products(h11, h22, h12, h12)
    c01 = diff_of_products(h02, h12, h01, h22)
    c02 = diff_of_products(h01, h12, h02, h11)
    c11 = diff_of_products(h00, h22, h02, h02)
    c12 = diff_of_products(h01, h02, h00, h12)
    c22 = diff_of_products(h00, h11, h01, h01)
    d = dot3(h00, c00, h01, c01, h02, c02)
    w0 = dot3(c00, m[0], c01, m[1], c02, m[2])
    w1 = dot3(c01, m[0], c11, m[1], c12, m[2])
    w2 = dot3(c02, m[0], c12, m[1], c22, m[2])
    ww = dot3(w0, w0, w1, w1, w2, w2)
    mm = dot3(m[0], m[0], m[1], m[1], m[2], m[2])
    return (w0, w1, w2, d, ww, d * d, mm, frobenius2(H))


@triton.jit
def cayley_increment(step):
    """K = Q - I for the Cayley parameters z = -w / d (Eq. 10), every
    product of two components of (d, w) formed as u (v * 2 / (d^2 + w.w))."""
    x, y, w, d = step[0], step[1], step[2], step[3]
    two_inv = div(constant(d, 2.0), step[5] + step[4])
    x2, y2, w2, d2 = x * two_inv, y * two_inv, w * two_inv, d * two_inv
    yy, ww = y * y2, w * w2
    xy, xw, yw = x * y2, x * w2, y * w2
    return (-mul_add(y, y2, ww), mul_add(w, d2, xy), mul_add(-y, d2, xw),
            mul_add(-w, d2, xy), -mul_add(x, x2, ww), mul_add(x, d2, yw),
            mul_add(y, d2, xw), mul_add(-x, d2, yw), -mul_add(x, x2, yy))


@triton.jit
def _rotate_by_entry(R, K, r: tl.constexpr, c: tl.constexpr):
    return R[3 * r + c] + dot3(R[3 * r], K[c], R[3 * r + 1], K[3 + c], R[3 * r + 2], K[6 + c])


@triton.jit
def rotate_by(R, K):
    """R Q = R + R K for Q = I + K, each entry summed at its own scale."""
    return (
        _rotate_by_entry(R, K, 0, 0), _rotate_by_entry(R, K, 0, 1), _rotate_by_entry(R, K, 0, 2),
        _rotate_by_entry(R, K, 1, 0), _rotate_by_entry(R, K, 1, 1), _rotate_by_entry(R, K, 1, 2),
        _rotate_by_entry(R, K, 2, 0), _rotate_by_entry(R, K, 2, 1), _rotate_by_entry(R, K, 2, 2),
    )
