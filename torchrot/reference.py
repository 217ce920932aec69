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

from torchrot.generic import fit_rotation_backward_generic
from torchrot._checks import bad_init_error, check_all, check_backward, check_matrix_arg
from torchrot._limits import (
    CONVERGED_CAP,
    ESTIMATE_SWITCH,
    GERSHGORIN_STEPS,
    GRADIENT_EPS,
    INIT_CLEAN,
    INIT_CLEAN_STEPS,
    INIT_TOLERANCE,
    MAX_CHECK_SLACK_EPS,
    MAX_ESCAPES,
)

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
    check_matrix_arg(M, "M", op="torchrot.rotation_svd")
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


def _cayley_fraction(S, c):
    """Algorithm 2 as a fraction (csrc/kernel/cayley.h): z = -w / d with
    w = adj(H) m and d = det H, H = S + S^T - (tr S + c) I (Eqs. 24, 31-33)."""
    m = _skew_vector(S)
    eye = torch.eye(3, dtype=S.dtype, device=S.device)
    H = S + S.mT - (_trace(S) + c)[..., None, None] * eye
    adj = _adjugate(H)
    d = (H[..., 0, :] * adj[..., :, 0]).sum(-1)
    w = (adj @ m.unsqueeze(-1)).squeeze(-1)
    return w, d


def _cayley_step(S, variant: str, newton_mask=None):
    """Algorithm 2: z solving (S + S^T - (t + c) I) z = -m (Eq. 24)."""
    t = _trace(S)
    c = _objective_estimate(S, t, (_skew_vector(S) ** 2).sum(-1), variant)
    if newton_mask is not None:
        c = torch.where(newton_mask, t, c)
    w, d = _cayley_fraction(S, c)
    return -w / d.unsqueeze(-1)


def _fraction_rotation(w, d):
    """Eq. 10 for z = -w / d, multiplied through by d^2 (one division)."""
    ww = (w * w).sum(-1)[..., None, None]
    dd = (d * d)[..., None, None]
    x, y, v = w.unbind(-1)
    zero = torch.zeros_like(x)
    cross = torch.stack([zero, -v, y, v, zero, -x, -y, x, zero], -1).reshape(w.shape + (3,))
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return ((dd - ww) * eye + 2 * w.unsqueeze(-1) * w.unsqueeze(-2) - 2 * d[..., None, None] * cross) / (dd + ww)


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
    return _fraction_rotation(-z, torch.ones_like(z[..., 0]))  # z = -w / d with d = 1


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


def _deviation2(G: torch.Tensor) -> torch.Tensor:
    """|G - I|_F^2 for a Gram matrix G = R^T R (orthonormality_deviation2)."""
    eye = torch.eye(3, dtype=G.dtype, device=G.device)
    return ((G - eye) ** 2).sum((-2, -1))


def _check_warm_start(init: torch.Tensor):
    """(finite, bad, deviation^2) of warm starts, as csrc/kernel/optimality.h's
    check_warm_start: bad where finite but |R^T R - I|_F >= INIT_TOLERANCE or
    det <= 0."""
    G = init.mT @ init
    finite = torch.isfinite(G.diagonal(dim1=-2, dim2=-1).sum(-1))
    deviation2 = _deviation2(G)
    rotation = (deviation2 < INIT_TOLERANCE**2) & (torch.linalg.det(init) > 0)
    return finite, finite & ~rotation, deviation2


def _clean_warm_start(init: torch.Tensor, usable: torch.Tensor, deviation2: torch.Tensor) -> torch.Tensor:
    """Newton-Schulz steps on the usable warm starts whose deviation is at or
    above the compute dtype's INIT_CLEAN, each until it is below
    (clean_warm_start in csrc/kernel/optimality.h); masked, no host sync."""
    clean2 = INIT_CLEAN[str(init.dtype).removeprefix("torch.")] ** 2
    rough = usable & ~(deviation2 < clean2)
    R = init
    for _ in range(INIT_CLEAN_STEPS):
        R = torch.where(rough[..., None, None], _reorthonormalize(R), R)
        rough = rough & ~(_deviation2(R.mT @ R) < clean2)
    return R


def _best_start_rotation(A: torch.Tensor) -> torch.Tensor:
    """The best of the 12 cold-start candidates, ties to the first (cold_start.h)."""
    C = start_candidates(A.dtype, A.device)
    K = horn_matrix(A)
    values = [K[..., 0, 0], K[..., 1, 1], K[..., 2, 2], K[..., 3, 3]]
    for signs in range(8):
        s1, s2, s3 = (-1.0 if (signs >> b) & 1 else 1.0 for b in range(3))
        values.append(0.5 * (s1 * K[..., 0, 1] + s2 * K[..., 0, 2] + s3 * K[..., 0, 3]
                             + s1 * s2 * K[..., 1, 2] + s1 * s3 * K[..., 1, 3] + s2 * s3 * K[..., 2, 3]))
    best = torch.stack(values, -1).argmax(-1)  # first maximum on ties
    return C.index_select(0, best.reshape(-1)).reshape(A.shape)


