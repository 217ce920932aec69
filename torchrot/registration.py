"""Weighted rigid (and similarity) registration of point sets: Kabsch / Umeyama.

``rigid_registration(x, y, w)`` finds the rotation R, translation t and
(optionally) scale s minimising

    sum_i w_i || s R x_i + t - y_i ||^2            (column vectors: R x ~ y)

in closed form (Umeyama, "Least-squares estimation of transformation parameters
between two point patterns", IEEE TPAMI 1991): with the normalised weights
p_i = w_i / sum_j w_j and the weighted centroids x̄ = sum p_i x_i, ȳ = sum p_i y_i,

    M   = sum_i p_i (y_i - ȳ)(x_i - x̄)^T          (3x3 cross-covariance)
    R   = fit_rotation(M)                           (maximises tr(R^T M))
    s   = tr(R^T M) / sum_i p_i ||x_i - x̄||^2      (Umeyama's scale; 1 if scale=False)
    t   = ȳ - s R x̄

R comes from :func:`torchrot.fit_rotation` (or, with ``allow_reflection=True``,
the orthogonal matrix of :func:`torchrot.fit_orthogonal`), so the whole map is
differentiable in x, y and the weights wherever those are.
"""
from __future__ import annotations

import contextlib
from typing import NamedTuple

import torch

from torchrot._checks import broadcast_shapes
from torchrot._constants import SUPPORTED_DTYPES, compute_dtype
from torchrot._torch_private import autocast_available, is_functorch_wrapped
from torchrot.fitting import fit_rotation
from torchrot.orthogonal import fit_orthogonal

__all__ = ["MIN_POINTS", "RigidTransform", "rigid_registration"]

_NAME = "torchrot.rigid_registration"
MIN_POINTS = 3


class RigidTransform(NamedTuple):
    """Result of :func:`rigid_registration`: ``y ~ s R x + t`` (column vectors).

    Attributes:
        R: ``(..., 3, 3)`` rotations (det +1); orthogonal matrices (det +1 or
            -1) with ``allow_reflection=True``.
        t: ``(..., 3)`` translations.
        s: ``(...)`` scales (ones when ``scale=False``).

    All three over the problems' broadcast batch shape, in the inputs' dtype.

    Examples:
        >>> x = torch.randn(2, 10, 3)
        >>> R, t, s = torchrot.rigid_registration(x, x + 1.0)  # a pure translation
        >>> R.shape, t.shape, s.shape
        (torch.Size([2, 3, 3]), torch.Size([2, 3]), torch.Size([2]))
        >>> torch.allclose(t, torch.ones(2, 3), atol=1e-5), torch.allclose(R, torch.eye(3), atol=1e-5)
        (True, True)
    """

    R: torch.Tensor
    t: torch.Tensor
    s: torch.Tensor


