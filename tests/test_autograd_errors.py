"""Errors of fit_rotation's derivative: out= with an input that requires
grad, bad gradient_eps and bad arguments of the derivative operator. (Second
derivatives work: tests/test_transforms_second_derivatives.py.)
"""
from __future__ import annotations

import pytest
import torch
from autograd_helpers import _backward_case, op

import torchrot
from torchrot.testing import make_matrices

# ---------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------


def test_out_with_requires_grad_raises():
    M = make_matrices("rot60", 2, seed=1).requires_grad_()
    with pytest.raises(ValueError, match="out= does not support automatic differentiation"):
        torchrot.fit_rotation(M, out=torch.empty(2, 3, 3, dtype=torch.float64))


@pytest.mark.parametrize("bad", [-1e-3, float("nan"), float("inf")])
def test_bad_gradient_eps(bad):
    M = make_matrices("rot60", 2, seed=1)
    with pytest.raises(ValueError, match="gradient_eps must be a finite number >= 0"):
        torchrot.fit_rotation(M, gradient_eps=bad)
    with pytest.raises(ValueError, match="gradient_eps must be a finite number >= 0"):
        op.fit_rotation_backward(M, M, M, bad)
    with pytest.raises(TypeError, match="gradient_eps must be a float"):
        torchrot.fit_rotation(M, gradient_eps="small")


def test_backward_op_argument_errors():
    G, R, M = _backward_case(4, torch.float64)
    with pytest.raises(ValueError, match="grad must have R's shape"):
        op.fit_rotation_backward(G[:2], R, M, 1e-6)
    with pytest.raises(ValueError, match="M of shape .* must broadcast to R's shape"):
        op.fit_rotation_backward(G, R, M[:3], 1e-6)
    with pytest.raises(TypeError, match="grad must have R's dtype"):
        op.fit_rotation_backward(G.float(), R, M, 1e-6)
    with pytest.raises(ValueError, match=r"R must have shape \(\.\.\., 3, 3\)"):
        op.fit_rotation_backward(G, R.view(4, 9), M, 1e-6)
    with pytest.raises(TypeError, match="R must be float32, float64"):
        op.fit_rotation_backward(G.long(), R.long(), M.long(), 1e-6)
