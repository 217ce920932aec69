"""Other ways to fit rotations, wrapped to torchrot's signature and convention.

Every function takes ``(..., 3, 3)`` matrices M and returns the rotations R
(det +1) maximising tr(R^T M), column-vector convention (M = sum_i w_i y_i x_i^T
gives R x_i ~ y_i), so the benchmark can time them on the same data and tests
can compare them with :func:`torchrot.fit_rotation`.
"""
from __future__ import annotations

import importlib.util

import torch

from torchrot.reference import rotation_svd

__all__ = ["rotation_svd", "roma_special_procrustes", "igl_fit_rotations", "available"]


def available(module: str) -> bool:
    """Whether an optional package (``"roma"``, ``"igl"``) is installed.

    Examples:
        >>> from torchrot import baselines
        >>> baselines.available("torch"), baselines.available("no_such_package")
        (True, False)
    """
    return importlib.util.find_spec(module) is not None


def roma_special_procrustes(M: torch.Tensor) -> torch.Tensor:
    """RoMa's ``special_procrustes`` (SVD based): ``(..., 3, 3)`` -> rotations.

    Requires the ``roma`` package (ImportError without it). Same convention
    as torchrot (RoMa returns the rotation closest to M); M's dtype and
    device.

    Examples:
        >>> from torchrot import baselines
        >>> M = torch.randn(4, 3, 3, dtype=torch.float64)
        >>> if baselines.available("roma"):
        ...     R = baselines.roma_special_procrustes(M)
        ... else:  # (without RoMa, the SVD answer it computes)
        ...     R = torchrot.rotation_svd(M)
        >>> torch.allclose(R, torchrot.fit_rotation(M))
        True
    """
    import roma

    return roma.special_procrustes(M)


def igl_fit_rotations(M: torch.Tensor, single_precision: bool = False) -> torch.Tensor:
    """libigl's ``fit_rotations`` (the ARAP local step), wrapped.

    Requires the ``libigl`` package. libigl takes a float64 (3n, 3) NumPy stack
    interleaved by row (row i of matrix r at row i n + r) and returns each
    rotation transposed (it maximises tr(R M)); both conversions are part of
    the call, as they would be for a PyTorch user.

    Args:
        M: ``(..., 3, 3)`` on any device (copied to the CPU; not differentiable).
        single_precision: libigl's float32 path.

    Returns:
        ``(..., 3, 3)`` rotations in M's dtype, on the CPU.

    Raises:
        ImportError: libigl is not installed.

    Examples:
        >>> from torchrot import baselines
        >>> M = torch.randn(4, 3, 3, dtype=torch.float64)
        >>> if baselines.available("igl"):
        ...     R = baselines.igl_fit_rotations(M)
        ... else:  # (without libigl, the SVD answer it computes)
        ...     R = torchrot.rotation_svd(M)
        >>> torch.allclose(R, torchrot.fit_rotation(M))
        True
    """
    import igl

    batch = M.shape[:-2]
    flat = M.reshape(-1, 3, 3)
    n = flat.shape[0]
    stack = flat.detach().to(torch.float64).permute(1, 0, 2).reshape(3 * n, 3).cpu().numpy()
    blocks = torch.from_numpy(igl.fit_rotations(stack, single_precision))  # (3, 3n), block r transposed
    R = blocks.reshape(3, n, 3).permute(1, 2, 0)
    return R.to(M.dtype).reshape(batch + (3, 3))
