"""``torch.nn`` modules for learning with rotations.

``RotationFit`` turns a network's raw 3x3 (or 9-D) output into a rotation, the
special orthogonalisation R = argmax tr(R^T M) (the rotation nearest M), as
:func:`torchrot.fit_rotation`; ``RigidRegistration`` fits (R, t, s) between
point sets as :func:`torchrot.rigid_registration`. Column-vector convention:
for centred point sets M = sum_i w_i y_i x_i^T gives R x_i ~ y_i.

Both modules hold no parameters or buffers (their state_dict is empty), are
plain picklable Python objects, and work inside DistributedDataParallel.
"""
from __future__ import annotations

import torch
from torch import nn

from torchrot._checks import check_gradient_eps, check_max_iter, check_variant
from torchrot._constants import DEFAULT_VARIANT
from torchrot.fitting import fit_rotation
from torchrot.registration import RigidTransform, rigid_registration

__all__ = ["RotationFit", "RigidRegistration"]


class RotationFit(nn.Module):
    """Rotation layer: M ``(..., 3, 3)`` or ``(..., 9)`` -> R ``(..., 3, 3)``.

    R (det +1) maximises tr(R^T M), i.e. is the rotation nearest M in the
    Frobenius norm (the "special orthogonalisation" used for rotation
    regression). A ``(..., 9)`` input is read row-major: ``M = v.reshape(..., 3, 3)``.
    Column vectors: for centred point sets ``M = sum_i w_i y_i x_i^T`` gives
    ``R x_i ~ y_i``. Inputs are float32 or float64 (float16/bfloat16, e.g.
    under autocast, are computed in float32); R has the input's dtype and
    device, and gradients flow to M as :func:`torchrot.fit_rotation`'s.

    Args:
        max_iter: as :func:`torchrot.fit_rotation`: ``None`` converges every
            matrix; ``k >= 1`` (at most 1000) takes at most k Cayley steps
            (use with ``init``).
        variant: ``"newton"``, ``"conservative"`` (the default) or ``"gershgorin"``.
        gradient_eps: damping of the backward near singular systems, a float
            from 0 to 1000 (see :func:`torchrot.fit_rotation`); ``None`` uses
            :data:`torchrot.DEFAULT_GRADIENT_EPS`.

    Raises:
        TypeError: max_iter not an int or None, variant not a str, or
            gradient_eps not a float, int or None.
        ValueError: max_iter out of range, an unknown variant, or gradient_eps
            out of range.

    Examples:
        >>> layer = torchrot.nn.RotationFit()
        >>> layer
        RotationFit(max_iter=None, variant='conservative', gradient_eps=None)
        >>> v = torch.randn(8, 9, requires_grad=True)  # e.g. a network's 9-D output
        >>> R = layer(v)
        >>> R.shape, torch.allclose(R.mT @ R, torch.eye(3).expand(8, 3, 3), atol=1e-5)
        (torch.Size([8, 3, 3]), True)
        >>> R.sum().backward()
        >>> v.grad.shape
        torch.Size([8, 9])
    """

    def __init__(self, max_iter: int | None = None, variant: str = DEFAULT_VARIANT,
                 gradient_eps: float | None = None) -> None:
        super().__init__()
        check_max_iter(max_iter, "RotationFit")
        check_variant(variant, "RotationFit")
        if gradient_eps is not None:
            check_gradient_eps(gradient_eps, "RotationFit")
        self.max_iter = max_iter
        self.variant = variant
        self.gradient_eps = gradient_eps

    def forward(self, M: torch.Tensor, init: torch.Tensor | None = None) -> torch.Tensor:
        """R ``(..., 3, 3)`` for M ``(..., 3, 3)`` or ``(..., 9)`` (row-major).

        Args:
            M: ``(..., 3, 3)`` or ``(..., 9)`` float32 or float64 (float16/
                bfloat16 computed in float32).
            init: optional warm-start rotations ``(..., 3, 3)`` broadcastable
                to the batch, on M's device (no gradient flows to it).

        Returns:
            ``(..., 3, 3)`` rotations in M's dtype, differentiable in M.

        Raises:
            TypeError: M not a tensor; and :func:`torchrot.fit_rotation`'s
                errors for M's dtype and init.
            ValueError: M not ``(..., 3, 3)`` or ``(..., 9)``; init not
                broadcastable or not rotations (from :func:`torchrot.fit_rotation`).

        Examples:
            >>> layer = torchrot.nn.RotationFit(max_iter=1)  # one warm-started Cayley step
            >>> M = torch.randn(4, 3, 3)
            >>> R_previous = torchrot.fit_rotation(M)
            >>> layer(M + 0.01 * torch.randn(4, 3, 3), init=R_previous).shape
            torch.Size([4, 3, 3])
        """
        return fit_rotation(as_matrices(M), init, max_iter=self.max_iter, variant=self.variant,
                            gradient_eps=self.gradient_eps)

    def extra_repr(self) -> str:
        return f"max_iter={self.max_iter}, variant={self.variant!r}, gradient_eps={self.gradient_eps}"


