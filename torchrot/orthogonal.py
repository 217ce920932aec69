"""The orthogonal fit: the orthogonal matrix Q (det +1 or -1) nearest to M,
orthogonal Procrustes with reflections allowed (the polar factor of M), from
the rotation fit's operators and kernels.

With s = sign(det M) (+1 where det M = 0),

    Q = s fit_rotation(s M),

since the orthogonal matrices of det s are s times the rotations and
tr((s R)^T M) = tr(R^T (s M)): where det M > 0 this is the nearest rotation,
where det M < 0 minus the nearest rotation to -M (det(-M) > 0). The sign is
computed by pivoted elimination (torchrot/_det_sign.py), exact up to
rounding of M. Multiplying by s is exact, so Q is the rotation fit's result
to the bit, with its accuracy, layouts, derivatives (s is piecewise
constant) and every mode it runs in.
"""
from __future__ import annotations

import torch

from torchrot._checks import (
    ORTHOGONAL_NAME,
    check_all,
    check_gradient_eps,
    check_gradient_eps_type,
    check_max_iter_type,
    check_out,
    check_out_autograd,
    check_tensor,
    check_variant_type,
    not_orthogonal_error,
)
from torchrot._constants import DEFAULT_VARIANT, INIT_TOLERANCE, compute_dtype
from torchrot._det_sign import det_negative
from torchrot._torch_private import is_functorch_wrapped
from torchrot.fitting import fit_rotation

__all__ = ["fit_orthogonal"]



