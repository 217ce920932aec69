"""Quaternion helpers of the comparison methods (torchrot.methods): the
Hamilton product and rotations to quaternions. Quaternions to rotations are
torchrot.reference.quaternion_rotation (torchrot.generic.quaternion's
entries, stacked).
"""
from __future__ import annotations

import torch

from torchrot.methods._common import Tensor

__all__ = ["_quaternion_product", "rotation_to_quaternion"]


def _quaternion_product(p: Tensor, q: Tensor) -> Tensor:
    """Hamilton product p q of ``(..., 4)`` quaternions (w, x, y, z):
    R(p q) = R(p) R(q)."""
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - (pv * qv).sum(-1, keepdim=True)
    v = pw * qv + qw * pv + torch.linalg.cross(pv, qv)
    return torch.cat([w, v], -1)


def rotation_to_quaternion(R: Tensor) -> Tensor:
    """Unit quaternions (w, x, y, z) ``(..., 4)`` of rotations ``(..., 3, 3)``,
    R's dtype and device (Shepperd's method: the largest in magnitude of w, x,
    y, z is computed from the diagonal, the others from off-diagonal sums, so
    no component loses accuracy). Inverse of
    :func:`torchrot.reference.quaternion_rotation` up to the sign of q.

    Examples:
        >>> from torchrot.methods import rotation_to_quaternion
        >>> from torchrot.reference import quaternion_rotation
        >>> from torchrot.testing import rotations
        >>> rotation_to_quaternion(torch.diag(torch.tensor([-1.0, -1.0, 1.0])))  # 180 degrees about z
        tensor([0., 0., 0., 1.])
        >>> R = rotations(5, seed=0)
        >>> torch.allclose(quaternion_rotation(rotation_to_quaternion(R)), R)
        True
    """
    r = R.flatten(-2)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = r.unbind(-1)
    four_squares = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22,
                                1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    # Row k: 4 q_k q, computed with q_k the component of largest magnitude.
    rows = torch.stack([
        torch.stack([four_squares[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
        torch.stack([m21 - m12, four_squares[..., 1], m01 + m10, m02 + m20], -1),
        torch.stack([m02 - m20, m01 + m10, four_squares[..., 2], m12 + m21], -1),
        torch.stack([m10 - m01, m02 + m20, m12 + m21, four_squares[..., 3]], -1),
    ], -2)
    best = four_squares.argmax(-1)
    q = torch.gather(rows, -2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2)
    return q / q.norm(dim=-1, keepdim=True)