def _advance(state: dict, variant: str, max_iter: int | None, eps: float) -> None:
    """All Cayley steps of every running matrix, as the kernel's advance()
    (csrc/kernel/fit_rotation_impl.h), masked instead of branched."""
    A, R = state["A"], state["R"]
    converge = max_iter is None
    running = state["running"]
    zeros = torch.zeros_like(running)
    switched, fallback = zeros, zeros
    iterations = torch.zeros(running.shape, dtype=torch.int32, device=A.device)
    attempt = torch.zeros_like(iterations)
    escapes = torch.zeros_like(iterations)
    cap = CONVERGED_CAP if converge else max_iter
    budget = CONVERGED_CAP * (MAX_ESCAPES + 1) if converge else max_iter
    for _ in range(budget):
        S = R.mT @ A
        t = _trace(S)
        mm = (_skew_vector(S) ** 2).sum(-1)
        c = _objective_estimate(S, t, mm, variant)
        if converge and variant == "gershgorin":  # Tolerances::estimate_switch
            c = torch.where(switched, _objective_estimate(S, t, mm, "conservative"), c)
        w, d = _cayley_fraction(S, c)
        ww, dd = (w * w).sum(-1), d * d
        # as the kernel: no step where d^2 + w.w underflows (H singular to working precision)
        valid = (dd > 0) & torch.isfinite(dd + ww) & (dd + ww > torch.finfo(dd.dtype).tiny)
        stepping = running & valid
        stalled = running & ~valid
        safe_d = torch.where(stepping, d, torch.ones_like(d))
        R = torch.where(stepping[..., None, None], R @ _fraction_rotation(w, safe_d), R)
        iterations = iterations + stepping.to(torch.int32)
        attempt = attempt + stepping.to(torch.int32)
        undamped = ~(c - t > math.sqrt(eps) * t.abs())  # see Tolerances::undamped
        finished = stepping & undamped & (ww < eps * dd)
        if converge:
            switch_now = (ww < ESTIMATE_SWITCH * dd) | (attempt >= GERSHGORIN_STEPS)
            switched = switched | (stepping & switch_now)
            at_maximum = finished & _is_maximum(S, MAX_CHECK_SLACK_EPS * eps)
            saddle = finished & ~at_maximum
            escape = saddle & (escapes < MAX_ESCAPES)
            fallback = fallback | (saddle & ~escape)
            R = torch.where(escape[..., None, None], R @ saddle_escape_rotation(R.mT @ A), R)
            escapes = escapes + escape.to(torch.int32)
            attempt = torch.where(escape, 0, attempt)
            switched = switched & ~escape
            finished = finished & ~escape
            exhausted = stepping & ~finished & (attempt >= cap)
            fallback = fallback | exhausted | stalled
            finished = finished | exhausted | stalled
        else:
            finished = finished | stalled | (attempt >= cap)
        running = running & ~finished
    state.update(R=R, iterations=iterations, fallback=fallback)


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
    eps = torch.finfo(compute).eps
    A, max_abs = _normalized(M)
    finite = torch.isfinite(max_abs)  # amax propagates NaN
    zero = max_abs == 0
    bad_init = torch.zeros_like(finite)
    if init is not None:
        init = init.to(compute)
        init_finite, init_bad, deviation2 = _check_warm_start(init)
        if M.device.type != "meta" and bool(init_bad.any()):
            raise bad_init_error(int(init_bad.sum()), init_bad.numel())  # counted in init's own shape
        init_finite, init_bad, deviation2 = (t.expand(batch) for t in (init_finite, init_bad, deviation2))
        finite = finite & init_finite
        bad_init = init_bad
        R = _clean_warm_start(init.expand(M.shape), init_finite & ~init_bad, deviation2)
    else:
        R = _best_start_rotation(A)
    A = torch.where(finite[..., None, None], A, torch.zeros_like(A))  # keep NaN out of eigh
    state = {"A": A, "R": R, "running": finite & ~zero & ~bad_init}
    _advance(state, variant, max_iter, eps)
    R = state["R"]
    R = _reorthonormalize(R)  # one Newton-Schulz step for every result (finish())
    R = torch.where(state["fallback"][..., None, None], _horn_rotation(A), R)
    usable = finite & ~bad_init
    R = torch.where(usable[..., None, None], R, torch.full_like(R, float("nan")))
    status = torch.where(state["fallback"], STATUS_FALLBACK, STATUS_CAYLEY)
    status = torch.where(bad_init, STATUS_BAD_INIT, status)
    status = torch.where(finite, status, STATUS_NON_FINITE).to(torch.uint8)
    iterations = state["iterations"]
    R = R.to(out_dtype)
    if return_info:
        return R, iterations, status
    return R


def fit_rotation_backward_reference(
    grad: torch.Tensor, R: torch.Tensor, M: torch.Tensor, gradient_eps: float = GRADIENT_EPS
) -> torch.Tensor:
    """dL/dM from dL/dR = ``grad`` at R = fit_rotation(M), in batched PyTorch.

    The fitted R makes S = R^T M symmetric; differentiating that condition
    (csrc/kernel/rotation_gradient.h has the derivation) gives
    dL/dM = R [u]x with (tr(S) I - S) u = vex(R^T G - G^T R), solved with
    Tikhonov damping lambda = gradient_eps |M|_F:
    u = (A^2 + lambda^2 I)^-1 A g, evaluated as Re (A + i lambda I)^-1 g by
    the 3x3 adjugate, as the CPU kernel (forming A^2 would square A's
    condition number: ~3 digits lost in float32), elementwise over the 9
    entries (torchrot.generic.rotation_tangent). The map is self-adjoint, so
    with ``grad = dM`` this returns the forward-mode tangent dR.

    Convention: R (det +1) maximises tr(R^T M); M = sum_i w_i y_i x_i^T gives
    R x_i ~ y_i (column vectors).

    Args:
        grad: ``(..., 3, 3)`` with R's shape, dtype and device.
        R: ``(..., 3, 3)`` the fitted rotations.
        M: ``(..., 3, 3)`` the fitted matrices, broadcastable to R.
        gradient_eps: damping, a finite float >= 0 (0: undamped).
    Returns:
        ``(..., 3, 3)`` in R's dtype (reduced precision computed in float32).
    """
    check_backward(grad, R, M, gradient_eps)
    return fit_rotation_backward_generic(grad, R, M, gradient_eps)
