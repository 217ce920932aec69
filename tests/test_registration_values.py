"""torchrot.rigid_registration's values: recovery of known transforms,
agreement with a float64 SVD/Umeyama reference (also far from the origin),
the weighted cost at its minimum, and a rotation for mirrored data."""
from __future__ import annotations

import pytest
import torch
from registration_helpers import TOL, assert_close, umeyama_reference

import torchrot
from torchrot.testing import registration_problem

# ---------------------------------------------------------------------------
# Values
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("scale", [False, True])
def test_recovers_known_transform_noiseless(dtype, scale):
    x, y, (R, t, s) = registration_problem((6,), seed=1, dtype=dtype, with_scale=scale)
    out = torchrot.rigid_registration(x, y, scale=scale)
    assert isinstance(out, torchrot.RigidTransform)
    assert out.R.shape == (6, 3, 3) and out.t.shape == (6, 3) and out.s.shape == (6,)
    assert out.R.dtype == out.t.dtype == out.s.dtype == dtype
    tol = TOL[dtype]
    assert_close(out.R, R, tol, "R")
    assert_close(out.s, s, tol, "s")
    assert_close(out.t, t, 20 * tol, "t")  # |t| ~ 3 and |x| ~ 4: absolute error scales with them
    if not scale:
        assert torch.equal(out.s, torch.ones(6, dtype=dtype))


@pytest.mark.parametrize("scale", [False, True])
def test_matches_umeyama_reference_on_noisy_data(dtype, scale):
    x, y, _ = registration_problem((20,), n=25, seed=2, noise=0.5, dtype=dtype)
    weights = torch.rand(20, 25, generator=torch.Generator().manual_seed(3), dtype=dtype) + 0.1
    out = torchrot.rigid_registration(x, y, weights, scale=scale)
    R, t, s = umeyama_reference(x, y, weights, scale)
    tol = TOL[dtype] * 10
    assert_close(out.R, R, tol, "R")
    assert_close(out.t, t, 20 * tol, "t")
    assert_close(out.s, s, tol, "s")


@pytest.mark.parametrize("scale", [False, True])
def test_points_far_from_the_origin_lose_no_accuracy(dtype, scale):
    """The covariance is of centred points: far from the origin, R and s are as
    accurate as near it (sum p y x^T - ȳ x̄^T would cancel ~|offset|^2 / spread^2
    of the digits: R off by ~0.3 in float32 here)."""
    x, y, _ = registration_problem((50,), n=40, seed=5, noise=0.1, dtype=torch.float64, with_scale=scale)
    offset = torch.tensor([1e3, -2e3, 5e2], dtype=torch.float64)
    x, y = (x + offset).to(dtype), (y - 2 * offset).to(dtype)
    out = torchrot.rigid_registration(x, y, scale=scale)
    R, t, s = umeyama_reference(x, y, scale=scale)  # on the same rounded points
    tol = TOL[dtype]
    assert_close(out.R, R, tol, "R")
    assert_close(out.s, s, tol, "s")
    assert_close(out.t, t, tol * offset.abs().sum().item(), "t")  # t = ȳ - s R x̄ carries R's error times |x̄|


def test_result_minimises_the_weighted_cost():
    """The returned (R, t, s) beats nearby perturbations of itself."""
    x, y, _ = registration_problem((), n=30, seed=4, noise=1.0)
    w = torch.rand(30, generator=torch.Generator().manual_seed(5), dtype=torch.float64)

    def cost(R, t, s):
        return (w * (s * x @ R.mT + t - y).square().sum(-1)).sum()

    R, t, s = torchrot.rigid_registration(x, y, w, scale=True)
    best = cost(R, t, s)
    gen = torch.Generator().manual_seed(6)
    for _ in range(20):
        dR = torchrot.fit_rotation(torch.eye(3, dtype=torch.float64) + 1e-3 * torch.randn(3, 3, generator=gen,
                                                                                              dtype=torch.float64))
        dt = 1e-3 * torch.randn(3, generator=gen, dtype=torch.float64)
        ds = 1e-3 * torch.randn((), generator=gen, dtype=torch.float64)
        assert cost(dR @ R, t + dt, s + ds) > best


def test_reflection_data_gives_a_rotation():
    """y a mirror image of x: the best *rotation* (det +1), as Umeyama's reference."""
    x, _, _ = registration_problem((), n=30, seed=7)
    y = x * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    out = torchrot.rigid_registration(x, y, scale=True)
    R, t, s = umeyama_reference(x, y, scale=True)
    assert torch.linalg.det(out.R).item() == pytest.approx(1.0, abs=1e-12)
    assert_close(out.R, R, 1e-10, "R")
    assert_close(out.t, t, 1e-10, "t")
    assert_close(out.s, s, 1e-10, "s")