def rigid_registration(
    x: torch.Tensor,
    y: torch.Tensor,
    weights: torch.Tensor | None = None,
    *,
    scale: bool = False,
    init: torch.Tensor | None = None,
    allow_reflection: bool = False,
) -> RigidTransform:
    """Rigid (or similarity) transform minimising ``sum_i w_i ||s R x_i + t - y_i||^2``.

    Column-vector convention: the result maps x onto y, ``y_i ~ s R x_i + t``.
    R is :func:`torchrot.fit_rotation` of the weighted cross-covariance
    ``M = sum_i p_i (y_i - ȳ)(x_i - x̄)^T`` (p = w / sum w, x̄ and ȳ the weighted
    centroids), i.e. the Kabsch solution; with ``scale=True`` s is Umeyama's
    ``tr(R^T M) / sum_i p_i ||x_i - x̄||^2``.

    Args:
        x: ``(..., N, 3)`` source points, float32, float64, float16 or bfloat16
            (the last two computed in float32).
        y: ``(..., N, 3)`` target points, same N, dtype and device; batch
            dimensions of x, y and weights broadcast against each other.
        weights: optional ``(..., N)`` non-negative weights of x's dtype and
            device (used as given, not squared); a zero weight drops its point.
            ``None``: all ones.
        scale: also fit a uniform scale s (Umeyama). ``False``: s = 1.
        init: optional ``(..., 3, 3)`` rotations broadcastable to the batch,
            on x's device, of any float dtype (float32, float64, float16,
            bfloat16), forwarded to :func:`torchrot.fit_rotation` as its warm
            start (e.g. the previous frame's R), which checks that they are
            rotations and brings them to the compute precision. No gradient
            flows to init. With ``allow_reflection=True``: orthogonal matrices,
            forwarded to :func:`torchrot.fit_orthogonal`.
        allow_reflection: fit the orthogonal matrix (det +1 or -1) nearest to
            M, :func:`torchrot.fit_orthogonal`, instead of the rotation: a
            reflected y is then matched by a reflection (PyTorch3D's
            ``corresponding_points_alignment(..., allow_reflection=True)``),
            and s is ``tr(R^T M)``, the sum of M's singular values, over the
            same variance. ``False`` (the default): the Kabsch/Umeyama
            rotation.

    Returns:
        :class:`RigidTransform` ``(R, t, s)`` with R ``(..., 3, 3)``, t
        ``(..., 3)`` and s ``(...)`` over the broadcast batch shape, in the
        inputs' dtype (float16/bfloat16 are computed in float32). Differentiable
        in x, y and weights (through fit_rotation's backward); nothing is
        modified in place. Where the rotation is not unique (all points
        collinear, ...) fit_rotation's deterministic maximiser is returned; NaN
        in a problem's inputs gives NaN in that problem's outputs.

    Raises:
        TypeError: x, y, weights or init not a tensor, not float32/float64/
            float16/bfloat16, or x, y and weights of different dtypes; scale
            or allow_reflection not a bool.
        ValueError: shapes other than ``(..., N, 3)`` / ``(..., N)`` /
            ``(..., 3, 3)``, different N, batch dimensions that do not
            broadcast, tensors on different devices; negative weights; init
            that is not a rotation (from fit_rotation; with allow_reflection,
            not orthogonal, from fit_orthogonal); a problem with fewer than 3 points of
            nonzero weight (all-zero weights included); with ``scale=True``, a
            problem whose weighted points all coincide (s undefined). The value
            checks are skipped inside torch.compile and torch.func transforms,
            where they would need data-dependent control flow.

    Examples:
        >>> R_true = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        >>> x = torch.randn(10, 3, dtype=torch.float64)
        >>> y = 2.0 * x @ R_true.T + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)  # y_i = s R x_i + t
        >>> R, t, s = torchrot.rigid_registration(x, y, scale=True)
        >>> torch.allclose(R, R_true), t.round(decimals=6), s.round(decimals=6)
        (True, tensor([1., 2., 3.], dtype=torch.float64), tensor(2., dtype=torch.float64))

        Weights drop points: here the outliers of y.

        >>> y_outliers = y.clone()
        >>> y_outliers[:3] += 10.0
        >>> weights = torch.ones(10, dtype=torch.float64)
        >>> weights[:3] = 0.0
        >>> torch.allclose(torchrot.rigid_registration(x, y_outliers, weights).R, R_true)
        True

        A mirror image is matched by a reflection only where that is allowed:

        >>> mirror = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
        >>> round(torchrot.rigid_registration(x, x @ mirror).R.det().item(), 6)
        1.0
        >>> torch.allclose(torchrot.rigid_registration(x, x @ mirror, allow_reflection=True).R, mirror)
        True
    """
    _check_arguments(x, y, weights, scale, init, allow_reflection)
    if _values_readable(x, y, weights):
        _check_point_counts(x, weights)
    dtype = x.dtype
    compute = compute_dtype(dtype)
    # Autocast would run the covariance products in bf16; they need the input
    # precision. (Devices without autocast, such as meta, have none to turn off:
    # torch.autocast raises for them. Entering it is a noticeable part of a
    # small call's cost, so eager calls where autocast is off skip it:
    # benchmarks/lab_notes.md.)
    device_type = x.device.type
    autocast_on = autocast_available(device_type) and \
        (torch.compiler.is_compiling() or torch.is_autocast_enabled(device_type))
    no_autocast = torch.autocast(device_type, enabled=False) if autocast_on else contextlib.nullcontext()
    with no_autocast:
        if compute != dtype:
            x, y = x.to(compute), y.to(compute)
            weights = None if weights is None else weights.to(compute)
        R, t, s = _solve(x, y, weights, scale, init, allow_reflection)
    if compute != dtype:  # (Tensor.to has a cost even where it returns its tensor)
        R, t, s = R.to(dtype), t.to(dtype), s.to(dtype)
    return RigidTransform(R, t, s)


