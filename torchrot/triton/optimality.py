"""Per-lane predicates of the fit: is a fixed point the maximum, and is a
warm start a rotation (and its clean-up to the compute precision). The
Triton twin of csrc/kernel/optimality.h, which explains the pivoting of the
second-order check."""
from __future__ import annotations

import triton
import triton.language as tl

from torchrot.triton.lanes import any, select
from torchrot.triton.mat3 import diff_of_products, dot3, gram, reorthonormalize
from torchrot.triton.mul_add import mul_add

__all__ = ["is_maximum", "orthonormality_deviation2", "determinant", "check_warm_start", "is_usable",
           "used_as_is", "clean_warm_start"]


@triton.jit
def _pick(pivot0, pivot1, if0, if1, if2):
    return tl.where(pivot0, if0, tl.where(pivot1, if1, if2))


@triton.jit
def is_maximum(S, slack):
    """Second-order check at a fixed point S = R^T M: P = tr(S) I - sym(S)
    (+ slack I) positive semidefinite, by elimination on P's largest diagonal
    entry and the 2x2 Schur complement left."""
    t = S[0] + S[4] + S[8] + slack
    p00, p11, p22 = t - S[0], t - S[4], t - S[8]
    p01 = -0.5 * (S[1] + S[3])
    p02 = -0.5 * (S[2] + S[6])
    p12 = -0.5 * (S[5] + S[7])
    pivot0 = ~(p00 < p11) & ~(p00 < p22)
    pivot1 = ~pivot0 & ~(p11 < p22)
    pivot = _pick(pivot0, pivot1, p00, p11, p22)
    paa, pbb, pab = _pick(pivot0, pivot1, p11, p00, p00), _pick(pivot0, pivot1, p22, p22, p11), \
        _pick(pivot0, pivot1, p12, p02, p01)
    pai, pbi = _pick(pivot0, pivot1, p01, p01, p02), _pick(pivot0, pivot1, p02, p12, p12)
    qaa = paa * pivot - pai * pai
    qbb = pbb * pivot - pbi * pbi
    qab = pab * pivot - pai * pbi
    return (pivot > 0.0) & (qaa > 0.0) & (qaa * qbb - qab * qab > 0.0)


@triton.jit
def orthonormality_deviation2(G):
    """|G - I|_F^2 for the Gram matrix G = R^T R."""
    d0, d1, d2 = G[0] - 1.0, G[4] - 1.0, G[8] - 1.0
    off = dot3(G[1], G[1], G[2], G[2], G[5], G[5])
    return mul_add(d0, d0, mul_add(d1, d1, mul_add(d2, d2, 2.0 * off)))


@triton.jit
def determinant(R):
    """det R, expanded along the first row."""
    c0 = diff_of_products(R[4], R[8], R[5], R[7])
    c1 = diff_of_products(R[5], R[6], R[3], R[8])
    c2 = diff_of_products(R[3], R[7], R[4], R[6])
    return dot3(R[0], c0, R[1], c1, R[2], c2)


@triton.jit
def check_warm_start(R, TOLERANCE2: tl.constexpr):
    """WarmStartCheck of a warm start R: (finite, bad, deviation2): finite
    where all its entries are, bad where it is finite but not a rotation
    (|R^T R - I|_F^2 >= TOLERANCE2, limits::kInitTolerance squared, or
    det R <= 0), its squared deviation."""
    G = gram(R)
    deviation2 = orthonormality_deviation2(G)
    finite = tl.abs(G[0] + G[4] + G[8]) < float("inf")  # the Gram diagonal is finite iff every entry of R is
    rotation = (deviation2 < TOLERANCE2) & (determinant(R) > 0.0)
    return finite, finite & ~rotation, deviation2


@triton.jit
def is_usable(finite, bad):
    """The lanes whose warm start is used at all: finite rotations."""
    return finite & ~bad


@triton.jit
def used_as_is(finite, bad, deviation2, CLEAN2: tl.constexpr):
    """The lanes whose warm start clean_warm_start returns as it is (deviation
    below the clean threshold, CLEAN2 its square)."""
    return is_usable(finite, bad) & (deviation2 < CLEAN2)


@triton.jit
def clean_warm_start(R0, finite, bad, deviation2, CLEAN2: tl.constexpr, STEPS: tl.constexpr):
    """The warm start at the compute dtype's precision: lanes whose squared
    deviation is at or above CLEAN2 take Newton-Schulz steps until they are below (at most
    STEPS, limits::kInitCleanSteps); the others are returned unchanged."""
    rough = is_usable(finite, bad) & ~(deviation2 < CLEAN2)
    R = R0
    if any(rough):
        G = gram(R0)
        k = 0
        while (k < STEPS) & any(rough):
            R = select(rough, reorthonormalize(R, G), R)
            G = gram(R)
            rough = rough & ~(orthonormality_deviation2(G) < CLEAN2)
            k += 1
    return R
