"""Where det M < 0, for a batch of 3x3 matrices, backward stable: by
Gaussian elimination with partial pivoting, as elementwise tensor operations
(any device, torch.func, torch.compile), for the orthogonal fit
(torchrot/orthogonal.py).

Why elimination and not the cofactor formula: the sign that elimination
computes is the exact sign of det(M + E) for a perturbation |E| of a few
units of rounding of |M| (Wilkinson: partial pivoting is backward stable, and
a 3x3 elimination grows its entries at most 4-fold). So it can be wrong only
where M is within rounding of a singular matrix, sigma_3 <= c eps |M|, where
both orthogonal candidates are equally near to M up to rounding
(tr(Q^T M) differs by 2 sigma_3). The cofactor formula cancels in its 2x2
minors: on float32 matrices with singular values (1, 3e-5, +-3e-5) it gave
the wrong sign for 2% of them (an objective shortfall of 6e-5, 30 times the
float32 criterion), elimination for none (measured on 100,000).
"""
from __future__ import annotations

import torch

from torchrot._constants import compute_dtype

__all__ = ["det_negative"]


def _pick(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per matrix, row ``a`` where ``mask`` else row ``b`` (rows ``(..., k)``)."""
    return torch.where(mask.unsqueeze(-1), a, b)


def det_negative(M: torch.Tensor) -> torch.Tensor:
    """True where det M < 0, False elsewhere (det M = 0, M holding NaN/Inf), per matrix.

    Args:
        M: ``(..., 3, 3)`` float tensor (float16 and bfloat16 are computed in
            float32), any strides; not differentiated.

    Returns:
        ``(...)`` bool tensor on M's device.
    """
    A = M.detach()
    A = A.to(compute_dtype(A.dtype))
    # Scaled by the largest entry (any positive factor keeps the sign), so that
    # the elimination can neither overflow nor lose the matrix to underflow.
    scale = A.abs().amax((-2, -1), keepdim=True)
    A = A / torch.where(scale > 0, scale, 1.0)
    r0, r1, r2 = A[..., 0, :], A[..., 1, :], A[..., 2, :]
    # First column: the row of largest |entry| becomes the pivot row (a swap
    # of two rows flips the sign).
    a0, a1, a2 = r0[..., 0].abs(), r1[..., 0].abs(), r2[..., 0].abs()
    take1 = (a1 > a0) & (a1 >= a2)
    take2 = (a2 > a0) & (a2 > a1)
    top = _pick(take2, r2, _pick(take1, r1, r0))
    second = _pick(take1, r0, r1)  # row 1 of (r1, r0, r2) or (r2, r1, r0)
    third = _pick(take2, r0, r2)
    pivot = top[..., 0]
    safe = torch.where(pivot != 0, pivot, 1.0)  # pivot 0: the column is 0, and so is det M
    b = second[..., 1:] - (second[..., 0] / safe).unsqueeze(-1) * top[..., 1:]
    c = third[..., 1:] - (third[..., 0] / safe).unsqueeze(-1) * top[..., 1:]
    # Second column of the 2x2 remainder, pivoted the same way.
    swap2 = c[..., 0].abs() > b[..., 0].abs()
    upper = _pick(swap2, c, b)
    lower = _pick(swap2, b, c)
    pivot2 = upper[..., 0]
    safe2 = torch.where(pivot2 != 0, pivot2, 1.0)
    last = lower[..., 1] - (lower[..., 0] / safe2) * upper[..., 1]
    sign = pivot.sign() * pivot2.sign() * last.sign()
    sign = torch.where(take1 | take2, -sign, sign)
    return torch.where(swap2, -sign, sign) < 0
