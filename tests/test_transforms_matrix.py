"""torch.func transforms of fit_rotation, the operator, fit_orthogonal,
rigid_registration and the nn modules: in eager and under torch.compile (with and without
fullgraph=True), on the CPU kernel and on the device-generic path (the
pure-PyTorch kernels that torchrot/_device_kernels.py registers for other devices, run on
CPU tensors by torchrot.testing.generic_kernel).

Every cell of the matrix must give the eager CPU answer: eager on the CPU
kernel is checked against central differences, every other cell against
eager on the CPU kernel (float64, rtol 1e-9, atol 1e-10). Compiled cells also
check that the operator was captured in a single graph (no graph break), and
generic cells that the pure-PyTorch kernels ran. Every target runs every
transform in eager; which run compiled is in COMPILED.

The compile backend is ``aot_eager`` (dynamo and AOTAutograd, where the
transforms are traced; inductor only lowers the resulting graph, and costs
seconds a graph); ``TORCHROT_TEST_COMPILE_BACKEND=inductor`` runs the matrix
with inductor.
"""
from __future__ import annotations

import collections
import contextlib

import pytest
import torch
import torch.autograd.forward_ad as fwAD
from torch._dynamo.backends.registry import lookup_backend
from torch.func import grad, jacfwd, jacrev, jvp, vjp, vmap
from transforms_helpers import BACKEND, _central_jacobians, _directions, _inputs

import torchrot
from torchrot._extension import torch_release as release_of
from torchrot.nn import RigidRegistration, RotationFit
from torchrot.testing import generic_kernel

# ---------------------------------------------------------------------------
# The device-generic path on CPU (torchrot.testing.generic_kernel)
# ---------------------------------------------------------------------------


@pytest.fixture
def reference_calls(monkeypatch):
    """Counts the calls of the pure-PyTorch reference behind the
    device-generic kernels (they look it up in torchrot._device_kernels at each call)."""
    calls = collections.Counter()
    for name in ("fit_rotation_reference", "fit_rotation_backward_reference"):
        function = getattr(torchrot._device_kernels, name)

        def counting(*args, _name=name, _function=function, **kwargs):
            calls[_name] += 1
            return _function(*args, **kwargs)
        monkeypatch.setattr(torchrot._device_kernels, name, counting)
    return calls


