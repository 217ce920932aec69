"""Bad arguments: every row of docs/errors.md, raised with the documented
exception type and a message naming the argument (tests/test_api.py covers
the shape/dtype/broadcast/out cases of fit_rotation in depth; this file adds
the hardening audit: None, non-tensors, out-of-range options, the derivative
operator, the references, and checks the docs table against these cases).

Convention: R (det +1) maximises tr(R^T M); column vectors.
"""
from __future__ import annotations

import math
import os
import pathlib
import re
import subprocess
import sys

import numpy as np
import pytest
import torch
from kernel_paths import KERNEL_PATHS, kernel_path_params

import torchrot
from torchrot._constants import MAX_GRADIENT_EPS, MAX_ITER
from torchrot.testing import make_matrices

op = torch.ops.torchrot
M = make_matrices("gaussian", 4, 0, torch.float32)
R = torchrot.fit_rotation(M)
DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs" / "errors.md"


def _inference_tensor(like):
    with torch.inference_mode():
        return torch.empty_like(like)


def _backward(grad=R, R_=R, M_=M, eps=1e-6):
    return op.fit_rotation_backward(grad, R_, M_, eps)


# id -> (call, exception type, regex the message must match)
CASES = {
    # M
    "fit-M-none": (lambda: torchrot.fit_rotation(None), TypeError, r"\bM\b.*Tensor"),
    "fit-M-none-with-init": (lambda: torchrot.fit_rotation(None, R), TypeError, r"\bM\b.*Tensor, got NoneType"),
    "fit-M-ndarray": (lambda: torchrot.fit_rotation(np.eye(3)), TypeError, r"\bM\b.*Tensor, got ndarray"),
    "fit-M-list": (lambda: torchrot.fit_rotation([[1.0, 0, 0]] * 3), TypeError, r"\bM\b.*Tensor, got list"),
    "fit-M-shape": (lambda: torchrot.fit_rotation(torch.randn(4, 4)), ValueError, r"\bM\b.*\(\.\.\., 3, 3\)"),
    "fit-M-dtype": (lambda: torchrot.fit_rotation(M.int()), TypeError, r"\bM\b.*float32.*got torch\.int32"),
    "fit-M-sparse": (lambda: torchrot.fit_rotation(torch.eye(3).to_sparse()), NotImplementedError, r"Sparse"),
    # init
    "fit-init-ndarray": (lambda: torchrot.fit_rotation(M, np.eye(3)), TypeError, r"\binit\b.*Tensor, got ndarray"),
    "fit-init-not-rotation": (lambda: torchrot.fit_rotation(M, 2 * R), ValueError,
                              r"\binit\b must hold rotations.*4 of 4 are not"),
    # max_iter
    "fit-max_iter-zero": (lambda: torchrot.fit_rotation(M, max_iter=0), ValueError, r"max_iter.*>= 1"),
    "fit-max_iter-too-large": (lambda: torchrot.fit_rotation(M, max_iter=1001), ValueError,
                               r"max_iter.*<= 1000"),
    "op-max_iter-huge": (lambda: op.fit_rotation(M, None, 2**62, "newton"), ValueError, r"max_iter.*<= 1000"),
    "fit-max_iter-enormous": (lambda: torchrot.fit_rotation(M, max_iter=2**70), ValueError, r"max_iter.*<= 1000"),
    "fit-max_iter-float": (lambda: torchrot.fit_rotation(M, max_iter=2.0), TypeError, r"max_iter.*int"),
    "fit-max_iter-bool": (lambda: torchrot.fit_rotation(M, max_iter=True), TypeError, r"max_iter.*int"),
    "reference-max_iter-too-large": (lambda: torchrot.fit_rotation_reference(M, max_iter=10**6), ValueError,
                                     r"max_iter.*<= 1000"),
    # variant
    "fit-variant-unknown": (lambda: torchrot.fit_rotation(M, variant="Newton"), ValueError,
                            r"variant.*'newton', 'conservative', 'gershgorin', got 'Newton'"),
    "fit-variant-none": (lambda: torchrot.fit_rotation(M, variant=None), TypeError, r"variant must be a str"),
    # gradient_eps
    "fit-gradient_eps-negative": (lambda: torchrot.fit_rotation(M, gradient_eps=-1e-6), ValueError,
                                  r"gradient_eps.*>= 0 and <= 1000"),
    "fit-gradient_eps-nan": (lambda: torchrot.fit_rotation(M, gradient_eps=math.nan), ValueError,
                             r"gradient_eps.*finite"),
    "fit-gradient_eps-too-large": (lambda: torchrot.fit_rotation(M, gradient_eps=1e4), ValueError,
                                   r"gradient_eps.*<= 1000, got 10000"),
    "fit-gradient_eps-str": (lambda: torchrot.fit_rotation(M, gradient_eps="1e-6"), TypeError,
                             r"gradient_eps.*float"),
    "op-gradient_eps-too-large": (lambda: op.fit_rotation(M, None, None, "newton", 1e4), ValueError,
                                  r"gradient_eps.*<= 1000"),
    # out
    "op-out-none": (lambda: op.fit_rotation_out(M, None, None, "newton", None), TypeError,
                    r"\bout\b must be a torch.Tensor, got NoneType"),
    "fit-out-ndarray": (lambda: torchrot.fit_rotation(M, out=np.empty((4, 3, 3), np.float32)), TypeError,
                        r"\bout\b must be a torch.Tensor, got ndarray"),
    "fit-out-overlapping": (lambda: torchrot.fit_rotation(M, out=torch.empty(1, 3, 3).expand(4, 3, 3)), ValueError,
                            r"\bout\b must not have overlapping elements"),
    "fit-out-requires-grad": (lambda: torchrot.fit_rotation(M.clone().requires_grad_(), out=torch.empty_like(M)),
                              ValueError, r"out= does not support automatic differentiation"),
    "fit-out-is-leaf-requiring-grad": (lambda: torchrot.fit_rotation(M, out=torch.empty_like(M).requires_grad_()),
                                       ValueError, r"out= does not support automatic differentiation"),
    "op-out-inference": (lambda: op.fit_rotation_out(M, None, None, "newton", _inference_tensor(M)), ValueError,
                         r"\bout\b is an inference tensor.*inside torch\.inference_mode\(\)"),
    # fit_rotation_backward
    "backward-grad-none": (lambda: _backward(grad=None), TypeError, r"\bgrad\b must be a torch.Tensor, got NoneType"),
    "backward-R-none": (lambda: _backward(R_=None), TypeError, r"\bR\b must be a torch.Tensor, got NoneType"),
    "backward-M-none": (lambda: _backward(M_=None), TypeError, r"\bM\b must be a torch.Tensor, got NoneType"),
    "backward-grad-shape": (lambda: _backward(grad=R[:3]), ValueError, r"\bgrad\b.*R's shape"),
    "backward-M-broadcast": (lambda: _backward(M_=M[:3]), ValueError, r"\bM\b.*broadcast"),
    "backward-dtype": (lambda: _backward(grad=R.double()), TypeError, r"\bgrad\b.*dtype"),
    "backward-R-dtype": (lambda: _backward(grad=R.int(), R_=R.int(), M_=M.int()), TypeError, r"\bR\b.*float32"),
    "backward-gradient_eps": (lambda: _backward(eps=-1.0), ValueError, r"gradient_eps.*>= 0"),
    # references
    "reference-M-ndarray": (lambda: torchrot.fit_rotation_reference(np.eye(3)), TypeError, r"\bM\b.*Tensor"),
    "rotation_svd-M-shape": (lambda: torchrot.rotation_svd(torch.randn(4, 4)), ValueError,
                             r"rotation_svd: M.*\(\.\.\., 3, 3\)"),
    "rotation_svd-M-ndarray": (lambda: torchrot.rotation_svd(np.eye(3)), TypeError, r"rotation_svd: M.*Tensor"),
    # torch.ops parses arguments against the schema before any torchrot code runs
    "op-init-ndarray": (lambda: op.fit_rotation(M, np.eye(3)), RuntimeError, r"argument 'init'"),
    # fit_orthogonal: fit_rotation's checks, naming it, and its own for init
    "orthogonal-M-shape": (lambda: torchrot.fit_orthogonal(torch.randn(4, 4)), ValueError,
                           r"^torchrot\.fit_orthogonal: M must have shape \(\.\.\., 3, 3\)"),
    "orthogonal-init-not-orthogonal": (lambda: torchrot.fit_orthogonal(M, 2 * R), ValueError,
                                       r"^torchrot\.fit_orthogonal: init must hold orthogonal matrices.*4 of 4"),
    "orthogonal-variant-unknown": (lambda: torchrot.fit_orthogonal(M, variant="Newton"), ValueError,
                                   r"^torchrot\.fit_orthogonal: variant must be one of"),
    "orthogonal-out-requires-grad": (lambda: torchrot.fit_orthogonal(M.clone().requires_grad_(),
                                                                     out=torch.empty_like(M)),
                                     ValueError, r"^torchrot\.fit_orthogonal: out= does not support"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_argument_raises_naming_it(case):
    call, exception, pattern = CASES[case]
    with pytest.raises(exception, match=pattern) as excinfo:
        call()
    assert type(excinfo.value) is exception, f"{type(excinfo.value).__name__}: {excinfo.value}"


def test_environment_variable_error_names_it():
    """TORCHROT_CPU_CAPABILITY is read once, at import: a bad value fails it."""
    env = dict(os.environ, TORCHROT_CPU_CAPABILITY="sse2")
    proc = subprocess.run([sys.executable, "-c", "import torchrot"], env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode != 0
    assert "ValueError: TORCHROT_CPU_CAPABILITY must be one of scalar, default, avx2, avx512; got 'sse2'" in (
        proc.stderr
    )


def test_limits_are_accepted():
    """The largest accepted max_iter and gradient_eps work (finite results)."""
    X = M.double().clone().requires_grad_()
    R_ = torchrot.fit_rotation(X, max_iter=MAX_ITER, gradient_eps=MAX_GRADIENT_EPS)
    R_.sum().backward()
    assert torch.isfinite(R_).all() and torch.isfinite(X.grad).all()


# ---- one error model: every path raises the same type with the same message ----

# id -> (operator, arguments): bad calls of torch.ops.torchrot.*, run on every
# kernel: the C++ CPU kernel, the fake (meta) kernel, the device-generic kernel.
ROT = R.double()
M64 = M.double()
OP_CASES = {
    "M-shape": ("fit_rotation", (torch.randn(4, 4), None, None, "newton", 1e-6)),
    "M-0d": ("fit_rotation", (torch.tensor(1.0), None, None, "newton", 1e-6)),
    "M-dtype": ("fit_rotation", (M.int(), None, None, "newton", 1e-6)),
    "init-shape": ("fit_rotation", (M, torch.eye(2), None, "newton", 1e-6)),
    "init-dtype": ("fit_rotation", (M, ROT.int(), None, "newton", 1e-6)),
    "init-broadcast": ("fit_rotation", (M, R[:3], None, "newton", 1e-6)),
    "init-not-rotation": ("fit_rotation", (M, 2 * R, None, "newton", 1e-6)),
    "init-one-reflection": ("fit_rotation_info", (M64, torch.cat([ROT[:3], -ROT[3:]]), 1, "newton")),
    "init-not-rotation-broadcast": ("fit_rotation", (M, 2 * R[:1], 1, "newton", 1e-6)),
    "max_iter-zero": ("fit_rotation", (M, None, 0, "newton", 1e-6)),
    "max_iter-large": ("fit_rotation_info", (M, None, 1001, "newton")),
    "variant": ("fit_rotation", (M, None, None, "Newton", 1e-6)),
    "gradient_eps-negative": ("fit_rotation", (M, None, None, "newton", -1e-6)),
    "gradient_eps-nan": ("fit_rotation", (M, None, None, "newton", math.nan)),
    "gradient_eps-inf": ("fit_rotation", (M, None, None, "newton", math.inf)),
    "gradient_eps-large": ("fit_rotation", (M, None, None, "newton", 1e4)),
    "shape-before-variant": ("fit_rotation", (torch.randn(4, 4), None, 0, "Newton", -1.0)),
    "out-shape": ("fit_rotation_out", (M, None, None, "newton", torch.empty(3, 3, 3))),
    "out-dtype": ("fit_rotation_out", (M, None, None, "newton", torch.empty(4, 3, 3, dtype=torch.float64))),
    "out-expanded": ("fit_rotation_out", (M, None, None, "newton", torch.empty(3, 3).expand(4, 3, 3))),
    "out-overlapping-strides": ("fit_rotation_out",
                                (M, None, None, "newton", torch.empty(20).as_strided((4, 3, 3), (1, 3, 1)))),
    "out-init-not-rotation": ("fit_rotation_out", (M, 2 * R, 1, "newton", torch.empty_like(M))),
    "backward-R-dtype": ("fit_rotation_backward", (R.int(), R.int(), M.int(), 1e-6)),
    "backward-grad-dtype": ("fit_rotation_backward", (ROT, R, M, 1e-6)),
    "backward-grad-shape": ("fit_rotation_backward", (R[:3], R, M, 1e-6)),
    "backward-M-shape": ("fit_rotation_backward", (R, R, torch.randn(4, 4), 1e-6)),
    "backward-M-broadcast": ("fit_rotation_backward", (R, R, M[:3], 1e-6)),
    "backward-gradient_eps": ("fit_rotation_backward", (R, R, M, -1.0)),
}
# value checks need the data: the fake kernel cannot make them
DATA_DEPENDENT = {"init-not-rotation", "init-one-reflection", "init-not-rotation-broadcast", "out-init-not-rotation"}


def _error(call) -> tuple[type, str]:
    try:
        call()
    except Exception as error:  # noqa: BLE001 (the type is what is compared)
        return type(error), str(error)
    raise AssertionError("no error")


def _to_meta(args):
    """The arguments on the meta device, with their strides (overlaps included)."""
    return tuple(
        torch.empty_strided(a.shape, a.stride(), dtype=a.dtype, device="meta") if isinstance(a, torch.Tensor) else a
        for a in args
    )


@pytest.mark.parametrize("kernel", kernel_path_params("generic", "triton"))
@pytest.mark.parametrize("case", sorted(OP_CASES))
def test_every_kernel_raises_the_same_error(case, kernel):
    """The C++ CPU kernel, the fake (meta) kernel and the device-generic and
    Triton kernels raise the same exception type with the same message."""
    name, args = OP_CASES[case]
    call = getattr(op, name)
    cpu = _error(lambda: call(*args))
    assert cpu[0] in (TypeError, ValueError), cpu
    with KERNEL_PATHS[kernel]():
        assert _error(lambda: call(*args)) == cpu
    if case not in DATA_DEPENDENT:
        assert _error(lambda: call(*_to_meta(args))) == cpu


@pytest.mark.parametrize("kernel", kernel_path_params())
def test_errors_change_nothing_on_any_kernel(kernel, fit):
    """A raising fit_rotation_out (or fit_orthogonal's out=) leaves out, M and init as they were."""
    init = R.clone()
    init[2] *= 2  # one bad warm start: the in-place update must not touch the others
    M_ = M.clone()
    before = (init.clone(), M_.clone())
    with KERNEL_PATHS[kernel]():
        with pytest.raises(ValueError, match="1 of 4 are not"):
            fit.fn(M_, init, max_iter=1, out=init)
        with pytest.raises(ValueError, match="1 of 4 are not"):
            fit.fn(M_, init, max_iter=1, out=M_)
    assert torch.equal(init, before[0]) and torch.equal(M_, before[1])


# (wrapper call, exception type) under torch.compile: the wrapper checks its
# arguments itself while traced, so the error is the eager one, not one the
# tracer wraps around the fake kernel's.
COMPILE_CASES = {
    "M-shape": lambda m: torchrot.fit_rotation(m.reshape(4, 9)),
    "variant": lambda m: torchrot.fit_rotation(m, variant="Newton"),
    "max_iter": lambda m: torchrot.fit_rotation(m, max_iter=0),
    "gradient_eps": lambda m: torchrot.fit_rotation(m, gradient_eps=-1.0),
    "init-dtype": lambda m: torchrot.fit_rotation(m, ROT.int()),
    "out-dtype": lambda m: torchrot.fit_rotation(m, out=torch.empty(4, 3, 3, dtype=torch.float64)),
    "info-variant": lambda m: torchrot.fit_rotation_info(m, variant="x"),
    "orthogonal-variant": lambda m: torchrot.fit_orthogonal(m, variant="Newton"),
    "orthogonal-out-dtype": lambda m: torchrot.fit_orthogonal(m, out=torch.empty(4, 3, 3, dtype=torch.float64)),
}


@pytest.mark.parametrize("case", sorted(COMPILE_CASES))
def test_compiled_wrapper_raises_the_eager_error(case):
    fn = COMPILE_CASES[case]
    eager = _error(lambda: fn(M))
    assert eager[0] in (TypeError, ValueError)
    torch._dynamo.reset()
    assert _error(lambda: torch.compile(fn)(M)) == eager
    # fullgraph: torch reports any exception raised in traced code as
    # Unsupported ("Observed exception"); the original is its cause
    torch._dynamo.reset()
    kind, message = _error(lambda: torch.compile(fn, fullgraph=True)(M))
    assert issubclass(kind, torch._dynamo.exc.Unsupported) and eager[1] in message


def _documented_ids() -> list[str]:
    """First-column ids of the tables in docs/errors.md (rows like ``| `id` | ...``)."""
    return re.findall(r"^\|\s*`([a-z_A-Z-]+)`\s*\|", DOCS.read_text(), flags=re.MULTILINE)


def test_docs_table_matches_the_cases():
    """Every documented error is tested here, and every tested one documented."""
    documented = _documented_ids()
    assert len(documented) == len(set(documented)), "duplicate ids in docs/errors.md"
    tested = set(CASES) | {"env-TORCHROT_CPU_CAPABILITY"}
    assert set(documented) == tested, (
        f"only in docs: {sorted(set(documented) - tested)}; only in tests: {sorted(tested - set(documented))}"
    )


def test_wrapper_reports_the_first_bad_argument_as_the_operator_does():
    """With several bad arguments, torchrot.fit_rotation raises what the
    operator raises (its checks run in the operator's order)."""
    bad_M = torch.randn(4, 4)
    for kwargs in ({"gradient_eps": -1.0}, {"max_iter": 0, "gradient_eps": -1.0}, {"variant": "x"}):
        args = (bad_M, None, kwargs.get("max_iter"), kwargs.get("variant", "newton"), kwargs.get("gradient_eps", 1e-6))
        assert _error(lambda kwargs=kwargs: torchrot.fit_rotation(bad_M, **kwargs)) == _error(
            lambda args=args: op.fit_rotation(*args))
    out = torch.empty(4, 3, 3)
    assert _error(lambda: torchrot.fit_rotation(M, variant="x", gradient_eps=-1.0, out=out)) == _error(
        lambda: op.fit_rotation_out(M, None, None, "x", out))
