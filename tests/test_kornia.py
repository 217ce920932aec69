"""Point-set alignment checked against kornia, an independent implementation
of the rotation conversions and of the SO(3) log map.

Convention (column vectors): for centred points x_i and y_i = R x_i, stored as
(N, 3) rows, M = sum_i w_i y_i x_i^T = (w * y)^T x, and fit_rotation(M) = R.
"""
from __future__ import annotations

import math

import pytest
import torch

import torchrot

kornia = pytest.importorskip("kornia")
from kornia.geometry.conversions import (  # noqa: E402
    axis_angle_to_rotation_matrix,
    quaternion_to_rotation_matrix,
    rotation_matrix_to_axis_angle,
    rotation_matrix_to_quaternion,
)
from kornia.geometry.liegroup import So3  # noqa: E402

GEODESIC_TOL = {torch.float32: 1e-5, torch.float64: 1e-10}


def _axis_angles(n: int, gen: torch.Generator) -> torch.Tensor:
    """(n, 3) float64 axis-angle vectors: angles uniform in [0, pi), plus a
    block within 1 degree below 180, one near 179.99 and a block of tiny ones."""
    axis = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(n, generator=gen, dtype=torch.float64) * math.pi
    k = n // 5
    angle[:k] = math.radians(179) + torch.rand(k, generator=gen, dtype=torch.float64) * math.radians(0.999)
    angle[k] = math.radians(179.99)
    angle[k + 1 : 2 * k] = 10.0 ** (-8 + 6 * torch.rand(k - 1, generator=gen, dtype=torch.float64))
    return axis * angle[:, None]


def _point_sets(R_true: torch.Tensor, n_points: int, gen: torch.Generator, noise: float = 0.0):
    """Centred x (B, N, 3), y = R x (+ noise) and positive weights (B, N), float64."""
    B = R_true.shape[0]
    x = torch.randn(B, n_points, 3, generator=gen, dtype=torch.float64)
    w = torch.rand(B, n_points, generator=gen, dtype=torch.float64) + 0.1
    x = x - (w[..., None] * x).sum(1, keepdim=True) / w.sum(1)[:, None, None]  # weighted centring
    y = x @ R_true.mT  # rows: y_i^T = x_i^T R^T, i.e. y_i = R x_i
    if noise:
        y = y + noise * torch.randn(y.shape, generator=gen, dtype=torch.float64)
    return x, y, w


def _cross_covariance(x, y, w, dtype):
    """M = sum_i w_i y_i x_i^T, computed in ``dtype``."""
    x, y, w = x.to(dtype), y.to(dtype), w.to(dtype)
    return (w[..., None] * y).mT @ x


def _geodesic(R_a: torch.Tensor, R_b: torch.Tensor) -> torch.Tensor:
    """Angle of R_a^T R_b through kornia's SO(3) log map (float64)."""
    return rotation_matrix_to_axis_angle(R_a.double().mT @ R_b.double()).norm(dim=-1)


def test_convention_quarter_turn(dtype):
    """x = e1 -> y = e2, e2 -> -e1, e3 -> e3 is +90 degrees about z."""
    x = torch.eye(3, dtype=dtype)
    y = torch.tensor([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)
    M = y.mT @ x
    R = torchrot.fit_rotation(M)
    expected = axis_angle_to_rotation_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=dtype))
    torch.testing.assert_close(R, expected, rtol=0, atol=4 * torch.finfo(dtype).eps)
    torch.testing.assert_close(R @ x.mT, y.mT, rtol=0, atol=4 * torch.finfo(dtype).eps)


def test_noise_free_recovery(dtype, variant):
    gen = torch.Generator().manual_seed(100)
    aa = _axis_angles(1000, gen)
    R_true = axis_angle_to_rotation_matrix(aa)
    x, y, w = _point_sets(R_true, 20, gen)
    M = _cross_covariance(x, y, w, dtype)
    R = torchrot.fit_rotation(M, variant=variant)
    assert R.dtype == dtype
    rotation_matrix_to_axis_angle(R, check_rotation=True)  # kornia: R is a rotation to 100 eps
    err = _geodesic(R, R_true)
    tol = GEODESIC_TOL[dtype]
    worst = int(err.argmax())
    assert err.max().item() <= tol, (
        f"geodesic error {err[worst].item():.3g} rad > {tol:g} for a rotation of "
        f"{math.degrees(aa[worst].norm().item()):.4f} degrees"
    )
    # the same through kornia's Lie-group API
    err_lie = So3.from_matrix(R.double().mT @ R_true).log().norm(dim=-1)
    assert err_lie.max().item() <= tol
    # and R maps the x onto the y
    residual = (x.to(dtype) @ R.mT - y.to(dtype)).abs().max().item()
    assert residual <= (1e-5 if dtype == torch.float32 else 1e-12)


