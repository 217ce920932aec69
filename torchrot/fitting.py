"""The public fitting functions: thin wrappers over the operators
torch.ops.torchrot.fit_rotation / fit_rotation_out / fit_rotation_info
(schemas: csrc/ops/schemas.cpp), with their argument checks.

Convention: R (det +1) maximises tr(R^T M), the rotation nearest to M;
column vectors, M = sum_i w_i y_i x_i^T gives R x_i ~ y_i.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from torchrot import _C
from torchrot._checks import (
    check_all,
    check_gradient_eps,
    check_gradient_eps_type,
    check_max_iter_type,
    check_out,
    check_out_autograd,
    check_tensor,
    check_variant_type,
)
from torchrot._constants import DEFAULT_VARIANT, GRADIENT_EPS
from torchrot._torch_private import below_autograd, forward_level, functorch_transforms_active

__all__ = ["FitInfo", "fit_rotation", "fit_rotation_info"]

# The operators, bound once (a lookup through torch.ops costs about a
# microsecond a call), the direct entry of plain eager calls (csrc/module.cpp:
# without torch.ops' argument parsing; NotImplemented where torch.ops is
# needed) and the dtypes that entry takes.
_fit_rotation_op = torch.ops.torchrot.fit_rotation.default
_fit_rotation_out_op = torch.ops.torchrot.fit_rotation_out.default
_fit_rotation_info_op = torch.ops.torchrot.fit_rotation_info.default
_fit_rotation_eager = _C.fit_rotation_eager
_EAGER_DTYPES = (torch.float32, torch.float64)


class FitInfo(NamedTuple):
    """Result of :func:`fit_rotation_info`.

    R: ``(..., 3, 3)`` the fitted rotations.
    iterations: ``(...)`` int32, Cayley steps taken per matrix.
    status: ``(...)`` uint8 per matrix, a :class:`torchrot.FitStatus` code
        (CAYLEY, FALLBACK: the Horn/Jacobi fallback in converged mode,
        NON_FINITE: M or init held NaN/Inf and R is NaN).
    """

    R: torch.Tensor
    iterations: torch.Tensor
    status: torch.Tensor


def fit_rotation(
    M: torch.Tensor,
    init: torch.Tensor | None = None,
    *,
    max_iter: int | None = None,
    variant: str = DEFAULT_VARIANT,
    gradient_eps: float | None = None,
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """The rotation R (det R = +1) maximising tr(R^T M): the rotation nearest to M.

    Column-vector convention: for centred point sets x_i, y_i and weights w_i,
    ``M = sum_i w_i y_i x_i^T`` gives ``R x_i ~ y_i``. Implements Algorithm 1 of
    Zhang, Jacobson & Alexa, "Fast Updates for Least-Squares Rotational
    Alignment", with the Cayley step of their Algorithm 2.

    Args:
        M: ``(..., 3, 3)`` float32 or float64 (float16/bfloat16 are computed in
            float32 and returned in their dtype); any batch shape and strides.
        init: optional ``(..., 3, 3)`` rotations broadcastable to M, on M's
            device, of any float dtype (cast to M's): the warm start R0 (e.g.
            the previous iteration's R). Rotations rounded to any float dtype
            are accepted (|R^T R - I|_F < 0.05, det > 0) and brought to the
            compute dtype's precision by Newton-Schulz steps, so results fed
            back call after call, or across precisions, do not drift. Without
            init, the fit starts from the best of the 24 rotations of the cube
            (the signed permutation matrices of det +1), and its first step
            takes the maximal objective itself as c (Horn's largest
            eigenvalue, by Laguerre's method on its characteristic
            polynomial), which puts it on the maximum. No gradient flows to
            init.
        max_iter: ``None`` (default) iterates each matrix to convergence at its
            dtype's precision and guarantees the maximum (a Horn/Jacobi
            fallback takes over matrices that do not converge within 12 steps
            or stop at a saddle point). ``k >= 1`` takes at most k Cayley steps
            with the chosen variant and no fallback: ``max_iter=1`` with
            ``init`` is the paper's one-step warm start for local-global
            solvers. The result is always an exact rotation.
        variant: how each step (but a cold start's first) estimates the
            maximal objective c (paper Sec. 4.2): ``"newton"`` (c = tr M),
            ``"conservative"`` (c = sqrt(tr(M)^2 + m^T m)) or ``"gershgorin"``
            (Eqs. 27-28). With ``max_iter=None``, Gershgorin hands over to
            the conservative estimate after two steps (its slack makes
            convergence linear).
        gradient_eps: damping of the derivative (autograd, forward mode,
            torch.func): the optimality system (tr(S) I - S) u = g is solved
            as (A^2 + lambda^2 I)^-1 A g with lambda = gradient_eps |M|_F. The
            exact derivative up to a relative (lambda / (sigma_i + sigma_j))^2
            where it exists; bounded (|u| <= |g| / (2 lambda)) where R is not
            unique (rank-deficient M, rotations by pi). ``0``: undamped.
            ``None`` (the default): ``torchrot.DEFAULT_GRADIENT_EPS``.
        out: optional tensor of M's shape, dtype and device to write into; it
            may be ``init`` or ``M`` itself (an in-place warm-start update).
            Written as torch's out= operators write: its version counter is
            bumped (autograd then refuses to differentiate through values it
            overwrote), it is not differentiable (raises where M or out
            requires grad in grad mode, or carries a forward-mode tangent),
            and an inference tensor is written only in inference mode.

    Returns:
        ``(..., 3, 3)`` rotations, M's dtype. A matrix whose M or init holds
        NaN/Inf gives NaN; other matrices are unaffected. Where the maximiser
        is not unique (M = 0, rank-1 M, ...) a maximising rotation is returned
        deterministically (for M = 0: init, else the identity).

    Derivatives: differentiable in M through the optimality condition (R^T M
    symmetric; see torchrot/_autograd.py), not through an SVD; finite for
    every finite M. With a finite ``max_iter`` the derivative is that of the
    exact maximiser evaluated at the returned R. Under ``torch.autocast`` the
    fit runs in float32.

    Raises:
        TypeError for an argument of the wrong type or dtype, ValueError for a
        wrong value, shape or device (docs/errors.md), naming the argument: M
        not ``(..., 3, 3)`` or not floating point; init of another shape,
        dtype or device, or not a rotation; out of the wrong shape, dtype or
        device, with overlapping elements, an inference tensor outside
        inference mode, or given while M or out requires grad;
        unknown variant; max_iter out of range; gradient_eps out of range.
        A call that raises changes no tensor it was given.
    """
    compiling = torch.compiler.is_compiling()
    _check_call(M, init, max_iter, variant, gradient_eps, out, compiling)
    if gradient_eps is None:
        gradient_eps = GRADIENT_EPS
    plain = _plain_eager(M, compiling)
    if out is None and plain:
        # The common call, in training or not: the operator, entered from C++,
        # whose C++ Autograd kernel runs the kernel and, where M requires grad,
        # records the reverse-mode derivative (csrc/autograd.cpp), without
        # Python autograd machinery or a Python context manager, which cost
        # several times a small fit. Tested first, with the fewest Python
        # operations: a small batch's fit costs about as much as them.
        R = _fit_rotation_eager(M, init, max_iter, variant, gradient_eps, None)
        if R is NotImplemented:  # a tensor subclass, a torch function mode, ...: through torch.ops
            R = _fit_rotation_op(M, init, max_iter, variant, gradient_eps)
        return R
    if out is not None:
        # The plain call, from C++ as above; through torch.ops where that
        # declines. The operator's Autograd kernel refuses a call that would
        # need a derivative, its ADInplaceOrView kernel bumps out's version
        # (csrc/autograd.cpp).
        if not plain or _fit_rotation_eager(M, init, max_iter, variant, gradient_eps, out) is NotImplemented:
            _fit_rotation_out_op(M, init, max_iter, variant, out)
        return out
    if _needs_derivative(M) or compiling:
        # The operator's Autograd kernel (csrc/autograd.cpp, handing torch.func,
        # forward AD and tracing to torchrot/_autograd.py) records the
        # derivatives in every mode (backward, forward AD, each torch.func
        # level), in eager and where torch.compile traces it, so both run the
        # same path. (Not FitRotationFunction.apply: dynamo cannot trace an
        # autograd.Function with a custom jvp, and apply costs twice as much.)
        # Under torch.autocast the operator's autocast kernel casts to float32.
        return _fit_rotation_op(M, init, max_iter, variant, gradient_eps)
    # Nothing to differentiate: below the operator's Autograd kernel, which
    # hands every call under a torch.func transform (vmap, say) to its Python
    # kernel (csrc/autograd.cpp), more than the cost of a small fit.
    with below_autograd():
        return _fit_rotation_op(M, init, max_iter, variant, gradient_eps)


def _check_call(M, init, max_iter, variant, gradient_eps, out=None, compiling: bool | None = None) -> None:
    """The wrapper's share of the argument checks. Eager: the types that the
    operator's schema would reject with a generic RuntimeError; the operator
    checks the rest (csrc/ops/checks.cpp). While torch.compile traces: all of them,
    in the operator's order, so that a bad argument raises its own TypeError /
    ValueError (a graph break runs it eagerly) instead of an error wrapped by
    the tracer around the fake kernel's. ``compiling``: torch.compiler.is_compiling(),
    if the caller has it."""
    check_tensor(M, "M")
    if init is not None:
        check_tensor(init, "init")
    check_max_iter_type(max_iter)
    check_variant_type(variant)
    if out is not None:
        check_tensor(out, "out")
    custom_eps = gradient_eps is not None
    if custom_eps:
        check_gradient_eps_type(gradient_eps)
    # All checks, in the operator's order: while traced, and for out=, whose
    # operator does not take gradient_eps (its value is checked after the rest).
    if compiling is None:
        compiling = torch.compiler.is_compiling()
    if compiling or (custom_eps and out is not None):
        if out is not None:
            check_out_autograd(M, out)  # the operator's Autograd kernel checks first
        check_all(M, init, max_iter, variant)
        if out is not None:
            check_out(M, out)
        if custom_eps:
            check_gradient_eps(gradient_eps)


def _plain_eager(M: torch.Tensor, compiling: bool) -> bool:
    """Whether a call can enter the operator from C++ (_fit_rotation_eager):
    eager (not ``compiling``), on a plain float32/float64 tensor, with no
    torch.func level and no forward AD (autocast casts reduced precision, and
    the other modes record their derivatives in the operator's Python
    Autograd kernel). A derivative, if any, is then a reverse-mode one in M,
    which the operator's C++ Autograd kernel records where M requires grad
    (none flows to init)."""
    return (
        type(M) is torch.Tensor
        and not compiling
        and forward_level() < 0
        and M.dtype in _EAGER_DTYPES
        and not functorch_transforms_active()
    )


def _needs_derivative(M: torch.Tensor) -> bool:
    """Whether a call must record derivatives: reverse mode (also under
    torch.func.grad, whose tensors require grad) or forward mode (a dual
    level is open, also under torch.func.jvp)."""
    return (torch.is_grad_enabled() and M.requires_grad) or forward_level() >= 0


def fit_rotation_info(
    M: torch.Tensor,
    init: torch.Tensor | None = None,
    *,
    max_iter: int | None = None,
    variant: str = DEFAULT_VARIANT,
) -> FitInfo:
    """:func:`fit_rotation` plus per-matrix diagnostics.

    Args: as :func:`fit_rotation` (M ``(..., 3, 3)`` float32/float64, float16/
    bfloat16 computed in float32; init, max_iter, variant), without ``out``.
    Convention: R (det +1) maximises tr(R^T M); for centred point sets
    M = sum_i w_i y_i x_i^T gives R x_i ~ y_i (column vectors).

    Returns:
        :class:`FitInfo` ``(R, iterations, status)``: R ``(..., 3, 3)`` in M's
        dtype; iterations ``(...)`` int32, the Cayley steps each matrix took;
        status ``(...)`` uint8, a :class:`torchrot.FitStatus` code per matrix.

    Not differentiable: none of the outputs requires grad or carries a
    gradient, whatever M does; use :func:`fit_rotation` for that.

    Raises: the errors of :func:`fit_rotation`.
    """
    _check_call(M, init, max_iter, variant, None)
    return FitInfo(*_fit_rotation_info_op(M, init, max_iter, variant))