def _solve(x, y, weights, scale: bool, init, allow_reflection: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Umeyama's closed form; shapes as in :func:`rigid_registration`.

    The points are first copied to coordinate rows, ``(..., 3, N)``, so that the
    centring, the weighting and the reductions run along the points, contiguous:
    on ``(..., N, 3)`` every elementwise op runs inner loops of 3 elements,
    slower than the copy to the rows and the op on them together
    (benchmarks/lab_notes.md).
    """
    x_rows = x.mT.contiguous()  # (..., 3, N)
    y_rows = y.mT.contiguous()
    if weights is None:
        # (x.new_full: a DTensor x makes it a replicated DTensor, which the
        # products with x's sharded batch accept; torch.full would not mix.)
        p = x.new_full((x.shape[-2],), 1.0 / x.shape[-2])
    else:
        p = _normalized_weights(weights)
    p_row = p.unsqueeze(-2)  # (..., 1, N)
    x_mean = _matmul(x_rows, p.unsqueeze(-1))  # (..., 3, 1)
    y_mean = _matmul(y_rows, p.unsqueeze(-1))
    xc = x_rows - x_mean  # (..., 3, N): the centred points' coordinates
    yc = y_rows - y_mean
    xc_weighted = xc * p_row
    # M = sum_i p_i yc_i xc_i^T: (..., 3, N) @ (..., N, 3).
    M = _matmul(yc, xc_weighted.mT)
    R = (fit_orthogonal if allow_reflection else fit_rotation)(M, init)
    if scale:
        variance_x = (xc_weighted * xc).sum((-2, -1))  # sum_i p_i |xc_i|^2
        # sum_i p_i |x_i|^2 = variance_x + |x̄|^2 (without another pass over the points)
        _check_spread(variance_x, variance_x + x_mean.square().sum((-2, -1)))
        # tr(R^T M) at the maximum: the sum of M's singular values (sign-corrected for a rotation).
        s = (R * M).sum((-2, -1)) / variance_x
    else:
        s = torch.ones_like(M[..., 0, 0])  # M's batch shape (and a DTensor M's placements)
    t = (y_mean - s[..., None, None] * _matmul(R, x_mean)).squeeze(-1)
    return R, t, s


def _normalized_weights(weights: torch.Tensor) -> torch.Tensor:
    """p = w / sum(w) along the points, for any finite non-negative weights: w
    is first divided by its largest entry, so that the sum can neither
    overflow (a sum of large finite float32 weights is Inf, which made p zero
    and the fit the identity) nor lose small weights to underflow. The
    divisor is detached: p does not depend on it, so the derivative is that
    of w / sum(w)."""
    scaled = weights / weights.detach().amax(-1, keepdim=True)
    return scaled / scaled.sum(-1, keepdim=True)


def _matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a @ b. Traced by torch.compile, as a broadcast product summed over the
    inner dimension: dynamo fails on a matmul of a forward-AD dual with a
    plain tensor under vmap (vmap(jvp(...)), "Tensor device mismatch ... meta
    and cpu", pytorch/pytorch#151196); inductor fuses the sum into one
    reduction. Equal to a @ b up to rounding."""
    if torch.compiler.is_compiling():
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return a @ b


def _check_arguments(x, y, weights, scale, init, allow_reflection) -> None:
    for name, value in (("x", x), ("y", y)):
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"{_NAME}: {name} must be a torch.Tensor, got {type(value).__name__}")
        if value.dim() < 2 or value.shape[-1] != 3:
            raise ValueError(f"{_NAME}: {name} must have shape (..., N, 3), got {list(value.shape)}")
        if value.dtype not in SUPPORTED_DTYPES:
            raise TypeError(f"{_NAME}: {name} must be float32, float64, float16 or bfloat16, got {value.dtype}")
    if y.dtype != x.dtype:
        raise TypeError(f"{_NAME}: y must have x's dtype ({x.dtype}), got {y.dtype}")
    if y.device != x.device:
        raise ValueError(f"{_NAME}: y must be on x's device ({x.device}), got {y.device}")
    n = x.shape[-2]
    if y.shape[-2] != n:
        raise ValueError(f"{_NAME}: x and y must have the same number of points N, got x {list(x.shape)} "
                         f"and y {list(y.shape)}")
    batches = {"x": x.shape[:-2], "y": y.shape[:-2]}
    if weights is not None:
        if not isinstance(weights, torch.Tensor):
            raise TypeError(f"{_NAME}: weights must be None or a torch.Tensor, got {type(weights).__name__}")
        if weights.dim() < 1 or weights.shape[-1] != n:
            raise ValueError(f"{_NAME}: weights must have shape (..., N) with N = {n} (the points of x), "
                             f"got {list(weights.shape)}")
        if weights.dtype != x.dtype:
            raise TypeError(f"{_NAME}: weights must have x's dtype ({x.dtype}), got {weights.dtype}")
        if weights.device != x.device:
            raise ValueError(f"{_NAME}: weights must be on x's device ({x.device}), got {weights.device}")
        batches["weights"] = weights.shape[:-1]
    try:
        batch = broadcast_shapes(*batches.values())
    except RuntimeError:
        shapes = ", ".join(f"{name} {list(shape)}" for name, shape in batches.items())
        raise ValueError(f"{_NAME}: the batch dimensions must broadcast, got {shapes}") from None
    if not isinstance(scale, bool):
        raise TypeError(f"{_NAME}: scale must be a bool, got {scale!r}")
    if not isinstance(allow_reflection, bool):
        raise TypeError(f"{_NAME}: allow_reflection must be a bool, got {allow_reflection!r}")
    if init is not None:
        _check_init(init, x, batch)


