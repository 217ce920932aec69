"""Warm starts of torchrot.fit_rotation against the float64 SVD answer: a
start at the answer stays, a nearby one converges to it (also for
torchrot.fit_orthogonal, the ``fit`` fixture, on matrices of either
determinant; a warm start of the other determinant than M's still
converges); one step matches
the Cayley step computed by hand from the paper's formulas; drifted starts
are reorthonormalised; feeding R back as init does not drift.
"""
from __future__ import annotations

import math

import pytest
import torch
from accuracy_helpers import N_SMALL, _assert_close_to_svd

import torchrot
from torchrot.reference import cayley_rotation
from torchrot.testing import (
    CRITERIA,
    WELL_CONDITIONED,
    dtype_id,
    orthogonal_errors,
    random_rotations,
    rotation_errors,
    rotation_svd,
)

# ---------------------------------------------------------------------------
# Warm start
# ---------------------------------------------------------------------------


def _mixed_signs(M: torch.Tensor, fit) -> torch.Tensor:
    """M, with every other matrix negated for the orthogonal fit (det < 0 there)."""
    if fit.orthogonal:
        M = M.clone()
        M[1::2] = -M[1::2]
    return M


@pytest.mark.parametrize("name", WELL_CONDITIONED)
def test_warm_start_at_answer_stays(name, dtype, variant, fit, matrices):
    """init = the exact answer, one step: the result stays at the answer."""
    M64 = _mixed_signs(matrices(name, N_SMALL, 8, torch.float64), fit)
    M = M64.to(dtype)
    init = fit.svd(M.double()).to(dtype)
    if not fit.orthogonal:
        R, iterations, status = torchrot.fit_rotation_info(M, init, max_iter=1, variant=variant)
        assert (iterations <= 1).all() and (status == 0).all()
    R = fit.fn(M, init, max_iter=1, variant=variant)
    _assert_close_to_svd(R, M, f"{fit.name}/{name}/{variant}/{dtype_id(dtype)} max_iter=1 from R*", fit.orthogonal)


@pytest.mark.parametrize("name", WELL_CONDITIONED)
def test_warm_start_nearby_converges(name, dtype, variant, fit, matrices):
    """init a few degrees from the answer, converged mode: reaches R*."""
    M = _mixed_signs(matrices(name, N_SMALL, 9, dtype), fit)
    gen = torch.Generator().manual_seed(9)
    init = (fit.svd(M.double()) @ random_rotations(N_SMALL, gen, math.radians(5))).to(dtype)
    R = fit.fn(M, init, variant=variant)
    _assert_close_to_svd(R, M, f"{fit.name}/{name}/{variant}/{dtype_id(dtype)} converged from 5 deg", fit.orthogonal)
    if fit.orthogonal:
        return
    R, iterations, status = torchrot.fit_rotation_info(M, init, variant=variant)
    # measured (1000 matrices per distribution, seed 9): at most 3.9 steps on
    # average (float64 gershgorin) and no fallback; limits leave ~15% / 5 matrices
    assert iterations.float().mean().item() <= 4.5
    assert (status == 1).float().mean().item() <= 0.005


def test_orthogonal_warm_start_of_the_other_determinant(dtype, variant, matrices):
    """A warm start whose determinant is not det M's (det M changed sign since
    the previous fit) is an orthogonal start all the same: converged mode
    reaches the polar factor, one step gives an exact orthogonal matrix."""
    M = matrices("rot60", N_SMALL, 10, dtype)
    init = -torchrot.reference.orthogonal_svd(M.double()).to(dtype)  # det -1, M's det > 0
    Q = torchrot.fit_orthogonal(M, init, variant=variant)
    _assert_close_to_svd(Q, M, f"{variant}/{dtype_id(dtype)} from the reflection", orthogonal=True)
    Q1 = torchrot.fit_orthogonal(M, init, max_iter=1, variant=variant)
    errors = orthogonal_errors(Q1, M)
    assert errors["orthonormality"].max() <= CRITERIA[dtype]["orthonormality"]
    assert (torch.linalg.det(Q1.double()) > 0).all()


def _hand_objective_estimate(S: torch.Tensor, variant: str) -> torch.Tensor:
    """c of each variant, written out from the paper for one matrix at a time
    (not the reference's vectorised code): Newton c = tr S; conservative
    c = sqrt(tr(S)^2 + m.m) (Eq. 26 with g ~ tr S); Gershgorin Eq. 27,
    sqrt(max(t, 2 lambda_2 - t)^2 + m.m), with 2 lambda_2 bounded by Eq. 28,
    max_i (2 s_ii + sum_{j != i} |s_ij + s_ji|)."""
    values = []
    for Si in S.reshape(-1, 3, 3).tolist():
        t = Si[0][0] + Si[1][1] + Si[2][2]
        m = (Si[2][1] - Si[1][2], Si[0][2] - Si[2][0], Si[1][0] - Si[0][1])
        mm = sum(x * x for x in m)
        if variant == "newton":
            c = t
        elif variant == "conservative":
            c = math.sqrt(t * t + mm)
        else:
            two_lambda2 = max(2 * Si[i][i] + sum(abs(Si[i][j] + Si[j][i]) for j in range(3) if j != i)
                              for i in range(3))
            g = max(t, two_lambda2 - t)  # the term the text before Eq. 28 approximates
            c = math.sqrt(g * g + mm)
        values.append(c)
    return torch.tensor(values, dtype=torch.float64).reshape(S.shape[:-2])


