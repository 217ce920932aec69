"""Shared by the tests of torch.func transforms, tests/test_transforms_*.py:
the compile backend (``aot_eager``, or TORCHROT_TEST_COMPILE_BACKEND), the
inputs of each function under test (P, the differentiated input, and the
constants C), random directions and incoming gradients, and Jacobians by
central differences.
"""
from __future__ import annotations

import os

import torch

import torchrot

BACKEND = os.environ.get("TORCHROT_TEST_COMPILE_BACKEND", "aot_eager")


def _inputs(target: str, name: str):
    """(P, C): float64, batch 4 (``name``: "gaussian", "identity", or "mixed_det", gaussian with det of both signs)."""
    gen = torch.Generator().manual_seed(7)
    if target in ("rigid_registration", "RigidRegistration"):
        x = torch.randn(4, 5, 3, generator=gen, dtype=torch.float64)
        R = torchrot.fit_rotation(torch.randn(4, 3, 3, generator=gen, dtype=torch.float64))
        y = 1.3 * x @ R.mT + 0.1 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
        w = torch.rand(4, 5, generator=gen, dtype=torch.float64) + 0.5
        return x, ((y, w) if target == "rigid_registration" else (y,))
    if name == "identity":
        M = torch.eye(3, dtype=torch.float64).repeat(4, 1, 1)
    else:
        M = torch.randn(4, 3, 3, generator=gen, dtype=torch.float64)
        if name == "mixed_det":  # det < 0 for matrices 1 and 3 (det > 0 for all four above)
            M[1::2] = -M[1::2]
    return (M.reshape(4, 9) if target == "RotationFit" else M), ()


def _directions(P, outputs):
    gen = torch.Generator().manual_seed(11)
    dP = torch.randn(P.shape, generator=gen, dtype=P.dtype)
    Gs = tuple(torch.randn(o.shape, generator=gen, dtype=o.dtype) for o in outputs)
    return dP, Gs


def _central_jacobians(f, P, C, h=1e-6):
    """d outputs / dP by central differences, each ``output.shape + P.shape``
    (all perturbations in one batched call: every target broadcasts C)."""
    n = P.numel()
    E = (h * torch.eye(n, dtype=P.dtype)).reshape(n, *P.shape)
    plus, minus = f(P + E, *C), f(P - E, *C)
    return tuple(((p - m) / (2 * h)).movedim(0, -1).reshape(*p.shape[1:], *P.shape)
                 for p, m in zip(plus, minus))
