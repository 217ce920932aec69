"""Derivatives of fit_rotation: autograd, forward mode, vmap and autocast rules.

The fitted rotation R maximises tr(R^T M), so S = R^T M is symmetric. Perturbing
M by dM and R by R [w]x and keeping S symmetric gives the 3x3 system

    (tr(S) I - S) w = vex(R^T dM - dM^T R),        dR = R [w]x,

whose matrix has eigenvalues sigma_i + sigma_j (derivation in
csrc/kernel/rotation_gradient.h). The map dM -> dR is self-adjoint, so one
operator, ``torch.ops.torchrot.fit_rotation_backward(X, R, M, gradient_eps)``,
gives the backward (X = dL/dR, result dL/dM) and the forward-mode tangent
(X = dM, result dR). No SVD is involved. The system is solved with Tikhonov
damping lambda = gradient_eps |M|_F, (A^2 + lambda^2 I)^-1 A, which equals the
exact derivative up to a relative (lambda / (sigma_i + sigma_j))^2 and stays
bounded where R is not unique (rank-deficient M, rotations by pi).

No gradient flows to ``init``: the maximiser does not depend on where the
iteration starts. With a finite ``max_iter`` the derivative is that of the
exact maximiser, evaluated at the returned R.

The derivative operator is differentiable in turn, in X, R and M
(torchrot/_tangent_derivative.py: the same damped map, differentiated
exactly), so second (and higher) derivatives of fit_rotation work: double
backward, gradgradcheck, torch.func.hessian and every nesting of jacrev,
jacfwd, grad, vjp and jvp. Where the first derivative is finite, so are they.

Registered here:
  * ``FitRotationFunction`` (forward-mode ``jvp``, generated vmap rule) as
    the Python Autograd kernel of ``torchrot::fit_rotation``, and
    ``_TangentFunction`` (the same, differentiating the tangent) as that of
    ``torchrot::fit_rotation_backward`` (the operators' C++ Autograd kernels,
    csrc/autograd.cpp, hand them the calls of torch.func, forward mode,
    tracing and create_graph): derivatives of every order in reverse and
    forward mode, under every torch.func transform and composition, in eager
    and under torch.compile (which traces the operator; :func:`torchrot.
    fit_rotation` calls it). Each records at the torch.func level that calls
    it and hands its own operations on to the levels below, which record
    them in turn (``_at_levels_below``);
  * vmap rules for both operators, and autocast (CPU, CUDA) to float32.
"""
from __future__ import annotations

import contextlib

import torch
from torch.autograd import forward_ad

from torchrot._constants import DEFAULT_VARIANT, GRADIENT_EPS
from torchrot._tangent_derivative import tangent_jvp, tangent_vjp
from torchrot._torch_private import (
    after_autograd_keyset,
    any_requires_grad,
    below_autograd,
    enable_single_level_autograd_function,
    forward_grad_enabled,
    forward_grad_mode,
    forward_level,
    functorch_front_excluded,
    functorch_transforms_active,
    single_level_function,
    unwrap_dead_wrappers,
)

__all__ = ["FitRotationFunction", "rotation_tangent"]


def rotation_tangent(X: torch.Tensor, R: torch.Tensor, M: torch.Tensor, gradient_eps: float) -> torch.Tensor:
    """dL/dM for X = dL/dR, or dR for X = dM, at R = fit_rotation(M).

    X and R: ``(..., 3, 3)`` of the same shape; M: broadcastable to R (for
    fit_rotation's own derivatives it has R's shape).
    """
    return torch.ops.torchrot.fit_rotation_backward(X, R, M, gradient_eps)


class _TangentFunction(torch.autograd.Function):
    """rotation_tangent (the operator fit_rotation_backward) with its own
    derivatives in X, R and M, in both modes (torchrot/_tangent_derivative.py):
    the second derivatives of fit_rotation. The values are the operator's
    kernels'; their derivatives are exact (autograd of the same damped map
    in reverse mode, the map's derivative written out in forward mode) and
    differentiable again."""

    generate_vmap_rule = True

    @staticmethod
    def forward(X, R, M, gradient_eps):
        return _at_levels_below(_BACKWARD_OP, X, R, M, gradient_eps)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(*inputs[:3])
        ctx.save_for_forward(*inputs[:3])
        ctx.gradient_eps = inputs[3]

    @staticmethod
    def backward(ctx, grad):
        X, R, M = ctx.saved_tensors
        grads = tangent_vjp(X, R, M, ctx.gradient_eps, grad)
        return *(g if needed else None for g, needed in zip(grads, ctx.needs_input_grad)), None

    @staticmethod
    def jvp(ctx, dX, dR, dM, _gradient_eps):
        X, R, M = ctx.saved_tensors
        if not _inside_level():
            return tangent_jvp(X, R, M, ctx.gradient_eps, dX, dR, dM)
        with _recording_below(), below_autograd():  # as _at_levels_below
            return tangent_jvp(X, R, M, ctx.gradient_eps, dX, dR, dM)


