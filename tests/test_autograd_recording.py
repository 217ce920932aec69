"""Where a call of fit_rotation records its derivative: the plain
reverse-mode fit in the operator's C++ Autograd kernel (csrc/autograd.cpp),
bit for bit the gradients of the Python Autograd kernel, which still records
calls with a tangent and those of torch.func and traced code; calls with
nothing to record run no Python and record nothing; the eager entry leaves
tensor subclasses and torch function modes to torch.ops; the operator's own
autograd uses gradient_eps.
"""
from __future__ import annotations

import sys

import torch
from autograd_helpers import op
from torch.autograd import forward_ad

import torchrot
from torchrot._constants import GRADIENT_EPS
from torchrot._torch_private import below_autograd
from torchrot.testing import make_matrices, make_warm_start


def test_training_call_records_in_cpp():
    """A plain reverse-mode fit (torchrot.fit_rotation, torch.ops) records its
    derivative in C++, in the operator's Autograd kernel (csrc/autograd.cpp):
    the same gradients, bit for bit, as the Python Autograd kernel (its twin
    operator's, which the C++ kernel hands torch.func, forward-mode and
    traced calls); init gets none."""
    M, init = make_warm_start("warm", 37, seed=5, dtype=torch.float32)
    G = make_matrices("gaussian", 37, seed=6, dtype=torch.float32)
    for kwargs in ({}, {"max_iter": 1}):
        Mc = M.clone().requires_grad_()
        R = torchrot.fit_rotation(Mc, init, **kwargs)
        assert "FitRotationAutograd" in R.grad_fn.name()  # the C++ node
        (g_cpp,) = torch.autograd.grad(R, Mc, G)
        Mp = M.clone().requires_grad_()
        R_py = op._fit_rotation_python_autograd(Mp, init, kwargs.get("max_iter"), "conservative", 1e-6)
        assert "FitRotationFunction" in R_py.grad_fn.name()
        (g_py,) = torch.autograd.grad(R_py, Mp, G)
        assert torch.equal(g_cpp, g_py)


def test_eager_call_without_derivative_records_nothing():
    """The plain eager call with nothing to record (M not requiring grad, also
    with an init that does; or grad mode off) runs the kernel through the same
    C++ operator and returns a result without autograd history, equal bit for
    bit to the operator's."""
    M, init = make_warm_start("warm", 11, seed=7, dtype=torch.float32)
    expected = op.fit_rotation(M, init, None, "conservative", 1e-6)
    cases = [(M, init.clone().requires_grad_(), True), (M.clone().requires_grad_(), init, False)]
    for M_in, init_in, grad_mode in cases:
        with torch.set_grad_enabled(grad_mode):
            R = torchrot.fit_rotation(M_in, init_in)
        assert R.grad_fn is None and not R.requires_grad
        assert torch.equal(R, expected)


def _torchrot_python_calls(fn):
    """fn() and the names of the functions in torchrot/_autograd.py that ran
    during it (this thread's Python calls, through sys.setprofile)."""
    source = torchrot._autograd.__file__
    names = []

    def profile(frame, event, arg):
        if event == "call" and frame.f_code.co_filename == source:
            names.append(frame.f_code.co_name)

    sys.setprofile(profile)
    try:
        result = fn()
    finally:
        sys.setprofile(None)
    return result, names


def _without_grad_mode(fn, *args):
    with torch.no_grad():
        return fn(*args)