def fit_orthogonal(
    M: torch.Tensor,
    init: torch.Tensor | None = None,
    *,
    max_iter: int | None = None,
    variant: str = DEFAULT_VARIANT,
    gradient_eps: float | None = None,
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """The orthogonal matrix Q (det Q = +1 or -1) maximising tr(Q^T M): the orthogonal matrix nearest to M.

    Orthogonal Procrustes with reflections allowed: Q is the polar factor
    U V^T of the SVD M = U S V^T (PyTorch3D's ``allow_reflection=True``,
    RoMa's ``procrustes``), where :func:`fit_rotation` gives the nearest
    rotation (det +1). Computed through the rotation fit: with s = sign(det
    M), ``Q = s * fit_rotation(s * M)`` (the nearest rotation where det M >
    0; minus the nearest rotation to -M where det M < 0). Column vectors: for
    centred point sets ``M = sum_i w_i y_i x_i^T`` gives ``Q x_i ~ y_i``,
    reflections included.

    Non-unique maxima. Where det M = 0 (rank-deficient M) a rotation and a
    reflection are both nearest; the rotation, ``fit_rotation(M)``, is
    returned. The sign of det M is computed by pivoted elimination, exact for
    M perturbed within rounding: where M is within rounding of a singular
    matrix (sigma_3 of the order of eps sigma_1) the two candidates are
    equally near up to rounding, a tie, and the sign computed from M's
    rounded entries decides it, deterministically. Elsewhere Q is unique.

    Args:
        M: ``(..., 3, 3)`` float32 or float64 (float16/bfloat16 are computed
            in float32 and returned in their dtype); any batch shape and strides.
        init: optional ``(..., 3, 3)`` orthogonal matrices (det +1 or -1)
            broadcastable to M, on M's device, of any float dtype: the warm
            start (e.g. the previous call's Q), accepted as
            :func:`fit_rotation`'s (``|Q^T Q - I|_F < 0.05``). The rotation
            fit of s M starts from sign(det init) init, which is s init where
            init's determinant has M's sign; where the signs differ (det M
            changed sign since), init is no nearer than any rotation, and a
            converged fit (``max_iter=None``) still finds the maximum. No
            gradient flows to init.
        max_iter: as :func:`fit_rotation`: ``None`` converges every matrix;
            ``k >= 1`` (at most 1000) takes at most k Cayley steps.
        variant: ``"newton"``, ``"conservative"`` (the default) or
            ``"gershgorin"``, as :func:`fit_rotation`.
        gradient_eps: damping of the derivative, as :func:`fit_rotation`'s
            (a float from 0 to 1000; ``None``: :data:`torchrot.DEFAULT_GRADIENT_EPS`).
            The system solved has the eigenvalues sigma_i + sigma_j of M's
            unsigned singular values, regular wherever M is nonsingular.
        out: optional tensor of M's shape, dtype and device to write into; it
            may be ``init`` or ``M`` itself. As :func:`fit_rotation`'s out=:
            written once (its version counter bumped once), not
            differentiable, an inference tensor only in inference mode.

    Returns:
        ``(..., 3, 3)`` orthogonal matrices, M's dtype and device (``out``
        itself where given), det +1 where det M >= 0 and -1 where det M < 0.
        A matrix whose M or init holds NaN/Inf gives NaN; other matrices are
        unaffected.

    Derivatives: differentiable in M to any order, in every mode, as
    :func:`fit_rotation` (the sign is piecewise constant; at det M = 0, where
    Q jumps, the derivative is the rotation fit's).

    Raises:
        TypeError: as :func:`fit_rotation` (M, init or out not a tensor or of
            an unsupported dtype, out not of M's dtype, max_iter not an int or
            None, variant not a str, gradient_eps not a float, int or None).
        ValueError: as :func:`fit_rotation` (shapes, devices, broadcasting,
            out's rules, an unknown variant, values out of range), and init
            finite but not orthogonal. Errors name ``torchrot.fit_orthogonal``;
            a call that raises changes no tensor it was given. (Inside
            torch.compile and torch.func transforms init's values are not
            read here: the rotation fit's own check applies.)

    Examples:
        A reflection is fitted as itself, where the rotation fit cannot:

        >>> F = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
        >>> torchrot.fit_orthogonal(F).diagonal().tolist(), torchrot.fit_rotation(F).det().item()
        ([1.0, 1.0, -1.0], 1.0)

        The polar factor U V^T of the SVD, batched:

        >>> M = torch.randn(100, 3, 3, dtype=torch.float64)
        >>> U, _, Vh = torch.linalg.svd(M)
        >>> torch.allclose(torchrot.fit_orthogonal(M), U @ Vh)
        True
        >>> torch.equal(torchrot.fit_orthogonal(M).det().sign(), M.det().sign())
        True
    """
    compiling = torch.compiler.is_compiling()
    _check_call(M, init, max_iter, variant, gradient_eps, out)
    if init is not None and _values_readable(init, compiling):
        _check_orthogonal(init, M.dtype)
    # s M as a selection, not a product with s: dynamo fails on a product with a
    # tensor under nested forward-mode transforms (jvp(jvp(...)), jacfwd(jacfwd(...))).
    # (Contiguous: read from a permuted batch of M, the mask would give the
    # result that layout; the rotation fit's result has its own.)
    flip = det_negative(M).contiguous()[..., None, None]
    signed = _flip(flip, M)
    start = None if init is None else _flip(det_negative(init).contiguous()[..., None, None], init)
    if out is None:
        R = fit_rotation(signed, start, max_iter=max_iter, variant=variant, gradient_eps=gradient_eps)
        return _flip(flip, R)
    # Written once, as the rotation fit's out= is (M and init may be out:
    # the signs and start were read from them first).
    R = fit_rotation(signed, start, max_iter=max_iter, variant=variant)
    return torch.where(flip, -R, R, out=out)


def _flip(flip: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """-X where ``flip``, else X (exact)."""
    return torch.where(flip, -X, X)


def _check_call(M, init, max_iter, variant, gradient_eps, out) -> None:
    """Every argument check of :func:`fit_rotation`, in its order, naming
    fit_orthogonal, before anything is computed."""
    check_tensor(M, "M", ORTHOGONAL_NAME)
    if init is not None:
        check_tensor(init, "init", ORTHOGONAL_NAME)
    check_max_iter_type(max_iter, ORTHOGONAL_NAME)
    check_variant_type(variant, ORTHOGONAL_NAME)
    if out is not None:
        check_tensor(out, "out", ORTHOGONAL_NAME)
    if gradient_eps is not None:
        check_gradient_eps_type(gradient_eps, ORTHOGONAL_NAME)
    if out is not None:
        check_out_autograd(M, out, ORTHOGONAL_NAME)
    check_all(M, init, max_iter, variant, ORTHOGONAL_NAME)
    if out is not None:
        check_out(M, out, ORTHOGONAL_NAME)
    if gradient_eps is not None:
        check_gradient_eps(gradient_eps, ORTHOGONAL_NAME)


def _values_readable(init: torch.Tensor, compiling: bool) -> bool:
    """Whether init's values can be read here: eager, concrete values (not
    meta, not inside a torch.func transform)."""
    return not compiling and init.device.type != "meta" and not is_functorch_wrapped(init)


def _check_orthogonal(init: torch.Tensor, dtype: torch.dtype) -> None:
    """Every finite warm start is orthogonal (|Q^T Q - I|_F < INIT_TOLERANCE,
    in M's compute dtype, as the rotation fit measures it); one host read."""
    compute = compute_dtype(dtype)
    Q = init.detach().to(compute)
    # |Q^T Q - I|_F^2 = |Q^T Q|_F^2 - 2 |Q|_F^2 + 3, without an identity
    # tensor (which a DTensor init would not mix with). Q^T Q as a broadcast
    # product summed over rows, not a matmul: a batched matmul flattens the
    # batch dimensions, which DTensor (torch 2.11) cannot do where an inner
    # one is sharded.
    P = (Q.unsqueeze(-1) * Q.unsqueeze(-2)).sum(-3)
    deviation = P.square().sum((-2, -1)) - 2 * Q.square().sum((-2, -1)) + 3
    bad = Q.isfinite().all(-1).all(-1) & ~(deviation < INIT_TOLERANCE**2)
    if bool(bad.any()):
        raise not_orthogonal_error(int(bad.sum()), bad.numel(), ORTHOGONAL_NAME)
