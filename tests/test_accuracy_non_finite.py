"""Non-finite input to torchrot.fit_rotation: a NaN/Inf entry of M or of the
warm start makes exactly its matrix NaN with status 3, at every position of
the entry; every other matrix of the batch is bit-identical.
"""
from __future__ import annotations

import pytest
import torch

import torchrot
from torchrot.testing import random_rotations

# ---------------------------------------------------------------------------
# Non-finite input
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")], ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize("max_iter", [None, 2])
@pytest.mark.parametrize("where", ["M", "init"])
def test_non_finite_isolated(dtype, variant, bad, max_iter, where, matrices):
    """A non-finite entry (here M[k, 1, 2] or init[k, 0, 1]) makes exactly
    matrix k NaN with status 3; every other matrix is bit-identical."""
    n, k = 1000, 17
    M = matrices("gaussian", n, 5, dtype).clone()
    init = None
    if where == "init":
        init = random_rotations(n, torch.Generator().manual_seed(2)).to(dtype)
    expected = torchrot.fit_rotation(M, init, max_iter=max_iter, variant=variant)
    if where == "M":
        M[k, 1, 2] = bad
    else:
        init = init.clone()
        init[k, 0, 1] = bad
    R, _, status = torchrot.fit_rotation_info(M, init, max_iter=max_iter, variant=variant)
    assert torch.isnan(R[k]).all(), f"matrix {k} with {bad} in {where}: got {R[k].tolist()}"
    assert status[k].item() == 3, f"matrix {k} with {bad} in {where}: status {status[k].item()}"
    keep = torch.ones(n, dtype=torch.bool)
    keep[k] = False
    assert torch.equal(R[keep], expected[keep])
    assert not torch.isnan(R[keep]).any()
    assert (status[keep] != 3).all()
    # and fit_rotation gives the same bits as fit_rotation_info
    torch.testing.assert_close(
        torchrot.fit_rotation(M, init, max_iter=max_iter, variant=variant), R, rtol=0, atol=0, equal_nan=True
    )


@pytest.mark.parametrize("position", range(9))
def test_nan_detected_at_every_position(dtype, position):
    """NaN in any one of the nine entries of M is reported (status 3, NaN R),
    in converged mode and with a step limit."""
    M = torch.eye(3, dtype=dtype).repeat(3, 1, 1)
    M.view(3, 9)[1, position] = float("nan")
    for max_iter in (None, 1):
        R, _, status = torchrot.fit_rotation_info(M, max_iter=max_iter)
        assert torch.isnan(R[1]).all() and status[1].item() == 3, (
            f"NaN at M[1].flatten()[{position}], max_iter={max_iter}: status {status[1].item()}, R={R[1].tolist()}"
        )
        assert torch.equal(R[0], torch.eye(3, dtype=dtype)) and torch.equal(R[2], torch.eye(3, dtype=dtype))
