"""Second derivatives of fit_rotation and fit_orthogonal: every nesting of
torch.func's transforms (hessian, jacrev/jacfwd, jvp/vjp/grad) and double
backward, eager and compiled with fullgraph=True, equal to the second
derivatives of the float64 SVD's answer (exactly, undamped; within the
damping's (lambda / (sigma_i + sigma_j))^2 with the default gradient_eps);
gradgradcheck; vmap of hessian; finite where the first derivative is finite;
the derivative operator's own derivatives (torchrot/_tangent_derivative.py)
against autograd and against each other.
"""
from __future__ import annotations

import pytest
import torch
from kernel_paths import KERNEL_PATHS, kernel_path_params
from torch.func import grad, hessian, jacfwd, jacrev, jvp, vjp, vmap
from transforms_helpers import BACKEND

import torchrot
from torchrot._tangent_derivative import tangent_jvp, tangent_value, tangent_vjp
from torchrot.testing import DEGENERATE_FAMILIES, make_degenerate_matrices, make_matrices

op = torch.ops.torchrot
GEN = torch.Generator().manual_seed(5)
M0 = torch.randn(3, 3, generator=GEN, dtype=torch.float64)  # singular values well apart, det either sign
W = torch.randn(3, 3, generator=GEN, dtype=torch.float64)
V = torch.randn(3, 3, generator=GEN, dtype=torch.float64)


def _svd_fit(orthogonal: bool):
    """The SVD's answer, twice differentiable by autograd: U diag(1, 1, d) V^T
    with d = sign det M (detached), or d = 1 for the orthogonal fit."""
    def fit(M):
        U, _, Vh = torch.linalg.svd(M)
        if orthogonal:
            return U @ Vh
        d = torch.linalg.det(M).sign().detach()
        return (U * torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1).unsqueeze(-2)) @ Vh
    return fit


FITS = {"fit_rotation": torchrot.fit_rotation, "fit_orthogonal": torchrot.fit_orthogonal}


def _undamped(fit):
    """``fit`` with gradient_eps=0 (a lambda: dynamo's jacrev cannot wrap a functools.partial)."""
    return lambda M: fit(M, gradient_eps=0.0)


def _second_derivative(fit, M):
    """d^2 fit(M) / dM^2, ``(3, 3, 3, 3, 3, 3)``, by plain autograd (loops of double backward)."""
    x = M.clone().requires_grad_()
    R = fit(x)
    H = torch.empty(3, 3, 3, 3, 3, 3, dtype=M.dtype)
    for i in range(3):
        for j in range(3):
            (g,) = torch.autograd.grad(R[i, j], x, create_graph=True)
            for k in range(3):
                for m in range(3):
                    H[i, j, k, m] = torch.autograd.grad(g[k, m], x, retain_graph=True)[0]
    return H


def _objective(fit):
    return lambda x: (fit(x) * W).sum()


# case -> (the second derivative taken by f, what it equals in terms of H = d^2 fit / dM^2)
SECOND_ORDER = {
    "hessian": (lambda f, m: hessian(_objective(f))(m), lambda H: torch.einsum("ijklmn,ij->klmn", H, W)),
    "jacrev_jacrev": (lambda f, m: jacrev(jacrev(f))(m), lambda H: H),
    "jacfwd_jacfwd": (lambda f, m: jacfwd(jacfwd(f))(m), lambda H: H),
    "jacrev_jacfwd": (lambda f, m: jacrev(jacfwd(f))(m), lambda H: H),
    "jacfwd_jacrev": (lambda f, m: jacfwd(jacrev(f))(m), lambda H: H),
    "jvp_jvp": (lambda f, m: jvp(lambda x: jvp(f, (x,), (V,))[1], (m,), (W,))[1],
                lambda H: torch.einsum("ijklmn,kl,mn->ij", H, V, W)),
    "vjp_jvp": (lambda f, m: vjp(lambda x: jvp(f, (x,), (V,))[1], m)[1](W)[0],
                lambda H: torch.einsum("ijklmn,ij,kl->mn", H, W, V)),
    "jvp_vjp": (lambda f, m: jvp(lambda x: vjp(f, x)[1](W)[0], (m,), (V,))[1],
                lambda H: torch.einsum("ijklmn,ij,mn->kl", H, W, V)),
    "grad_grad": (lambda f, m: grad(lambda x: (grad(_objective(f))(x) * V).sum())(m),
                  lambda H: torch.einsum("ijklmn,ij,kl->mn", H, W, V)),
    "double_backward": (lambda f, m: _double_backward(f, m), lambda H: torch.einsum("ijklmn,ij,kl->mn", H, W, V)),
}


