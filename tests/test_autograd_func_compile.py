"""Derivatives of fit_rotation under torch.func (grad, vmap, jacrev, jacfwd,
jvp), forward-mode AD, torch.compile (fullgraph backward) and autocast, and
opcheck of the derivative operator and of the autograd registration.
"""
from __future__ import annotations

import pytest
import torch
from autograd_helpers import _backward_case, _svd_gradient, op
from torch.func import grad, jacfwd, jacrev, jvp, vmap

import torchrot
from torchrot.testing import make_matrices, make_warm_start

# ---------------------------------------------------------------------------
# torch.func, torch.compile, autocast, forward mode
# ---------------------------------------------------------------------------


def _weights():
    return torch.arange(1.0, 10.0, dtype=torch.float64).view(3, 3)


def _loss(M):
    return (torchrot.fit_rotation(M) * _weights()).sum()


def test_func_grad_and_vmap():
    M = make_matrices("rot60", 8, seed=2)
    per_matrix = vmap(grad(_loss))(M)
    for i in range(8):
        expected = _svd_gradient(M[i], _weights().expand(3, 3))
        torch.testing.assert_close(per_matrix[i], expected, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("transform", [jacrev, jacfwd], ids=["jacrev", "jacfwd"])
def test_func_jacobians_match_svd(transform):
    M = make_matrices("uniform", 1, seed=3)[0]
    J = transform(torchrot.fit_rotation)(M)
    J_svd = jacrev(torchrot.rotation_svd)(M)
    torch.testing.assert_close(J, J_svd, rtol=1e-9, atol=1e-10)


def test_func_jvp_and_forward_ad():
    M = make_matrices("gaussian", 5, seed=4)
    dM = torch.randn(M.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    R, dR = jvp(torchrot.fit_rotation, (M,), (dM,))
    _, dR_svd = jvp(torchrot.rotation_svd, (M,), (dM,))
    torch.testing.assert_close(R, torchrot.fit_rotation(M))
    torch.testing.assert_close(dR, dR_svd, rtol=1e-8, atol=1e-10)
    import torch.autograd.forward_ad as fwAD

    with fwAD.dual_level():
        out = torchrot.fit_rotation(fwAD.make_dual(M, dM))
        torch.testing.assert_close(fwAD.unpack_dual(out).tangent, dR, rtol=0, atol=0)


def test_vmap_with_batched_init():
    M, init = make_warm_start("warm", 12, seed=5)
    M, init = M.view(3, 4, 3, 3), init.view(3, 4, 3, 3)
    for in_dims, args in (((0, 0), (M, init)), ((None, 0), (M[0], init)), ((0, None), (M, init[0, 0]))):
        got = vmap(lambda m, r: torchrot.fit_rotation(m, r), in_dims=in_dims)(*args)
        m_i, r_i = ([a[i] if d is not None else a for i in range(3)] for a, d in zip(args, in_dims))
        expected = torch.stack([torchrot.fit_rotation(m, r) for m, r in zip(m_i, r_i)])
        assert torch.equal(got, expected)


def test_compile_fullgraph_backward(fit):
    torch._dynamo.reset()
    M = make_matrices("gaussian", 16, seed=1, dtype=torch.float32)

    def loss(m, eps):
        return (fit.fn(m, gradient_eps=eps) * m).sum()

    compiled = torch.compile(loss, fullgraph=True)
    for eps in (1e-6, 0.3):
        Mc = M.clone().requires_grad_()
        compiled(Mc, eps).backward()
        Me = M.clone().requires_grad_()
        loss(Me, eps).backward()
        torch.testing.assert_close(Mc.grad, Me.grad)


def test_autocast_runs_in_float32(fit):
    M = make_matrices("gaussian", 8, seed=2, dtype=torch.float32).requires_grad_()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        x = torch.nn.functional.linear(M.view(8, 9), torch.eye(9)).view(8, 3, 3)  # bf16 under autocast
        assert x.dtype == torch.bfloat16
        R = fit.fn(x)
        R_op = op.fit_rotation(x.detach())
    assert R.dtype == torch.float32 and R_op.dtype == torch.float32
    R.sum().backward()
    assert M.grad.dtype == torch.float32 and torch.isfinite(M.grad).all()


def test_opcheck_backward_and_autograd_registration():
    G, R, M = _backward_case(6, torch.float64)
    torch.library.opcheck(op.fit_rotation_backward.default, (G, R, M, 1e-6))
    torch.library.opcheck(op.fit_rotation.default, (M.clone().requires_grad_(), None, None, "conservative", 1e-6))
