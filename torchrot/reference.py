"""Pure-PyTorch implementations: the SVD reference and torchrot's algorithm.

``rotation_svd`` is the textbook answer (Eq. 4 of the paper), kept public as the
reference the tests measure against. ``fit_rotation_reference`` is the same
algorithm as the C++ kernel (csrc/kernel/), batched with masks instead of
per-matrix branches, so it has no data-dependent control flow: it runs on any
device, on ``meta`` tensors and under tracing. It serves as the kernel of
``torch.ops.torchrot.fit_rotation`` on devices without a native kernel.

Convention everywhere: R (det R = +1) maximises tr(R^T M); for centred point
sets, M = sum_i w_i y_i x_i^T gives R x_i ~ y_i (column vectors).
"""
from __future__ import annotations

import math

import torch

from torchrot._checks import OP_NAME, check_all

# Mirrors kernel::Tolerances (csrc/kernel/fit_rotation_impl.h).
CONVERGED_CAP = 12
MAX_ESCAPES = 2
NEWTON_SWITCH = 1e-4
MAX_CHECK_SLACK_EPS = 4.0
INIT_ORTHONORMALITY = {torch.float32: 1e-4, torch.float64: 1e-7}

# FitStatus codes (csrc/fit_rotation.h).
STATUS_CAYLEY, STATUS_FALLBACK, STATUS_BAD_INIT, STATUS_NON_FINITE = 0, 1, 2, 3


def rotation_svd(M: torch.Tensor) -> torch.Tensor:
    """Rotation maximising tr(R^T M) by SVD: R = U diag(1, 1, det(U V^T)) V^T.

    Args:
        M: ``(..., 3, 3)`` floating tensor (computed in M's dtype; pass float64
            for a reference answer).
    Returns:
        ``(..., 3, 3)`` rotations, det R = +1. Column-vector convention: for
        centred point sets M = sum_i w_i y_i x_i^T, R x_i ~ y_i.
    """
    U, _, Vh = torch.linalg.svd(M)
    d = torch.linalg.det(U @ Vh)
    D = torch.ones(M.shape[:-1], dtype=M.dtype, device=M.device)
    D[..., 2] = d
    return (U * D.unsqueeze(-2)) @ Vh


def _skew_vector(S: torch.Tensor) -> torch.Tensor:
    """m = vee(S - S^T) = (S21 - S12, S02 - S20, S10 - S01) (paper Eq. 12)."""
    return torch.stack(
        [S[..., 2, 1] - S[..., 1, 2], S[..., 0, 2] - S[..., 2, 0], S[..., 1, 0] - S[..., 0, 1]], -1
    )


def _trace(S: torch.Tensor) -> torch.Tensor:
    return S.diagonal(dim1=-2, dim2=-1).sum(-1)


def _objective_estimate(S, t, mm, variant: str):
    """The maximal objective c of each variant (paper Eqs. 26-28)."""
    if variant == "newton":
        return t
    if variant == "conservative":
        return torch.sqrt(t * t + mm)
    sym = (S + S.mT).abs()
    diag = 2 * S.diagonal(dim1=-2, dim2=-1)
    two_lambda2 = (diag + sym.sum(-1) - sym.diagonal(dim1=-2, dim2=-1)).amax(-1)  # Eq. 28
    g_sym = torch.maximum(t, two_lambda2 - t)
    return torch.sqrt(g_sym * g_sym + mm)  # Eq. 27


def _cayley_step(S, variant: str, newton_mask=None):
    """Algorithm 2: z solving (S + S^T - (t + c) I) z = -m (Eq. 24)."""
    m = _skew_vector(S)
    t = _trace(S)
    mm = (m * m).sum(-1)
    c = _objective_estimate(S, t, mm, variant)
    if newton_mask is not None:
        c = torch.where(newton_mask, t, c)
    eye = torch.eye(3, dtype=S.dtype, device=S.device)
    H = S + S.mT - (t + c)[..., None, None] * eye
    # Cramer's rule through the adjugate, as in the kernel (Eqs. 31-33).
    adj = _adjugate(H)
    det = (H[..., 0, :] * adj[..., :, 0]).sum(-1)
    z = -(adj @ m.unsqueeze(-1)).squeeze(-1) / det.unsqueeze(-1)
    return z