def _double_backward(f, m):
    x = m.clone().requires_grad_()
    (g,) = torch.autograd.grad(_objective(f)(x), x, create_graph=True)
    return torch.autograd.grad((g * V).sum(), x)[0]


def _expected(name: str, case: str, sign: float) -> torch.Tensor:
    return SECOND_ORDER[case][1](_second_derivative(_svd_fit(name == "fit_orthogonal"), sign * M0))


CASES = [(case, "eager") for case in SECOND_ORDER] + [
    (case, "fullgraph") for case in SECOND_ORDER if case != "double_backward"  # (AOTAutograd refuses it)
]


@pytest.mark.parametrize("case, mode", CASES, ids=[f"{c}-{m}" for c, m in CASES])
@pytest.mark.parametrize("name", sorted(FITS))
def test_second_derivatives_are_the_svds(name, case, mode):
    """Undamped (gradient_eps=0), the second derivative is the SVD's exactly
    (rounding apart), for a matrix of either determinant sign."""
    fit = _undamped(FITS[name])
    fn = SECOND_ORDER[case][0]
    if mode == "fullgraph":
        torch._dynamo.reset()
        fn = torch.compile(fn, backend=BACKEND, fullgraph=True)
    for sign in (1.0, -1.0):
        got, want = fn(fit, sign * M0), _expected(name, case, sign)
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-11 * want.abs().max().item())


@pytest.mark.parametrize("name", sorted(FITS))
def test_damped_second_derivatives_are_close(name):
    """With the default gradient_eps the second derivative is the exact one
    up to the damping: lambda = 1e-6 |M|_F, sigma_i + sigma_j ~ 1 here."""
    got = SECOND_ORDER["hessian"][0](FITS[name], M0)
    torch.testing.assert_close(got, _expected(name, "hessian", 1.0), rtol=1e-9, atol=1e-9)


def test_forward_and_reverse_second_derivatives_agree():
    """Forward over reverse and reverse over reverse give one Hessian (a
    batch of gaussian matrices; undamped, the Hessian is symmetric)."""
    M = make_matrices("gaussian", 64, 3, torch.float64)
    fit = _undamped(torchrot.fit_rotation)
    loss = lambda x: (fit(x) * W).sum()  # noqa: E731
    forward = jvp(grad(loss), (M,), (V.expand_as(M),))[1]
    reverse = _double_backward(fit, M)
    torch.testing.assert_close(forward, reverse, rtol=1e-9, atol=1e-10)


def test_vmap_of_hessian():
    M = make_matrices("gaussian", 5, 4, torch.float64)
    batched = vmap(hessian(_objective(torchrot.fit_rotation)))(M)
    for b in range(5):
        assert torch.equal(batched[b], hessian(_objective(torchrot.fit_rotation))(M[b]))


