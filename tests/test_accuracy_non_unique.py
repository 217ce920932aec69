"""Non-unique maximisers of tr(R^T M) (the zero matrix, rank-1 matrices):
torchrot.fit_rotation gives deterministic answers that attain the maximum;
M = 0 gives the identity, or keeps the warm start.
"""
from __future__ import annotations

import pytest
import torch
from accuracy_helpers import N

import torchrot
from torchrot.testing import CRITERIA, random_rotations


def _eye(dtype, batch=()):
    return torch.eye(3, dtype=dtype).expand(*batch, 3, 3)


# ---------------------------------------------------------------------------
# Non-unique maximisers: deterministic answers
# ---------------------------------------------------------------------------


def test_zero_matrix_gives_identity(dtype, variant):
    M = torch.zeros(4, 3, 3, dtype=dtype)
    R, iterations, status = torchrot.fit_rotation_info(M, variant=variant)
    assert torch.equal(R, _eye(dtype, (4,)))
    assert (iterations == 0).all() and (status == 0).all()
    # also for -0.0 and within a batch of other matrices
    M2 = torch.randn(3, 3, 3, dtype=dtype)
    M2[1] = -0.0
    assert torch.equal(torchrot.fit_rotation(M2, variant=variant)[1], _eye(dtype))


@pytest.mark.parametrize("max_iter", [None, 1])
def test_zero_matrix_keeps_init(dtype, variant, max_iter):
    init = random_rotations(5, torch.Generator().manual_seed(7)).to(dtype)
    M = torch.zeros(5, 3, 3, dtype=dtype)
    R = torchrot.fit_rotation(M, init, max_iter=max_iter, variant=variant)
    eps = torch.finfo(dtype).eps
    assert (R - init).abs().max().item() <= 8 * eps
    orth = (R.mT @ R - _eye(dtype)).abs().max().item()
    assert orth <= CRITERIA[dtype]["orthonormality"]


def test_rank1_attains_maximum_deterministically(dtype, variant, matrices, assert_meets_criteria):
    M = matrices("rank1", N, 3, dtype)
    R1 = torchrot.fit_rotation(M, variant=variant)
    R2 = torchrot.fit_rotation(M.clone(), variant=variant)
    assert_meets_criteria(R1, M, dtype, f"rank1/{variant}")
    assert torch.equal(R1, R2)


def test_rank1_hand_picked_deterministic(dtype, variant):
    a = torch.tensor([1.0, 2.0, -0.5], dtype=dtype)
    b = torch.tensor([-0.3, 0.7, 1.1], dtype=dtype)
    M = torch.outer(a, b)
    R1 = torchrot.fit_rotation(M, variant=variant)
    R2 = torchrot.fit_rotation(M, variant=variant)
    assert torch.equal(R1, R2)
    # R b/|b| = a/|a| attains the maximum |a||b|
    obj = (R1.double() * M.double()).sum().item()
    assert obj == pytest.approx((a.norm() * b.norm()).item(), rel=10 * torch.finfo(dtype).eps)
