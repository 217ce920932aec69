"""Accuracy of fitted rotations against the float64 SVD, and the acceptance
criteria the tests apply."""
from __future__ import annotations

import torch

from torchrot.reference import orthogonal_svd, rotation_svd

__all__ = ['dtype_id', 'bits', 'objective', 'rotation_errors', 'orthogonal_errors', 'CRITERIA', 'conditioning']


def dtype_id(dtype: torch.dtype) -> str:
    """``"float32"`` for torch.float32: test ids and messages.

    Examples:
        >>> from torchrot.testing import dtype_id
        >>> dtype_id(torch.bfloat16)
        'bfloat16'
    """
    return str(dtype).removeprefix("torch.")

_INTEGER_VIEW = {torch.float32: torch.int32, torch.float64: torch.int64, torch.float16: torch.int16,
                 torch.bfloat16: torch.int16}

def bits(t: torch.Tensor) -> torch.Tensor:
    """The bits of a float tensor as integers (contiguous), for bit-for-bit
    comparisons in which NaN payloads and signed zeros count; other dtypes
    are returned as they are.

    Returns:
        t's bits, its shape: int32 for float32, int64 for float64, int16 for
        float16 and bfloat16.

    Examples:
        >>> from torchrot.testing import bits
        >>> zeros = torch.tensor([0.0, -0.0])
        >>> torch.equal(zeros[0], zeros[1]), torch.equal(bits(zeros[0]), bits(zeros[1]))
        (True, False)
        >>> bits(zeros).dtype
        torch.int32
    """
    t = t.contiguous()
    return t.view(_INTEGER_VIEW[t.dtype]) if t.dtype in _INTEGER_VIEW else t