def _inside_level() -> bool:
    """Whether code runs inside an Autograd kernel called for one torch.func
    level (the operators' Python Autograd kernels, below), where operations
    reach the levels below only past the Autograd keys, and not in a
    derivative rule that torch.func's own custom_function_call runs (its
    operations go through every level as any call does)."""
    return functorch_transforms_active() and functorch_front_excluded()


def _recording_below() -> contextlib.AbstractContextManager:
    """Inside an Autograd kernel called for one torch.func level (a
    Function's forward or jvp rule, where both modes are off): the
    operations record their derivatives at the levels below that one again,
    as the transform would have them recorded (each level then restores the
    grad modes it was entered with, as functorch's own single-level
    Functions rely on). Elsewhere a no-op."""
    if not _inside_level():
        return contextlib.nullcontext()
    stack = contextlib.ExitStack()
    stack.enter_context(torch.enable_grad())
    stack.enter_context(forward_grad_mode(True))
    return stack


def _at_levels_below(op, *args) -> torch.Tensor:
    """``op(*args)`` past the operator's Autograd kernel at the current
    level, from inside a derivative rule: outside torch.func straight to its
    kernel, recording nothing; under torch.func on to the levels below, each
    of which records the operator's derivatives for itself."""
    with _recording_below(), below_autograd():
        return op(*args)


def _below_autograd(op, *args) -> torch.Tensor:
    """``op(*args)`` straight to its kernel, past the operator's Autograd
    kernel: for calls that record no derivative outside torch.func, whatever
    tangents their tensors carry."""
    with below_autograd():
        return op(*args)


def _tangent(X: torch.Tensor, R: torch.Tensor, M: torch.Tensor, gradient_eps: float) -> torch.Tensor:
    """rotation_tangent inside a derivative rule of FitRotationFunction,
    recorded wherever it may be differentiated again (second derivatives).

    Outside torch.func, the operator's Autograd kernel applies
    _TangentFunction itself wherever a derivative would be recorded
    (create_graph=True, reverse over forward). Under torch.func, a backward
    run by the transform's autograd call applies _TangentFunction at every
    level. A jvp rule, though, runs inside the operator's Autograd kernel for
    one level with both modes off: there the operator goes on to the levels
    below, with their modes restored, each of which records _TangentFunction
    (forward over forward: jacfwd(jacfwd(...)), jvp(jvp(...))).
    """
    if not functorch_transforms_active():
        if not torch.is_grad_enabled():  # backward without create_graph: nothing to record
            return _below_autograd(_BACKWARD_OP, X, R, M, gradient_eps)
        return rotation_tangent(X, R, M, gradient_eps)
    if not functorch_front_excluded():
        return _TangentFunction.apply(X, R, M, gradient_eps)
    return _at_levels_below(_BACKWARD_OP, X, R, M, gradient_eps)


class FitRotationFunction(torch.autograd.Function):
    """R = fit_rotation(M, init, max_iter, variant, gradient_eps) with its
    derivatives in M: the operator's Autograd kernel (below).

    See the module docstring for the formula. ``init`` receives no gradient;
    R has M's shape (init broadcasts to M), so dL/dM needs no reduction.
    """

    generate_vmap_rule = True

    @staticmethod
    def forward(M, init, max_iter, variant, gradient_eps):
        # Both derivative modes are off here: the operator runs below autograd
        # (under torch.func through the dispatcher, for the levels below,
        # which record it for themselves: second derivatives).
        return _at_levels_below(_FIT_OP, M, init, max_iter, variant, gradient_eps)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(output, inputs[0])
        ctx.save_for_forward(output, inputs[0])
        ctx.gradient_eps = inputs[4]

    @staticmethod
    def backward(ctx, grad_R):
        R, M = ctx.saved_tensors
        grad_M = _tangent(grad_R, R, M, ctx.gradient_eps) if ctx.needs_input_grad[0] else None
        return grad_M, None, None, None, None

    @staticmethod
    def jvp(ctx, dM, _dinit, _max_iter, _variant, _gradient_eps):
        R, M = ctx.saved_tensors
        if dM is None:  # only init carries a tangent
            return torch.zeros_like(R)
        return _tangent(dM, R, M, ctx.gradient_eps)


# ---- autograd of the operators themselves (torch.ops.torchrot.*) ----
#
# Not torch.library.register_autograd: the autograd.Function it generates has
# no forward-mode rule (under torch.func.jvp / forward AD the tangent silently
# came out as zero) and no setup_context (torch.func.grad raised). These
# Autograd kernels apply the autograd.Functions above instead, so the operator
# is differentiable in every mode and under every torch.func transform, also
# where torch.compile traces it. Each is registered on the operator's twin
# torchrot::_<name>_python_autograd: the operator's own Autograd kernel
# (csrc/autograd.cpp) runs calls that can record no derivative below
# autograd, records a plain reverse-mode fit in M with a C++ node, and hands
# the others (torch.func, forward mode, tracing), with their dispatch keys,
# to the twin.