def _check_init(init, x: torch.Tensor, batch: torch.Size) -> None:
    if not isinstance(init, torch.Tensor):
        raise TypeError(f"{_NAME}: init must be None or a torch.Tensor, got {type(init).__name__}")
    if init.dtype not in SUPPORTED_DTYPES:  # any of them: fit_rotation casts init to its compute dtype
        raise TypeError(f"{_NAME}: init must be float32, float64, float16 or bfloat16, got {init.dtype}")
    if init.device != x.device:
        raise ValueError(f"{_NAME}: init must be on x's device ({x.device}), got {init.device}")
    try:
        fits = init.dim() >= 2 and init.shape[-2:] == (3, 3) and len(init.shape) - 2 <= len(batch) \
            and broadcast_shapes(init.shape[:-2], batch) == batch
    except RuntimeError:
        fits = False
    if not fits:
        raise ValueError(f"{_NAME}: init must have shape (..., 3, 3) broadcastable to the batch shape "
                         f"{list(batch)}, got {list(init.shape)}")


def _values_readable(*tensors) -> bool:
    """Whether the tensors hold concrete values the checks may read (not while
    tracing with torch.compile, inside a torch.func transform, or on meta)."""
    if torch.compiler.is_compiling():
        return False
    for t in tensors:
        if t is None:
            continue
        if t.device.type == "meta" or is_functorch_wrapped(t):
            return False
    return True


def _check_point_counts(x: torch.Tensor, weights: torch.Tensor | None) -> None:
    """At least MIN_POINTS points of nonzero weight per problem; no negative weights."""
    if weights is None:
        if x.shape[-2] < MIN_POINTS:
            raise ValueError(f"{_NAME}: need at least {MIN_POINTS} points, got N = {x.shape[-2]}")
        return
    w = weights.detach()
    negative = (w < 0).any(-1)
    counts = (w != 0).sum(-1)
    too_few = counts < MIN_POINTS
    # One host read where all is well (on an accelerator each bool() synchronises).
    if not bool((negative | too_few).any()):
        return
    if bool(negative.any()):
        index = _first_index(negative)
        raise ValueError(f"{_NAME}: weights must be >= 0, got a negative weight in problem {index} "
                         f"(batch index of weights)")
    if bool(too_few.any()):
        index = _first_index(too_few)
        count = int(counts[index])
        what = "all weights are zero" if count == 0 else f"only {count} point(s) have nonzero weight"
        raise ValueError(f"{_NAME}: need at least {MIN_POINTS} points of nonzero weight per problem; in "
                         f"problem {index} (batch index of weights) {what}")


def _check_spread(variance_x: torch.Tensor, second_moment_x: torch.Tensor) -> None:
    """With scale=True, x must spread beyond rounding: coincident points leave s = 0/0."""
    if not _values_readable(variance_x):
        return
    rounding = (64 * torch.finfo(variance_x.dtype).eps) ** 2
    flat = variance_x.detach() <= rounding * second_moment_x.detach()
    if bool(flat.any()):
        raise ValueError(f"{_NAME}: with scale=True the points x (of nonzero weight) must not all coincide; "
                         f"they do in problem {_first_index(flat)}, so the scale is undefined")


def _first_index(mask: torch.Tensor) -> tuple[int, ...]:
    """Batch index of the first True entry of ``mask``."""
    return tuple(int(i) for i in torch.nonzero(mask)[0]) if mask.dim() else ()
