"""Bad arguments: every row of docs/errors.md, raised with the documented
exception type and a message naming the argument (tests/test_api.py covers
the shape/dtype/broadcast/out cases of fit_rotation in depth; this file adds
the hardening audit: None, non-tensors, out-of-range options, the derivative
operator, the references, and checks the docs table against these cases).

Convention: R (det +1) maximises tr(R^T M); column vectors.
"""
from __future__ import annotations

import math
import pathlib
import re

import numpy as np
import pytest
import torch

import torchrot
from torchrot.testing import make_matrices

op = torch.ops.torchrot
M = make_matrices("gaussian", 4, 0, torch.float32)
R = torchrot.fit_rotation(M)
DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs" / "errors.md"


def _backward(grad=R, R_=R, M_=M, eps=1e-6):
    return op.fit_rotation_backward(grad, R_, M_, eps)


# id -> (call, exception types, regex the message must match)
CASES = {
    # M
    "fit-M-none": (lambda: torchrot.fit_rotation(None), TypeError, r"\bM\b.*Tensor"),
    "fit-M-none-with-init": (lambda: torchrot.fit_rotation(None, R), TypeError, r"\bM\b.*Tensor, got NoneType"),
    "fit-M-ndarray": (lambda: torchrot.fit_rotation(np.eye(3)), TypeError, r"\bM\b.*Tensor, got ndarray"),
    "fit-M-list": (lambda: torchrot.fit_rotation([[1.0, 0, 0]] * 3), TypeError, r"\bM\b.*Tensor, got list"),
    "fit-M-shape": (lambda: torchrot.fit_rotation(torch.randn(4, 4)), RuntimeError, r"\bM\b.*\(\.\.\., 3, 3\)"),
    "fit-M-dtype": (lambda: torchrot.fit_rotation(M.int()), RuntimeError, r"\bM\b.*float32"),
    "fit-M-sparse": (lambda: torchrot.fit_rotation(torch.eye(3).to_sparse()), NotImplementedError, r"Sparse"),
    # init
    "fit-init-ndarray": (lambda: torchrot.fit_rotation(M, np.eye(3)), RuntimeError, r"argument 'init'"),
    "fit-init-not-rotation": (lambda: torchrot.fit_rotation(M, 2 * R), RuntimeError, r"\binit\b.*rotations"),
    # max_iter
    "fit-max_iter-zero": (lambda: torchrot.fit_rotation(M, max_iter=0), RuntimeError, r"max_iter.*>= 1"),
    "fit-max_iter-too-large": (lambda: torchrot.fit_rotation(M, max_iter=1001), RuntimeError,
                               r"max_iter.*<= 1000"),
    "op-max_iter-huge": (lambda: op.fit_rotation(M, None, 2**62, "newton"), RuntimeError, r"max_iter.*<= 1000"),
    "fit-max_iter-float": (lambda: torchrot.fit_rotation(M, max_iter=2.0), TypeError, r"max_iter.*int"),
    "fit-max_iter-bool": (lambda: torchrot.fit_rotation(M, max_iter=True), TypeError, r"max_iter.*int"),
    "reference-max_iter-too-large": (lambda: torchrot.fit_rotation_reference(M, max_iter=10**6), ValueError,
                                     r"max_iter.*<= 1000"),
    # variant
    "fit-variant-unknown": (lambda: torchrot.fit_rotation(M, variant="Newton"), RuntimeError,
                            r"variant.*'newton', 'conservative', 'gershgorin'"),
    "fit-variant-none": (lambda: torchrot.fit_rotation(M, variant=None), RuntimeError, r"argument 'variant'"),
    # gradient_eps
    "fit-gradient_eps-negative": (lambda: torchrot.fit_rotation(M, gradient_eps=-1e-6), ValueError,
                                  r"gradient_eps.*>= 0 and <= 1000"),
    "fit-gradient_eps-nan": (lambda: torchrot.fit_rotation(M, gradient_eps=math.nan), ValueError,
                             r"gradient_eps.*finite"),
    "fit-gradient_eps-too-large": (lambda: torchrot.fit_rotation(M, gradient_eps=1e4), ValueError,
                                   r"gradient_eps.*<= 1000"),
    "fit-gradient_eps-str": (lambda: torchrot.fit_rotation(M, gradient_eps="1e-6"), TypeError,
                             r"gradient_eps.*float"),
    "op-gradient_eps-too-large": (lambda: op.fit_rotation(M, None, None, "newton", 1e4), RuntimeError,
                                  r"gradient_eps.*<= 1000"),
    # out
    "op-out-none": (lambda: op.fit_rotation_out(M, None, None, "newton", None), RuntimeError,
                    r"\bout\b.*got None"),
    "fit-out-ndarray": (lambda: torchrot.fit_rotation(M, out=np.empty((4, 3, 3), np.float32)), RuntimeError,
                        r"argument 'out'"),
    "fit-out-requires-grad": (lambda: torchrot.fit_rotation(M.clone().requires_grad_(), out=torch.empty_like(M)),
                              RuntimeError, r"out= does not support automatic differentiation"),
    # fit_rotation_backward
    "backward-grad-none": (lambda: _backward(grad=None), RuntimeError, r"\bgrad\b.*got None"),
    "backward-R-none": (lambda: _backward(R_=None), RuntimeError, r"\bR\b.*got None"),
    "backward-M-none": (lambda: _backward(M_=None), RuntimeError, r"\bM\b.*got None"),
    "backward-grad-shape": (lambda: _backward(grad=R[:3]), RuntimeError, r"\bgrad\b.*R's shape"),
    "backward-M-broadcast": (lambda: _backward(M_=M[:3]), RuntimeError, r"\bM\b.*broadcast"),
    "backward-dtype": (lambda: _backward(grad=R.double()), RuntimeError, r"\bgrad\b.*dtype"),
    "backward-R-dtype": (lambda: _backward(grad=R.int(), R_=R.int(), M_=M.int()), RuntimeError, r"\bR\b.*float32"),
    "backward-gradient_eps": (lambda: _backward(eps=-1.0), RuntimeError, r"gradient_eps.*>= 0"),
    # references
    "reference-M-ndarray": (lambda: torchrot.fit_rotation_reference(np.eye(3)), TypeError, r"\bM\b.*Tensor"),
    "rotation_svd-M-shape": (lambda: torchrot.rotation_svd(torch.randn(4, 4)), ValueError,
                             r"rotation_svd: M.*\(\.\.\., 3, 3\)"),
    "rotation_svd-M-ndarray": (lambda: torchrot.rotation_svd(np.eye(3)), TypeError, r"rotation_svd: M.*Tensor"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_argument_raises_naming_it(case):
    call, exception, pattern = CASES[case]
    with pytest.raises(exception, match=pattern):
        call()


def test_environment_variable_error_names_it(monkeypatch):
    monkeypatch.setenv("TORCHROT_CPU_CAPABILITY", "sse2")
    with pytest.raises(RuntimeError, match=r"TORCHROT_CPU_CAPABILITY must be one of .*'sse2'"):
        torchrot.fit_rotation(M)


def test_limits_are_accepted():
    """The largest accepted max_iter and gradient_eps work (finite results)."""
    X = M.double().clone().requires_grad_()
    R_ = torchrot.fit_rotation(X, max_iter=1000, gradient_eps=1e3)
    R_.sum().backward()
    assert torch.isfinite(R_).all() and torch.isfinite(X.grad).all()


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
