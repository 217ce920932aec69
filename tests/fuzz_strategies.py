"""Hypothesis strategies of tests/test_fuzz.py: matrices that mix
hypothesis's own "nasty" floats (signed zeros, subnormals, the largest finite
values), matrices scaled by 2^e over the whole exponent range, rank-1
matrices, matrices with exactly repeated singular values (built from signed
permutations, so that the repetition is exact in floating point),
near-rotations and NaN/Inf entries; warm starts, whole problems and incoming
gradients.
"""
from __future__ import annotations

import itertools
import math

import torch
from fuzz_checks import scale_pow2
from hypothesis import strategies as st

from torchrot._constants import VARIANTS
from torchrot.reference import quaternion_rotation

# ---------------------------------------------------------------------------
# Strategies
# ---------------------------------------------------------------------------


def _signed_permutations() -> list[torch.Tensor]:
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            P = torch.zeros(3, 3, dtype=torch.float64)
            for row, col in enumerate(perm):
                P[row, col] = signs[row]
            mats.append(P)
    return mats


SIGNED_PERMUTATIONS = _signed_permutations()  # 48, exact in any precision
CUBE_ROTATIONS = [P for P in SIGNED_PERMUTATIONS if torch.linalg.det(P) > 0]  # 24


def _floats(dtype, **kw):
    return st.floats(width=32 if dtype == torch.float32 else 64, **kw)


def _exponent_range(dtype):
    """(lo, hi): 2^lo is the smallest subnormal, 2^hi overflows."""
    info = torch.finfo(dtype)
    mantissa_bits = round(-math.log2(info.eps))
    return round(math.log2(info.smallest_normal)) - mantissa_bits, round(math.log2(info.max)) + 1


@st.composite
def _elementwise(draw, dtype):
    """Nine independent floats: hypothesis favours 0, -0, subnormals, max, ..."""
    return torch.tensor(draw(st.lists(_floats(dtype, allow_nan=False, allow_infinity=False), min_size=9,
                                      max_size=9)), dtype=torch.float64).view(3, 3)


@st.composite
def _scaled(draw, dtype):
    """A matrix of O(1) entries (some exactly 0) times 2^e over the whole
    exponent range of the dtype, down to subnormals (where entries lose
    bits or vanish) and up to overflow (Inf after the cast, expected NaN)."""
    lo, hi = _exponent_range(dtype)
    entries = draw(st.lists(st.one_of(st.just(0.0), st.floats(-1, 1)), min_size=9, max_size=9))
    exponent = draw(st.integers(lo, hi))
    return scale_pow2(torch.tensor(entries, dtype=torch.float64), exponent).view(3, 3)


@st.composite
def _repeated_singular_values(draw, dtype):
    """P1 B P2 with signed permutations P1, P2 and B = diag(a, a, b),
    a I, or a similarity block [[a, -b], [b, a]] (+) c (singular values
    sqrt(a^2 + b^2) twice): repeated singular values, exact in floating point."""
    value = _floats(dtype, allow_nan=False, allow_infinity=False)
    a, b, c = draw(value), draw(value), draw(value)
    kind = draw(st.sampled_from(["aab", "aaa", "similarity"]))
    if kind == "aab":
        B = torch.diag(torch.tensor([a, a, b], dtype=torch.float64))
    elif kind == "aaa":
        B = a * torch.eye(3, dtype=torch.float64)
    else:
        B = torch.tensor([[a, -b, 0.0], [b, a, 0.0], [0.0, 0.0, c]], dtype=torch.float64)
    P1, P2 = draw(st.sampled_from(SIGNED_PERMUTATIONS)), draw(st.sampled_from(SIGNED_PERMUTATIONS))
    return P1 @ B @ P2


