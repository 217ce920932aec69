"""The rotation fit of a local-global solver's local step, selectable.

Every solver in :mod:`torchrot.apps` hands its covariances to a
:class:`LocalStep`, so the same session can run with the SVD, with the
paper's one-step warm start, or with torchrot converged from the warm start.

Convention: the fitted R (det +1) maximises tr(R^T M); column vectors, for
M = sum_i w_i y_i x_i^T, R x_i ~ y_i. The solvers may pass transposed
problems (M^T with warm start R_prev^T gives R^T): the maximiser of
tr(Q^T M^T) is Q = R^T, so every method here is unaffected.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from torchrot._checks import check_variant
from torchrot._constants import DEFAULT_VARIANT
from torchrot.fitting import fit_rotation
from torchrot.reference import rotation_svd

__all__ = ["METHODS", "LocalStep", "keep_better", "objective"]

Tensor = torch.Tensor

#: method name -> what it computes (``LocalStep.method``).
METHODS = {
    "svd": "torch.linalg.svd special Procrustes (U diag(1, 1, det UV^T) V^T), ignores the warm start",
    "one_step": "torchrot, one Cayley step from the previous rotations (max_iter=1): the paper's warm start",
    "converged": "torchrot, iterated to convergence from the previous rotations",
}


@dataclass
class LocalStep:
    """Fits ``(n, 3, 3)`` rotations to ``(n, 3, 3)`` covariances.

    method: ``"svd"``, ``"one_step"`` or ``"converged"`` (see METHODS).
        Without a previous rotation (the very first local step), ``one_step``
        converges from a cold start, as the paper starts its Cayley runs from
        an exact fit (Fig. 7).
    variant: the Cayley step's estimate of the maximum (paper Sec. 4.2).
    monotone: for ``one_step``, keep the previous rotation of every matrix
        whose single step did not increase tr(R^T M), so a local step can never
        raise the solver's energy (one Cayley step from far away may overshoot).
        Off by default: the two traces per matrix cost about as much as the
        step itself, and the sessions here never needed it (the benchmark
        checks that the energy never increases).
    """

    method: str = "one_step"
    variant: str = DEFAULT_VARIANT
    monotone: bool = False

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"LocalStep: method must be one of {sorted(METHODS)}, got {self.method!r}")
        check_variant(self.variant, "LocalStep")

    @property
    def label(self) -> str:
        """Short name for tables and plots."""
        return {"svd": "torch.linalg.svd", "one_step": "torchrot 1-step warm",
                "converged": "torchrot converged warm"}[self.method]

    def __call__(self, M: Tensor, R_prev: Tensor | None, out: Tensor | None = None) -> Tensor:
        """Rotations for ``M`` ``(n, 3, 3)``, warm-started from ``R_prev``
        ``(n, 3, 3)`` or None. ``out``: optional preallocated ``(n, 3, 3)``
        result of M's dtype (with ``monotone``, not ``R_prev`` itself).
        Returns ``(n, 3, 3)`` rotations of M's dtype."""
        if self.method == "svd":
            R = rotation_svd(M)
            return R if out is None else out.copy_(R)
        if self.method == "converged" or R_prev is None:
            return fit_rotation(M, R_prev, variant=self.variant, out=out)
        if self.monotone and out is not None and out.data_ptr() == R_prev.data_ptr():
            raise ValueError("LocalStep: with monotone=True, out must not be R_prev (it is compared with it)")
        R = fit_rotation(M, R_prev, max_iter=1, variant=self.variant, out=out)
        if self.monotone:
            keep_better(R, R_prev, M)
        return R


def objective(R: Tensor, M: Tensor) -> Tensor:
    """tr(R^T M) per matrix: ``(..., 3, 3)`` -> ``(...)``."""
    return (R * M).sum((-2, -1))


def keep_better(R: Tensor, R_prev: Tensor, M: Tensor) -> int:
    """Puts ``R_prev`` back, in place, into the matrices of ``R`` that fit
    M worse (smaller tr(R^T M)); returns how many. All ``(n, 3, 3)``."""
    worse = objective(R, M) < objective(R_prev, M)
    count = int(worse.sum())
    if count:
        R[worse] = R_prev[worse]
    return count
