"""torchrot.rigid_registration's weights: zero weights drop points, weights
are neither squared nor scale-dependent, and three points suffice."""
from __future__ import annotations

import torch
from registration_helpers import TOL, assert_close

import torchrot
from torchrot.testing import registration_problem

# ---------------------------------------------------------------------------
# Weights
# ---------------------------------------------------------------------------


def test_zero_weights_drop_points(dtype):
    x, y, (R, t, s) = registration_problem((), n=20, seed=8, dtype=dtype)
    # wreck some points and give them zero weight
    y_bad = y.clone()
    y_bad[::3] += 100.0
    w = torch.ones(20, dtype=dtype)
    w[::3] = 0
    out = torchrot.rigid_registration(x, y_bad, w, scale=True)
    subset = torchrot.rigid_registration(x[w > 0], y_bad[w > 0], scale=True)
    tol = TOL[dtype] * 10
    for a, b, name in zip(out, subset, "Rts"):
        assert_close(a, b, 20 * tol, name)
    assert_close(out.R, R, tol, "R")


def test_weights_are_not_squared_and_scale_free():
    """Weight 2 on a point == the point listed twice; w and 10 w agree."""
    x, y, _ = registration_problem((), n=12, seed=9, noise=0.3)
    w = torch.ones(12, dtype=torch.float64)
    w[0] = 2.0
    doubled = torchrot.rigid_registration(torch.cat([x, x[:1]]), torch.cat([y, y[:1]]), scale=True)
    weighted = torchrot.rigid_registration(x, y, w, scale=True)
    scaled = torchrot.rigid_registration(x, y, 10 * w, scale=True)
    for a, b, c, name in zip(weighted, doubled, scaled, "Rts"):
        assert_close(a, b, 1e-11, name)
        assert_close(a, c, 1e-11, name)


def test_exactly_three_points():
    x, y, (R, t, s) = registration_problem((), n=3, seed=10)
    out = torchrot.rigid_registration(x, y, scale=True)
    assert_close(out.R, R, 1e-10, "R")
    assert_close(out.s, s, 1e-10, "s")
