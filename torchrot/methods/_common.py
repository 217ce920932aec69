"""Shared pieces of the comparison methods (torchrot.methods): argument checks
that name the function, small batched 3x3 helpers, and the bookkeeping of
iterations over a shrinking set of matrices.
"""
from __future__ import annotations

import torch

from torchrot._checks import broadcast_shapes

__all__ = ["Tensor", "_check_matrices", "_trace", "_cofactor", "_flat", "_max_normalized", "_finish", "_retire"]

Tensor = torch.Tensor


def _check_matrices(fn: str, M, init=None, max_iter=None, init_required: bool = False) -> None:
    """Errors name the function and the argument: M (..., 3, 3) float32/float64;
    init the same dtype and device, broadcastable to M; max_iter None or >= 1."""
    where = f"torchrot.methods.{fn}"
    for name, t in (("M", M), ("init", init)):
        if t is None:
            if name == "init" and init_required:
                raise TypeError(f"{where}: init (the warm-start rotations, (..., 3, 3)) is required")
            continue
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{where}: {name} must be a torch.Tensor, got {type(t).__name__}")
        if t.dim() < 2 or t.shape[-2:] != (3, 3):
            raise ValueError(f"{where}: {name} must have shape (..., 3, 3), got {list(t.shape)}")
        if t.dtype not in (torch.float32, torch.float64):
            raise TypeError(f"{where}: {name} must be float32 or float64, got {t.dtype}")
    if init is not None:
        if init.dtype != M.dtype or init.device != M.device:
            raise TypeError(f"{where}: init must have M's dtype and device ({M.dtype}, {M.device}), "
                            f"got {init.dtype}, {init.device}")
        try:
            ok = broadcast_shapes(init.shape[:-2], M.shape[:-2]) == M.shape[:-2]
        except RuntimeError:
            ok = False
        if not ok:
            raise ValueError(f"{where}: init of shape {list(init.shape)} must broadcast to M's shape "
                             f"{list(M.shape)}")
    if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1):
        raise ValueError(f"{where}: max_iter must be None (iterate until converged) or an int >= 1, "
                         f"got {max_iter!r}")


def _trace(S: Tensor) -> Tensor:
    return S.diagonal(dim1=-2, dim2=-1).sum(-1)


def _cofactor(X: Tensor) -> Tensor:
    """cof(X) = det(X) X^{-T}: its columns are x1 x x2, x2 x x0, x0 x x1 for the
    columns x0, x1, x2 of X."""
    x0, x1, x2 = X.unbind(-1)
    return torch.stack([torch.linalg.cross(x1, x2), torch.linalg.cross(x2, x0), torch.linalg.cross(x0, x1)], -1)


def _flat(M: Tensor, init: Tensor | None = None):
    """(n, 3, 3) views/copies of M and of init expanded to M's batch."""
    flat_M = M.reshape(-1, 3, 3)
    flat_init = None if init is None else init.expand(M.shape).reshape(-1, 3, 3)
    return flat_M, flat_init


def _max_normalized(A: Tensor) -> Tensor:
    """A divided by its largest |entry| (matrices of zeros stay zero). The
    maximiser of tr(R^T A) does not depend on A's scale; the methods whose
    arithmetic does (guards, the "+1" of FA3R, inverses that overflow) use it."""
    max_abs = A.abs().amax((-2, -1), keepdim=True)
    return A / torch.where(max_abs > 0, max_abs, torch.ones_like(max_abs))


def _finish(R: Tensor, M: Tensor, iterations: Tensor | None, return_iterations: bool):
    R = R.reshape(M.shape)
    if return_iterations:
        return R, iterations.reshape(M.shape[:-2])
    return R


def _retire(done: Tensor, active: Tensor, result: Tensor, current: Tensor, *lane_tensors: Tensor):
    """Iterations over a shrinking set of matrices: writes the ``done`` lanes'
    ``current`` iterate into ``result`` (at their indices ``active``) and drops
    them from ``active``, ``current`` and every other per-lane tensor."""
    if not bool(done.any()):
        return (active, current, *lane_tensors)
    result[active[done]] = current[done]
    keep = ~done
    return (active[keep], current[keep], *(t[keep] for t in lane_tensors))