class RigidRegistration(nn.Module):
    """Weighted point-set registration layer: ``(x, y, weights) -> (R, t, s)``.

    Minimises ``sum_i w_i ||s R x_i + t - y_i||^2`` (column vectors,
    ``y ~ s R x + t``) as :func:`torchrot.rigid_registration`: x, y
    ``(..., N, 3)``, weights ``(..., N)`` >= 0 or None; returns R ``(..., 3, 3)``,
    t ``(..., 3)``, s ``(...)`` in the inputs' dtype (float32, float64;
    float16/bfloat16 computed in float32), differentiable in x, y and weights.

    Args:
        scale: also fit Umeyama's uniform scale (otherwise s = 1); a bool.
        allow_reflection: fit the nearest orthogonal matrix (det +1 or -1),
            :func:`torchrot.fit_orthogonal`, instead of the nearest rotation
            (PyTorch3D's name); a bool.

    Raises:
        TypeError: scale or allow_reflection is not a bool.

    Examples:
        >>> register = torchrot.nn.RigidRegistration(scale=True)
        >>> x = torch.randn(2, 10, 3, dtype=torch.float64)
        >>> R, t, s = register(x, 3.0 * x + 1.0)  # y = s x + t: R = I, s = 3
        >>> R.shape, t.shape, s.round(decimals=6)
        (torch.Size([2, 3, 3]), torch.Size([2, 3]), tensor([3., 3.], dtype=torch.float64))
    """

    def __init__(self, scale: bool = False, allow_reflection: bool = False) -> None:
        super().__init__()
        if not isinstance(scale, bool):
            raise TypeError(f"RigidRegistration: scale must be a bool, got {scale!r}")
        if not isinstance(allow_reflection, bool):
            raise TypeError(f"RigidRegistration: allow_reflection must be a bool, got {allow_reflection!r}")
        self.scale = scale
        self.allow_reflection = allow_reflection

    def forward(self, x: torch.Tensor, y: torch.Tensor, weights: torch.Tensor | None = None, *,
                init: torch.Tensor | None = None) -> RigidTransform:
        """``(R, t, s)`` mapping x onto y: ``y_i ~ s R x_i + t``.

        Args:
            x: ``(..., N, 3)`` source points.
            y: ``(..., N, 3)`` target points, x's N, dtype and device; batch
                dimensions of x, y and weights broadcast.
            weights: optional ``(..., N)`` non-negative weights; ``None``: all ones.
            init: optional ``(..., 3, 3)`` warm-start rotations (orthogonal
                matrices with ``allow_reflection``) broadcastable to the batch
                (no gradient flows to it).

        Returns:
            :class:`torchrot.RigidTransform` ``(R, t, s)``: ``(..., 3, 3)``,
            ``(..., 3)`` and ``(...)`` over the broadcast batch shape.

        Raises:
            TypeError: as :func:`torchrot.rigid_registration` (a non-tensor,
                an unsupported or mismatched dtype).
            ValueError: as :func:`torchrot.rigid_registration` (shapes,
                devices, negative weights, fewer than 3 points of nonzero weight).

        Examples:
            >>> register = torchrot.nn.RigidRegistration()
            >>> x = torch.randn(5, 3)
            >>> R, t, s = register(x, x, torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0]))  # the first 3 points only
            >>> torch.allclose(R, torch.eye(3), atol=1e-5), torch.allclose(t, torch.zeros(3), atol=1e-5)
            (True, True)
        """
        return rigid_registration(x, y, weights, scale=self.scale, init=init, allow_reflection=self.allow_reflection)

    def extra_repr(self) -> str:
        return f"scale={self.scale}, allow_reflection={self.allow_reflection}"


def as_matrices(M: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` view of M given as ``(..., 3, 3)`` or row-major ``(..., 9)``."""
    if not isinstance(M, torch.Tensor):
        raise TypeError(f"RotationFit: M must be a torch.Tensor, got {type(M).__name__}")
    shape = M.shape
    if len(shape) >= 2 and shape[-1] == 3 and shape[-2] == 3:  # (the cheapest test: a layer's fixed cost)
        return M
    if len(shape) >= 1 and shape[-1] == 9:
        return M.unflatten(-1, (3, 3))
    raise ValueError(f"RotationFit: M must have shape (..., 3, 3) or (..., 9), got {list(M.shape)}")

