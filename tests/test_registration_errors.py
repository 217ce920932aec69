"""torchrot.rigid_registration's errors: each bad argument raises the right
exception, naming the function; NaN stays in its own problem."""
from __future__ import annotations

import pytest
import torch
from registration_helpers import assert_close

import torchrot
from torchrot.testing import registration_problem

# ---------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------

_X = torch.randn(5, 10, 3, dtype=torch.float64)
_W = torch.ones(5, 10, dtype=torch.float64)

ERRORS = [
    ("x not a tensor", lambda: torchrot.rigid_registration(_X.tolist(), _X), TypeError, "x must be a torch.Tensor"),
    ("y wrong last dim", lambda: torchrot.rigid_registration(_X, _X[..., :2]), ValueError,
     r"y must have shape \(\.\.\., N, 3\)"),
    ("x 1-D", lambda: torchrot.rigid_registration(_X[0, 0], _X), ValueError, r"x must have shape"),
    ("N differs", lambda: torchrot.rigid_registration(_X, _X[:, :9]), ValueError, "same number of points"),
    ("integer x", lambda: torchrot.rigid_registration(_X.long(), _X.long()), TypeError, "x must be float32"),
    ("dtypes differ", lambda: torchrot.rigid_registration(_X, _X.float()), TypeError, "y must have x's dtype"),
    ("batch mismatch", lambda: torchrot.rigid_registration(_X, _X[:4]), ValueError,
     "batch dimensions must broadcast"),
    ("weights batch mismatch", lambda: torchrot.rigid_registration(_X, _X, _W[:3]), ValueError, "batch dimensions"),
    ("weights wrong N", lambda: torchrot.rigid_registration(_X, _X, _W[:, :9]), ValueError,
     r"weights must have shape \(\.\.\., N\)"),
    ("weights dtype", lambda: torchrot.rigid_registration(_X, _X, _W.float()), TypeError,
     "weights must have x's dtype"),
    ("weights not a tensor", lambda: torchrot.rigid_registration(_X, _X, [1.0] * 10), TypeError,
     "weights must be None or a torch.Tensor"),
    ("negative weight", lambda: torchrot.rigid_registration(_X, _X, _W - 2 * (torch.arange(10) == 4)), ValueError,
     "weights must be >= 0"),
    ("all-zero weights", lambda: torchrot.rigid_registration(_X, _X, _W * (torch.arange(5) != 3)[:, None]), ValueError,
     r"problem \(3,\).*all weights are zero"),
    ("two effective points", lambda: torchrot.rigid_registration(_X, _X, _W * (torch.arange(10) < 2)), ValueError,
     r"at least 3 points of nonzero weight.*only 2 point"),
    ("two points", lambda: torchrot.rigid_registration(_X[:, :2], _X[:, :2]), ValueError,
     "at least 3 points, got N = 2"),
    ("scale not bool", lambda: torchrot.rigid_registration(_X, _X, scale=1), TypeError, "scale must be a bool"),
    ("allow_reflection not bool", lambda: torchrot.rigid_registration(_X, _X, allow_reflection=None), TypeError,
     "allow_reflection must be a bool, got None"),
    ("init not orthogonal with allow_reflection",
     lambda: torchrot.rigid_registration(_X, _X, init=2 * torch.eye(3), allow_reflection=True), ValueError,
     r"^torchrot\.fit_orthogonal: init must hold orthogonal matrices"),
    ("coincident x with scale", lambda: torchrot.rigid_registration(_X[:, :1].expand(5, 10, 3), _X, scale=True),
     ValueError, "must not all coincide"),
]


@pytest.mark.parametrize("what, call, error, message", ERRORS, ids=[e[0] for e in ERRORS])
def test_errors(what, call, error, message):
    with pytest.raises(error, match=message):
        call()


def test_errors_name_the_function():
    with pytest.raises(ValueError, match=r"^torchrot\.rigid_registration: "):
        torchrot.rigid_registration(_X, _X[:, :9])


def test_nan_stays_in_its_problem():
    x, y, (R, _, _) = registration_problem((3,), n=10, seed=17, with_scale=False)
    y = y.clone()
    y[1, 4, 0] = float("nan")
    out = torchrot.rigid_registration(x, y)
    assert torch.isnan(out.R[1]).all() and torch.isnan(out.t[1]).all()
    assert_close(out.R[[0, 2]], R[[0, 2]], 1e-12, "R of the other problems")