def test_hessian_under_inductor():
    """torch.func.hessian compiles with the default backend too, to one graph."""
    torch._dynamo.reset()
    fn = lambda m: hessian(_objective(torchrot.fit_rotation))(m)  # noqa: E731
    torch.testing.assert_close(torch.compile(fn, fullgraph=True)(M0), fn(M0), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("path", kernel_path_params())
@pytest.mark.parametrize("name", sorted(FITS))
def test_second_derivatives_on_every_kernel_path(name, path):
    """The C++ kernel, the device-generic kernels and the Triton kernels give
    the same Hessian (their first derivatives agree to rounding, and the
    second derivative is computed from them), for a matrix of either sign."""
    objective = _objective(FITS[name])
    for sign in (1.0, -1.0):
        want = hessian(objective)(sign * M0)
        with KERNEL_PATHS[path]():
            got = hessian(objective)(sign * M0)
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_third_derivatives_match_finite_differences():
    """The derivative of the derivative is differentiable again."""
    M = make_matrices("rot60", 1, 6, torch.float64)[0]
    second = lambda m: jacrev(jacrev(_objective(torchrot.fit_rotation)))(m)  # noqa: E731
    third = jacfwd(second)(M)
    h = 1e-5
    for k, m in ((0, 1), (2, 2)):
        E = torch.zeros(3, 3, dtype=torch.float64)
        E[k, m] = h
        central = (second(M + E) - second(M - E)) / (2 * h)
        torch.testing.assert_close(third[..., k, m], central, rtol=1e-6, atol=1e-7)


def test_compiled_double_backward_raises():
    """A first-order gradient with create_graph=True through a compiled
    function is fine; differentiating it again raises AOTAutograd's own
    refusal of double backward (torch.func.hessian inside the compiled
    function is what compiles: test_second_derivatives_are_the_svds)."""
    torch._dynamo.reset()
    M = M0.clone().requires_grad_()
    loss = torch.compile(lambda m: torchrot.fit_rotation(m).sum(), backend=BACKEND, fullgraph=True)(M)
    (g,) = torch.autograd.grad(loss, M, create_graph=True)
    torch.testing.assert_close(g, grad(lambda m: torchrot.fit_rotation(m).sum())(M0), rtol=1e-9, atol=1e-10)
    with pytest.raises(RuntimeError, match="double backward"):
        g.sum().backward()


# ---------------------------------------------------------------------------
# gradgradcheck: fit_rotation, fit_orthogonal, rigid_registration, the operator
# ---------------------------------------------------------------------------


def _well_separated(n: int, seed: int, det_sign: float) -> torch.Tensor:
    """Matrices with singular values 1, 2, 3.5 (well apart) and det of sign ``det_sign``."""
    gen = torch.Generator().manual_seed(seed)
    U, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))
    Vq, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))
    sigma = torch.tensor([3.5, 2.0, 1.0], dtype=torch.float64)
    M = U @ torch.diag_embed(sigma.expand(n, 3)) @ Vq.mT
    return M * torch.where(torch.linalg.det(M) * det_sign < 0, -1.0, 1.0)[:, None, None]


@pytest.mark.parametrize("det_sign", [1.0, -1.0])
@pytest.mark.parametrize("name", sorted(FITS))
def test_gradgradcheck(name, det_sign):
    M = _well_separated(3, 1, det_sign).requires_grad_()
    assert torch.autograd.gradgradcheck(FITS[name], (M,), check_fwd_over_rev=True)


