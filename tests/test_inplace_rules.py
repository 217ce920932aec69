"""out= is an in-place operation under torch's rules, on the C++ kernel and on
the device-generic path alike, through fit_rotation, the operator and
fit_orthogonal: out's version counter is bumped once per
write (so autograd refuses to differentiate through a result it overwrote),
no call that would record a derivative is accepted (M or out requiring grad in
grad mode, a forward-mode tangent, torch.func.grad), an inference tensor is
written only in inference mode, and every refusal leaves every tensor as it
was. fit_rotation_info's outputs never require grad.

Convention: R (det +1) maximises tr(R^T M); column vectors.
"""
from __future__ import annotations

import warnings

import pytest
import torch
from kernel_paths import KERNEL_PATHS, kernel_path_params
from torch.autograd import forward_ad

import torchrot
from torchrot.testing import bits, make_warm_start

N = 37  # a full SIMD block and a tail


def _fit_out(M, init, out):
    return torchrot.fit_rotation(M, init, max_iter=1, out=out)


def _op_out(M, init, out):
    torch.ops.torchrot.fit_rotation_out(M, init, 1, "conservative", out)
    return out


def _orthogonal_out(M, init, out):
    return torchrot.fit_orthogonal(M, init, max_iter=1, out=out)


CALLS = {"fit_rotation": _fit_out, "op": _op_out, "fit_orthogonal": _orthogonal_out}
#: call -> the fit it writes (without out=)
EXPECTED = {"fit_rotation": torchrot.fit_rotation, "op": torchrot.fit_rotation,
            "fit_orthogonal": torchrot.fit_orthogonal}
AUTOGRAD_ERROR = r"out= does not support automatic differentiation"


def _problem(dtype, seed=3):
    M, init = make_warm_start("warm", N, seed, dtype)
    return M, init


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("call", sorted(CALLS))
@pytest.mark.parametrize("where", ["fresh", "init", "M"])
def test_version_bumped_once_per_write(where, call, kernel, dtype):
    M, init = _problem(dtype)
    out = {"fresh": torch.empty_like(M), "init": init, "M": M}[where]
    before = out._version
    with KERNEL_PATHS[kernel]():
        expected = EXPECTED[call](M.clone(), init.clone(), max_iter=1)
        CALLS[call](M, init, out)
    assert out._version == before + 1
    assert torch.equal(bits(out), bits(expected))


@pytest.mark.parametrize("kernel", kernel_path_params())
def test_overwritten_result_is_not_differentiated(kernel):
    """The issue's case: a result saved for backward, then overwritten in
    place by a warm-started update, must make backward raise (it returned a
    gradient of the overwritten values)."""
    M, init = _problem(torch.float64)
    x = M.clone().requires_grad_()
    with KERNEL_PATHS[kernel]():
        R = torchrot.fit_rotation(x)
        torchrot.fit_rotation(M + 0.1, R.detach(), max_iter=1, out=R.detach())
    # (On the generic path R is a view of the kernel's result, and torch
    # words the same refusal for views.)
    with pytest.raises(RuntimeError, match="modified by an inplace operation|has been modified inplace"):
        R.sum().backward()


