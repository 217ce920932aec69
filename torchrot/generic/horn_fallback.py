"""The guaranteed fallback, Horn's quaternion method in float64, on
structure-of-arrays lanes: the Python twin of csrc/kernel/horn_fallback.h
(horn_rotation). The kernel's cyclic Jacobi eigensolver (jacobi_eigen4) is
replaced by torch.linalg.eigh.
"""
from __future__ import annotations

import torch

from torchrot.generic.quaternion import horn_matrix, quaternion_rotation

__all__ = ["horn_rotation"]


def horn_rotation(A):
    """The guaranteed fallback (horn_fallback.h): Horn's quaternion method in
    float64, the top eigenvector of K by torch.linalg.eigh (an extern kernel:
    the kernel's unrolled Jacobi sweeps would be a pointwise chain too deep
    for inductor to compile)."""
    device = A[0].device
    if device.type == "mps":  # no float64 and no eigh there: the (rare) fallback lanes go to the CPU
        A = [a.cpu() for a in A]
    K = torch.stack(horn_matrix([a.double() for a in A]), -1).reshape(-1, 4, 4)
    q = torch.linalg.eigh(K).eigenvectors[..., 3]  # eigenvalues ascending: the largest is last
    R = quaternion_rotation(q[:, 0], q[:, 1], q[:, 2], q[:, 3])
    return [r.to(device=device, dtype=A[0].dtype) for r in R]