def _adjugate(H: torch.Tensor) -> torch.Tensor:
    """Adjugate of a batch of 3x3 matrices (cofactors, transposed)."""
    a = H
    c = torch.stack(
        [
            a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1],
            a[..., 0, 2] * a[..., 2, 1] - a[..., 0, 1] * a[..., 2, 2],
            a[..., 0, 1] * a[..., 1, 2] - a[..., 0, 2] * a[..., 1, 1],
            a[..., 1, 2] * a[..., 2, 0] - a[..., 1, 0] * a[..., 2, 2],
            a[..., 0, 0] * a[..., 2, 2] - a[..., 0, 2] * a[..., 2, 0],
            a[..., 0, 2] * a[..., 1, 0] - a[..., 0, 0] * a[..., 1, 2],
            a[..., 1, 0] * a[..., 2, 1] - a[..., 1, 1] * a[..., 2, 0],
            a[..., 0, 1] * a[..., 2, 0] - a[..., 0, 0] * a[..., 2, 1],
            a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0],
        ],
        -1,
    )
    return c.reshape(H.shape)


def cayley_rotation(z: torch.Tensor) -> torch.Tensor:
    """The rotation ((1 - z.z) I + 2 z z^T + 2 [z]x) / (1 + z.z) (paper Eq. 10).

    Args:
        z: ``(..., 3)`` Cayley parameters, z = tan(theta / 2) * axis (Eq. 7).
    Returns:
        ``(..., 3, 3)`` rotations.
    """
    s = (z * z).sum(-1)[..., None, None]
    x, y, w = z.unbind(-1)
    zero = torch.zeros_like(x)
    cross = torch.stack([zero, -w, y, w, zero, -x, -y, x, zero], -1).reshape(z.shape + (3,))
    eye = torch.eye(3, dtype=z.dtype, device=z.device)
    return ((1 - s) * eye + 2 * z.unsqueeze(-1) * z.unsqueeze(-2) + 2 * cross) / (1 + s)


def quaternion_rotation(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of unit quaternions ``(..., 4)`` ordered (w, x, y, z)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z,
        ],
        -1,
    ).reshape(q.shape[:-1] + (3, 3))


def horn_matrix(M: torch.Tensor) -> torch.Tensor:
    """Horn's symmetric 4x4 K with tr(R(q)^T M) = q^T K q for unit q (w, x, y, z)."""
    t = _trace(M)
    m = _skew_vector(M)
    eye = torch.eye(3, dtype=M.dtype, device=M.device)
    T = M + M.mT - t[..., None, None] * eye
    top = torch.cat([t[..., None], m], -1).unsqueeze(-2)
    bottom = torch.cat([m.unsqueeze(-1), T], -1)
    return torch.cat([top, bottom], -2)


def start_candidates(dtype=torch.float64, device=None) -> torch.Tensor:
    """The 12 cold-start rotations (tetrahedral group), in the kernel's order."""
    q = [[1.0 if i == k else 0.0 for i in range(4)] for k in range(4)]
    for signs in range(8):
        q.append([0.5] + [-0.5 if (signs >> b) & 1 else 0.5 for b in range(3)])
    return quaternion_rotation(torch.tensor(q, dtype=dtype, device=device))


def saddle_escape_rotation(S: torch.Tensor, squarings: int = 4) -> torch.Tensor:
    """Half-turn about the top eigenvector of sym(S) (csrc/kernel/saddle_escape.h).

    At a fixed point with lambda_0 + lambda_1 < 0 (a saddle) this rotation
    leads to the maximum (paper Sec. 3, Eq. 18). The eigenvector comes from
    repeated squaring of sym(S) shifted by its Gershgorin lower bound.
    """
    eye = torch.eye(3, dtype=S.dtype, device=S.device)
    B = 0.5 * (S + S.mT)
    diag = B.diagonal(dim1=-2, dim2=-1)
    lower = (diag - (B.abs().sum(-1) - diag.abs())).amin(-1)
    B = B - lower[..., None, None] * eye
    for _ in range(squarings):
        B = B / _trace(B)[..., None, None]
        B = B @ B
    norms = (B * B).sum(-2)
    best = norms.argmax(-1, keepdim=True)
    v = torch.gather(B, -1, best.unsqueeze(-2).expand(B.shape[:-1] + (1,))).squeeze(-1)
    vv = torch.gather(norms, -1, best)
    return 2 * v.unsqueeze(-1) * v.unsqueeze(-2) / vv.unsqueeze(-1) - eye