def _refused(call, M, init, out, error=ValueError, match=AUTOGRAD_ERROR):
    """``call`` raises and leaves M, init and out bit for bit as they were."""
    tensors = [t for t in (M, init, out) if t is not None]
    saved = [bits(t.detach()).clone() for t in tensors]
    versions = [None if t.is_inference() else t._version for t in tensors]  # (inference tensors have none)
    with pytest.raises(error, match=match):
        call(M, init, out)
    for t, b, v in zip(tensors, saved, versions):
        assert torch.equal(bits(t.detach()), b)
        assert v is None or t._version == v


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("call", sorted(CALLS))
@pytest.mark.parametrize("case", ["leaf out", "non-leaf out", "M", "M is out"])
def test_requires_grad_refused_in_grad_mode(case, call, kernel, dtype):
    M, init = _problem(dtype)
    leaf = torch.zeros_like(M).requires_grad_()
    if case == "leaf out":
        args = (M, init, leaf)
    elif case == "non-leaf out":
        args = (M, init, leaf * 2)  # keeps a grad_fn that the write would make wrong
    elif case == "M":
        args = (M.clone().requires_grad_(), init, torch.empty_like(M))
    else:
        M_leaf = M.clone().requires_grad_()
        args = (M_leaf, init, M_leaf)
    with KERNEL_PATHS[kernel]():
        _refused(CALLS[call], *args)


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("call", sorted(CALLS))
def test_requires_grad_written_under_no_grad(call, kernel, dtype):
    """As torch's out= and in-place operators: under no_grad, a leaf that
    requires grad may be written (its version is bumped)."""
    M, init = _problem(dtype)
    out = torch.zeros_like(M).requires_grad_()
    with KERNEL_PATHS[kernel](), torch.no_grad():
        CALLS[call](M, init, out)
        expected = EXPECTED[call](M, init, max_iter=1)
    assert out._version == 1 and out.requires_grad and out.is_leaf
    assert torch.equal(out.detach(), expected)


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("call", sorted(CALLS))
def test_init_requiring_grad_is_allowed(call, kernel, dtype):
    """No gradient flows to init (the maximiser does not depend on the start),
    so out= accepts an init that requires grad, as fit_rotation records
    nothing for it."""
    M, init = _problem(dtype)
    out = torch.empty_like(M)
    with KERNEL_PATHS[kernel]():
        CALLS[call](M, init.clone().requires_grad_(), out)
        expected = EXPECTED[call](M, init, max_iter=1)
    assert not out.requires_grad
    assert torch.equal(out, expected)


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("call", sorted(CALLS))
@pytest.mark.parametrize("dual", ["M", "out"])
def test_forward_mode_tangent_refused(dual, call, kernel):
    M, init = _problem(torch.float64)
    out = torch.empty_like(M)
    with KERNEL_PATHS[kernel](), forward_ad.dual_level():
        if dual == "M":
            M = forward_ad.make_dual(M, torch.ones_like(M))
        else:
            out = forward_ad.make_dual(out, torch.ones_like(out))
        _refused(CALLS[call], M, init, out)


@pytest.mark.parametrize("kernel", kernel_path_params())
def test_torch_func_grad_refused(kernel, fit):
    M, init = _problem(torch.float64)
    out = torch.zeros_like(M)
    with KERNEL_PATHS[kernel](), pytest.raises(ValueError, match=AUTOGRAD_ERROR):
        torch.func.grad(lambda m: fit.fn(m, init, max_iter=1, out=out).sum())(M)
    assert (out == 0).all()


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("call", sorted(CALLS))
@pytest.mark.parametrize("inputs", ["normal", "inference"])
def test_inference_out_written_only_in_inference_mode(inputs, call, kernel, dtype):
    M, init = _problem(dtype)
    with torch.inference_mode():
        out = torch.zeros_like(M)
        if inputs == "inference":
            M, init = M.clone(), init.clone()
    with KERNEL_PATHS[kernel]():
        _refused(CALLS[call], M, init, out, match="out is an inference tensor")
        with torch.inference_mode():
            CALLS[call](M, init, out)
        expected = EXPECTED[call](M, init, max_iter=1)
    assert torch.equal(out, expected)


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("call", sorted(CALLS))
def test_normal_out_written_in_inference_mode(call, kernel, dtype):
    M, init = _problem(dtype)
    out = torch.zeros_like(M)
    with KERNEL_PATHS[kernel]():
        with torch.inference_mode():
            CALLS[call](M, init, out)
        expected = EXPECTED[call](M, init, max_iter=1)
    assert torch.equal(out, expected)


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("path", ["fit_rotation_info", "op"])
def test_info_outputs_never_require_grad(path, kernel, dtype):
    M, init = _problem(dtype)
    M = M.clone().requires_grad_()
    with KERNEL_PATHS[kernel](), warnings.catch_warnings():
        warnings.simplefilter("error")  # torch's "autograd kernel was not registered" warning
        if path == "op":
            outputs = torch.ops.torchrot.fit_rotation_info(M, init, None, "conservative")
        else:
            outputs = tuple(torchrot.fit_rotation_info(M, init))
        assert not any(t.requires_grad for t in outputs)
        assert all(t.grad_fn is None for t in outputs)
        R = torchrot.fit_rotation(M, init)
        assert torch.equal(outputs[0].detach(), R.detach())
        # A loss of R and of the info's R: the latter contributes nothing.
        (expected,) = torch.autograd.grad(R.sum(), M, retain_graph=True)
        (grad,) = torch.autograd.grad(R.sum() + outputs[0].sum(), M)
        assert torch.equal(grad, expected)


def test_info_outputs_never_require_grad_under_torch_func():
    M, _ = _problem(torch.float64)

    def loss(m):
        info = torchrot.fit_rotation_info(m)
        assert not info.R.requires_grad
        return torchrot.fit_rotation(m).sum() + info.R.sum()

    grad = torch.func.grad(loss)(M)
    expected = torch.func.grad(lambda m: torchrot.fit_rotation(m).sum())(M)
    assert torch.equal(grad, expected)
