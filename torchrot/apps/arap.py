"""As-rigid-as-possible surface deformation (Sorkine & Alexa 2007).

Energy (the "spokes" energy, cotangent weights w_ij of ``igl.cotmatrix``):

    E(P', R) = sum_i sum_{j in N(i)} w_ij |(p'_i - p'_j) - R_i (p_i - p_j)|^2

over deformed positions P' (handles fixed at their targets) and one rotation
per vertex. Local step: with e_ij = p_i - p_j and e'_ij = p'_i - p'_j, the
best R_i maximises tr(R_i^T M_i) for the covariance

    M_i = sum_j w_ij e'_ij e_ij^T          (torchrot's convention: R e ~ e')

Global step: L P' = b, b_i = sum_j w_ij/2 (R_i + R_j) e_ij (SA07 Eq. 9), L the
cotangent Laplacian, factored once for the free vertices.

Both steps are sparse products with constant matrices, so nothing loops over
vertices in Python. Internally the solver keeps M^T and R^T (the same fit,
transposed: R^T maximises tr(Q^T M^T)), because those are the layouts the
sparse products produce and consume without copies.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch

from torchrot.apps._phases import phase
from torchrot.apps.local_step import LocalStep
from torchrot.apps.sparse import SpdSolver, torch_csr

__all__ = ["ArapSolver", "ArapState", "cotangent_weights"]

Tensor = torch.Tensor


def cotangent_weights(V: np.ndarray, F: np.ndarray) -> sp.csc_matrix:
    """The PSD cotangent Laplacian K = -igl.cotmatrix(V, F) ``(n, n)``:
    K_ij = -w_ij (w_ij = (cot a_ij + cot b_ij) / 2), K_ii = sum_j w_ij."""
    import igl

    return sp.csc_matrix(-igl.cotmatrix(np.ascontiguousarray(V, dtype=np.float64),
                                        np.ascontiguousarray(F, dtype=np.int64)))


@dataclass
class ArapState:
    """Deformed positions ``P`` ``(n, 3)`` and the last local step's
    rotations, stored transposed: ``Rt`` ``(n, 3, 3)`` with Rt[i] = R_i^T
    (None before the first local step)."""

    P: Tensor
    Rt: Tensor | None = None

    @property
    def R(self) -> Tensor | None:
        """The rotations R_i ``(n, 3, 3)`` (a transposed view)."""
        return None if self.Rt is None else self.Rt.mT


@dataclass
class ArapSolver:
    """Factor-once ARAP solver for one mesh and one set of handle vertices.

    Args:
        V: ``(n, 3)`` rest positions; F: ``(f, 3)`` triangles (int).
        handles: indices of the vertices whose positions are prescribed.
        fit: how the local step fits rotations (SVD / one step / converged);
            each step method also takes a ``fit`` for that call.
        dtype: precision of the local step (covariances, rotation fit) and
            of the right-hand side's product with the rotations; positions,
            energies and the solve are always float64. float32 is the
            precision of the paper's AVX code.
    """

    V: np.ndarray
    F: np.ndarray
    handles: np.ndarray
    fit: LocalStep = field(default_factory=LocalStep)
    dtype: torch.dtype = torch.float64

    def __post_init__(self) -> None:
        V = np.ascontiguousarray(self.V, dtype=np.float64)
        n = len(V)
        if V.ndim != 2 or V.shape[1] != 3:
            raise ValueError(f"ArapSolver: V must be (n, 3), got {V.shape}")
        if self.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"ArapSolver: dtype must be torch.float32 or torch.float64, got {self.dtype}")
        handles = np.unique(np.asarray(self.handles, dtype=np.int64))
        if len(handles) == 0 or handles[0] < 0 or handles[-1] >= n:
            raise ValueError(f"ArapSolver: handles must be a non-empty set of vertex indices in [0, {n})")
        self.n, self.handles = n, handles
        self.free = np.setdiff1d(np.arange(n), handles)
        self.K = cotangent_weights(V, self.F)
        W = sp.coo_matrix(-self.K)
        off = W.row != W.col
        I, J, w = W.row[off].astype(np.int64), W.col[off].astype(np.int64), W.data[off]
        E = V[I] - V[J]  # rest edges e_ij, one per directed edge
        wE = w[:, None] * E
        c = np.zeros((n, 3))
        np.add.at(c, I, wE)  # c_i = sum_j w_ij e_ij
        k = np.arange(3)
        diagonal_rows = (3 * np.arange(n)[:, None] + k).ravel()
        # covariance operator, M_i^T = c_i p'_i^T - sum_j w_ij e_ij p'_j^T: (C P')[3i + k] = (M_i^T)[k]
        C = sp.csr_matrix((np.concatenate([-wE.ravel(), c.ravel()]),
                           (np.concatenate([(3 * I[:, None] + k).ravel(), diagonal_rows]),
                            np.concatenate([np.repeat(J, 3), np.repeat(np.arange(n), 3)]))), shape=(3 * n, n))
        # right-hand-side operator, 2 b_i = R_i c_i + sum_j w_ij R_j e_ij with Rt_flat[3j + k] = R_j[:, k]^T
        B = sp.csr_matrix((np.concatenate([wE.ravel(), c.ravel()]),
                           (np.concatenate([np.repeat(I, 3), np.repeat(np.arange(n), 3)]),
                            np.concatenate([(3 * J[:, None] + k).ravel(), diagonal_rows]))), shape=(n, 3 * n))
        self._C64 = torch_csr(C)  # energies are always evaluated in float64
        self._C, self._B = torch_csr(C, self.dtype), torch_csr(0.5 * B, self.dtype)
        self.rest = torch.from_numpy(V)
        self._rest_energy = float(np.sum(V * (self.K @ V)))  # sum_edges w |e|^2 = tr(V^T K V)
        K = sp.csr_matrix(self.K)
        self._K_free = SpdSolver(K[self.free][:, self.free])
        self._K_handles = K[self.free][:, handles]
        self._last_targets: np.ndarray | None = None

    # -- the two steps -------------------------------------------------------
    def covariances_t(self, P: Tensor, dtype: torch.dtype = torch.float64) -> Tensor:
        """M_i^T ``(n, 3, 3)`` in ``dtype`` for positions ``P`` ``(n, 3)``, one
        sparse product: M_i^T = c_i p'_i^T - sum_j w_ij e_ij p'_j^T (expanding
        e'_ij, c_i = sum_j w_ij e_ij)."""
        if dtype == torch.float64:
            return (self._C64 @ P.double()).view(self.n, 3, 3)
        return (self._C @ P.to(dtype)).view(self.n, 3, 3)

    def local_step(self, state: ArapState, recorder=None, meta: dict | None = None, *,
                   fit: LocalStep | None = None, timer=None) -> Tensor:
        """Fits the rotations of ``state.P`` warm-started from ``state.Rt``
        with ``fit`` (default: the solver's); returns the new Rt ``(n, 3, 3)``.
        ``recorder(M, R_prev, meta)``, if given, sees each step's covariances
        M and warm start R_prev (torchrot convention, untransposed) before the
        fit. ``timer``: optional, its ``phase(name)`` contexts time "assembly"
        and "fit" (see :mod:`torchrot.apps._phases`)."""
        with phase(timer, "assembly"):
            Mt = self.covariances_t(state.P, self.dtype)
        if recorder is not None:
            recorder(Mt.mT, None if state.Rt is None else state.Rt.mT, meta or {})
        with phase(timer, "fit"):
            return (fit or self.fit)(Mt, state.Rt)

    def global_step(self, Rt: Tensor, targets: np.ndarray, *, timer=None) -> Tensor:
        """Positions ``(n, 3)`` minimising E for fixed rotations (given as
        Rt ``(n, 3, 3)``) with the handles at ``targets`` ``(h, 3)``;
        ``timer`` times "rhs" and "solve"."""
        with phase(timer, "rhs"):
            b = (self._B @ Rt.reshape(-1, 3)).double().numpy()
        with phase(timer, "solve"):
            P = np.empty((self.n, 3))
            P[self.handles] = targets
            P[self.free] = self._K_free.solve(b[self.free] - self._handle_terms(targets))
        return torch.from_numpy(P)

    def _handle_terms(self, targets: np.ndarray) -> np.ndarray:
        """K_free,handles @ targets, recomputed only when the targets change (per frame)."""
        if self._last_targets is None or not np.array_equal(self._last_targets, targets):
            self._last_targets = np.array(targets, dtype=np.float64)
            self._last_terms = self._K_handles @ self._last_targets
        return self._last_terms

    def iterate(self, state: ArapState, targets: np.ndarray, recorder=None, meta: dict | None = None, *,
                fit: LocalStep | None = None, timer=None) -> ArapState:
        """One local-global iteration: new rotations, then new positions."""
        Rt = self.local_step(state, recorder, meta, fit=fit, timer=timer)
        return ArapState(self.global_step(Rt, targets, timer=timer), Rt)

    # -- energy ----------------------------------------------------------------
    def energy(self, P: Tensor, Rt: Tensor | None = None) -> float:
        """E(P, R) for rotations Rt (transposed, ``(n, 3, 3)``), or, for
        ``Rt=None``, the energy of P with its optimal rotations (min over R).

        Uses sum_ij w_ij |e'_ij - R_i e_ij|^2 = 2 tr(P^T K P) + 2 tr(V^T K V)
        - 2 sum_i tr(R_i^T M_i) (each edge appears once per end point)."""
        Mt = self.covariances_t(P)
        Rt = LocalStep("converged")(Mt, None) if Rt is None else Rt.double()
        Pn = P.numpy()
        quadratic = float(np.sum(Pn * (self.K @ Pn))) + self._rest_energy
        return 2.0 * quadratic - 2.0 * float((Rt * Mt).sum())

    def initial_state(self, targets: np.ndarray | None = None) -> ArapState:
        """The rest pose (handles moved to ``targets`` if given), no rotations yet."""
        P = self.rest.clone()
        if targets is not None:
            P[torch.from_numpy(self.handles)] = torch.as_tensor(targets, dtype=P.dtype)
        return ArapState(P)
