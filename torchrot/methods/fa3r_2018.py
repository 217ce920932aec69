"""FA3R, Wu, Liu, Zhou & Li 2018: the cofactor iteration X <- k (X + cof(X))
(torchrot.methods.fa3r).
"""
from __future__ import annotations

import math

import torch

from torchrot.methods._common import Tensor, _check_matrices, _cofactor, _finish, _flat, _max_normalized, _retire

__all__ = ["FA3R_CAP", "FA3R_PAPER_ITERATIONS", "fa3r"]


#: Iteration cap of the converged mode (``max_iter=None``).
FA3R_CAP = 100
#: The number of iterations of the authors' FA3R implementation.
FA3R_PAPER_ITERATIONS = 10


def fa3r(M: Tensor, *, max_iter: int | None = FA3R_PAPER_ITERATIONS, return_iterations: bool = False):
    """FA3R, Wu, Liu, Zhou & Li (2018), "Fast rigid 3D registration solution: a
    simple method free of SVD and eigen-decomposition": the iteration on the
    columns h_x, h_y, h_z of M::

        h_x <- k (h_x + h_y x h_z),  h_y <- k (h_y + h_z x h_x),
        h_z <- k (h_z + h_x x h_y),  k = 2 / (|h_x|^2 + |h_y|^2 + |h_z|^2 + 1),

    i.e. X <- k (X + cof(X)). With X = U diag(s) V^T (U, V rotations, signed
    singular values s) it keeps U and V and maps s_1 <- k (s_1 + s_2 s_3) etc.,
    whose fixed point s = (1, 1, 1) is the rotation U V^T maximising tr(R^T M).
    Only +, x and one division per step.

    The iteration is not scale invariant (the "+1" in k; the authors apply it
    to a covariance averaged over the points), so M is first divided by
    ``||M||_F / sqrt(3)``, which leaves a rotation a fixed point.

    Args:
        M: ``(..., 3, 3)`` float32/float64.
        max_iter: ``k`` steps, default 10 (the authors' implementation);
            ``None``: until the step from an iterate with
            ``||X^T X - I||_F < sqrt(eps)`` (convergence is quadratic near the fixed point, so the
            result is orthonormal to ~eps), at most ``FA3R_CAP`` steps.
        return_iterations: also return the steps per matrix.
    Returns:
        ``(..., 3, 3)`` matrices X in M's dtype as the method leaves them,
        rotations only once converged (the method does not re-orthonormalise), and int32 step
        counts if ``return_iterations``.

    Accuracy: converged, ~1e-6 (float32) / ~1e-14 (float64). A small singular
    value s only doubles per step until it is O(1), so ~log2(condition number)
    steps are needed before the quadratic phase: the authors' 10 steps leave
    matrices of condition number >~ 1e3 (the warm data) visibly
    non-orthonormal. Where s_2 + s_3 = 0 (rank-1 M, the non-unique cases) the
    small values stay 0 and the result is not a rotation.

    Raises:
        TypeError: M not a tensor, or not float32 or float64.
        ValueError: M not ``(..., 3, 3)``; max_iter neither None nor an int >= 1.

    Examples:
        >>> from torchrot.methods import fa3r
        >>> from torchrot.testing import make_matrices
        >>> M = make_matrices("rot60", 8)
        >>> X, steps = fa3r(M, return_iterations=True)  # the authors' 10 steps
        >>> torch.allclose(X, torchrot.fit_rotation(M)), steps.tolist()
        (True, [10, 10, 10, 10, 10, 10, 10, 10])
    """
    _check_matrices("fa3r", M, None, max_iter)
    A, _ = _flat(M)
    n = A.shape[0]
    X = _max_normalized(A)  # first by the largest entry, so the norm cannot under/overflow
    scale = X.norm(dim=(-2, -1)) / math.sqrt(3.0)
    X = X / torch.where(scale > 0, scale, torch.ones_like(scale))[..., None, None]
    eps = torch.finfo(M.dtype).eps
    iterations = torch.zeros(n, dtype=torch.int32, device=M.device)
    active = torch.arange(n, device=M.device)
    X_active = X.clone()
    for _ in range(FA3R_CAP if max_iter is None else max_iter):
        if active.numel() == 0:
            break
        k = 2 / ((X_active * X_active).sum((-2, -1)) + 1)
        X_next = k[..., None, None] * (X_active + _cofactor(X_active))
        iterations[active] += 1
        if max_iter is not None:
            X_active = X_next
            continue
        # |X^T X - I|_F of the iterate just stepped from: the step squares it
        # (quadratic convergence), so below sqrt(eps) X_next is converged.
        residual = (X_active.mT @ X_active - torch.eye(3, dtype=M.dtype, device=M.device)).norm(dim=(-2, -1))
        X_active = X_next
        done = ~(residual >= math.sqrt(eps))  # NaN counts as done
        active, X_active = _retire(done, active, X, X_active)
    X[active] = X_active
    return _finish(X, M, iterations, return_iterations)
