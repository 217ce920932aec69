"""Horn 1987: the closed form by the eigenvector of Horn's 4x4 matrix
(torchrot.methods.horn).
"""
from __future__ import annotations

import torch

from torchrot.methods._common import Tensor, _check_matrices
from torchrot.reference import horn_matrix, quaternion_rotation

__all__ = ["horn"]


def horn(M: Tensor) -> Tensor:
    """Horn (1987), "Closed-form solution of absolute orientation using unit
    quaternions": the unit quaternion q maximising q^T K q, the dominant
    eigenvector of Horn's symmetric 4x4 matrix K(M) (tr(R(q)^T M) = q^T K q),
    by ``torch.linalg.eigh`` (batched LAPACK), in M's dtype.

    Args:
        M: ``(..., 3, 3)`` float32/float64.
    Returns:
        ``(..., 3, 3)`` rotations maximising tr(R^T M) in M's dtype (column
        vectors, ``M = sum w y x^T`` gives ``R x ~ y``); exact rotations to rounding.

    Accuracy: K's eigenvalues are the signed sums +-sigma_1 +- sigma_2 +-
    sigma_3 of M's singular values, and the gap at the top is
    2 (sigma_2 + sigma_3), so the eigenvector (hence R) errs by about
    ``eps ||M|| / (sigma_2 + sigma_3)``: ~1e-6 (float32) / ~1e-15 (float64) on
    well-conditioned M, growing on the warm data with condition number 1e5
    (float32 ~1e-2, like any float32 method there). Where sigma_2 + sigma_3 = 0
    (rank-1 M, M = -I, ...) the maximiser is not unique and Horn returns one of
    them. det M < 0, rank-2 M and 180-degree rotations are handled exactly (the
    quaternion needs no special case).

    Raises:
        TypeError: M not a tensor, or not float32 or float64.
        ValueError: M not ``(..., 3, 3)``.

    Examples:
        >>> from torchrot.methods import horn
        >>> from torchrot.testing import make_matrices
        >>> M = make_matrices("rot60", 8)
        >>> torch.allclose(horn(M), torchrot.fit_rotation(M))
        True
    """
    _check_matrices("horn", M)
    _, vectors = torch.linalg.eigh(horn_matrix(M))
    return quaternion_rotation(vectors[..., :, -1])
