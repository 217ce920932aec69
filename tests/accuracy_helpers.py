"""Shared by the accuracy tests of torchrot.fit_rotation against the float64
SVD answer, tests/test_accuracy_*.py: batch sizes and the bound on the
distance |R - R*|_F.

Data and metrics come from torchrot.testing. The answer R* maximises
tr(R^T M); ``rotation_errors`` measures orthonormality, det, the relative
objective shortfall and the distance |R - R*|_F (meaningful where R* is unique,
i.e. on the WELL_CONDITIONED distributions).
"""
from __future__ import annotations

import torch

from torchrot.reference import orthogonal_svd
from torchrot.testing import conditioning, orthogonal_errors, rotation_errors, rotation_svd

N = 3000  # matrices per accuracy case
N_SMALL = 1000


def _distance_limit(M: torch.Tensor, orthogonal: bool = False) -> torch.Tensor:
    """Per-matrix bound on |R - R*|_F for rotations fitted to the
    WELL_CONDITIONED matrices M: in float32, 4x what a float32 SVD achieves
    on the same data at worst, or 4 eps times the matrix's own conditioning
    where that is larger (rounding moves the fit of an ill-conditioned
    matrix by about eps kappa, whichever method: a uniform matrix of kappa
    7.9e3 is fitted to 2.5e-4 to 3.8e-4, 0.7-1.0 eps kappa, by every build
    and scale); in float64 an absolute 1e-10. ``orthogonal``: for the
    orthogonal fit, against the SVD's polar factor and with its conditioning."""
    if M.dtype == torch.float64:
        return torch.full(M.shape[:-2], 1e-10, dtype=torch.float64)
    errors, svd = (orthogonal_errors, orthogonal_svd) if orthogonal else (rotation_errors, rotation_svd)
    svd32 = errors(svd(M.float()), M)["distance"]
    return torch.maximum(4 * svd32.max(), 4 * torch.finfo(torch.float32).eps * conditioning(M, orthogonal))


def _assert_close_to_svd(R: torch.Tensor, M: torch.Tensor, what: str, orthogonal: bool = False) -> None:
    """|R - R*|_F within _distance_limit, R* the float64 SVD's rotation (or,
    ``orthogonal``, its polar factor)."""
    dist = (orthogonal_errors if orthogonal else rotation_errors)(R, M)["distance"]
    limits = _distance_limit(M, orthogonal)
    worst = int((dist / limits).argmax())
    limit = limits.flatten()[worst].item()
    assert bool((dist <= limits).all()), (
        f"{what}: |R - R*| = {dist.flatten()[worst].item():.3g} > {limit:.3g} at matrix {worst} "
        f"({int((dist > limits).sum())} of {dist.numel()} exceed their limits); M={M.reshape(-1, 3, 3)[worst].tolist()}"
    )
