"""Derivatives of fit_rotation (and of fit_orthogonal, the ``fit`` fixture)
through the optimality condition (R^T M symmetric), exact where the
gradient exists: against finite differences (gradcheck, float64), autograd
through float64 SVD where that is finite, float32 SVD's accuracy, RoMa's
special_procrustes and procrustes; the Jacobian is a rotational tangent;
init receives no gradient.
"""
from __future__ import annotations

import pytest
import torch
from autograd_helpers import DTYPES, _gradient, _smallest_pair_sum, _svd_gradient, op

import torchrot
from torchrot._constants import GRADIENT_EPS
from torchrot.testing import dtype_id, make_matrices, make_warm_start, random_rotations

SMOOTH = ("warm", "rot60", "uniform", "gaussian", "det_negative", "symmetric")


# ---------------------------------------------------------------------------
# Exactness where the gradient exists
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", SMOOTH)
def test_gradcheck_random(name, fit):
    M = make_matrices(name, 6, seed=3).requires_grad_()
    assert torch.autograd.gradcheck(fit.fn, (M,), eps=1e-6, atol=1e-8, rtol=1e-6)


@pytest.mark.parametrize(
    "M",
    [
        torch.eye(3),
        torch.diag(torch.tensor([2.0, 2.0, 1.0])),  # repeated singular values: SVD backward is NaN here
        torch.diag(torch.tensor([3.0, 3.0, 3.0])) @ random_rotations(1, torch.Generator().manual_seed(0))[0].float(),
        torch.diag(torch.tensor([3.0, 2.0, -1.0])),  # det < 0
        torch.diag(torch.tensor([-2.0, -2.0, 5.0])),  # det > 0, R a half-turn from I
    ],
    ids=["identity", "diag221", "scaled_rotation", "det_negative", "half_turn_pair"],
)
def test_gradcheck_structured(M, fit):
    M = M.double().requires_grad_()
    assert torch.autograd.gradcheck(fit.fn, (M,), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_matches_svd_autograd_where_finite():
    """Agrees with autograd through float64 SVD to 1e-8 relative (undamped
    and with the default damping) where singular values are distinct and
    sigma_i + sigma_j is well away from 0 (> 3e-2 |M|_F)."""
    M = torch.cat([make_matrices(name, 300, seed=5) for name in SMOOTH])
    keep = _smallest_pair_sum(M) > 3e-2  # damping's relative effect (1e-6 / 3e-2)^2 ~ 1e-9
    M = M[keep]
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    expected = _svd_gradient(M, G)
    finite = torch.isfinite(expected).all(-1).all(-1)
    assert finite.float().mean() > 0.99
    scale = expected.norm(dim=(-2, -1), keepdim=True)
    for eps in (0.0, GRADIENT_EPS):
        got = _gradient(M, G, gradient_eps=eps)
        err = ((got - expected).norm(dim=(-2, -1), keepdim=True) / scale)[finite]
        assert err.max() < 1e-8, f"gradient_eps={eps}: max relative error {err.max():.3g}"


@pytest.mark.parametrize("name", ("warm", "uniform", "gaussian"))
def test_float32_gradient_as_accurate_as_float32_svd(name):
    """float32 rounding is amplified by the system's condition only once (no
    A^2 is formed): on condition-1e3 data the 99th percentile of the relative
    error against float64 SVD autograd stays at float32 SVD's level."""
    M = make_matrices(name, 5000, seed=1)
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    reference = _svd_gradient(M, G)
    relative = lambda g: ((g.double() - reference).norm(dim=(-2, -1)) / reference.norm(dim=(-2, -1)))
    ours = relative(_gradient(M.float(), G.float()))
    svd32 = relative(_svd_gradient(M.float(), G.float()))
    svd32 = svd32[torch.isfinite(svd32)]
    assert ours.quantile(0.99) <= 2 * svd32.quantile(0.99) and ours.max() <= 2 * svd32.max()


def test_matches_roma(fit):
    """roma.special_procrustes for fit_rotation, roma.procrustes for
    fit_orthogonal (on matrices of either determinant)."""
    roma = pytest.importorskip("roma")
    M = make_matrices("uniform", 500, seed=2)
    M[1::2] = -M[1::2]
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    Mr = M.clone().requires_grad_()
    (roma.procrustes if fit.orthogonal else roma.special_procrustes)(Mr).backward(G)
    got = _gradient(M, G, fit.fn)
    err = (got - Mr.grad).norm(dim=(-2, -1)) / Mr.grad.norm(dim=(-2, -1))
    # RoMa damps its SVD backward (gradient_eps=1e-5 on sigma differences).
    assert err.median() < 1e-9 and err.max() < 1e-4


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
def test_jacobian_is_rotational_tangent(dtype):
    """dR = R [w]x: R^T dR is skew for every direction dM."""
    M = make_matrices("gaussian", 20, seed=4, dtype=dtype)
    R = torchrot.fit_rotation(M)
    dM = torch.randn(M.shape, generator=torch.Generator().manual_seed(4), dtype=dtype)
    dR = op.fit_rotation_backward(dM, R, M, GRADIENT_EPS)
    W = R.mT @ dR
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert (W + W.mT).abs().max() <= tol * W.abs().max()


def test_init_receives_no_gradient(fit):
    M, init = make_warm_start("warm", 10, seed=1)
    M.requires_grad_()
    init.requires_grad_()
    fit.fn(M, init).sum().backward()
    assert M.grad is not None and init.grad is None


def test_broadcast_init_gradient_shape(fit):
    M = make_matrices("rot60", 4, seed=1).reshape(2, 2, 3, 3).requires_grad_()
    init = torch.eye(3, dtype=torch.float64)
    fit.fn(M, init, max_iter=3).sum().backward()
    assert M.grad.shape == M.shape and torch.isfinite(M.grad).all()
