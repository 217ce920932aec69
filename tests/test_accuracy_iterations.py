"""Iteration counts of torchrot.fit_rotation (algorithm quality, not timing):
steps and fallback rates per distribution and variant, the cold start's
first step landing on the maximum, max_iter capping the steps; and the
inputs .ci/fuzz found, which reach the maximum (kernel and reference).
"""
from __future__ import annotations

import pytest
import torch
from accuracy_helpers import N_SMALL, N

import torchrot
from torchrot._constants import CONVERGED_CAP, MAX_ESCAPES
from torchrot.reference import fit_rotation_reference
from torchrot.testing import CRITERIA, rotation_errors

# ---------------------------------------------------------------------------
# Iteration counts (algorithm quality, not timing)
# ---------------------------------------------------------------------------


def test_iteration_counts_on_warm_default_variant(dtype, matrices):
    M = matrices("warm", N, 15, dtype)
    _, iterations, status = torchrot.fit_rotation_info(M)
    # measured (3000 "warm" matrices, seed 15, cold start): 1.9 (float32) and
    # 2.7 (float64) steps on average, no fallback; the limits leave ~50% / 60 matrices
    assert iterations.float().mean().item() <= 4
    assert (status == 1).float().mean().item() <= 0.02
    assert (status == 0).sum() + (status == 1).sum() == N


@pytest.mark.parametrize("name", ["uniform", "gaussian", "det_negative"])
def test_cold_first_step_lands_on_the_maximum(name, dtype, variant, matrices):
    # The first step from the cube start takes c = K's largest eigenvalue
    # (maximal_objective.h), so it solves Horn's eigenproblem: the second step
    # only confirms (measured, 1e5 uniform or Gaussian matrices: 2.000 steps on
    # average in both dtypes, against 3.2-3.9 with the estimates alone), and one
    # step alone is already the fit.
    M = matrices(name, N, 23, dtype)
    _, iterations, status = torchrot.fit_rotation_info(M, variant=variant)
    assert (status == 0).all()
    assert (iterations == 2).float().mean().item() >= 0.99
    errors = rotation_errors(torchrot.fit_rotation(M, max_iter=1, variant=variant), M)
    assert errors["shortfall"].max() <= CRITERIA[dtype]["shortfall"]


def test_fallback_rate_on_warm_every_variant(dtype, variant, matrices):
    M = matrices("warm", N, 15, dtype)
    _, iterations, status = torchrot.fit_rotation_info(M, variant=variant)
    # measured (3000 "warm" matrices, seed 15, cold start): at most 3.75 steps
    # on average (float64 gershgorin), at most 9 in one matrix, no fallback
    assert (status == 1).float().mean().item() <= 0.02
    assert iterations.float().mean().item() <= 6
    # at most CONVERGED_CAP steps per start and per saddle escape
    cap = CONVERGED_CAP * (1 + MAX_ESCAPES)
    assert iterations.max().item() <= cap


def test_exact_rotations_need_no_fallback(dtype, variant, matrices):
    M = matrices("rot180_exact", N, 16, dtype)
    _, iterations, status = torchrot.fit_rotation_info(M, variant=variant)
    assert (status == 0).all()
    # measured (3000 matrices, seed 16): at most 4.3 steps on average (float64 newton)
    assert iterations.float().mean().item() <= 5


def test_max_iter_caps_iterations(dtype, variant, matrices):
    M = matrices("gaussian", N_SMALL, 17, dtype)
    for k in (1, 2, 5):
        _, iterations, status = torchrot.fit_rotation_info(M, max_iter=k, variant=variant)
        assert (iterations <= k).all() and (iterations >= 1).all()
        assert (status == 0).all()  # no fallback with a step limit


# Found by .ci/fuzz (seed 287567313, test_batched_recipes[float32], newton,
# cold): three equal singular values, det M < 0, perturbed by one float32 ulp
# below the diagonal. The maximisers of the unperturbed M form a continuum, and
# at the saddles near it two eigenvalues of tr(S) I - sym(S) are ~1e-6: the
# maximum check's leading minors (Sylvester) let one pass on float32 rounding
# (8 steps, status 0, 2.1e-6 |M|_F short of the maximum); the pivoted check
# (optimality.h) rejects it.
NEAR_DEGENERATE_REFLECTION = [[-0.04649638012051582, -0.0, -0.0],
                              [1.1920928955078125e-07, 0.04649638012051582, -0.0],
                              [-0.0, 1.1920928955078125e-07, 0.04649638012051582]]

# Found by .ci/fuzz (seed 309661663, test_batched_recipes[float32], cold): at
# the start R = diag(-1, -1, 1), newton's H = S + S^T - 2 tr(S) I is singular
# and the gradient m = (1, 0, -1) (of M / 6) lies in its range, so Cramer's
# rule gives 0 / 0 and a step of rounding noise, which counted as converged (1
# step, status 0, 0.396 |M|_F short). Such a step is stalled
# (CayleyStep::singular, cayley.h): the fallback decides. Also scaled into
# float32 subnormals. (The cold start was then the best of the tetrahedral
# group's 12 rotations; the cube's 24 (cold_start.h) start elsewhere, so the
# singular start is now given as the warm start.)
NEWTON_WRONG_MAXIMUM = [[-3.0, -6.0, -2.0], [0.0, -2.0, 0.0], [2.0, 6.0, 3.0]]
NEWTON_SINGULAR_START = [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]


@pytest.mark.parametrize("case", ["near_degenerate_reflection", "newton_singular_start", "subnormal"])
@pytest.mark.parametrize("fit", ["kernel", "reference"])
def test_fuzz_findings_reach_the_maximum(case, fit, dtype, variant, assert_meets_criteria):
    matrix = NEAR_DEGENERATE_REFLECTION if case == "near_degenerate_reflection" else NEWTON_WRONG_MAXIMUM
    M = torch.tensor([matrix], dtype=dtype)
    if case == "subnormal":
        M = M * torch.finfo(dtype).tiny * 2.0**-10
        assert 0 < M.abs().max() < torch.finfo(dtype).tiny
    fitter = torchrot.fit_rotation if fit == "kernel" else fit_rotation_reference
    assert_meets_criteria(fitter(M, variant=variant), M, dtype, f"{case}, {variant}, cold")
    if case != "near_degenerate_reflection":
        init = torch.tensor([NEWTON_SINGULAR_START], dtype=dtype)
        assert_meets_criteria(fitter(M, init, variant=variant), M, dtype, f"{case}, {variant}, singular start")


def test_singular_newton_step_is_not_convergence():
    """The newton step at the singular start stalls: the fallback decides (status 1), in the
    kernel and in the generic path alike; with a step limit the lane stops there (status 0)."""
    M = torch.tensor([NEWTON_WRONG_MAXIMUM], dtype=torch.float64)
    init = torch.tensor([NEWTON_SINGULAR_START], dtype=torch.float64)
    reference = lambda M, init, **kw: fit_rotation_reference(M, init, return_info=True, **kw)
    for fit in (torchrot.fit_rotation_info, reference):
        _, iterations, status = fit(M, init, variant="newton")
        assert status.tolist() == [1]
        _, iterations, status = fit(M, init, variant="newton", max_iter=5)
        assert iterations.tolist() == [1] and status.tolist() == [0]
