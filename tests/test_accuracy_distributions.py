"""Accuracy of torchrot.fit_rotation and torchrot.fit_orthogonal (the ``fit``
fixture) against the float64 SVD answer (the rotation, the polar factor) on
every distribution of torchrot.testing and on the edge cases, for every dtype
and variant (converged mode): the accuracy criteria, the distance to the SVD
answer where that is unique (WELL_CONDITIONED), and exact results with a
step limit; the orthogonal fit also on the degenerate families (det < 0,
rank-deficient, near-tie singular values).
"""
from __future__ import annotations

import pytest
import torch
from accuracy_helpers import N, _assert_close_to_svd

import torchrot
from torchrot.testing import (
    CRITERIA,
    DEGENERATE_FAMILIES,
    DISTRIBUTIONS,
    WELL_CONDITIONED,
    conditioning,
    dtype_id,
    edge_case_matrices,
    make_degenerate_matrices,
    orthogonal_errors,
)

# ---------------------------------------------------------------------------
# Every distribution, every dtype, every variant (converged mode)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(DISTRIBUTIONS))
def test_distribution_meets_criteria(name, dtype, variant, fit, matrices, assert_meets_criteria):
    M = matrices(name, N, 0, dtype)
    R = fit.fn(M, variant=variant)
    assert R.shape == M.shape and R.dtype == dtype
    assert_meets_criteria(R, M, dtype, f"{fit.name}/{name}/{variant}", errors=fit.errors)


@pytest.mark.parametrize("name", WELL_CONDITIONED)
def test_well_conditioned_distance_to_svd(name, dtype, variant, fit, matrices):
    M = matrices(name, N, 0, dtype)
    R = fit.fn(M, variant=variant)
    _assert_close_to_svd(R, M, f"{fit.name}/{name}/{variant}/{dtype_id(dtype)}", fit.orthogonal)


def test_edge_cases(dtype, variant, fit, assert_meets_criteria):
    M = edge_case_matrices(dtype)
    R = fit.fn(M, variant=variant)
    assert torch.isfinite(R).all()
    if not fit.orthogonal:
        R_info, iterations, status = torchrot.fit_rotation_info(M, variant=variant)
        assert torch.equal(R_info, R)
        assert (status <= 1).all()  # Cayley or fallback: nothing is non-finite here
    assert_meets_criteria(R, M, dtype, f"{fit.name}/edge cases/{variant}", errors=fit.errors)


def test_edge_cases_with_max_iter_are_exact(dtype, variant, fit):
    """With a step limit the maximum is not promised, but the result is still
    an exact, finite rotation (orthogonal matrix)."""
    M = edge_case_matrices(dtype)
    R = fit.fn(M, max_iter=2, variant=variant)
    assert torch.isfinite(R).all()
    errors = fit.errors(R, M)
    assert errors["orthonormality"].max() <= CRITERIA[dtype]["orthonormality"]
    assert errors["det"].max() <= CRITERIA[dtype]["det"]


# ---------------------------------------------------------------------------
# The orthogonal fit on the degenerate families
# ---------------------------------------------------------------------------

#: Families whose polar factor is unique and well conditioned (every singular
#: value well away from 0), where Q itself is compared with the SVD's: det < 0
#: and the near-tie half_turn (sigma_2 + sigma_3 ~ 0 makes the nearest
#: *rotation* barely unique, not the nearest orthogonal matrix) among them.
ORTHOGONAL_WELL_CONDITIONED = ("identity", "scaled_rotation", "repeated_sigma", "half_turn")


@pytest.mark.parametrize("family", sorted(DEGENERATE_FAMILIES))
def test_orthogonal_fit_on_degenerate_families(family, dtype, variant, assert_meets_criteria):
    """The polar factor's objective on every degenerate family (det < 0,
    rank 1 and 2, zero, repeated and near-tie singular values, extreme
    scales), with det Q the sign of det M where M is far from singular."""
    M = make_degenerate_matrices(family, N, 2, dtype)
    Q = torchrot.fit_orthogonal(M, variant=variant)
    assert_meets_criteria(Q, M, dtype, f"fit_orthogonal/{family}/{variant}", errors=orthogonal_errors)
    nonsingular = conditioning(M, orthogonal=True) < 1e3
    assert torch.equal(Q.double().det().sign()[nonsingular], M.double().det().sign()[nonsingular])
    if family in ORTHOGONAL_WELL_CONDITIONED:
        _assert_close_to_svd(Q, M, f"fit_orthogonal/{family}/{variant}/{dtype_id(dtype)}", orthogonal=True)
