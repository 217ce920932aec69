"""The derivatives of fit_rotation's derivative: the tangent map of
``torch.ops.torchrot.fit_rotation_backward`` differentiated in all of its
inputs, which second derivatives of fit_rotation (double backward,
torch.func.hessian, jacfwd(jacrev(...)), gradgradcheck) are made of.

The operator computes, for X (dL/dR in the backward, dM in forward mode), the
fitted rotation R and the fitted matrix M (csrc/kernel/rotation_gradient.h has
the derivation),

    T(X, R, M) = R [u]x / |M|_F,     u = Re (K + i eps I)^-1 g,
    K = (tr(S) I - sym S) / |M|_F,  S = R^T M,  g = vex(R^T X - X^T R),

where eps is ``gradient_eps`` (the damping lambda = eps |M|_F of the
unnormalised system). Here, in batched ``(..., 3, 3)`` tensor operations:

* :func:`tangent_value`: T itself, differentiable by autograd (not used for
  values: the operator's kernels compute those), whose reverse-mode
  derivative :func:`tangent_vjp` is;
* :func:`tangent_jvp`: dT for tangents (dX, dR, dM), written out:
  dn = <A, dA> / n, dS = dR^T A + R^T dA, dK = (tr(dS) I - sym dS) / n - K dn / n,
  dg = vex(B - B^T) with B = dR^T X + R^T dX, c = (K + i eps)^-1 g,
  du = Re (K + i eps)^-1 (dg - dK c), dT = (dR [u]x + R [du]x) / n - T dn / n
  (A = M / max|M_ij|, n = |A|_F; T is homogeneous of degree -1 in M).

Both are exact: the same damped map as the kernels' (no finite differences),
differentiated exactly. (K + i eps I)^-1 is applied by the 3x3 adjugate, as
the kernels do, without forming K^2 (which would square its condition
number). Conventions at the points where T is not differentiable, as the
kernels define T there: where M = 0 (T = 0) and where the damped system is
singular (eps = 0 and K singular: u = 0) the derivatives are 0. Float16 and
bfloat16 are computed in float32, and the results returned in the inputs'
dtypes.
"""
from __future__ import annotations

import torch

from torchrot._constants import compute_dtype

__all__ = ["tangent_jvp", "tangent_value", "tangent_vjp"]


def _compute(*tensors: torch.Tensor) -> list[torch.Tensor]:
    """The tensors in their compute dtype (float16/bfloat16: float32)."""
    return [t.to(compute_dtype(t.dtype)) for t in tensors]


