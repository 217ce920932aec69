"""Accuracy of a fit against the float64 SVD answer, as the benchmark rows
report it."""
from __future__ import annotations

import math

import torch

__all__ = ["ACCURACY_SAMPLE", "FAILURE_THRESHOLD", "accuracy"]

ACCURACY_SAMPLE = 1_000_000  # accuracy is measured on the first matrices of each data set
FAILURE_THRESHOLD = 1e-3  # |R - R*|_F above this (or a non-finite result) counts as a failure


def accuracy(R: torch.Tensor, M64: torch.Tensor, R_star: torch.Tensor) -> dict:
    """max/median |R - R*|_F, the share and number of failures (> FAILURE_THRESHOLD
    or non-finite) and the largest objective shortfall relative to |M|_F, of
    rotations R ``(K, 3, 3)`` against R* = rotation_svd(M64) (float64, ``(K, 3, 3)``)."""
    # A non-finite result counts as infinitely wrong (a NaN would drop out of max and share).
    dist = torch.nan_to_num((R.double() - R_star).norm(dim=(-2, -1)), nan=math.inf)
    norm = M64.norm(dim=(-2, -1)).clamp_min(torch.finfo(torch.float64).tiny)
    shortfall = torch.nan_to_num(((R_star - R.double()) * M64).sum((-2, -1)) / norm, nan=math.inf)
    failed = dist > FAILURE_THRESHOLD
    return {
        "max_error": dist.max().item(),
        "median_error": dist.median().item(),
        "share_above_1e3": failed.double().mean().item(),
        "failures": int(failed.sum()),
        "max_shortfall": shortfall.max().item(),
    }