def test_near_half_turns(dtype, variant):
    """Rotations of 179 to 180 degrees (inclusive) via kornia's quaternions."""
    gen = torch.Generator().manual_seed(101)
    n = 400
    axis = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = math.pi - torch.rand(n, generator=gen, dtype=torch.float64) * math.radians(1)
    angle[:20] = math.pi  # exact half-turns: the Cayley map cannot represent these
    q = torch.cat([torch.cos(angle / 2)[:, None], torch.sin(angle / 2)[:, None] * axis], -1)
    R_true = quaternion_to_rotation_matrix(q)
    x, y, w = _point_sets(R_true, 12, gen)
    R = torchrot.fit_rotation(_cross_covariance(x, y, w, dtype), variant=variant)
    assert _geodesic(R, R_true).max().item() <= GEODESIC_TOL[dtype]
    # kornia's quaternion of the fit is +-q
    q_fit = rotation_matrix_to_quaternion(R.double())
    q_fit = q_fit / q_fit.norm(dim=-1, keepdim=True)
    q_dist = torch.minimum((q_fit - q).norm(dim=-1), (q_fit + q).norm(dim=-1))
    assert q_dist.max().item() <= GEODESIC_TOL[dtype]


def test_random_quaternions(dtype):
    gen = torch.Generator().manual_seed(102)
    q = torch.randn(2000, 4, generator=gen, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    R_true = quaternion_to_rotation_matrix(q)
    x, y, w = _point_sets(R_true, 8, gen)
    M = _cross_covariance(x, y, w, dtype)
    R = torchrot.fit_rotation(M)
    assert _geodesic(R, R_true).max().item() <= GEODESIC_TOL[dtype]


@pytest.mark.parametrize("max_iter", [1, 3])
def test_warm_start_tracks_a_moving_rotation(dtype, max_iter):
    """A local-global-style loop: the rotation moves 0.5 degrees per frame;
    one (or three) warm-started steps per frame keep up with it."""
    gen = torch.Generator().manual_seed(103)
    n, frames = 200, 20
    aa0 = _axis_angles(n, gen)[torch.randperm(n, generator=gen)]
    drift_axis = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    drift = axis_angle_to_rotation_matrix(drift_axis / drift_axis.norm(dim=-1, keepdim=True) * math.radians(0.5))
    R_true = axis_angle_to_rotation_matrix(aa0)
    x, _, w = _point_sets(R_true, 10, gen)
    R = torchrot.fit_rotation(_cross_covariance(x, x @ R_true.mT, w, dtype))
    for _ in range(frames):
        R_true = drift @ R_true
        M = _cross_covariance(x, x @ R_true.mT, w, dtype)
        R = torchrot.fit_rotation(M, R, max_iter=max_iter, variant="conservative")
    err = _geodesic(R, R_true)
    # one step per frame lags by O(step^2); three steps reach the dtype's precision
    assert err.max().item() <= (1e-6 if max_iter == 1 else GEODESIC_TOL[dtype])


def test_noisy_alignment(dtype, variant):
    """y = R x + noise: the fit is the least-squares rotation (= float64 SVD of
    the same M) and close to the truth."""
    gen = torch.Generator().manual_seed(104)
    aa = _axis_angles(1000, gen)
    R_true = axis_angle_to_rotation_matrix(aa)
    x, y, w = _point_sets(R_true, 50, gen, noise=1e-3)
    M = _cross_covariance(x, y, w, dtype)
    R = torchrot.fit_rotation(M, variant=variant)
    R_svd = torchrot.rotation_svd(M.double())
    assert _geodesic(R, R_svd).max().item() <= GEODESIC_TOL[dtype]
    err = _geodesic(R, R_true)
    assert err.max().item() <= 2e-3  # noise 1e-3 over 50 unit-scale points
    assert err.median().item() <= 5e-4
