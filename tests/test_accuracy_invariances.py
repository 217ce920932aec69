"""Invariances of torchrot.fit_rotation: scaling by a power of two is bit
exact, scaling by 1e+-20 keeps the accuracy against the float64 SVD answer,
and the fit is equivariant under transposition and rotations.
"""
from __future__ import annotations

import pytest
import torch
from accuracy_helpers import N_SMALL, _assert_close_to_svd, _distance_limit

import torchrot
from torchrot.testing import dtype_id, random_rotations

# ---------------------------------------------------------------------------
# Invariances
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("k", [66, -66])
def test_power_of_two_scale_is_bit_exact(dtype, variant, k, matrices):
    """M is normalised by its largest entry, so scaling by a power of two
    (2^+-66 ~ 1e+-20) must not change a single bit."""
    M = matrices("gaussian", N_SMALL, 4, dtype)
    assert torch.equal(torchrot.fit_rotation(M * 2.0**k, variant=variant), torchrot.fit_rotation(M, variant=variant))


@pytest.mark.parametrize("scale", [1e20, 1e-20])
@pytest.mark.parametrize("name", ["rot60", "uniform"])
def test_scale_invariance(dtype, variant, scale, name, matrices):
    """fit(M * 1e+-20) is as accurate as fit(M) and close to it (the scaled
    float32 data round differently, so they agree to the data's accuracy)."""
    M = matrices(name, N_SMALL, 4, dtype)
    Ms = M * scale
    assert torch.isfinite(Ms).all() and (Ms.abs().amax((-2, -1)) >= torch.finfo(dtype).tiny).all()
    R, Rs = torchrot.fit_rotation(M, variant=variant), torchrot.fit_rotation(Ms, variant=variant)
    _assert_close_to_svd(Rs, Ms, f"{name}*{scale:g}/{variant}/{dtype_id(dtype)}")
    assert bool(((R - Rs).norm(dim=(-2, -1)) <= 2 * _distance_limit(M)).all())


def test_transpose_and_rotation_equivariance(dtype, matrices):
    """fit(M^T) = fit(M)^T and fit(P M Q) = P fit(M) Q for rotations P, Q
    (default variant)."""
    variant = "conservative"
    M = matrices("rot60", N_SMALL, 6, dtype)
    gen = torch.Generator().manual_seed(6)
    P = random_rotations(N_SMALL, gen).to(dtype)
    Q = random_rotations(N_SMALL, gen).to(dtype)
    R = torchrot.fit_rotation(M, variant=variant)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert (torchrot.fit_rotation(M.mT, variant=variant) - R.mT).abs().max().item() <= tol
    assert (torchrot.fit_rotation(P @ M @ Q, variant=variant) - P @ R @ Q).abs().max().item() <= tol
