"""Derivatives of fit_rotation (and fit_orthogonal, where the fuzz runs on
both: the ``fit`` fixture) at the degenerate inputs where SVD gradients
fail (repeated singular values, rank-deficient M, half-turns): finite and
bounded by the damping, converging to the exact gradient as the damping
vanishes, NaN only where the input is NaN/Inf.
"""
from __future__ import annotations

import pytest
import torch
from autograd_helpers import DTYPES, _gradient

import torchrot
from torchrot._constants import GRADIENT_EPS
from torchrot.testing import DEGENERATE_FAMILIES, dtype_id, make_degenerate_matrices, make_matrices

# ---------------------------------------------------------------------------
# Degenerate inputs: finite, bounded, NaN only from NaN
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
def test_degenerate_fuzz_finite_and_bounded(dtype, fit):
    """>= 1e5 matrices over every degenerate family: no NaN/Inf gradient, and
    |dL/dM|_F <= |G|_F / (gradient_eps |M|_F) (the damping's bound:
    |u| <= |g| / (2 lambda), |g| <= sqrt(2) |G|_F, |R [u]x|_F = sqrt(2) |u|)."""
    per_family = 100_000 // len(DEGENERATE_FAMILIES) + 1
    M = torch.cat([make_degenerate_matrices(name, per_family, seed=11, dtype=dtype)
                   for name in DEGENERATE_FAMILIES])
    assert M.shape[0] >= 100_000
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(12), dtype=dtype)
    got = _gradient(M, G, fit.fn)
    assert torch.isfinite(got).all(), f"{int((~torch.isfinite(got)).sum())} non-finite entries"
    norm_M = M.double().norm(dim=(-2, -1))
    bound = 1.001 * G.double().norm(dim=(-2, -1)) / (GRADIENT_EPS * norm_M)
    nonzero = norm_M > 0
    assert (got.double().norm(dim=(-2, -1))[nonzero] <= bound[nonzero]).all()
    assert (got[~nonzero] == 0).all()  # M = 0: every rotation is optimal, nothing moves it


def test_damping_bound_and_limit():
    """At an exact half-turn ambiguity (sigma_2 + sigma_3 = 0) the gradient is
    bounded by 1 / gradient_eps; where the system is regular, damping -> 0
    converges to the exact gradient."""
    M = torch.diag(torch.tensor([2.0, 1.0, -1.0], dtype=torch.float64))
    G = torch.randn(3, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    for eps in (1e-2, 1e-4, 1e-6):
        g = _gradient(M, G, gradient_eps=eps)
        assert torch.isfinite(g).all()
        assert g.norm() <= 1.001 * G.norm() / (eps * M.norm())
    M = make_matrices("uniform", 50, seed=8)
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    exact = _gradient(M, G, gradient_eps=0.0)
    errors = [(_gradient(M, G, gradient_eps=eps) - exact).norm() / exact.norm() for eps in (1e-2, 1e-3, 1e-4)]
    # Tikhonov damping: the error falls quadratically, (lambda / (sigma_i + sigma_j))^2.
    assert errors[0] / errors[1] > 50 and errors[1] / errors[2] > 50 and errors[2] < 1e-6


def test_nan_only_where_input_nan():
    M = make_matrices("gaussian", 40, seed=6)
    M[3, 1, 2] = float("nan")
    M[17, 0, 0] = float("inf")
    M.requires_grad_()
    torchrot.fit_rotation(M).sum().backward()
    bad = torch.zeros(40, dtype=torch.bool)
    bad[[3, 17]] = True
    assert torch.isnan(M.grad[bad]).all()
    assert torch.isfinite(M.grad[~bad]).all()


def test_subnormal_input_saturates_instead_of_overflowing():
    M = torch.full((3, 3), 1e-40, dtype=torch.float32) + torch.diag(torch.tensor([3e-40, 0.0, 0.0]))
    g = _gradient(M, torch.ones(3, 3))
    assert not torch.isnan(g).any() and not torch.isinf(g).any()