def test_operator_calls_run_no_python_unless_a_transform_or_tangent_needs_it():
    """torch.ops.torchrot.fit_rotation and fit_rotation_backward decide in C++
    (csrc/autograd.cpp) what a call records: with nothing to record (grad
    mode off, nothing requiring grad but init, which receives no gradient; no
    tangent, also inside an open dual level) they run below autograd, and a
    fit whose M requires grad records the C++ node of torchrot.fit_rotation's
    plain call, both without a Python frame; the results and gradients are
    those of the Python Autograd kernel, bit for bit, which still records the
    calls with a tangent."""
    M, init = make_warm_start("warm", 9, seed=9, dtype=torch.float64)
    G = make_matrices("gaussian", 9, seed=10, dtype=torch.float64)
    with below_autograd():
        R = op.fit_rotation(M, init)
        tangent = op.fit_rotation_backward(G, R, M)
    quiet = {
        "plain": lambda: op.fit_rotation(M, init),
        "defaults": lambda: op.fit_rotation.default(M, init),
        "grad mode off": lambda: _without_grad_mode(op.fit_rotation, M.clone().requires_grad_(), init),
        "backward": lambda: op.fit_rotation_backward(G, R, M),
    }
    for name, call in quiet.items():
        result, python = _torchrot_python_calls(call)
        expected = tangent if name == "backward" else R
        assert python == [] and result.grad_fn is None and torch.equal(result, expected), name
    with forward_ad.dual_level():
        result, python = _torchrot_python_calls(lambda: op.fit_rotation(M, init))
        assert python == [] and forward_ad.unpack_dual(result).tangent is None and torch.equal(result, R)
        dual = forward_ad.make_dual(M, G)
        result, python = _torchrot_python_calls(lambda: op.fit_rotation(dual, init))
        assert "kernel" in python and torch.equal(forward_ad.unpack_dual(result).tangent, tangent)

    Mg = M.clone().requires_grad_()
    for init_in in (init, init.clone().requires_grad_()):
        result, python = _torchrot_python_calls(lambda init_in=init_in: op.fit_rotation(Mg, init_in))
        assert python == [] and "FitRotationAutograd" in result.grad_fn.name() and torch.equal(result.detach(), R)
        (g,) = torch.autograd.grad(result, Mg, G)
        assert torch.equal(g, tangent)
    # init receives no gradient: where only init requires grad, nothing is
    # recorded, as through torchrot.fit_rotation and under torch.compile.
    init_g = init.clone().requires_grad_()
    result, python = _torchrot_python_calls(lambda: op.fit_rotation(M, init_g))
    assert python == [] and result.grad_fn is None and torch.equal(result, R)
    for fit in (torchrot.fit_rotation, torch.compile(torchrot.fit_rotation, fullgraph=True)):
        assert not fit(M, init_g).requires_grad

    # A torch.compile'd training step: traced through the Python kernel, its
    # graphs then call both operators with grad mode off.
    compiled = torch.compile(lambda M, init: op.fit_rotation(M, init) * 2, fullgraph=True)
    step = lambda: torch.autograd.grad(compiled(Mg, init), Mg, G)  # noqa: E731
    step()
    (g,), python = _torchrot_python_calls(step)
    assert python == [] and torch.equal(g, 2 * tangent)


def test_eager_entry_leaves_subclasses_and_modes_to_torch_ops():
    """The plain eager call's direct entry (torchrot._C.fit_rotation_eager,
    with out= too) declines, before doing anything, what torch.ops handles: a
    tensor subclass's __torch_function__, an active torch function mode,
    max_iter beyond int64. fit_rotation then calls the operator through
    torch.ops: the mode sees that call and the subclass survives; the results
    are the same, and out= returns out itself."""
    M, init = make_warm_start("warm", 7, seed=8, dtype=torch.float32)
    expected = op.fit_rotation(M, init, None, "conservative", GRADIENT_EPS)
    entry = torchrot._C.fit_rotation_eager
    args = (None, "conservative", GRADIENT_EPS)
    assert torch.equal(entry(M, init, *args, None), expected)
    out = torch.empty_like(M)
    assert entry(M, init, *args, out) is out and torch.equal(out, expected)

    class Sub(torch.Tensor):
        pass

    declined = [(M.as_subclass(Sub), init, *args, None), (M, init.as_subclass(Sub), *args, None),
                (M, init, 2**63, "conservative", GRADIENT_EPS, None), (M, init, *args, out.as_subclass(Sub))]
    for call in declined:
        assert entry(*call) is NotImplemented
    R = torchrot.fit_rotation(M.as_subclass(Sub), init)
    assert type(R) is Sub and torch.equal(R.as_subclass(torch.Tensor), expected)
    out_sub = torch.zeros_like(M).as_subclass(Sub)
    assert torchrot.fit_rotation(M, init, out=out_sub) is out_sub and torch.equal(out_sub.as_subclass(torch.Tensor),
                                                                                  expected)

    class Recorder(torch.overrides.TorchFunctionMode):
        def __init__(self):
            super().__init__()
            self.calls = []

        def __torch_function__(self, func, types, args=(), kwargs=None):
            self.calls.append(func)
            return func(*args, **(kwargs or {}))

    out = torch.zeros_like(M)
    with Recorder() as mode:
        assert entry(M, init, *args, None) is NotImplemented
        assert entry(M, init, *args, out) is NotImplemented
        R = torchrot.fit_rotation(M, init)
        assert torchrot.fit_rotation(M, init, out=out) is out
    assert op.fit_rotation.default in mode.calls and op.fit_rotation_out.default in mode.calls
    assert torch.equal(R, expected) and torch.equal(out, expected)


def test_op_level_autograd_uses_gradient_eps():
    M = torch.diag(torch.tensor([2.0, 1.0, -1.0], dtype=torch.float64)).requires_grad_()
    G = torch.ones(3, 3, dtype=torch.float64)
    for eps in (1e-3, 1e-1):
        (g_op,) = torch.autograd.grad(op.fit_rotation(M, None, None, "conservative", eps), M, G)
        (g_api,) = torch.autograd.grad(torchrot.fit_rotation(M, gradient_eps=eps), M, G)
        torch.testing.assert_close(g_op, g_api, rtol=0, atol=0)