def _horn_rotation(A: torch.Tensor) -> torch.Tensor:
    """Fallback: Horn's quaternion method in float64 (eigh of K)."""
    K = horn_matrix(A.to(torch.float64))
    _, vecs = torch.linalg.eigh(K)
    return quaternion_rotation(vecs[..., :, -1]).to(A.dtype)


def _is_maximum(S: torch.Tensor, slack: float) -> torch.Tensor:
    """tr(S) I - sym(S) + slack I positive definite (Sylvester), as in the kernel."""
    eye = torch.eye(3, dtype=S.dtype, device=S.device)
    P = (_trace(S) + slack)[..., None, None] * eye - 0.5 * (S + S.mT)
    minor2 = P[..., 0, 0] * P[..., 1, 1] - P[..., 0, 1] * P[..., 1, 0]
    det = (P[..., 0, :] * _adjugate(P)[..., :, 0]).sum(-1)
    return (P[..., 0, 0] > 0) & (minor2 > 0) & (det > 0)


def _reorthonormalize(R: torch.Tensor) -> torch.Tensor:
    """One Newton-Schulz step R (3 I - R^T R) / 2 (see csrc/kernel/mat3.h)."""
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    return R @ (1.5 * eye - 0.5 * (R.mT @ R))


def _normalized(M: torch.Tensor):
    """M scaled to max |entry| 1 (subnormal-safe); also returns max |entry|."""
    max_abs = M.abs().amax((-2, -1), keepdim=True)
    tiny = torch.finfo(M.dtype).tiny
    digits = round(-math.log2(torch.finfo(M.dtype).eps)) + 1  # 24 / 53, as the kernel
    lift = torch.where(max_abs < tiny, float(2**digits), 1.0)
    denom = torch.where(max_abs > 0, max_abs * lift, torch.ones_like(max_abs))
    return (M * lift) / denom, max_abs[..., 0, 0]


def _is_rotation(R: torch.Tensor, tol: float) -> torch.Tensor:
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    ortho = ((R.mT @ R - eye).abs() <= tol).flatten(-2).all(-1)
    return ortho & (torch.linalg.det(R) > 0)


def _run_cayley_steps(A, R, cap: int, variant: str, switch_to_newton: bool, active, eps: float):
    """Up to ``cap`` masked Cayley steps R <- R Q(z) (Algorithm 1's loop).

    A matrix stops when its step is below eps or its H is singular (no step
    taken), or if it is not ``active``. Returns R, steps taken per matrix,
    whether each converged, and S = R^T A of each matrix's last step.
    """
    batch = A.shape[:-2]
    iterations = torch.zeros(batch, dtype=torch.int32, device=A.device)
    done = ~active.expand(batch)
    converged = torch.zeros(batch, dtype=torch.bool, device=A.device)
    newton = torch.zeros_like(converged)
    S_last = torch.zeros_like(A)
    for _ in range(cap):
        S = R.mT @ A
        z = _cayley_step(S, variant, newton if switch_to_newton else None)
        zz = (z * z).sum(-1)
        finite = torch.isfinite(zz)
        step = ~done & finite
        done = done | ~finite
        z = torch.where(step[..., None], z, torch.zeros_like(z))
        R = torch.where(step[..., None, None], R @ cayley_rotation(z), R)
        S_last = torch.where(step[..., None, None], S, S_last)
        iterations = iterations + step.to(torch.int32)
        if switch_to_newton:
            newton = newton | (step & (zz < NEWTON_SWITCH))
        now_converged = step & (zz < eps)
        converged = converged | now_converged
        done = done | now_converged
    return R, iterations, converged, S_last


