"""Gradients of torchrot.rigid_registration (through fit_rotation's
autograd): gradcheck, agreement with the gradients of the float64
SVD/Umeyama reference, torch.func's vmap and grad."""
from __future__ import annotations

import pytest
import torch
from registration_helpers import assert_close, umeyama_reference

import torchrot
from torchrot.testing import registration_problem

# ---------------------------------------------------------------------------
# Gradients (need fit_rotation's autograd)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("scale", [False, True])
def test_gradcheck(scale):
    x, y, _ = registration_problem((2,), n=6, seed=18, noise=0.3)
    w = torch.rand(2, 6, generator=torch.Generator().manual_seed(19), dtype=torch.float64) + 0.5
    inputs = tuple(t.clone().requires_grad_() for t in (x, y, w))

    def fn(x, y, w):
        return tuple(torchrot.rigid_registration(x, y, w, scale=scale))

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("scale", [False, True])
def test_gradients_match_svd_reference(scale):
    x, y, _ = registration_problem((16,), n=20, seed=20, noise=0.5)
    w = torch.rand(16, 20, generator=torch.Generator().manual_seed(21), dtype=torch.float64) + 0.1
    gen = torch.Generator().manual_seed(22)
    probes = [torch.randn(16, *shape, generator=gen, dtype=torch.float64) for shape in ((3, 3), (3,), ())]

    def grads(fn):
        leaves = [t.clone().requires_grad_() for t in (x, y, w)]
        outputs = fn(*leaves, scale=scale)
        loss = sum((o * p).sum() for o, p in zip(outputs, probes))
        return torch.autograd.grad(loss, leaves)

    ours = grads(torchrot.rigid_registration)
    reference = grads(umeyama_reference)
    for a, b, name in zip(ours, reference, ("x", "y", "weights")):
        assert torch.isfinite(a).all()
        assert_close(a, b, 1e-9 * max(1.0, b.abs().max().item()), f"d/d{name}")


def test_torch_func_vmap_and_grad():
    """vmap over problems equals the batched call; func.grad equals autograd
    (the value checks are skipped inside the transforms)."""
    x, y, _ = registration_problem((4,), n=10, seed=23, noise=0.3)
    w = torch.rand(4, 10, generator=torch.Generator().manual_seed(24), dtype=torch.float64) + 0.1

    def fn(x, y, w):
        return tuple(torchrot.rigid_registration(x, y, w, scale=True))

    for a, b in zip(torch.func.vmap(fn)(x, y, w), fn(x, y, w)):
        assert_close(a, b, 1e-13, "vmap")
    grad = torch.func.grad(lambda x: torchrot.rigid_registration(x, y[0], w[0], scale=True).t.sum())(x[0])
    leaf = x[0].clone().requires_grad_()
    torchrot.rigid_registration(leaf, y[0], w[0], scale=True).t.sum().backward()
    assert_close(grad, leaf.grad, 1e-13, "func.grad")
