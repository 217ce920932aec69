"""The issue's two examples (the jvp and the gradient of fit_rotation, at the
identity and at a Gaussian matrix) against central differences, and compiled
with the default backend (inductor), with and without fullgraph=True, against
eager.
"""
from __future__ import annotations

import pytest
import torch
from torch.func import grad, jvp
from transforms_helpers import _central_jacobians, _directions, _inputs

import torchrot

# ---------------------------------------------------------------------------
# The issue's examples, with the default backend (inductor)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["identity", "gaussian"])
def test_issue_examples_default_backend(name):
    M, _ = _inputs("fit_rotation", name)
    dM, (G,) = _directions(M, (M,))
    tangent = lambda M, dM: jvp(torchrot.fit_rotation, (M,), (dM,))[1]  # noqa: E731
    gradient = lambda M, G: grad(lambda m: (torchrot.fit_rotation(m) * G).sum())(M)  # noqa: E731
    (J,) = _central_jacobians(lambda P: (torchrot.fit_rotation(P),), M, ())
    torch.testing.assert_close(tangent(M, dM), torch.tensordot(J, dM, dims=3), rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(gradient(M, G), torch.tensordot(G, J, dims=3), rtol=1e-6, atol=1e-7)
    for fullgraph in (False, True):
        torch._dynamo.reset()  # each mode compiles afresh
        torch.testing.assert_close(torch.compile(tangent, fullgraph=fullgraph)(M, dM), tangent(M, dM),
                                   rtol=1e-9, atol=1e-10)
        torch.testing.assert_close(torch.compile(gradient, fullgraph=fullgraph)(M, G), gradient(M, G),
                                   rtol=1e-9, atol=1e-10)