def test_generic_kernel_runs_the_reference_and_restores(reference_calls):
    M = torch.randn(4, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    G = torch.ones_like(M)
    loss_grad = grad(lambda m: (torchrot.fit_rotation(m) * G).sum())
    native_R, native_grad = torch.ops.torchrot.fit_rotation(M), loss_grad(M)
    assert not reference_calls
    with generic_kernel():
        R = torch.ops.torchrot.fit_rotation(M)
        g = loss_grad(M)
        out = torchrot.fit_rotation(M, out=torch.empty_like(M))
        info = torchrot.fit_rotation_info(M)
    # fit_rotation twice, fit_rotation_out, fit_rotation_info; one backward.
    assert reference_calls == {"fit_rotation_reference": 4, "fit_rotation_backward_reference": 1}
    torch.testing.assert_close(R, native_R, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(g, native_grad, rtol=1e-9, atol=1e-10)
    assert torch.equal(out, R) and torch.equal(info.R, R)
    reference_calls.clear()
    assert torch.equal(torch.ops.torchrot.fit_rotation(M), native_R)  # the C++ kernels are back
    assert torch.equal(loss_grad(M), native_grad)
    assert not reference_calls


# ---------------------------------------------------------------------------
# Functions under test: P (the differentiated input), constants C -> tuple of outputs
# ---------------------------------------------------------------------------

_rotation_fit = RotationFit()
_rigid_registration = RigidRegistration()  # scale=False: s is a constant output


TARGETS = {
    "fit_rotation": lambda P: (torchrot.fit_rotation(P),),
    "op": lambda P: (torch.ops.torchrot.fit_rotation(P),),
    "fit_orthogonal": lambda P: (torchrot.fit_orthogonal(P),),
    "RotationFit": lambda P: (_rotation_fit(P),),
    "rigid_registration": lambda x, y, w: tuple(torchrot.rigid_registration(x, y, w, scale=True)),
    "RigidRegistration": lambda x, y: tuple(_rigid_registration(x, y)),
}


def _loss(outputs, Gs):
    return sum((o * g).sum() for o, g in zip(outputs, Gs))


# ---------------------------------------------------------------------------
# Transforms: body(f) is what torch.compile compiles, call(fn, ...) runs it
# ---------------------------------------------------------------------------


def _call(fn, P, dP, Gs, C):
    return fn(P, dP, Gs, C)


def _call_backward(fn, P, dP, Gs, C):
    P = P.detach().requires_grad_()
    fn(P, dP, Gs, C).backward()
    return P.grad


def _tangents_or_zeros(outputs):
    return tuple(torch.zeros_like(o) if t is None else t
                 for o, t in ((o, fwAD.unpack_dual(o).tangent) for o in outputs))


def _forward_ad(f):
    def body(P, dP, Gs, C):
        with fwAD.dual_level():
            return _tangents_or_zeros(f(fwAD.make_dual(P, dP), *C))
    return body


TRANSFORMS = {
    "grad": lambda f: lambda P, dP, Gs, C: grad(lambda p: _loss(f(p, *C), Gs))(P),
    "vjp": lambda f: lambda P, dP, Gs, C: vjp(lambda p: f(p, *C), P)[1](Gs)[0],
    "jvp": lambda f: lambda P, dP, Gs, C: jvp(lambda p: f(p, *C), (P,), (dP,)),
    "jacrev": lambda f: lambda P, dP, Gs, C: jacrev(lambda p: f(p, *C))(P),
    "jacfwd": lambda f: lambda P, dP, Gs, C: jacfwd(lambda p: f(p, *C))(P),
    "vmap": lambda f: lambda P, dP, Gs, C: vmap(f)(P, *C),
    "vmap_grad": lambda f: lambda P, dP, Gs, C: vmap(grad(lambda p, g, *c: _loss(f(p, *c), g)))(P, Gs, *C),
    "vmap_jvp": lambda f: lambda P, dP, Gs, C: vmap(
        lambda p, dp, *c: jvp(lambda q: f(q, *c), (p,), (dp,))[1])(P, dP, *C),
    "grad_vmap": lambda f: lambda P, dP, Gs, C: grad(lambda p: _loss(vmap(f)(p, *C), Gs))(P),
    "backward": lambda f: lambda P, dP, Gs, C: _loss(f(P, *C), Gs),
    "forward_ad": _forward_ad,
}
CALLS = {"backward": _call_backward}


def _run(transform, fn, P, dP, Gs, C):
    return CALLS.get(transform, _call)(fn, P, dP, Gs, C)


# ---------------------------------------------------------------------------
# References: central differences, eager on the CPU kernel
# ---------------------------------------------------------------------------


def _finite_difference_reference(transform, f, P, dP, Gs, C):
    outputs = f(P, *C)
    if transform == "vmap":
        return outputs
    J = _central_jacobians(f, P, C)
    gradient = sum(torch.tensordot(g, j, dims=g.dim()) for g, j in zip(Gs, J))
    tangents = tuple(torch.tensordot(j, dP, dims=P.dim()) for j in J)
    return {
        "grad": gradient, "vjp": gradient, "vmap_grad": gradient, "grad_vmap": gradient, "backward": gradient,
        "jvp": (outputs, tangents), "vmap_jvp": tangents, "forward_ad": tangents,
        "jacrev": J, "jacfwd": J,
    }[transform]


_eager_cpu_cache = {}


def _eager_cpu(target, name, transform):
    key = (target, name, transform)
    if key not in _eager_cpu_cache:
        f = TARGETS[target]
        P, C = _inputs(target, name)
        dP, Gs = _directions(P, f(P, *C))
        _eager_cpu_cache[key] = _run(transform, TRANSFORMS[transform](f), P, dP, Gs, C)
    return _eager_cpu_cache[key]


# ---------------------------------------------------------------------------
# Compiled functions, shared by the cells of one (target, transform, mode)
# ---------------------------------------------------------------------------


class _RecordingBackend:
    """The compile backend, recording each graph dynamo hands it."""

    def __init__(self):
        self.graphs = []

    def __call__(self, gm, example_inputs):
        self.graphs.append({str(node.target) for node in gm.graph.nodes if node.op == "call_function"})
        return lookup_backend(BACKEND)(gm, example_inputs)


_compiled = {}


def _compiled_function(target, transform, fullgraph):
    """One compiled function per (target, transform, mode); the matrix runs
    its inputs and paths consecutively. A new one resets dynamo, so the
    bodies (closures sharing code objects) never reach the recompile limit
    and fall back to eager unnoticed."""
    key = (target, transform, fullgraph)
    if key not in _compiled:
        _compiled.clear()
        torch._dynamo.reset()
        backend = _RecordingBackend()
        body = TRANSFORMS[transform](TARGETS[target])
        _compiled[key] = torch.compile(body, backend=backend, fullgraph=fullgraph), backend
    return _compiled[key]


# ---------------------------------------------------------------------------
# The matrix
# ---------------------------------------------------------------------------

TARGET_INPUTS = (
    ("fit_rotation", "gaussian"), ("fit_rotation", "identity"), ("op", "gaussian"), ("fit_orthogonal", "mixed_det"),
    ("RotationFit", "gaussian"),
    ("rigid_registration", "points"), ("RigidRegistration", "points"),
)
MODES = ("eager", "compile", "fullgraph")
PATHS = ("cpu", "generic")
# Compiling is the slow part (dynamo tracing the transforms, per graph). Every
# target runs every transform in eager; compiled, fit_rotation and
# rigid_registration run every transform and the wrappers (the operator, the
# modules) a sample. Without a graph break, fullgraph=False traces the very
# graph fullgraph=True does, so beyond fit_rotation only fullgraph runs.
COMPILED = {
    "fit_rotation": (tuple(TRANSFORMS), ("compile", "fullgraph")),
    "rigid_registration": (tuple(TRANSFORMS), ("fullgraph",)),
    "op": (("grad", "jvp", "jacfwd", "vmap_grad", "backward", "forward_ad"), ("fullgraph",)),
    "fit_orthogonal": (("grad", "jvp", "jacrev", "jacfwd", "vmap", "vmap_grad", "backward", "forward_ad"),
                       ("fullgraph",)),
    "RotationFit": (("grad", "jvp", "jacrev", "vmap", "backward"), ("fullgraph",)),
    "RigidRegistration": (("grad", "jvp", "vmap", "backward", "forward_ad"), ("fullgraph",)),
}


def _runs(target, transform, mode):
    transforms, modes = COMPILED[target]
    return mode == "eager" or (transform in transforms and mode in modes)


# torch 2.11's and 2.12's jacrev build their basis with a data-dependent
# offset when the function has several outputs, which dynamo cannot trace with
# fullgraph=True (UserError "Could not extract specialized integer from
# data-dependent expression"; (q.sin(), q.cos()) fails alike, torch 2.13
# traces it): the registration targets, whose outputs are (R, t, s), raise it
# there.
_JACREV_MULTI_OUTPUT_FULLGRAPH = pytest.mark.xfail(
    release_of(torch.__version__) < (2, 13), raises=torch._dynamo.exc.UserError, strict=True,
    reason="torch 2.11, 2.12: jacrev of a multi-output function cannot be traced with fullgraph=True")


def _marks(target, transform, mode):
    if target in ("rigid_registration", "RigidRegistration") and transform == "jacrev" and mode == "fullgraph":
        return [_JACREV_MULTI_OUTPUT_FULLGRAPH]
    return []


# Ordered so that each compiled function serves its cells one after another.
CASES = [
    pytest.param(target, name, transform, mode, path, id=f"{target}-{name}-{transform}-{mode}-{path}",
                 marks=_marks(target, transform, mode))
    for target in TARGETS for transform in TRANSFORMS for mode in MODES if _runs(target, transform, mode)
    for t, name in TARGET_INPUTS if t == target for path in PATHS
]
DERIVATIVE_FREE = ("vmap",)


@pytest.mark.parametrize("target, name, transform, mode, path", CASES)
def test_transform_matrix(target, name, transform, mode, path, reference_calls):
    f = TARGETS[target]
    P, C = _inputs(target, name)
    dP, Gs = _directions(P, f(P, *C))
    expected = _eager_cpu(target, name, transform)  # computed outside generic_kernel

    if mode == "eager":
        fn, backend = TRANSFORMS[transform](f), None
    else:
        fn, backend = _compiled_function(target, transform, fullgraph=mode == "fullgraph")
    reference_calls.clear()
    with generic_kernel() if path == "generic" else contextlib.nullcontext():
        got = _run(transform, fn, P, dP, Gs, C)

    if mode == "eager" and path == "cpu":
        reference = _finite_difference_reference(transform, f, P, dP, Gs, C)
        torch.testing.assert_close(got, reference, rtol=1e-6, atol=1e-7)
    else:
        torch.testing.assert_close(got, expected, rtol=1e-9, atol=1e-10)
    if path == "generic":  # the pure-PyTorch kernels ran (and only they)
        assert reference_calls["fit_rotation_reference"] > 0
        assert (reference_calls["fit_rotation_backward_reference"] > 0) == (transform not in DERIVATIVE_FREE)
    if backend is not None:
        # Fully captured: one graph, holding the operator (a graph break
        # would have left the transform to eager).
        assert len(backend.graphs) == 1, f"{len(backend.graphs)} graphs"
        assert any(op.split(".")[:2] == ["torchrot", "fit_rotation"] for op in backend.graphs[0]), backend.graphs[0]
