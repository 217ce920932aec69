"""Second derivatives of fit_rotation raise (torch.func's hessian and nested
jacrev/jacfwd/jvp/grad, double backward), in eager and compiled with
fullgraph=True; a compiled first-order gradient with create_graph=True is
fine, and differentiating it again raises.
"""
from __future__ import annotations

import pytest
import torch
from torch.func import grad, hessian, jacfwd, jacrev, jvp
from transforms_helpers import BACKEND, _inputs

import torchrot

SECOND_DERIVATIVE = "second derivatives are not implemented"


# ---------------------------------------------------------------------------
# Second derivatives raise, in every mode
# ---------------------------------------------------------------------------


def _double_backward(m):
    m = m.detach().requires_grad_()
    (g,) = torch.autograd.grad(torchrot.fit_rotation(m).sum(), m, create_graph=True)
    return torch.autograd.grad(g.sum(), m)[0]


SECOND_ORDER = {
    "hessian": lambda m: hessian(lambda x: torchrot.fit_rotation(x).sum())(m),
    "jacrev_jacrev": lambda m: jacrev(jacrev(torchrot.fit_rotation))(m),
    "jacfwd_jacfwd": lambda m: jacfwd(jacfwd(torchrot.fit_rotation))(m),  # was silently 0
    "jacrev_jacfwd": lambda m: jacrev(jacfwd(torchrot.fit_rotation))(m),
    "jvp_jvp": lambda m: jvp(lambda x: jvp(torchrot.fit_rotation, (x,), (m,))[1], (m,), (m,))[1],  # was 0
    "op_jacfwd_jacfwd": lambda m: jacfwd(jacfwd(lambda x: torch.ops.torchrot.fit_rotation(x)))(m),
    "grad_grad": lambda m: grad(lambda x: grad(lambda y: torchrot.fit_rotation(y).sum())(x).sum())(m),
    "double_backward": _double_backward,
}


SECOND_ORDER_CASES = [(case, "eager") for case in SECOND_ORDER] + [
    (case, "fullgraph") for case in ("hessian", "jacfwd_jacfwd", "jacrev_jacfwd", "jvp_jvp", "op_jacfwd_jacfwd")
]


@pytest.mark.parametrize("case, mode", SECOND_ORDER_CASES, ids=[f"{c}-{m}" for c, m in SECOND_ORDER_CASES])
def test_second_derivatives_raise(case, mode):
    M, _ = _inputs("fit_rotation", "gaussian")
    fn = SECOND_ORDER[case]
    if mode != "eager":
        torch._dynamo.reset()
        fn = torch.compile(fn, backend=BACKEND, fullgraph=True)
    with pytest.raises(RuntimeError, match=SECOND_DERIVATIVE):
        fn(M[0])


def test_compiled_double_backward_raises():
    """A first-order gradient with create_graph=True through a compiled
    function is fine; differentiating it again raises (AOTAutograd's own
    refusal of double backward)."""
    torch._dynamo.reset()
    M, _ = _inputs("fit_rotation", "gaussian")
    M.requires_grad_()
    loss = torch.compile(lambda m: torchrot.fit_rotation(m).sum(), backend=BACKEND, fullgraph=True)(M)
    (g,) = torch.autograd.grad(loss, M, create_graph=True)
    torch.testing.assert_close(g, grad(lambda m: torchrot.fit_rotation(m).sum())(M.detach()), rtol=1e-9, atol=1e-10)
    with pytest.raises(RuntimeError, match="double backward"):
        g.sum().backward()
