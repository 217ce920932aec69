"""The Cayley step (Algorithm 2 of Zhang, Jacobson & Alexa) and the Cayley
map back to a rotation (Eq. 10) on structure-of-arrays lanes: the Python twin
of csrc/kernel/cayley.h (trace, skew_vector, objective_estimate,
cayley_step, cayley_increment, rotate_by), whose comment has the derivation
and the convention (R = R0 Q maximises tr(Q^T S), S = R0^T M).
"""
from __future__ import annotations

import torch

from torchrot.generic.mat3 import diff_of_products, dot3

__all__ = ["trace", "skew_vector", "objective_estimate", "cayley_step", "cayley_increment", "rotate_by"]


def trace(S):
    """tr S."""
    return S[0] + S[4] + S[8]


def skew_vector(S):
    """m = vee(S - S^T) = (S21 - S12, S02 - S20, S10 - S01) (Eq. 12)."""
    return (S[7] - S[5], S[2] - S[6], S[3] - S[1])


def objective_estimate(S, t, mm, variant):
    """The estimate c of the maximal objective for ``variant`` (Sec. 4.2),
    given t = tr S and mm = m.m."""
    if variant == "newton":
        return t
    g = t
    if variant == "gershgorin":
        s01 = (S[1] + S[3]).abs()
        s02 = (S[2] + S[6]).abs()
        s12 = (S[5] + S[7]).abs()
        two_l2 = torch.maximum(2 * S[0] + s01 + s02, torch.maximum(2 * S[4] + s01 + s12, 2 * S[8] + s02 + s12))
        g = torch.maximum(t, two_l2 - t)
    return torch.sqrt(g * g + mm)


def cayley_step(S, t, m, c):
    """Algorithm 2 (cayley_step, cayley.h): w = adj(H) m, d = det H, w.w, d^2 and
    |H|_F^2 for H = S + S^T - (t + c) I."""
    shift = t + c
    h00, h11, h22 = 2 * S[0] - shift, 2 * S[4] - shift, 2 * S[8] - shift
    h01, h02, h12 = S[1] + S[3], S[2] + S[6], S[5] + S[7]
    c00 = diff_of_products(h11, h22, h12, h12)
    c01 = diff_of_products(h02, h12, h01, h22)
    c02 = diff_of_products(h01, h12, h02, h11)
    c11 = diff_of_products(h00, h22, h02, h02)
    c12 = diff_of_products(h01, h02, h00, h12)
    c22 = diff_of_products(h00, h11, h01, h01)
    d = h00 * c00 + h01 * c01 + h02 * c02
    w0 = c00 * m[0] + c01 * m[1] + c02 * m[2]
    w1 = c01 * m[0] + c11 * m[1] + c12 * m[2]
    w2 = c02 * m[0] + c12 * m[1] + c22 * m[2]
    hh = h00 * h00 + h11 * h11 + h22 * h22 + 2 * (h01 * h01 + h02 * h02 + h12 * h12)
    return (w0, w1, w2), d, w0 * w0 + w1 * w1 + w2 * w2, d * d, hh


def cayley_increment(w, d, ww, dd):
    """K = Q - I for the rotation Q of Eq. 10 with z = -w / d (cayley_increment):
    (2 w w^T - 2 (w.w) I - 2 d [w]x) / (d^2 + w.w), its diagonal
    -2 (w.w - w_i^2) / (d^2 + w.w), as small as the step; each product of two
    components of (d, w) as u (v * 2 / (d^2 + w.w))."""
    x, y, z = w
    two_inv = 2 / (dd + ww)
    x2, y2, z2, d2 = x * two_inv, y * two_inv, z * two_inv, d * two_inv
    yy, zz = y * y2, z * z2
    xy, xz, yz = x * y2, x * z2, y * z2
    dx, dy, dz = x * d2, y * d2, z * d2
    return [
        -torch.addcmul(zz, y, y2), xy + dz, xz - dy,
        xy - dz, -torch.addcmul(zz, x, x2), yz + dx,
        xz + dy, yz - dx, -torch.addcmul(yy, x, x2),
    ]


def rotate_by(R, K):
    """R Q = R + R K (rotate_by): each entry R's plus a correction summed at
    its own scale."""
    return [R[3 * r + c] + dot3(R[3 * r], K[c], R[3 * r + 1], K[3 + c], R[3 * r + 2], K[6 + c])
            for r in range(3) for c in range(3)]
