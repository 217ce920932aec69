"""Unit quaternions as rotations, and Horn's 4x4 matrix of the objective, on
structure-of-arrays lanes: the Python twin of csrc/kernel/quaternion.h
(quaternion_rotation, horn_matrix).

For a unit quaternion q = (w, x, y, z), tr(R(q)^T M) = q^T K q with
K = [[t, m^T], [m, M + M^T - t I]], t = tr M, m = vee(M - M^T) (Horn 1987;
the same t, m and T as the Cayley step, Eqs. 12 and 36).
"""
from __future__ import annotations

from torchrot.generic.cayley import skew_vector, trace

__all__ = ["quaternion_rotation", "horn_matrix"]


def quaternion_rotation(w, x, y, z):
    """The rotation matrix (9 entries, row-major) of the unit quaternion
    (w, x, y, z), column-vector convention."""
    return [
        w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z,
    ]


def horn_matrix(M):
    """Horn's K (16 entries, row-major)."""
    t = trace(M)
    m = skew_vector(M)
    K = [None] * 16
    K[0] = t
    for i in range(3):
        K[1 + i] = m[i]
        K[4 * (1 + i)] = m[i]
        for j in range(3):
            s = M[3 * i + j] + M[3 * j + i]
            K[4 * (1 + i) + 1 + j] = s - t if i == j else s
    return K
