"""Shared by the tests of torchrot.rigid_registration,
tests/test_registration_*.py: tolerances, an independent float64 reference
(Umeyama by SVD) and a bounded comparison with a readable failure message."""
from __future__ import annotations

import torch

from torchrot.reference import rigid_registration_svd

TOL = {torch.float32: 2e-5, torch.float64: 1e-11}


def umeyama_reference(x, y, weights=None, scale=False):
    """Independent float64 reference: Umeyama by SVD (torchrot.rigid_registration_svd)."""
    return rigid_registration_svd(x.double(), y.double(), None if weights is None else weights.double(), scale)


def assert_close(actual, expected, tol, what):
    err = (actual.double() - expected.double()).abs().max().item()
    assert err <= tol, f"{what}: max error {err:.3g} > {tol:g}"
