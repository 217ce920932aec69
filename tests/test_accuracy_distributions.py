"""Accuracy of torchrot.fit_rotation against the float64 SVD answer on every
distribution of torchrot.testing and on the edge cases, for every dtype and
variant (converged mode): the accuracy criteria, the distance to the SVD
answer where that is unique (WELL_CONDITIONED), and exact rotations with a
step limit.
"""
from __future__ import annotations

import pytest
import torch
from accuracy_helpers import N, _assert_close_to_svd

import torchrot
from torchrot.testing import CRITERIA, DISTRIBUTIONS, WELL_CONDITIONED, dtype_id, edge_case_matrices, rotation_errors

# ---------------------------------------------------------------------------
# Every distribution, every dtype, every variant (converged mode)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(DISTRIBUTIONS))
def test_distribution_meets_criteria(name, dtype, variant, matrices, assert_meets_criteria):
    M = matrices(name, N, 0, dtype)
    R = torchrot.fit_rotation(M, variant=variant)
    assert R.shape == M.shape and R.dtype == dtype
    assert_meets_criteria(R, M, dtype, f"{name}/{variant}")


@pytest.mark.parametrize("name", WELL_CONDITIONED)
def test_well_conditioned_distance_to_svd(name, dtype, variant, matrices):
    M = matrices(name, N, 0, dtype)
    R = torchrot.fit_rotation(M, variant=variant)
    _assert_close_to_svd(R, M, f"{name}/{variant}/{dtype_id(dtype)}")


def test_edge_cases(dtype, variant, assert_meets_criteria):
    M = edge_case_matrices(dtype)
    R, iterations, status = torchrot.fit_rotation_info(M, variant=variant)
    assert torch.isfinite(R).all()
    assert (status <= 1).all()  # Cayley or fallback: nothing is non-finite here
    assert_meets_criteria(R, M, dtype, f"edge cases/{variant}")


def test_edge_cases_with_max_iter_are_rotations(dtype, variant):
    """With a step limit the maximum is not promised, but the result is still
    an exact, finite rotation."""
    M = edge_case_matrices(dtype)
    R = torchrot.fit_rotation(M, max_iter=2, variant=variant)
    assert torch.isfinite(R).all()
    errors = rotation_errors(R, M)
    assert errors["orthonormality"].max() <= CRITERIA[dtype]["orthonormality"]
    assert errors["det"].max() <= CRITERIA[dtype]["det"]