_lib = torch.library.Library("torchrot", "IMPL")
_FIT_OP = torch.ops.torchrot.fit_rotation.default
_BACKWARD_OP = torch.ops.torchrot.fit_rotation_backward.default

def _has_tangent(args) -> bool:
    """Whether a tensor argument carries a forward-mode tangent. A dual level
    opened by forward_ad.dual_level sets forward_level(), but one
    replayed by torch.compile's tracer (AOTAutograd, make_fx) does not, so
    traced tensors (subclasses: FakeTensor, FunctionalTensor, ...) are
    checked one by one (the check costs about as much as a small fit)."""
    if forward_level() >= 0:
        return True
    return any(
        type(a) is not torch.Tensor and forward_ad.unpack_dual(a, level=0).tangent is not None
        for a in args if isinstance(a, torch.Tensor)
    )


def _register_autograd(name: str, function: type[torch.autograd.Function]) -> None:
    """Makes ``function`` (applied to the operator's full argument list) the
    Python Autograd kernel of ``torchrot::<name>``, registered on its twin
    ``torchrot::_<name>_python_autograd`` (see above)."""
    op = getattr(torch.ops.torchrot, name).default
    defaults = tuple(a.default_value for a in op._schema.arguments)
    apply = single_level_function(function).apply

    def kernel(keyset, *args):
        args = args + defaults[len(args):]  # the dispatcher drops trailing defaulted arguments
        functorch = functorch_transforms_active()
        # Derivatives to record: reverse mode with an input that requires
        # grad; forward mode while a dual level is open (torch.func.jvp's
        # levels, also replayed by torch.compile, are functorch levels; the
        # tangents themselves cannot be queried cheaply). Inside the
        # Function's forward both modes are off, so the operator it calls
        # comes back here and runs below autograd.
        if (torch.is_grad_enabled() and any_requires_grad(*args)) or (
            forward_grad_enabled() and (functorch or _has_tangent(args))
        ):
            if not functorch:
                return apply(*unwrap_dead_wrappers(args))
            # Called by a torch.func grad/jvp level on its wrapped tensors, as
            # any operator's autograd kernel is: the Function records at that
            # one level, like functorch's own per-level Functions.
            with enable_single_level_autograd_function():
                return apply(*args)
        with below_autograd():
            return op.redispatch(keyset & after_autograd_keyset, *args)

    _lib.impl(f"_{name}_python_autograd", kernel, "Autograd", with_keyset=True)


_register_autograd("fit_rotation", FitRotationFunction)
_register_autograd("fit_rotation_backward", _TangentFunction)


# ---- vmap rules: every operator takes any batch shape, so a vmapped
# dimension just becomes the leading batch dimension ----


def _leading(x: torch.Tensor | None, bdim: int | None, rank: int, size: int) -> torch.Tensor | None:
    """x with its vmapped dim first, padded to ``rank`` logical dims (so it
    broadcasts like the unbatched call); unbatched x is expanded to ``size``."""
    if x is None:
        return None
    if bdim is None:
        x = x.unsqueeze(0).expand(size, *x.shape)
    else:
        x = x.movedim(bdim, 0)
    while x.dim() < rank + 1:
        x = x.unsqueeze(1)
    return x


@torch.library.register_vmap("torchrot::fit_rotation")
def _fit_rotation_vmap(info, in_dims, M, init=None, max_iter=None, variant=DEFAULT_VARIANT,
                       gradient_eps=GRADIENT_EPS):
    in_dims = tuple(in_dims) + (None,) * (2 - len(in_dims))  # defaulted arguments have no entry
    rank = max(M.dim() - (in_dims[0] is not None), 0 if init is None else init.dim() - (in_dims[1] is not None))
    M = _leading(M, in_dims[0], rank, info.batch_size)
    init = _leading(init, in_dims[1], rank, info.batch_size)
    return torch.ops.torchrot.fit_rotation(M, init, max_iter, variant, gradient_eps), 0


@torch.library.register_vmap("torchrot::fit_rotation_backward")
def _fit_rotation_backward_vmap(info, in_dims, grad, R, M, gradient_eps=GRADIENT_EPS):
    rank = max(t.dim() - (d is not None) for t, d in zip((grad, R, M), in_dims))
    grad, R, M = (_leading(t, d, rank, info.batch_size) for t, d in zip((grad, R, M), in_dims))
    return torch.ops.torchrot.fit_rotation_backward(grad, R, M, gradient_eps), 0


# Under torch.autocast the fit runs in float32 (reduced precision would not
# resolve the objective, and the kernels compute in float32 anyway).
for _device in ("cpu", "cuda"):
    torch.library.register_autocast("torchrot::fit_rotation", _device, torch.float32)
    torch.library.register_autocast("torchrot::fit_rotation_info", _device, torch.float32)