def fit_rotation_reference(
    M: torch.Tensor,
    init: torch.Tensor | None = None,
    *,
    max_iter: int | None = None,
    variant: str = "conservative",
    return_info: bool = False,
):
    """torchrot's algorithm in batched PyTorch (any device, ``meta`` included).

    Same contract as :func:`torchrot.fit_rotation`: returns R (det +1)
    maximising tr(R^T M), column-vector convention (M = sum_i w_i y_i x_i^T
    gives R x_i ~ y_i). Agrees with the C++ kernel to rounding.

    Args:
        M: ``(..., 3, 3)`` float32/float64 (float16/bfloat16 computed in float32).
        init: optional rotations broadcastable to M: the warm start.
        max_iter: None to converge each matrix; k >= 1 for at most k Cayley steps.
        variant: "newton", "conservative" or "gershgorin" (paper Sec. 4.2).
        return_info: also return per-matrix iteration counts and status codes.
    Returns:
        R, or (R, iterations int32, status uint8) if ``return_info``.
    Raises:
        ValueError/TypeError for bad arguments; ValueError if a finite ``init``
        is not a rotation (not checked on ``meta`` tensors).
    """
    check_all(M, init, max_iter, variant)
    out_dtype = M.dtype
    compute = torch.float32 if M.dtype in (torch.float16, torch.bfloat16) else M.dtype
    M = M.to(compute)
    batch = M.shape[:-2]
    if init is not None:
        init = init.to(compute).expand(M.shape)
    A, max_abs = _normalized(M)
    finite = torch.isfinite(max_abs)
    if init is not None:
        finite = finite & torch.isfinite(init).flatten(-2).all(-1)
        good_init = _is_rotation(init, INIT_ORTHONORMALITY[compute]) | ~finite
        if M.device.type != "meta" and not bool(good_init.all()):
            bad = int((~good_init).sum())
            raise ValueError(
                f"{OP_NAME}: init must hold rotations (|R^T R - I| <= {INIT_ORTHONORMALITY[compute]:g},"
                f" det R > 0); {bad} of {good_init.numel()} matrices do not"
            )
        A = torch.where(finite[..., None, None], A, torch.zeros_like(A))
        eye = torch.eye(3, dtype=compute, device=M.device)
        R = _reorthonormalize(torch.where(finite[..., None, None], init, eye))
    else:
        A = torch.where(finite[..., None, None], A, torch.zeros_like(A))
        C = start_candidates(compute, M.device)
        best = torch.einsum("kij,...ij->...k", C, A).argmax(-1)  # first maximum on ties
        R = C[best]
    eps = torch.finfo(compute).eps
    zero_matrix = max_abs == 0
    status = torch.zeros(batch, dtype=torch.uint8, device=M.device)
    # M = 0 needs no case of its own: its step is 0/0, so it keeps the warm
    # start (else the first candidate, I) and is excluded from the fallback.
    if max_iter is not None:
        R, iterations, _, _ = _run_cayley_steps(A, R, max_iter, variant, False, finite, eps)
    else:
        R, iterations, converged, S = _run_cayley_steps(A, R, CONVERGED_CAP, variant, True, finite, eps)
        accepted = converged & _is_maximum(S, MAX_CHECK_SLACK_EPS * eps)
        for _ in range(MAX_ESCAPES):  # saddle escapes (csrc/kernel/saddle_escape.h)
            restart = converged & ~accepted
            R = torch.where(restart[..., None, None], R @ saddle_escape_rotation(R.mT @ A), R)
            R, more, converged, S = _run_cayley_steps(A, R, CONVERGED_CAP, variant, True, restart, eps)
            iterations = iterations + more
            accepted = accepted | (restart & converged & _is_maximum(S, MAX_CHECK_SLACK_EPS * eps))
        R = torch.where(accepted[..., None, None], _reorthonormalize(R), R)
        use_fallback = ~accepted & ~zero_matrix & finite
        R = torch.where(use_fallback[..., None, None], _horn_rotation(A), R)
        status = torch.where(use_fallback, STATUS_FALLBACK, status).to(torch.uint8)
    nan = torch.full_like(R, float("nan"))
    R = torch.where(finite[..., None, None], R, nan)
    status = torch.where(finite, status, STATUS_NON_FINITE).to(torch.uint8)
    iterations = torch.where(finite & ~zero_matrix, iterations, 0)
    R = R.to(out_dtype)
    if return_info:
        return R, iterations, status
    return R
