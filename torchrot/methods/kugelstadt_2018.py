"""Kugelstadt, Koschier & Bender 2018: Newton steps on tr(R^T M) from a warm
start, Alg. 3 (torchrot.methods.kugelstadt).
"""
from __future__ import annotations

import torch

from torchrot.methods._common import Tensor, _check_matrices, _cofactor, _flat, _max_normalized, _trace
from torchrot.reference import quaternion_rotation

__all__ = ["kugelstadt"]


def _kugelstadt_step(A: Tensor, R: Tensor) -> Tensor:
    """One Newton step of Kugelstadt et al. 2018 (Alg. 3, "APD"): with
    B = R^T A, gradient g = (B12 - B21, B20 - B02, B01 - B10) and the 3x3
    Hessian H = tr(B) I - (B + B^T) / 2, omega = -H^{-1} g / 4; if det H ~ 0
    omega = -g, and if omega is not an ascent direction (omega . g > 0)
    omega = -g / 8. The step is the unit quaternion
    ((1 - |omega|^2), 2 omega) / (1 + |omega|^2), applied on the right."""
    B = R.mT @ A
    g = torch.stack([B[..., 1, 2] - B[..., 2, 1], B[..., 2, 0] - B[..., 0, 2], B[..., 0, 1] - B[..., 1, 0]], -1)
    eye = torch.eye(3, dtype=A.dtype, device=A.device)
    H = _trace(B)[..., None, None] * eye - 0.5 * (B + B.mT)
    adj = _cofactor(H)  # H symmetric: adj(H) = cof(H)^T = cof(H)
    det = (H[..., :, 0] * adj[..., :, 0]).sum(-1)
    singular = det.abs() < 1e-9
    safe_det = torch.where(singular, torch.ones_like(det), det)
    omega = -0.25 * (adj @ g.unsqueeze(-1)).squeeze(-1) / safe_det.unsqueeze(-1)
    omega = torch.where(singular.unsqueeze(-1), -g, omega)
    omega = torch.where(((omega * g).sum(-1) > 0).unsqueeze(-1), -0.125 * g, omega)
    ww = (omega * omega).sum(-1, keepdim=True)
    step = torch.cat([1 - ww, 2 * omega], -1) / (1 + ww)
    return R @ quaternion_rotation(step)


def kugelstadt(M: Tensor, init: Tensor, *, max_iter: int = 1) -> Tensor:
    """Kugelstadt, Koschier & Bender (2018), "Fast corotated FEM using operator
    splitting", Alg. 3: Newton steps on tr(R^T M) from a warm start, in the
    rotation's local frame (the paper uses one step per solver iteration).

    The Newton step vector is the one of torchrot's ``variant="newton"`` (the
    Cayley step with c = tr S, Eq. 24 of Zhang et al.: z = 2 omega), but Alg. 3
    turns it into a rotation with the quaternion
    ``((1 - |omega|^2), 2 omega) / (1 + |omega|^2)``, a rotation by
    ``4 atan(|z| / 2)`` about z, where the Cayley map Q(z) rotates by
    ``2 atan(|z|)``. The two results therefore agree to third order in the
    step, not to rounding: ``~|z|^3 / 2`` radians apart, 3e-7 for a one
    degree step, 1e-3 for 15 degrees (``tests/test_methods.py`` checks that relation
    to rounding). Alg. 3's guards (gradient steps where det H ~ 0 or the
    Newton step descends) are kept; M is first divided by its largest entry
    so the paper's absolute threshold det H < 1e-9 is meaningful for any
    scale (the Newton step itself is scale invariant). The quaternion of
    Alg. 3 is kept here as a rotation matrix (R <- R R(step)), as torchrot's
    warm start is.

    Args:
        M: ``(..., 3, 3)`` float32/float64.
        init: rotations broadcastable to M: the warm start (required).
        max_iter: number of Newton steps (default 1, as in the paper).
    Returns:
        ``(..., 3, 3)`` rotations (exact rotations to rounding).

    Accuracy: one step from init at angle theta from R* errs by O(theta^2)
    (quadratic convergence) times a constant that grows with M's anisotropy:
    from inits within 2 degrees of R* on condition-number-10 data, below
    1e-3; on the warm data (up to 15 degrees, condition number 1e3) median
    ~9e-5 but ~35% above 1e-3, and where the Newton model is not concave the
    guards' gradient steps leave errors up to 180 degrees. Useless for large
    remaining rotations (60 degrees: ~90% above 1e-3), like torchrot's
    ``variant="newton", max_iter=1``.

    Raises:
        TypeError: M or init not a tensor, not float32 or float64, or init not
            of M's dtype and device; init missing (None).
        ValueError: M or init not ``(..., 3, 3)``, init not broadcastable to
            M; max_iter not an int >= 1.

    Examples:
        >>> from torchrot.methods import kugelstadt
        >>> from torchrot.testing import make_warm_start
        >>> M, init = make_warm_start("rot60", 8, seed=0)  # init: the previous rotations
        >>> R_best = torchrot.rotation_svd(M)
        >>> error = lambda R: (R - R_best).norm(dim=(-2, -1))
        >>> bool((error(kugelstadt(M, init)) < error(init)).all())  # one Newton step closer
        True
    """
    _check_matrices("kugelstadt", M, init, max_iter, init_required=True)
    if max_iter is None:
        raise ValueError("torchrot.methods.kugelstadt: max_iter must be an int >= 1 (Newton steps), got None")
    A, R = _flat(M, init)
    A = _max_normalized(A)
    for _ in range(max_iter):
        R = _kugelstadt_step(A, R)
    return R.reshape(M.shape)