@st.composite
def _rank_one(draw, dtype):
    unit = st.one_of(st.just(0.0), st.floats(-1, 1))
    u = torch.tensor(draw(st.lists(unit, min_size=3, max_size=3)), dtype=torch.float64)
    v = torch.tensor(draw(st.lists(unit, min_size=3, max_size=3)), dtype=torch.float64)
    lo, hi = _exponent_range(dtype)
    return scale_pow2(torch.outer(u, v), draw(st.integers(lo, hi)))


@st.composite
def _quaternion_rotation(draw):
    """A rotation from a drawn quaternion (float64), or a cube rotation (exact)."""
    if draw(st.booleans()):
        return draw(st.sampled_from(CUBE_ROTATIONS))
    q = torch.tensor(draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4)), dtype=torch.float64)
    if float(q.norm()) < 1e-3:
        q = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    q = q / q.norm()
    return quaternion_rotation(q)


@st.composite
def _near_rotation(draw, dtype):
    """A rotation times a positive scale plus a tiny perturbation (the warm
    data of local-global solvers, at any magnitude)."""
    R = draw(_quaternion_rotation())
    noise = torch.tensor(draw(st.lists(st.floats(-1e-6, 1e-6), min_size=9, max_size=9)), dtype=torch.float64)
    lo, hi = _exponent_range(dtype)
    return scale_pow2(R + noise.view(3, 3), draw(st.integers(lo + 30, hi - 2)))


@st.composite
def _with_non_finite(draw, base):
    """``base`` with 1-9 entries replaced by NaN, +Inf or -Inf."""
    M = draw(base).clone().view(9)
    for index in draw(st.lists(st.integers(0, 8), min_size=1, max_size=9)):
        M[index] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    return M.view(3, 3)


def matrices(dtype):
    finite = st.one_of(
        _elementwise(dtype), _scaled(dtype), _repeated_singular_values(dtype), _rank_one(dtype),
        _near_rotation(dtype),
    )
    return st.one_of(finite, _with_non_finite(finite))


@st.composite
def warm_starts(draw, n: int, dtype):
    """``(n, 3, 3)`` rotations (a few with NaN/Inf entries), or one ``(3, 3)``
    rotation broadcast to the batch."""
    if n and draw(st.integers(0, 4)) == 0:
        return draw(_quaternion_rotation()).to(dtype)
    inits = []
    for _ in range(n):
        R = draw(_quaternion_rotation())
        if draw(st.integers(0, 9)) == 0:
            R = draw(_with_non_finite(st.just(R)))
        inits.append(R)
    return torch.stack(inits).to(dtype) if inits else torch.empty(0, 3, 3, dtype=dtype)


@st.composite
def problems(draw, dtype, max_size=40):
    """(M (n, 3, 3), init or None, max_iter, variant) for n in 0..max_size."""
    Ms = draw(st.lists(matrices(dtype), min_size=0, max_size=max_size))
    M = torch.stack(Ms).to(dtype) if Ms else torch.empty(0, 3, 3, dtype=dtype)
    init = draw(warm_starts(M.shape[0], dtype)) if draw(st.booleans()) else None
    max_iter = draw(st.sampled_from([None, None, 1, 2, 5]))
    variant = draw(st.sampled_from(VARIANTS))
    return M, init, max_iter, variant


@st.composite
def incoming_gradients(draw, n: int, dtype):
    """``(n, 3, 3)`` dL/dR (or dM): O(1) values, arbitrary floats (huge,
    subnormal, +-0) or, rarely, NaN/Inf entries."""
    kind = draw(st.sampled_from(["unit", "unit", "arbitrary", "with_non_finite"]))
    if kind == "unit":
        seed = draw(st.integers(0, 2**32 - 1))
        return torch.randn(n, 3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64).to(dtype)
    entries = draw(st.lists(_floats(dtype, allow_nan=kind == "with_non_finite",
                                    allow_infinity=kind == "with_non_finite"), min_size=9 * n, max_size=9 * n))
    return torch.tensor(entries, dtype=torch.float64).view(n, 3, 3).to(dtype)