def objective(R: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """tr(R^T M) per matrix, computed and returned in float64.

    Args:
        R, M: ``(..., 3, 3)`` tensors, broadcastable against each other.

    Returns:
        float64 tensor of the broadcast batch shape ``(...)``.

    Examples:
        >>> from torchrot.testing import objective
        >>> objective(torch.eye(3), torch.diag(torch.tensor([3.0, 2.0, 1.0])))
        tensor(6., dtype=torch.float64)
    """
    return (R.double() * M.double()).sum((-2, -1))

def rotation_errors(R: torch.Tensor, M: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-matrix accuracy of rotations R fitted to M, against float64 SVD.

    Args:
        R: ``(..., 3, 3)`` fitted rotations, any float dtype.
        M: ``(..., 3, 3)`` the matrices they were fitted to, R's batch shape.

    Returns:
        dict[str, torch.Tensor]: float64 tensors of M's batch shape ``(...)``,
        by key: ``"orthonormality"``, ``max |R^T R - I|`` (largest entry);
        ``"det"``, ``|det R - 1|``; ``"shortfall"``, the relative objective
        shortfall ``(tr(R*^T M) - tr(R^T M)) / |M|_F`` (0 for M = 0), with
        R* the float64 SVD's rotation; ``"distance"``, ``|R - R*|_F``
        (meaningful only where R* is unique).

    Examples:
        >>> from torchrot.testing import CRITERIA, make_matrices, rotation_errors
        >>> M = make_matrices("gaussian", 100, dtype=torch.float32)
        >>> errors = rotation_errors(torchrot.fit_rotation(M), M)
        >>> sorted(errors), errors["det"].shape, errors["det"].dtype
        (['det', 'distance', 'orthonormality', 'shortfall'], torch.Size([100]), torch.float64)
        >>> all(bool(errors[key].max() <= limit) for key, limit in CRITERIA[torch.float32].items())
        True
    """
    Md = M.double()
    return _errors_against(R.double(), Md, rotation_svd(Md), lambda det: (det - 1).abs())


def _errors_against(X: torch.Tensor, M: torch.Tensor, X_star: torch.Tensor, det_error) -> dict[str, torch.Tensor]:
    """The keys of :func:`rotation_errors` for float64 fits X of M against
    the SVD's X_star, ``det_error(det X)`` the determinant's."""
    eye = torch.eye(3, dtype=torch.float64)
    norm = M.norm(dim=(-2, -1))
    safe = torch.where(norm > 0, norm, torch.ones_like(norm))
    return {
        "orthonormality": (X.mT @ X - eye).abs().amax((-2, -1)),
        "det": det_error(torch.linalg.det(X)),
        "shortfall": (objective(X_star, M) - objective(X, M)) / safe,
        "distance": (X - X_star).norm(dim=(-2, -1)),
    }

def orthogonal_errors(Q: torch.Tensor, M: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-matrix accuracy of orthogonal matrices Q fitted to M
    (:func:`torchrot.fit_orthogonal`), against the float64 SVD's polar factor.

    Args:
        Q: ``(..., 3, 3)`` fitted orthogonal matrices, any float dtype.
        M: ``(..., 3, 3)`` the matrices they were fitted to, Q's batch shape.

    Returns:
        dict[str, torch.Tensor]: float64 tensors of M's batch shape, the keys
        of :func:`rotation_errors`: ``"orthonormality"``; ``"det"``,
        ``||det Q| - 1|``; ``"shortfall"``, ``(tr(Q*^T M) - tr(Q^T M)) /
        |M|_F`` with Q* = U V^T the float64 polar factor; ``"distance"``,
        ``|Q - Q*|_F`` (meaningful only where M is nonsingular).

    Examples:
        >>> from torchrot.testing import CRITERIA, make_matrices, orthogonal_errors
        >>> M = make_matrices("det_negative", 100)
        >>> errors = orthogonal_errors(torchrot.fit_orthogonal(M), M)
        >>> all(bool(errors[key].max() <= limit) for key, limit in CRITERIA[torch.float64].items())
        True
    """
    Md = M.double()
    return _errors_against(Q.double(), Md, orthogonal_svd(Md), lambda det: (det.abs() - 1).abs())

#: Acceptance criteria per dtype (issue #2): max orthonormality / det error
#: and max relative objective shortfall.
CRITERIA = {
    torch.float32: {"orthonormality": 1e-6, "det": 1e-6, "shortfall": 2e-6},
    torch.float64: {"orthonormality": 1e-13, "det": 1e-13, "shortfall": 1e-12},
}

def conditioning(M: torch.Tensor, orthogonal: bool = False) -> torch.Tensor:
    """Per matrix, how much rounding can move the fitted rotation:
    ``|M|_F / min(s_i + s_j)`` over the signed singular values s of M (the
    eigenvalues of the optimality system, csrc/kernel/rotation_gradient.h;
    Inf where the maximiser is not unique). A fit at working precision is
    within about eps times this of the exact rotation, in float64.

    Args:
        M: ``(..., 3, 3)`` any float dtype (computed in float64).
        orthogonal: the conditioning of the orthogonal fit
            (:func:`torchrot.fit_orthogonal`) instead: ``|M|_F / s_3``, s_3
            the smallest singular value (Inf where M is singular). Its pair
            sums are unsigned, so its derivative's system is no worse than
            this, and rounding that flips the sign of det M (where s_3 is of
            the order of rounding) moves the fit by 2.

    Returns:
        float64 tensor of M's batch shape ``(...)``: positive, or Inf.

    Examples:
        >>> from torchrot.testing import conditioning
        >>> conditioning(torch.stack([torch.eye(3), torch.diag(torch.tensor([1.0, 1.0, -1.0]))]))
        tensor([0.8660,    inf], dtype=torch.float64)
        >>> conditioning(torch.diag(torch.tensor([1.0, 1.0, -1.0])), orthogonal=True)
        tensor(1.7321, dtype=torch.float64)
    """
    M = M.double()
    s = torch.linalg.svdvals(M)
    if orthogonal:
        return M.norm(dim=(-2, -1)) / s[..., 2]
    s[..., 2] = s[..., 2] * torch.linalg.det(M).sign()
    pair_sums = torch.stack([s[..., 0] + s[..., 1], s[..., 0] + s[..., 2], s[..., 1] + s[..., 2]], -1)
    return M.norm(dim=(-2, -1)) / pair_sums.amin(-1).clamp_min(0)