def _hand_step(M: torch.Tensor, init: torch.Tensor, variant: str) -> torch.Tensor:
    """One Cayley step in float64 straight from the paper's formula:
    S = init^T M, m = vee(S - S^T), t = tr S, c the variant's estimate,
    z solving (S + S^T - (t + c) I) z = -m (Eq. 24), R = init Q(z) (Eq. 10)."""
    Md, Id = M.double(), init.double()
    S = Id.mT @ Md
    m = torch.stack([S[..., 2, 1] - S[..., 1, 2], S[..., 0, 2] - S[..., 2, 0], S[..., 1, 0] - S[..., 0, 1]], -1)
    t = S.diagonal(dim1=-2, dim2=-1).sum(-1)
    c = _hand_objective_estimate(S, variant)
    H = S + S.mT - (t + c)[..., None, None] * torch.eye(3, dtype=torch.float64)
    z = torch.linalg.solve(H, -m)
    return Id @ cayley_rotation(z)


def test_one_step_matches_hand_computed_cayley_step(dtype, variant, matrices):
    M = matrices("rot60", N_SMALL, 10, dtype)
    gen = torch.Generator().manual_seed(10)
    init = (rotation_svd(M.double()) @ random_rotations(N_SMALL, gen, math.radians(20))).to(dtype)
    R, iterations, _ = torchrot.fit_rotation_info(M, init, max_iter=1, variant=variant)
    assert (iterations == 1).all()
    expected = _hand_step(M, init, variant)
    tol = 2e-6 if dtype == torch.float32 else 1e-12
    assert (R.double() - expected).abs().max().item() <= tol
    # and it is a real step: the objective improves on init's
    obj = lambda Rx: (Rx.double() * M.double()).sum((-2, -1))  # noqa: E731
    assert (obj(R) >= obj(init) - 1e-6 * M.double().norm(dim=(-2, -1))).all()


def test_newton_step_hand_computed_single_matrix():
    """One explicit matrix, float64, newton: R = init Q(z) with
    (S + S^T - 2 tr(S) I) z = -m, S = init^T M."""
    gen = torch.Generator().manual_seed(11)
    M = torch.tensor([[2.0, 0.3, -0.1], [-0.4, 1.5, 0.2], [0.25, -0.3, 1.0]], dtype=torch.float64)
    init = random_rotations(1, gen, math.radians(10))[0]
    R = torchrot.fit_rotation(M, init, max_iter=1, variant="newton")
    S = init.mT @ M
    m = torch.tensor([S[2, 1] - S[1, 2], S[0, 2] - S[2, 0], S[1, 0] - S[0, 1]], dtype=torch.float64)
    H = S + S.mT - 2 * S.trace() * torch.eye(3, dtype=torch.float64)
    z = torch.linalg.solve(H, -m)
    zz = z @ z
    cross = torch.tensor([[0, -z[2], z[1]], [z[2], 0, -z[0]], [-z[1], z[0], 0]], dtype=torch.float64)
    Q = ((1 - zz) * torch.eye(3, dtype=torch.float64) + 2 * torch.outer(z, z) + 2 * cross) / (1 + zz)
    torch.testing.assert_close(R, init @ Q, rtol=0, atol=1e-13)
    torch.testing.assert_close(cayley_rotation(z), Q, rtol=0, atol=1e-15)


@pytest.mark.parametrize("max_iter", [1, 3])
def test_drifted_init_is_reorthonormalised(variant, max_iter, matrices):
    """float32 init with ~1e-5 orthonormality drift (allowed up to 1e-4): the
    result is still an exact rotation at float32 precision."""
    n = N_SMALL
    M = matrices("warm", n, 12, torch.float32)
    gen = torch.Generator().manual_seed(12)
    R0 = rotation_svd(M.double()) @ random_rotations(n, gen, math.radians(3))
    noise = torch.rand(n, 3, 3, generator=gen, dtype=torch.float64) * 2 - 1
    init = (R0 + 1e-5 * noise).float()
    drift = (init.double().mT @ init.double() - torch.eye(3, dtype=torch.float64)).abs().amax((-2, -1))
    assert drift.max() > 5e-6 and drift.max() < 1e-4  # the setup really drifts
    R = torchrot.fit_rotation(M, init, max_iter=max_iter, variant=variant)
    errors = rotation_errors(R, M)
    assert errors["orthonormality"].max() <= CRITERIA[torch.float32]["orthonormality"]
    assert errors["det"].max() <= CRITERIA[torch.float32]["det"]


def test_drifted_init_float64(variant, matrices):
    n = N_SMALL
    M = matrices("rot60", n, 13, torch.float64)
    gen = torch.Generator().manual_seed(13)
    R0 = random_rotations(n, gen)
    init = R0 + 1.5e-8 * (torch.rand(n, 3, 3, generator=gen, dtype=torch.float64) * 2 - 1)
    R = torchrot.fit_rotation(M, init, max_iter=1, variant=variant)
    errors = rotation_errors(R, M)
    assert errors["orthonormality"].max() <= CRITERIA[torch.float64]["orthonormality"]
    assert errors["det"].max() <= CRITERIA[torch.float64]["det"]


def test_repeated_warm_start_does_not_drift(dtype, variant, matrices):
    """Feeding R back as init 50 times (a local-global solver's loop), from up
    to 30 degrees off, keeps R an exact rotation and ends at the maximum."""
    M = matrices("rot60", 500, 14, dtype)
    gen = torch.Generator().manual_seed(14)
    R = (rotation_svd(M.double()) @ random_rotations(500, gen, math.radians(30))).to(dtype)
    for _ in range(50):
        torchrot.fit_rotation(M, R, max_iter=1, variant=variant, out=R)
    errors = rotation_errors(R, M)
    assert errors["orthonormality"].max() <= CRITERIA[dtype]["orthonormality"]
    assert errors["det"].max() <= CRITERIA[dtype]["det"]
    assert errors["shortfall"].max() <= CRITERIA[dtype]["shortfall"]
