"""What the recorded data look like (the paper's Fig. 5 and Sec. 6.1).

For every recorded local step (M, warm start R_prev): the angle of the
optimal rotation of M_local = R_prev^T M (how far R* is from the warm start),
the condition number of M, and the error |R_1 - R*|_F of one Cayley step from
the warm start (Newton, i.e. the paper's red dots, and the conservative
estimate). R* is the float64 SVD answer; convention: R maximises tr(R^T M).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from torchrot.bench.recording import Recording
from torchrot.fitting import fit_rotation
from torchrot.reference import rotation_svd

__all__ = ["condition_numbers", "one_step_errors", "recording_statistics", "rotation_angle"]

Tensor = torch.Tensor


def rotation_angle(R: Tensor) -> Tensor:
    """Angle in radians of rotations ``(..., 3, 3)`` -> ``(...)``, accurate
    near 0 (atan2 of sin = |vee(R - R^T)|/2 and cos = (tr R - 1)/2)."""
    skew = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = skew.norm(dim=-1) / 2
    cos = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return torch.atan2(sin, cos)


def condition_numbers(M: Tensor) -> Tensor:
    """sigma_max / sigma_min per matrix ``(..., 3, 3)`` (inf where singular)."""
    s = torch.linalg.svdvals(M.double())
    return s[..., 0] / s[..., -1]


def one_step_errors(M: Tensor, R_prev: Tensor, R_star: Tensor, variant: str) -> Tensor:
    """|R_1 - R*|_F of one Cayley step from R_prev (float64), ``(n,)``."""
    R1 = fit_rotation(M.double(), R_prev.double(), max_iter=1, variant=variant)
    return (R1 - R_star).norm(dim=(-2, -1))


def _log_histogram(values: np.ndarray, lo: float, hi: float, bins: int) -> dict:
    """Counts in log-spaced bins over [lo, hi]; values outside are clipped to the ends."""
    edges = np.logspace(math.log10(lo), math.log10(hi), bins + 1)
    counts, _ = np.histogram(np.clip(values, lo, hi), bins=edges)
    return {"edges": edges.tolist(), "counts": counts.tolist()}


def _quantiles(values: np.ndarray) -> dict:
    q = np.quantile(values, [0.1, 0.5, 0.9, 0.99])
    return {"p10": q[0], "median": q[1], "p90": q[2], "p99": q[3], "max": float(values.max())}


def recording_statistics(recording: Recording, sample: int = 200_000, scatter: int = 4_000,
                         seed: int = 0) -> dict:
    """Fig. 5 statistics of a recording, on up to ``sample`` matrices (seeded
    draw); ``scatter`` of them are kept as points for the scatter plot.

    Returns plain floats/lists: angle and condition-number histograms and
    quantiles, per-variant one-step error quantiles and the shares below
    1e-5 (the paper: "over 90%") and 1e-3, and scatter points (angle in
    degrees, Newton and conservative one-step errors).
    """
    n = len(recording)
    gen = torch.Generator().manual_seed(seed)
    index = torch.randperm(n, generator=gen)[: min(sample, n)]
    M, R_prev = recording.M[index], recording.R_prev[index]
    R_star = rotation_svd(M)
    angle = torch.rad2deg(rotation_angle(R_prev.mT @ R_star)).numpy()
    cond = condition_numbers(M).numpy()
    stats = {
        "matrices": n,
        "sampled": int(index.numel()),
        "angle_degrees": {**_quantiles(angle), "share_below_1": float(np.mean(angle < 1)),
                          "share_below_10": float(np.mean(angle < 10)),
                          "histogram": _log_histogram(angle, 1e-6, 180.0, 54)},
        "condition_number": {**_quantiles(np.where(np.isfinite(cond), cond, 1e300)),
                             "histogram": _log_histogram(cond, 1.0, 1e8, 64)},
        "one_step": {},
    }
    k = min(scatter, len(angle))
    stats["scatter"] = {"angle_degrees": angle[:k].tolist()}
    for variant in ("newton", "conservative"):
        err = one_step_errors(M, R_prev, R_star, variant).numpy()
        stats["one_step"][variant] = {**_quantiles(err), "share_below_1e-5": float(np.mean(err < 1e-5)),
                                      "share_below_1e-3": float(np.mean(err < 1e-3))}
        stats["scatter"][variant] = err[:k].tolist()
    return _plain(stats)


def _plain(x):
    """numpy scalars -> Python floats, recursively (for JSON)."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x