def _matvec(A: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """A v for ``(..., 3, 3)`` A and ``(..., 3)`` v, as three broadcast
    products added in one order: each entry the same whatever the batch
    around it. (A batched matmul may sum in another order for another batch
    size: vmap's Hessian differed from the unbatched one in the last bits on
    a CPU whose BLAS did so. Dynamo also fails on a matmul of a forward-AD
    dual with a plain tensor under vmap, pytorch/pytorch#151196.)"""
    return A[..., 0] * v[..., 0, None] + A[..., 1] * v[..., 1, None] + A[..., 2] * v[..., 2, None]


def _transpose_times(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """A^T B for ``(..., 3, 3)`` A and B, row k of A times row k of B added
    over k in one order (as _matvec)."""
    return (A[..., 0, :, None] * B[..., 0, None, :] + A[..., 1, :, None] * B[..., 1, None, :]
            + A[..., 2, :, None] * B[..., 2, None, :])


def _vex_skew(B: torch.Tensor) -> torch.Tensor:
    """vex(B - B^T) = (B21 - B12, B02 - B20, B10 - B01), ``(..., 3)``."""
    return torch.stack([B[..., 2, 1] - B[..., 1, 2], B[..., 0, 2] - B[..., 2, 0], B[..., 1, 0] - B[..., 0, 1]], -1)


def _times_cross(R: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """R [u]x: row r is R[r] x u."""
    return torch.linalg.cross(R, u.unsqueeze(-2).expand_as(R), dim=-1)


def _trace(A: torch.Tensor) -> torch.Tensor:
    return A.diagonal(dim1=-2, dim2=-1).sum(-1)


def _optimality_matrix(S: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """(tr(S) I - sym S) / n, ``(..., 3, 3)``; n ``(...)``."""
    eye = torch.eye(3, dtype=S.dtype, device=S.device)
    sym = 0.5 * (S + S.mT)
    return (_trace(S)[..., None, None] * eye - sym) / n[..., None, None]


class _DampedInverse:
    """(K + i eps I)^-1 applied to complex 3-vectors h_re + i h_im, by the
    adjugate: adj(K + i eps I) = (adj K - eps^2 I) + i eps (tr(K) I - K),
    det(K + i eps I) = (det K - eps^2 tr K) + i eps (tr adj K - eps^2) = a + i b.
    (a, b) are scaled by max(|a|, |b|) before they are squared; where both
    are below the dtype's tiny the system is singular and the result is 0,
    as the kernels take it."""

    def __init__(self, K: torch.Tensor, eps: float) -> None:
        r0, r1, r2 = K[..., 0, :], K[..., 1, :], K[..., 2, :]
        adj = torch.stack([torch.linalg.cross(r1, r2, dim=-1), torch.linalg.cross(r2, r0, dim=-1),
                           torch.linalg.cross(r0, r1, dim=-1)], -1)
        eye = torch.eye(3, dtype=K.dtype, device=K.device)
        trace = _trace(K)
        det = (r0 * adj[..., :, 0]).sum(-1)
        self.adj_re = adj - eps * eps * eye
        self.adj_im = eps * (trace[..., None, None] * eye - K)
        a = det - eps * eps * trace
        b = eps * (_trace(adj) - eps * eps)
        scale = torch.maximum(a.abs(), b.abs())
        solvable = scale > torch.finfo(K.dtype).tiny
        inv_scale = torch.where(solvable, 1 / torch.where(solvable, scale, 1.0), 0.0)
        a, b = a * inv_scale, b * inv_scale
        norm2 = torch.where(solvable, a * a + b * b, 1.0)
        # 1 / (a + i b) = (a - i b) / (a^2 + b^2), in units of inv_scale.
        self.w_re = (a * inv_scale / norm2).unsqueeze(-1)
        self.w_im = (-b * inv_scale / norm2).unsqueeze(-1)

    def __call__(self, h_re: torch.Tensor, h_im: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        p = _matvec(self.adj_re, h_re)
        q = _matvec(self.adj_im, h_re)
        if h_im is not None:
            p = p - _matvec(self.adj_im, h_im)
            q = q + _matvec(self.adj_re, h_im)
        return p * self.w_re - q * self.w_im, p * self.w_im + q * self.w_re


def _scaled(M: torch.Tensor):
    """(A, zero, c): A = M / c with c = max |M_ij| per matrix (detached, 1
    where M = 0), and where M = 0. T is homogeneous of degree -1 in M, so
    T(M) = T(A) / c for any constant c: scaling first keeps |A|_F in [1, 3]."""
    c = M.detach().abs().amax((-2, -1))
    zero = c == 0
    c = torch.where(zero, 1.0, c)
    return M / c[..., None, None], zero, c


def _norm(A: torch.Tensor, zero: torch.Tensor) -> torch.Tensor:
    """|A|_F, 1 where M = 0 (so that nothing divides by 0 there)."""
    return torch.where(zero, 1.0, A.square().sum((-2, -1))).sqrt()


def tangent_value(X: torch.Tensor, R: torch.Tensor, M: torch.Tensor, eps: float) -> torch.Tensor:
    """T(X, R, M) = fit_rotation_backward(X, R, M, eps) up to rounding, in
    differentiable tensor operations (0 where M = 0).

    Args:
        X, R: ``(..., 3, 3)`` of the same shape; M: ``(..., 3, 3)``
            broadcastable to R; all of one float dtype.
        eps: ``gradient_eps``, a float >= 0.

    Returns:
        ``(..., 3, 3)``, R's shape and dtype.
    """
    dtype = R.dtype
    X, R, M = _compute(X, R, M)
    A, zero, c = _scaled(M)
    n = _norm(A, zero)
    K = _optimality_matrix(_transpose_times(R, A), n)
    u, _ = _DampedInverse(K, eps)(_vex_skew(_transpose_times(R, X)))
    T = _times_cross(R, u) / (n * c)[..., None, None]
    return torch.where(zero[..., None, None], 0.0, T).to(dtype)


def tangent_vjp(X, R, M, eps: float, W: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(dL/dX, dL/dR, dL/dM) for W = dL/dT, T = fit_rotation_backward(X, R,
    M, eps): the reverse-mode derivative of :func:`tangent_value` (each of
    its input's shape). Differentiable again."""
    _, pullback = torch.func.vjp(lambda x, r, m: tangent_value(x, r, m, eps), X, R, M)
    return pullback(W)


def tangent_jvp(X, R, M, eps: float, dX, dR, dM) -> torch.Tensor:
    """dT for the tangents (dX, dR, dM) of (X, R, M) (``None``: zero), T =
    fit_rotation_backward(X, R, M, eps): the formula of the module
    docstring. ``(..., 3, 3)``, R's shape and dtype."""
    dtype = R.dtype
    X, R, M = _compute(X, R, M)
    A, zero, c = _scaled(M)
    n = _norm(A, zero)
    K = _optimality_matrix(_transpose_times(R, A), n)
    inverse = _DampedInverse(K, eps)
    u, v = inverse(_vex_skew(_transpose_times(R, X)))
    T = _times_cross(R, u) / n[..., None, None]  # times c: the scaled T
    B = torch.zeros_like(R)  # dR^T X + R^T dX
    dS = torch.zeros(torch.broadcast_shapes(R.shape, M.shape), dtype=R.dtype, device=R.device)
    dn = torch.zeros_like(n)
    if dR is not None:
        dR = _compute(dR)[0]
        B = B + _transpose_times(dR, X)
        dS = dS + _transpose_times(dR, A)
    if dX is not None:
        B = B + _transpose_times(R, _compute(dX)[0])
    if dM is not None:
        dA = _compute(dM)[0] / c[..., None, None]
        dn = (A * dA).sum((-2, -1)) / n
        dS = dS + _transpose_times(R, dA)
    dK = _optimality_matrix(dS, n) - K * (dn / n)[..., None, None]
    du, _ = inverse(_vex_skew(B) - _matvec(dK, u), -_matvec(dK, v))
    dT = _times_cross(R, du) / n[..., None, None] - T * (dn / n)[..., None, None]
    if dR is not None:
        dT = dT + _times_cross(dR, u) / n[..., None, None]
    dT = dT / c[..., None, None]
    return torch.where(zero[..., None, None], 0.0, dT).to(dtype)
