"""Per-lane predicates of the driver on structure-of-arrays lanes: is a fixed
point the maximum (is_maximum), and is a warm start a rotation
(check_warm_start) and its clean-up to the compute precision
(clean_warm_start): the Python twin of csrc/kernel/optimality.h, with its
orthonormality_deviation2 and determinant.
"""
from __future__ import annotations

import torch

from torchrot._constants import INIT_CLEAN_STEPS, INIT_TOLERANCE
from torchrot.generic.cayley import trace
from torchrot.generic.control_flow import _any, _compiling
from torchrot.generic.lanes import select
from torchrot.generic.mat3 import gram, reorthonormalize

__all__ = ["is_maximum", "orthonormality_deviation2", "determinant", "check_warm_start", "is_usable", "used_as_is",
           "clean_warm_start"]


def is_maximum(S, slack):
    """is_maximum (optimality.h): P = tr(S) I - sym(S) + slack I positive definite, by
    elimination on P's largest diagonal entry and the 2x2 Schur complement."""
    t = trace(S) + slack
    p00, p11, p22 = t - S[0], t - S[4], t - S[8]
    p01, p02, p12 = -0.5 * (S[1] + S[3]), -0.5 * (S[2] + S[6]), -0.5 * (S[5] + S[7])
    pivot0 = ~(p00 < p11) & ~(p00 < p22)
    pivot1 = ~pivot0 & ~(p11 < p22)

    def pick(if0, if1, if2):
        return torch.where(pivot0, if0, torch.where(pivot1, if1, if2))

    pivot = pick(p00, p11, p22)
    paa, pbb, pab = pick(p11, p00, p00), pick(p22, p22, p11), pick(p12, p02, p01)
    pai, pbi = pick(p01, p01, p02), pick(p02, p12, p12)
    qaa = paa * pivot - pai * pai  # the Schur complement times the pivot
    qbb = pbb * pivot - pbi * pbi
    qab = pab * pivot - pai * pbi
    return (pivot > 0) & (qaa > 0) & (qaa * qbb - qab * qab > 0)


def orthonormality_deviation2(G):
    """|G - I|_F^2 for the Gram matrix G = R^T R (orthonormality_deviation2)."""
    d0, d1, d2 = G[0] - 1, G[4] - 1, G[8] - 1
    return d0 * d0 + d1 * d1 + d2 * d2 + 2 * (G[1] * G[1] + G[2] * G[2] + G[5] * G[5])


def determinant(R):
    """det R, expanded along the first row (determinant)."""
    return (R[0] * (R[4] * R[8] - R[5] * R[7]) - R[1] * (R[3] * R[8] - R[5] * R[6])
            + R[2] * (R[3] * R[7] - R[4] * R[6]))


def check_warm_start(I):
    """check_warm_start: the warm start I's Gram matrix, finiteness, rejection
    (finite but not a rotation: deviation at or above INIT_TOLERANCE, or det
    <= 0) and squared deviation from orthonormality."""
    G = gram(I)
    finite = torch.isfinite(trace(G))
    dev2 = orthonormality_deviation2(G)
    bad = finite & ~((dev2 < INIT_TOLERANCE**2) & (determinant(I) > 0))
    return G, finite, bad, dev2


def is_usable(finite, bad):
    """The lanes whose warm start is used at all: finite rotations."""
    return finite & ~bad


def used_as_is(finite, bad, dev2, clean):
    """The lanes whose warm start clean_warm_start returns as it is (deviation below ``clean``)."""
    return is_usable(finite, bad) & (dev2 < clean**2)


def clean_warm_start(R, G, finite, bad, dev2, clean):
    """clean_warm_start: masked Newton-Schulz steps for the usable lanes
    (finite, not bad) whose deviation is at or above ``clean`` (eager: only
    while some lane needs one); ``G``: R's Gram matrix."""
    clean2 = clean ** 2
    rough = is_usable(finite, bad) & ~(dev2 < clean2)
    for _ in range(INIT_CLEAN_STEPS):
        if not _compiling() and not _any(rough):
            break
        R = select(rough, reorthonormalize(R, G), R)
        G = gram(R)
        rough = rough & ~(orthonormality_deviation2(G) < clean2)
    return R
