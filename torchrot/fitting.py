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

# The operators, bound once (a lookup through torch.ops on every call would
# add to every call's fixed cost), the direct entry of plain eager calls (csrc/module.cpp:
# without torch.ops' argument parsing; NotImplemented where torch.ops is
# needed) and the dtypes that entry takes.
_fit_rotation_op = torch.ops.torchrot.fit_rotation.default
_fit_rotation_out_op = torch.ops.torchrot.fit_rotation_out.default
_fit_rotation_info_op = torch.ops.torchrot.fit_rotation_info.default
_fit_rotation_eager = _C.fit_rotation_eager
_EAGER_DTYPES = (torch.float32, torch.float64)


class FitInfo(NamedTuple):
    """Result of :func:`fit_rotation_info`: the fitted rotations and per-matrix diagnostics.

    Attributes:
        R: ``(..., 3, 3)`` the fitted rotations (det +1), in M's dtype.
        iterations: ``(...)`` int32, the Cayley steps each matrix took.
        status: ``(...)`` uint8, a :class:`torchrot.FitStatus` code per matrix
            (``CAYLEY``; ``FALLBACK``: the Horn/Jacobi fallback of converged
            mode took over; ``NON_FINITE``: M or init held NaN/Inf and R is NaN).

    Examples:
        >>> info = torchrot.fit_rotation_info(torch.randn(2, 5, 3, 3))
        >>> info.R.shape, info.iterations.shape, info.iterations.dtype, info.status.dtype
        (torch.Size([2, 5, 3, 3]), torch.Size([2, 5]), torch.int32, torch.uint8)
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
            are accepted (``|R^T R - I|_F < 0.05``, det > 0) and brought to the
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
            or stop at a saddle point). ``k >= 1`` (at most 1000) takes at most
            k Cayley steps with the chosen variant and no fallback:
            ``max_iter=1`` with ``init`` is the paper's one-step warm start for
            local-global solvers. The result is always an exact rotation.
        variant: how each step (but a cold start's first) estimates the
            maximal objective c (paper Sec. 4.2): ``"newton"`` (c = tr M),
            ``"conservative"`` (the default; c = sqrt(tr(M)^2 + m^T m)) or
            ``"gershgorin"`` (Eqs. 27-28). With ``max_iter=None``, Gershgorin
            hands over to the conservative estimate after two steps (its slack
            makes convergence linear).
        gradient_eps: damping of the derivative (autograd, forward mode,
            torch.func): the optimality system (tr(S) I - S) u = g is solved
            as (A^2 + lambda^2 I)^-1 A g with ``lambda = gradient_eps |M|_F``.
            The exact derivative up to a relative (lambda / (sigma_i +
            sigma_j))^2 where it exists; bounded (``|u| <= |g| / (2 lambda)``)
            where R is not unique (rank-deficient M, rotations by pi). A float
            from 0 (undamped) to 1000; ``None`` (the default):
            :data:`torchrot.DEFAULT_GRADIENT_EPS`.
        out: optional tensor of M's shape, dtype and device to write into; it
            may be ``init`` or ``M`` itself (an in-place warm-start update).
            Written as torch's out= operators write: its version counter is
            bumped (autograd then refuses to differentiate through values it
            overwrote), it is not differentiable (raises where M or out
            requires grad in grad mode, or carries a forward-mode tangent),
            and an inference tensor is written only in inference mode.

    Returns:
        ``(..., 3, 3)`` rotations, M's dtype and device (``out`` itself where
        given). A matrix whose M or init holds NaN/Inf gives NaN; other
        matrices are unaffected. Where the maximiser is not unique (M = 0,
        rank-1 M, ...) a maximising rotation is returned deterministically
        (for M = 0: init, else the identity).

    Derivatives: differentiable in M through the optimality condition (R^T M
    symmetric; see torchrot/_autograd.py), not through an SVD; finite for
    every finite M. With a finite ``max_iter`` the derivative is that of the
    exact maximiser evaluated at the returned R. Under ``torch.autocast`` the
    fit runs in float32.

    Errors name the argument (the messages: :doc:`errors`); a call that
    raises changes no tensor it was given.

    Raises:
        TypeError: an argument of the wrong type or dtype: M, init or out not a
            tensor; M or init not float32, float64, float16 or bfloat16; out
            not of M's dtype; max_iter not an int or None; variant not a str;
            gradient_eps not a float, int or None.
        ValueError: a wrong value, shape or device: M not ``(..., 3, 3)``; init
            not broadcastable to M, on another device, or finite but not a
            rotation; out of another shape or device than M, with overlapping
            elements, an inference tensor outside inference mode, or given
            while M or out requires grad (or carries a forward-mode tangent);
            an unknown variant; max_iter or gradient_eps out of range.

    Examples:
        The rotation that maps points x onto y (column vectors, ``y_i = R x_i``):

        >>> R_true = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z
        >>> x = torch.randn(10, 3)
        >>> y = x @ R_true.T                    # row i: y_i = R_true x_i
        >>> M = y.T @ x                         # sum_i y_i x_i^T
        >>> R = torchrot.fit_rotation(M)
        >>> torch.allclose(R, R_true, atol=1e-5)
        True

        Any batch shape; the result is a rotation in M's dtype, differentiable in M:

        >>> M = torch.randn(4, 5, 3, 3, dtype=torch.float64, requires_grad=True)
        >>> R = torchrot.fit_rotation(M)
        >>> R.shape, R.dtype
        (torch.Size([4, 5, 3, 3]), torch.float64)
        >>> torch.allclose(R.mT @ R, torch.eye(3, dtype=torch.float64)), bool((R.det() > 0).all())
        (True, True)
        >>> R.sum().backward()
        >>> M.grad.shape
        torch.Size([4, 5, 3, 3])

        A local-global solver's update: one Cayley step from the previous
        rotations, written over them:

        >>> M_next = M.detach() + 0.01 * torch.randn(4, 5, 3, 3, dtype=torch.float64)
        >>> R = R.detach()
        >>> torchrot.fit_rotation(M_next, init=R, max_iter=1, out=R) is R
        True

        A bad argument raises before anything is computed:

        >>> torchrot.fit_rotation(torch.zeros(3, 4))
        Traceback (most recent call last):
            ...
        ValueError: torchrot.fit_rotation: M must have shape (..., 3, 3), got [3, 4]
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
    """:func:`fit_rotation` plus per-matrix diagnostics: the Cayley steps and how R was found.

    Convention: R (det +1) maximises tr(R^T M); for centred point sets
    ``M = sum_i w_i y_i x_i^T`` gives ``R x_i ~ y_i`` (column vectors).

    Args:
        M: ``(..., 3, 3)`` float32 or float64 (float16/bfloat16 are computed in
            float32 and returned in their dtype); any batch shape and strides.
        init: optional ``(..., 3, 3)`` warm-start rotations broadcastable to M,
            on M's device, of any float dtype (as :func:`fit_rotation`'s).
        max_iter: ``None`` (default): iterate each matrix to convergence (with
            the Horn/Jacobi fallback); ``k >= 1`` (at most 1000): at most k
            Cayley steps, no fallback.
        variant: ``"newton"``, ``"conservative"`` (the default) or
            ``"gershgorin"``: how each step estimates the maximal objective
            (see :func:`fit_rotation`).

    Returns:
        :class:`FitInfo` ``(R, iterations, status)``: R ``(..., 3, 3)`` in M's
        dtype; iterations ``(...)`` int32, the Cayley steps each matrix took;
        status ``(...)`` uint8, a :class:`torchrot.FitStatus` code per matrix.
        All on M's device.

    Not differentiable: none of the outputs requires grad or carries a
    gradient, whatever M does; use :func:`fit_rotation` for that.

    Raises:
        TypeError: an argument of the wrong type or dtype (M or init not a
            float tensor, max_iter not an int or None, variant not a str), as
            :func:`fit_rotation`.
        ValueError: a wrong value, shape or device (M not ``(..., 3, 3)``, init
            not broadcastable to M or finite but not a rotation, an unknown
            variant, max_iter out of range), as :func:`fit_rotation`.

    Examples:
        >>> M = torch.stack([torch.diag(torch.tensor([3.0, 2.0, 1.0])), torch.full((3, 3), float("nan"))])
        >>> R, iterations, status = torchrot.fit_rotation_info(M)
        >>> torch.allclose(R[0], torch.eye(3)), bool(R[1].isnan().all())
        (True, True)
        >>> iterations.dtype, [torchrot.FitStatus(code).name for code in status.tolist()]
        (torch.int32, ['CAYLEY', 'NON_FINITE'])
    """
    _check_call(M, init, max_iter, variant, None)
    return FitInfo(*_fit_rotation_info_op(M, init, max_iter, variant))
