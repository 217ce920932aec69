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
    Column vectors: for centred point sets M = sum_i w_i y_i x_i^T gives R x_i ~ y_i.

    Args:
        max_iter: as :func:`torchrot.fit_rotation`: ``None`` converges every
            matrix; ``k >= 1`` takes at most k Cayley steps (use with ``init``).
        variant: ``"newton"``, ``"conservative"`` or ``"gershgorin"``.
        gradient_eps: damping of the backward near singular systems (see
            :func:`torchrot.fit_rotation`); ``None`` uses the library default.
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

        ``init``: optional warm-start rotations ``(..., 3, 3)`` broadcastable
        to the batch (no gradient flows to it).
        """
        return fit_rotation(as_matrices(M), init, max_iter=self.max_iter, variant=self.variant,
                            gradient_eps=self.gradient_eps)

    def extra_repr(self) -> str:
        return f"max_iter={self.max_iter}, variant={self.variant!r}, gradient_eps={self.gradient_eps}"


class RigidRegistration(nn.Module):
    """Weighted point-set registration layer: ``(x, y, weights) -> (R, t, s)``.

    Minimises sum_i w_i ||s R x_i + t - y_i||^2 (column vectors, y ~ s R x + t)
    as :func:`torchrot.rigid_registration`: x, y ``(..., N, 3)``, weights
    ``(..., N)`` >= 0 or None; returns R ``(..., 3, 3)``, t ``(..., 3)``,
    s ``(...)``.

    Args:
        scale: also fit Umeyama's uniform scale (otherwise s = 1).
    """

    def __init__(self, scale: bool = False) -> None:
        super().__init__()
        if not isinstance(scale, bool):
            raise TypeError(f"RigidRegistration: scale must be a bool, got {scale!r}")
        self.scale = scale

    def forward(self, x: torch.Tensor, y: torch.Tensor, weights: torch.Tensor | None = None, *,
                init: torch.Tensor | None = None) -> RigidTransform:
        """``(R, t, s)`` mapping x onto y; ``init``: optional warm-start rotations."""
        return rigid_registration(x, y, weights, scale=self.scale, init=init)

    def extra_repr(self) -> str:
        return f"scale={self.scale}"


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