@pytest.mark.parametrize("allow_reflection", [False, True])
@pytest.mark.parametrize("scale", [False, True])
def test_gradgradcheck_registration(scale, allow_reflection):
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(2, 6, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    y = (1.5 * x.detach() @ _well_separated(2, 3, 1.0).mT + 0.1).requires_grad_()
    w = (torch.rand(2, 6, generator=gen, dtype=torch.float64) + 0.5).requires_grad_()

    def register(x, y, w):
        return tuple(torchrot.rigid_registration(x, y, w, scale=scale, allow_reflection=allow_reflection))

    assert torch.autograd.gradgradcheck(register, (x, y, w))


def test_derivative_operator_is_differentiable_in_every_input():
    M = _well_separated(3, 4, 1.0)
    R = torchrot.fit_rotation(M)
    X = torch.randn(3, 3, 3, generator=GEN, dtype=torch.float64)
    inputs = tuple(t.clone().requires_grad_() for t in (X, R, M))
    fn = lambda x, r, m: op.fit_rotation_backward(x, r, m, 1e-3)  # noqa: E731
    assert torch.autograd.gradcheck(fn, inputs, check_forward_ad=True)
    assert torch.autograd.gradgradcheck(fn, inputs)


# ---------------------------------------------------------------------------
# Finite where the first derivative is finite
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("family", sorted(DEGENERATE_FAMILIES))
@pytest.mark.parametrize("name", sorted(FITS))
def test_second_derivatives_finite_on_degenerate_matrices(name, family):
    """Repeated, zero and half-turn singular values, M = 0, tiny and huge
    scales: the damped second derivatives are finite as the first are."""
    M = make_degenerate_matrices(family, 8, 7)
    forward = jvp(grad(lambda x: (FITS[name](x) * W).sum()), (M,), (V.expand_as(M),))[1]
    reverse = _double_backward(FITS[name], M)
    assert forward.isfinite().all() and reverse.isfinite().all()


def test_float32_second_derivatives_close_to_float64():
    M = make_matrices("rot60", 16, 8, torch.float64)
    hvp = lambda m: jvp(grad(lambda x: (torchrot.fit_rotation(x) * W.to(x.dtype)).sum()), (m,),  # noqa: E731
                        (V.to(m.dtype).expand_as(m),))[1]
    torch.testing.assert_close(hvp(M.float()).double(), hvp(M), rtol=1e-3, atol=1e-4)


# ---------------------------------------------------------------------------
# The derivative operator's derivatives (torchrot/_tangent_derivative.py)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("eps", [0.0, 1e-6, 0.3])
def test_tangent_formula_is_the_operator(eps, dtype):
    M = make_matrices("gaussian", 40, 9, dtype)
    M[0] = 0
    R = torchrot.fit_rotation(M)
    X = torch.randn(M.shape, generator=GEN, dtype=torch.float64).to(dtype)
    T = op.fit_rotation_backward(X, R, M, eps)
    tolerance = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(tangent_value(X, R, M, eps), T, rtol=tolerance, atol=tolerance * T.abs().max().item())


@pytest.mark.parametrize("eps", [0.0, 1e-6, 0.3])
def test_tangent_jvp_is_the_formulas_derivative_and_the_vjps_adjoint(eps):
    M = make_matrices("gaussian", 40, 10, torch.float64)
    M[0] = 0
    R = torchrot.fit_rotation(M)
    X, dX, dR, dM, Wt = (torch.randn(M.shape, generator=GEN, dtype=torch.float64) for _ in range(5))
    got = tangent_jvp(X, R, M, eps, dX, dR, dM)
    want = jvp(lambda x, r, m: tangent_value(x, r, m, eps), (X, R, M), (dX, dR, dM))[1]
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12 * want.abs().max().item())
    assert (got[0] == 0).all()  # M = 0: T is 0, a constant
    pulled = tangent_vjp(X, R, M, eps, Wt)
    torch.testing.assert_close((got * Wt).sum(), sum((p * d).sum() for p, d in zip(pulled, (dX, dR, dM))),
                               rtol=1e-12, atol=0.0)


def test_tangent_derivatives_broadcast_M_and_reduced_precision():
    M = make_matrices("gaussian", 1, 11, torch.float64)[0]
    R = torchrot.fit_rotation(M).expand(4, 3, 3)
    X = torch.randn(4, 3, 3, generator=GEN, dtype=torch.float64)
    dX, dR, dM = torch.randn_like(X), torch.randn_like(X), torch.randn_like(M)
    assert [t.shape for t in tangent_vjp(X, R, M, 1e-6, X)] == [X.shape, X.shape, M.shape]
    assert tangent_jvp(X, R, M, 1e-6, None, None, dM).shape == X.shape
    half = tangent_jvp(X.half(), R.half(), M.half(), 1e-6, dX.half(), dR.half(), dM.half())
    assert half.dtype == torch.float16
    full = tangent_jvp(*(t.half().float() for t in (X, R, M)), 1e-6, *(t.half().float() for t in (dX, dR, dM)))
    assert torch.equal(half, full.half())
