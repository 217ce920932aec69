"""Aliasing: ``out`` may be M or init itself; any other overlap with them, in
any layout (offset, strided, transposed, expanded, permuted batch views), is
computed through a temporary, so the result is bit for bit the fit into a
fresh tensor. The derivative operator's arguments may alias each other.
Both the C++ kernel and the device-generic kernel (torchrot.testing.generic_kernel),
for fit_rotation and fit_orthogonal (the ``fit`` fixture).

Convention: R (det +1) maximises tr(R^T M); column vectors.
"""
from __future__ import annotations

import pytest
import torch
from kernel_paths import KERNEL_PATHS, kernel_path_params

import torchrot
from torchrot.testing import make_matrices, rotations

op = torch.ops.torchrot


# id -> builder of (base, M view, init view or None, out view) over one
# buffer `base` of 3x3 matrices; every view is into `base`.
def _offset(base):  # out one matrix further than M: partial overlap
    return base[0:64], None, base[1:65]


def _interleaved_same(base):  # the case: every other matrix, shifted by one step
    return base[0:128:2], None, base[2:130:2]


def _interleaved_disjoint(base):  # no shared element, but interleaved ranges
    return base[0:128:2], None, base[1:129:2]


def _transposed(base):  # the same elements in another layout
    return base[:64], None, base[:64].mT


def _batch_permuted(base):  # (8, 8) batch, out with its batch dims swapped
    grid = base[:64].view(8, 8, 3, 3)
    return grid, None, grid.transpose(0, 1)


def _init_offset(base):  # in-place warm start, shifted: out partially overlaps init
    return None, base[0:64], base[1:65]


def _init_expanded(base):  # one warm start for all, and it is out's first matrix
    return None, base[0:1].expand(64, 3, 3), base[0:64]


def _init_transposed(base):  # out is init transposed (R^T is a rotation too)
    return None, base[:64], base[:64].mT


def _both(base):  # out overlaps M and init
    return base[0:64], base[32:96], base[16:80]


LAYOUTS = {f.__name__.lstrip("_"): f for f in (
    _offset, _interleaved_same, _interleaved_disjoint, _transposed, _batch_permuted,
    _init_offset, _init_expanded, _init_transposed, _both,
)}


def _case(layout: str, dtype):
    """(base, M, init, out): M comes from base where the layout puts it there,
    else it is a separate tensor; base holds rotations where init is a view."""
    base = make_matrices("gaussian", 130, 11, torch.float64).to(dtype)
    views = LAYOUTS[layout](base)
    if views[1] is not None:  # init is a view into base: make base hold rotations
        base.copy_(rotations(130, 12, dtype))
    M, init, out = views
    if M is None:
        M = make_matrices("warm", out.shape[0], 13, torch.float64).to(dtype)
    return base, M, init, out


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("max_iter", [None, 1])
@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_overlapping_out_gives_the_fresh_result(layout, max_iter, kernel, dtype, fit):
    base, M, init, out = _case(layout, dtype)
    with KERNEL_PATHS[kernel]():
        # the answer: the same fit from copies of the inputs into a fresh tensor
        expected = fit.fn(M.clone(), None if init is None else init.clone(), max_iter=max_iter)
        fit.fn(M, init, max_iter=max_iter, out=out)
    if kernel == "cpu":
        assert torch.equal(out, expected)
    else:  # batched PyTorch: rounding may depend on the operands' layout
        torch.testing.assert_close(out, expected, rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-14)


@pytest.mark.parametrize("low", [torch.float16, torch.bfloat16], ids=str)
def test_overlapping_out_reduced_precision(low, fit):
    base = make_matrices("gaussian", 130, 14, torch.float64).to(low)
    M, out = base[0:128:2], base[2:130:2]
    expected = fit.fn(M.clone())
    fit.fn(M, out=out)
    assert torch.equal(out, expected)


@pytest.mark.parametrize("kernel", kernel_path_params())
def test_exact_identity_is_in_place(kernel, dtype, fit):
    """out = M and out = init (the in-place warm-start update) need no copy."""
    M = make_matrices("warm", 50, 15, torch.float64).to(dtype)
    init = rotations(50, 16, dtype)
    with KERNEL_PATHS[kernel]():
        expected_M = fit.fn(M)
        expected_init = fit.fn(M, init, max_iter=1)
        M_, init_ = M.clone(), init.clone()
        fit.fn(M_, out=M_)
        fit.fn(M, init_, max_iter=1, out=init_)
    assert torch.equal(M_, expected_M) and torch.equal(init_, expected_init)


def test_out_from_another_storage_on_the_same_memory(fit):
    """Two tensors over the same memory without sharing a storage (NumPy views)."""
    import numpy as np

    array = make_matrices("gaussian", 65, 17, torch.float64).numpy()
    M, out = torch.from_numpy(array[0:64]), torch.from_numpy(np.asarray(array)[1:65])
    expected = fit.fn(M.clone())
    fit.fn(M, out=out)
    assert torch.equal(out, expected)


@pytest.mark.parametrize("kernel", kernel_path_params())
def test_backward_arguments_may_alias(kernel, dtype):
    """grad, R and M of the derivative operator may be one tensor or views of
    one another: they are only read."""
    M = make_matrices("gaussian", 40, 18, torch.float64).to(dtype)
    R = torchrot.fit_rotation(M)
    with KERNEL_PATHS[kernel]():
        for grad, R_, M_ in ((M, R, M), (R, R, M), (R.mT, R, R), (M[:1].expand(40, 3, 3), R, M[:1])):
            expected = op.fit_rotation_backward(grad.clone(), R_.clone(), M_.clone(), 1e-6)
            assert torch.equal(op.fit_rotation_backward(grad, R_, M_, 1e-6), expected)


def test_failed_call_leaves_overlapping_out_untouched(fit):
    """A bad warm start raises before anything is written, also through the temporary."""
    base = rotations(65, 19, torch.float64)
    base[40] *= 2
    before = base.clone()
    with pytest.raises(ValueError, match="1 of 64 are not"):
        fit.fn(make_matrices("warm", 64, 20), base[0:64], max_iter=1, out=base[1:65])
    assert torch.equal(base, before)
