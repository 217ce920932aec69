"""Shared by the tests of fit_rotation's derivative, tests/test_autograd_*.py:
gradients through fit_rotation and through float64 SVD, the system's
conditioning, and a backward case (incoming gradient, R, M).
"""
from __future__ import annotations

import torch

import torchrot
from torchrot.testing import make_matrices

op = torch.ops.torchrot
DTYPES = (torch.float32, torch.float64)


def _svd_gradient(M: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    M = M.detach().clone().requires_grad_()
    torchrot.rotation_svd(M).backward(G)
    return M.grad


def _gradient(M: torch.Tensor, G: torch.Tensor, fit=torchrot.fit_rotation, **kwargs) -> torch.Tensor:
    """dL/dM for dL/dR = G through ``fit`` (fit_rotation, or fit_orthogonal)."""
    M = M.detach().clone().requires_grad_()
    fit(M, **kwargs).backward(G)
    return M.grad


def _smallest_pair_sum(M: torch.Tensor) -> torch.Tensor:
    """min sigma_i + sigma_j (signed smallest singular value), relative to |M|_F."""
    sigma = torch.linalg.svdvals(M.double())
    sign = torch.sign(torch.linalg.det(M.double()))
    return (sigma[..., 1] + sign * sigma[..., 2]) / M.double().norm(dim=(-2, -1))


def _backward_case(n, dtype, seed=0):
    M = make_matrices("gaussian", n, seed=seed, dtype=dtype)
    R = torchrot.fit_rotation(M)
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(seed + 1), dtype=torch.float64).to(dtype)
    return G, R, M
