"""Sparse linear algebra shared by the solvers: torch CSR operators and a
factor-once symmetric positive definite solve (SciPy's SuperLU)."""
from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import torch

__all__ = ["SpdSolver", "torch_csr"]


def torch_csr(A: sp.spmatrix, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """A SciPy sparse matrix as a torch sparse CSR tensor (for ``A @ dense``)."""
    A = sp.csr_matrix(A)
    A.sort_indices()
    with warnings.catch_warnings():  # "sparse CSR support is in beta": matmul with a dense tensor is all we use
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(torch.from_numpy(A.indptr.astype(np.int64)),
                                       torch.from_numpy(A.indices.astype(np.int64)),
                                       torch.from_numpy(A.data).to(dtype), size=A.shape)


class SpdSolver:
    """Factors a sparse symmetric positive definite ``(n, n)`` matrix once;
    :meth:`solve` then back-substitutes ``(n, k)`` right-hand sides.

    SuperLU with a minimum-degree ordering of A + A^T, symmetric mode and no
    pivoting: for an SPD matrix this is a sparse LDL^T-like factorization, many
    times faster than SciPy's default column ordering on mesh Laplacians.
    """

    def __init__(self, A: sp.spmatrix):
        A = sp.csc_matrix(A)
        if A.shape[0] != A.shape[1]:
            raise ValueError(f"SpdSolver: A must be square, got {A.shape}")
        self.n = A.shape[0]
        self.factor = sla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                               options={"SymmetricMode": True})

    @property
    def fill(self) -> int:
        """Non-zeros of the factors L and U."""
        return int(self.factor.L.nnz + self.factor.U.nnz)

    def solve(self, B: np.ndarray) -> np.ndarray:
        """A^{-1} B for ``B`` ``(n,)`` or ``(n, k)`` float64."""
        return self.factor.solve(np.ascontiguousarray(B, dtype=np.float64))
