"""The paper's comparison methods (Table 1) as batched, plain PyTorch functions.

Every function takes ``(..., 3, 3)`` float32/float64 matrices M (any batch
shape, any strides) and returns the rotations R (det R = +1) maximising
tr(R^T M), i.e. the rotation nearest to M in the Frobenius norm: the same
convention as :func:`torchrot.fit_rotation`. Column vectors: for centred
point sets x_i, y_i, M = sum_i w_i y_i x_i^T gives R x_i ~ y_i. Results have
M's dtype and are computed in it (no hidden float64), so the benchmark
measures each method as a user of that dtype would run it.

Each is written from its paper's formulas; where a paper leaves something
open for general batched input (scale, guards), the docstring says what was
chosen. Warm-startable methods take ``init`` (rotations broadcastable to M,
e.g. the previous iteration's R) and an iteration count ``max_iter``
(``None`` = iterate each matrix until its step stalls, under a cap).

Accuracy. Where the maximiser is unique, fitting R is itself ill-conditioned
by kappa = sigma_1 / (sigma_2 + sigma_3) (singular values of M, sigma_3 signed
by det M): a backward-stable method errs by about eps * kappa in |R - R*|_F
(float32 SVD does no better). ``tests/test_methods.py`` checks
|R - R*|_F <= 100 eps max(kappa, 1) against float64 SVD where the table says
"accurate"; the benchmark reports every method on every data set.

============================  ====================================  ==========================================
method                        accurate on (torchrot.testing)        fails or is inaccurate where
============================  ====================================  ==========================================
horn                          all WELL_CONDITIONED, warm_cond1e5    sigma_2 + sigma_3 = 0 (R* not unique)
mueller, converged            rot60, rot180 (kappa <~ 10)           anisotropic M: linear rate sigma_1 /
                                                                    (sigma_1 + sigma_2 + sigma_3) per step,
                                                                    so ~kappa ln(1/eps) steps are needed and
                                                                    the cap (1000) leaves ~10% (warm) to ~40%
                                                                    (warm_cond1e5) of results off by > 1e-3;
                                                                    stationary points (M = -I from I)
mueller, k steps              init close and kappa small            as above, after k steps
higham_polar                  all WELL_CONDITIONED, warm_cond1e5    singular M (NaN/Inf); with
                                                                    ``inverse="cofactor"`` in float32, det M
                                                                    of the wrong sign for kappa >~ 1e4 (2% of
                                                                    warm_cond1e5 come out 180 degrees off)
fa3r, converged               all WELL_CONDITIONED, warm_cond1e5    sigma_2 + sigma_3 = 0 (rank 1, diag(1, 1,
                                                                    -1)): the result is not a rotation
fa3r, 10 steps (authors')     rot60, rot180                         small singular values only double per
                                                                    step: condition number >~ 1e3 (warm) is
                                                                    not orthonormal after 10 steps
kugelstadt, 1 step            error O(theta^2) for init theta       large remaining rotations; the Hessian
                              from R* (warm data: most)             indefinite (guards take gradient steps)
============================  ====================================  ==========================================
"""
from __future__ import annotations

import math

import torch

from torchrot._checks import broadcast_shapes
from torchrot.reference import horn_matrix, quaternion_rotation

__all__ = ["horn", "mueller", "higham_polar", "fa3r", "kugelstadt", "rotation_to_quaternion"]

Tensor = torch.Tensor

#: Iteration caps of the converged modes (``max_iter=None``).
MUELLER_CAP = 1000
HIGHAM_CAP = 30
FA3R_CAP = 100
#: The number of iterations of the authors' FA3R implementation.
FA3R_PAPER_ITERATIONS = 10


# ---------------------------------------------------------------------------
# Argument checks
# ---------------------------------------------------------------------------

def _check_matrices(fn: str, M, init=None, max_iter=None, init_required: bool = False) -> None:
    """Errors name the function and the argument: M (..., 3, 3) float32/float64;
    init the same dtype and device, broadcastable to M; max_iter None or >= 1."""
    where = f"torchrot.methods.{fn}"
    for name, t in (("M", M), ("init", init)):
        if t is None:
            if name == "init" and init_required:
                raise TypeError(f"{where}: init (the warm-start rotations, (..., 3, 3)) is required")
            continue
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{where}: {name} must be a torch.Tensor, got {type(t).__name__}")
        if t.dim() < 2 or t.shape[-2:] != (3, 3):
            raise ValueError(f"{where}: {name} must have shape (..., 3, 3), got {list(t.shape)}")
        if t.dtype not in (torch.float32, torch.float64):
            raise TypeError(f"{where}: {name} must be float32 or float64, got {t.dtype}")
    if init is not None:
        if init.dtype != M.dtype or init.device != M.device:
            raise TypeError(f"{where}: init must have M's dtype and device ({M.dtype}, {M.device}), "
                            f"got {init.dtype}, {init.device}")
        try:
            ok = broadcast_shapes(init.shape[:-2], M.shape[:-2]) == M.shape[:-2]
        except RuntimeError:
            ok = False
        if not ok:
            raise ValueError(f"{where}: init of shape {list(init.shape)} must broadcast to M's shape "
                             f"{list(M.shape)}")
    if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1):
        raise ValueError(f"{where}: max_iter must be None (iterate until converged) or an int >= 1, "
                         f"got {max_iter!r}")


# ---------------------------------------------------------------------------
# Small batched helpers
# ---------------------------------------------------------------------------

def _trace(S: Tensor) -> Tensor:
    return S.diagonal(dim1=-2, dim2=-1).sum(-1)


def _cofactor(X: Tensor) -> Tensor:
    """cof(X) = det(X) X^{-T}: its columns are x1 x x2, x2 x x0, x0 x x1 for the
    columns x0, x1, x2 of X."""
    x0, x1, x2 = X.unbind(-1)
    return torch.stack([torch.linalg.cross(x1, x2), torch.linalg.cross(x2, x0), torch.linalg.cross(x0, x1)], -1)


def _quaternion_product(p: Tensor, q: Tensor) -> Tensor:
    """Hamilton product p q of ``(..., 4)`` quaternions (w, x, y, z):
    R(p q) = R(p) R(q)."""
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - (pv * qv).sum(-1, keepdim=True)
    v = pw * qv + qw * pv + torch.linalg.cross(pv, qv)
    return torch.cat([w, v], -1)


def rotation_to_quaternion(R: Tensor) -> Tensor:
    """Unit quaternions (w, x, y, z) of rotations ``(..., 3, 3)`` (Shepperd's
    method: the largest of |w|, |x|, |y|, |z| is computed from the diagonal, the
    others from off-diagonal sums, so no component loses accuracy). Inverse of
    :func:`torchrot.reference.quaternion_rotation` up to the sign of q."""
    r = R.flatten(-2)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = r.unbind(-1)
    four_squares = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22,
                                1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    # Row k: 4 q_k q, computed with q_k the component of largest magnitude.
    rows = torch.stack([
        torch.stack([four_squares[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
        torch.stack([m21 - m12, four_squares[..., 1], m01 + m10, m02 + m20], -1),
        torch.stack([m02 - m20, m01 + m10, four_squares[..., 2], m12 + m21], -1),
        torch.stack([m10 - m01, m02 + m20, m12 + m21, four_squares[..., 3]], -1),
    ], -2)
    best = four_squares.argmax(-1)
    q = torch.gather(rows, -2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2)
    return q / q.norm(dim=-1, keepdim=True)


def _flat(M: Tensor, init: Tensor | None = None):
    """(n, 3, 3) views/copies of M and of init expanded to M's batch."""
    flat_M = M.reshape(-1, 3, 3)
    flat_init = None if init is None else init.expand(M.shape).reshape(-1, 3, 3)
    return flat_M, flat_init


def _max_normalized(A: Tensor) -> Tensor:
    """A divided by its largest |entry| (matrices of zeros stay zero). The
    maximiser of tr(R^T A) does not depend on A's scale; the methods whose
    arithmetic does (guards, the "+1" of FA3R, inverses that overflow) use it."""
    max_abs = A.abs().amax((-2, -1), keepdim=True)
    return A / torch.where(max_abs > 0, max_abs, torch.ones_like(max_abs))


def _finish(R: Tensor, M: Tensor, iterations: Tensor | None, return_iterations: bool):
    R = R.reshape(M.shape)
    if return_iterations:
        return R, iterations.reshape(M.shape[:-2])
    return R


# ---------------------------------------------------------------------------
# Horn 1987
# ---------------------------------------------------------------------------

def horn(M: Tensor) -> Tensor:
    """Horn (1987), "Closed-form solution of absolute orientation using unit
    quaternions": the unit quaternion q maximising q^T K q, the dominant
    eigenvector of Horn's symmetric 4x4 matrix K(M) (tr(R(q)^T M) = q^T K q),
    by ``torch.linalg.eigh`` (batched LAPACK), in M's dtype.

    Args:
        M: ``(..., 3, 3)`` float32/float64.
    Returns:
        ``(..., 3, 3)`` rotations maximising tr(R^T M) (column vectors:
        M = sum w y x^T gives R x ~ y); exact rotations to rounding.

    Accuracy: K's eigenvalues are the signed sums +-sigma_1 +- sigma_2 +-
    sigma_3 of M's singular values, and the gap at the top is
    2 (sigma_2 + sigma_3), so the eigenvector (hence R) errs by about
    eps ||M|| / (sigma_2 + sigma_3): ~1e-6 (float32) / ~1e-15 (float64) on
    well-conditioned M, growing on the warm data with condition number 1e5
    (float32 ~1e-2, like any float32 method there). Where sigma_2 + sigma_3 = 0
    (rank-1 M, M = -I, ...) the maximiser is not unique and Horn returns one of
    them. det M < 0, rank-2 M and 180-degree rotations are handled exactly (the
    quaternion needs no special case).
    """
    _check_matrices("horn", M)
    _, vectors = torch.linalg.eigh(horn_matrix(M))
    return quaternion_rotation(vectors[..., :, -1])


# ---------------------------------------------------------------------------
# Mueller, Bender, Chentanez, Macklin 2016
# ---------------------------------------------------------------------------

def _retire(done: Tensor, active: Tensor, result: Tensor, current: Tensor, *lane_tensors: Tensor):
    """Iterations over a shrinking set of matrices: writes the ``done`` lanes'
    ``current`` iterate into ``result`` (at their indices ``active``) and drops
    them from ``active``, ``current`` and every other per-lane tensor."""
    if not bool(done.any()):
        return (active, current, *lane_tensors)
    result[active[done]] = current[done]
    keep = ~done
    return (active[keep], current[keep], *(t[keep] for t in lane_tensors))


def _mueller_step(A: Tensor, q: Tensor, guard: float):
    """One update of Mueller et al. 2016 (their Eq. for omega): with r_i, a_i
    the columns of R(q) and A, omega = sum_i r_i x a_i / (|sum_i r_i . a_i| + guard)
    and q <- normalise(exp(omega) q) (rotation by |omega| about omega, applied on
    the left). Returns the new q and |omega|. A is max-normalised, so the
    paper's guard 1e-9 is relative to M's largest entry."""
    R = quaternion_rotation(q)
    omega = torch.linalg.cross(R, A, dim=-2).sum(-1) / ((R * A).sum((-2, -1)).abs() + guard).unsqueeze(-1)
    angle = omega.norm(dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(angle / 2) / angle, finite at angle = 0
    scale = torch.where(angle > 1e-4, torch.sin(half) / angle.clamp_min(1e-30), 0.5 - angle * angle / 48)
    step = torch.cat([torch.cos(half), omega * scale], -1)
    q = _quaternion_product(step, q)
    return q / q.norm(dim=-1, keepdim=True), angle.squeeze(-1)


def mueller(
    M: Tensor,
    init: Tensor | None = None,
    *,
    max_iter: int | None = None,
    tol: float | None = None,
    return_iterations: bool = False,
):
    """Mueller, Bender, Chentanez, Macklin (2016), "A robust method to extract
    the rotational part of deformations": iterative quaternion update, warm
    startable.

    Each step rotates the current R(q) about omega = sum_i r_i x a_i /
    (|sum_i r_i . a_i| + guard) by |omega| (r_i, a_i: columns of R and M), i.e.
    a gradient-ascent step on tr(R^T M) with step length 1 / |tr(R^T M)|, and
    renormalises q. M is first divided by its largest entry, so that the
    paper's guard 1e-9 is relative to M's scale (the step itself is scale
    invariant).

    Args:
        M: ``(..., 3, 3)`` float32/float64.
        init: optional rotations broadcastable to M (the warm start; default
            identity), converted to quaternions once.
        max_iter: ``k``: exactly k updates (the paper's fixed-count use, warm
            started from the previous frame). ``None``: iterate each matrix
            until its step angle |omega| < ``tol`` (default 16 eps of the
            dtype; the paper's double-precision code breaks at 1e-9), at most
            ``MUELLER_CAP`` updates.
        tol: stopping threshold of the converged mode (radians).
        return_iterations: also return the number of updates per matrix.
    Returns:
        ``(..., 3, 3)`` rotations (always exact rotations: R = R(q)), and
        int32 iteration counts if ``return_iterations``.

    Accuracy: converged, ~1e-5 (float32) / ~1e-14 (float64) on the 60- and
    180-degree data (condition number 10; 30-100 steps). The iteration is
    linearly convergent: near the optimum an error about M's singular
    direction i shrinks by sigma_i / (sigma_1 + sigma_2 + sigma_3) per step,
    and it stops when a step is below ``tol``, which for a rate close to 1 is
    far from converged. On anisotropic M (the warm data, condition number 1e3:
    ~260 steps on average in float32, ~600 in float64) ~10% of the results
    stay off by more than 1e-3 (the cap or the early stop), ~40% at condition
    number 1e5. A fixed small count from a warm start is accurate only where
    init is already close (10 steps on the warm data: ~65% above 1e-3). At a
    stationary point that is not the maximum (e.g. init exactly 180 degrees
    off, or M = -I from the identity) the step is zero and the method stays
    there; where tr(R^T M) = 0 the guard makes the first step an arbitrary
    rotation (as in the paper).
    """
    _check_matrices("mueller", M, init, max_iter)
    A, R0 = _flat(M, init)
    A = _max_normalized(A)
    n = A.shape[0]
    guard = 1e-9
    if R0 is None:
        q = torch.zeros(n, 4, dtype=M.dtype, device=M.device)
        q[:, 0] = 1
    else:
        q = rotation_to_quaternion(R0)
    if max_iter is not None:
        for _ in range(max_iter):
            q, _ = _mueller_step(A, q, guard)
        iterations = torch.full((n,), max_iter, dtype=torch.int32, device=M.device)
        return _finish(quaternion_rotation(q), M, iterations, return_iterations)
    tol = 16 * torch.finfo(M.dtype).eps if tol is None else tol
    iterations = torch.zeros(n, dtype=torch.int32, device=M.device)
    active = torch.arange(n, device=M.device)
    A_active, q_active = A, q.clone()
    for _ in range(MUELLER_CAP):
        if active.numel() == 0:
            break
        q_active, angle = _mueller_step(A_active, q_active, guard)
        iterations[active] += 1
        done = ~(angle >= tol)  # NaN counts as done
        active, q_active, A_active = _retire(done, active, q, q_active, A_active)
    q[active] = q_active  # matrices still moving at the cap
    return _finish(quaternion_rotation(q), M, iterations, return_iterations)


# ---------------------------------------------------------------------------
# Higham 1986: scaled Newton iteration for the polar decomposition
# ---------------------------------------------------------------------------

def _det_fix(U: Tensor, A: Tensor) -> Tensor:
    """The nearest rotation from the orthogonal polar factor U of A = U H:
    where det U < 0, R = U (I - 2 v v^T) with v the eigenvector of H's smallest
    eigenvalue (flipping the direction that costs least objective)."""
    reflect = torch.linalg.det(U) < 0
    if not bool(reflect.any()):
        return U
    U = U.clone()
    Ur = U[reflect]
    H = Ur.mT @ A[reflect]
    _, vectors = torch.linalg.eigh(0.5 * (H + H.mT))
    v = vectors[..., :, 0]
    U[reflect] = Ur - 2 * (Ur @ v.unsqueeze(-1)) * v.unsqueeze(-2)
    return U


def _norm_1_inf(X: Tensor) -> Tensor:
    """||X||_1 ||X||_inf (max column sum times max row sum)."""
    a = X.abs()
    return a.sum(-2).amax(-1) * a.sum(-1).amax(-1)


def _inverse_transpose(X: Tensor, inverse: str) -> Tensor:
    """X^{-T}: by LU with partial pivoting (``torch.linalg.inv_ex``, the
    backward-stable inversion Higham's analysis assumes) or in closed form,
    cof(X) / det X (as 3x3 code usually does; det by cofactor expansion)."""
    if inverse == "lu":
        return torch.linalg.inv_ex(X)[0].mT
    cof = _cofactor(X)
    det = (X[..., :, 0] * cof[..., :, 0]).sum(-1)
    return cof / det[..., None, None]


def higham_polar(M: Tensor, *, max_iter: int | None = None, inverse: str = "lu", return_iterations: bool = False):
    """Polar decomposition by Higham's (1986) scaled Newton iteration
    X <- (gamma X + X^{-T} / gamma) / 2, X_0 = M, with his (1, inf)-norm
    scaling gamma = (||X^{-1}||_1 ||X^{-1}||_inf / (||X||_1 ||X||_inf))^{1/4}
    (switched off once the relative change is below 1e-2, where the unscaled
    iteration converges quadratically), then the det-fix: where det U < 0 the
    last axis of H = U^T M is flipped (the eigenvector of the smallest
    eigenvalue, ``torch.linalg.eigh`` on those matrices only). M is first
    divided by its largest entry (the iteration is scale invariant; this keeps
    X^{-1} in range for tiny or huge M).

    Args:
        M: ``(..., 3, 3)`` float32/float64.
        max_iter: ``None``: iterate each matrix until the relative change
            ||X_{k+1} - X_k||_F / ||X_{k+1}||_F < sqrt(eps) (the next iterate
            would change by ~eps: quadratic convergence), at most
            ``HIGHAM_CAP`` steps. ``k``: exactly k steps (scaling always on).
        inverse: ``"lu"`` (default): X^{-1} by batched LU with partial
            pivoting, as Higham's algorithm assumes. ``"cofactor"``: the closed
            form cof(X) / det X, cheaper in principle, but not backward stable:
            in float32 the determinant of a matrix with condition number
            >~ 1e4 can come out with the wrong sign (the warm data with
            condition number 1e5: ~2% of the results are 180 degrees off).
        return_iterations: also return the Newton steps per matrix.
    Returns:
        ``(..., 3, 3)`` rotations maximising tr(R^T M) (column vectors), and
        int32 step counts if ``return_iterations``.

    Accuracy (``inverse="lu"``): ~1e-6 (float32) / ~1e-14 (float64) on
    well-conditioned M, in ~4-7 steps (condition numbers up to 1e5); about
    eps times the condition number beyond (like SVD in the same dtype). Not
    warm-startable. Fails on singular M (X^{-1} does not exist: NaN/Inf, e.g.
    exactly rank-deficient M), and where det M < 0 with two small singular
    values nearly equal the det-fix axis is ill-defined (as is the answer).
    """
    _check_matrices("higham_polar", M, None, max_iter)
    if inverse not in ("lu", "cofactor"):
        raise ValueError(f"torchrot.methods.higham_polar: inverse must be 'lu' or 'cofactor', got {inverse!r}")
    A, _ = _flat(M)
    A = _max_normalized(A)  # the iteration is scale invariant; this keeps X^{-1} in range
    n = A.shape[0]
    eps = torch.finfo(M.dtype).eps
    iterations = torch.zeros(n, dtype=torch.int32, device=M.device)
    X = A.clone()
    active = torch.arange(n, device=M.device)
    X_active = X.clone()
    scaled = torch.ones(n, dtype=torch.bool, device=M.device)
    for _ in range(HIGHAM_CAP if max_iter is None else max_iter):
        if active.numel() == 0:
            break
        inverse_t = _inverse_transpose(X_active, inverse)
        # ||X^{-1}||_1 ||X^{-1}||_inf = ||X^{-T}||_inf ||X^{-T}||_1
        gamma = (_norm_1_inf(inverse_t) / _norm_1_inf(X_active)).pow(0.25)
        gamma = torch.where(scaled[active], gamma, torch.ones_like(gamma))
        X_next = 0.5 * (gamma[..., None, None] * X_active + inverse_t / gamma[..., None, None])
        change = (X_next - X_active).norm(dim=(-2, -1)) / X_next.norm(dim=(-2, -1))
        iterations[active] += 1
        X_active = X_next
        if max_iter is not None:
            continue
        scaled[active] = scaled[active] & (change >= 1e-2)
        done = ~(change >= math.sqrt(eps))  # NaN counts as done
        active, X_active = _retire(done, active, X, X_active)
    X[active] = X_active
    return _finish(_det_fix(X, A), M, iterations, return_iterations)


# ---------------------------------------------------------------------------
# FA3R: Wu, Liu, Zhou, Li 2018
# ---------------------------------------------------------------------------

def fa3r(M: Tensor, *, max_iter: int | None = FA3R_PAPER_ITERATIONS, return_iterations: bool = False):
    """FA3R, Wu, Liu, Zhou & Li (2018), "Fast rigid 3D registration solution: a
    simple method free of SVD and eigen-decomposition": the iteration on the
    columns h_x, h_y, h_z of M

        h_x <- k (h_x + h_y x h_z),  h_y <- k (h_y + h_z x h_x),
        h_z <- k (h_z + h_x x h_y),  k = 2 / (|h_x|^2 + |h_y|^2 + |h_z|^2 + 1),

    i.e. X <- k (X + cof(X)). With X = U diag(s) V^T (U, V rotations, signed
    singular values s) it keeps U and V and maps s_1 <- k (s_1 + s_2 s_3) etc.,
    whose fixed point s = (1, 1, 1) is the rotation U V^T maximising tr(R^T M).
    Only +, x and one division per step.

    The iteration is not scale invariant (the "+1" in k; the authors apply it
    to a covariance averaged over the points), so M is first divided by
    ||M||_F / sqrt(3), which leaves a rotation a fixed point.

    Args:
        M: ``(..., 3, 3)`` float32/float64.
        max_iter: ``k`` steps, default 10 (the authors' implementation);
            ``None``: until the step from an iterate with ||X^T X - I||_F <
            sqrt(eps) (convergence is quadratic near the fixed point, so the
            result is orthonormal to ~eps), at most ``FA3R_CAP`` steps.
        return_iterations: also return the steps per matrix.
    Returns:
        ``(..., 3, 3)`` matrices X as the method leaves them: rotations only
        once converged (the method does not re-orthonormalise), and int32 step
        counts if ``return_iterations``.

    Accuracy: converged, ~1e-6 (float32) / ~1e-14 (float64). A small singular
    value s only doubles per step until it is O(1), so ~log2(condition number)
    steps are needed before the quadratic phase: the authors' 10 steps leave
    matrices of condition number >~ 1e3 (the warm data) visibly
    non-orthonormal. Where s_2 + s_3 = 0 (rank-1 M, the non-unique cases) the
    small values stay 0 and the result is not a rotation.
    """
    _check_matrices("fa3r", M, None, max_iter)
    A, _ = _flat(M)
    n = A.shape[0]
    X = _max_normalized(A)  # first by the largest entry, so the norm cannot under/overflow
    scale = X.norm(dim=(-2, -1)) / math.sqrt(3.0)
    X = X / torch.where(scale > 0, scale, torch.ones_like(scale))[..., None, None]
    eps = torch.finfo(M.dtype).eps
    iterations = torch.zeros(n, dtype=torch.int32, device=M.device)
    active = torch.arange(n, device=M.device)
    X_active = X.clone()
    for _ in range(FA3R_CAP if max_iter is None else max_iter):
        if active.numel() == 0:
            break
        k = 2 / ((X_active * X_active).sum((-2, -1)) + 1)
        X_next = k[..., None, None] * (X_active + _cofactor(X_active))
        iterations[active] += 1
        if max_iter is not None:
            X_active = X_next
            continue
        # |X^T X - I|_F of the iterate just stepped from: the step squares it
        # (quadratic convergence), so below sqrt(eps) X_next is converged.
        residual = (X_active.mT @ X_active - torch.eye(3, dtype=M.dtype, device=M.device)).norm(dim=(-2, -1))
        X_active = X_next
        done = ~(residual >= math.sqrt(eps))  # NaN counts as done
        active, X_active = _retire(done, active, X, X_active)
    X[active] = X_active
    return _finish(X, M, iterations, return_iterations)


# ---------------------------------------------------------------------------
# Kugelstadt, Koschier, Bender 2018
# ---------------------------------------------------------------------------

def _kugelstadt_step(A: Tensor, R: Tensor) -> Tensor:
    """One Newton step of Kugelstadt et al. 2018 (Alg. 3, "APD"): with
    B = R^T A, gradient g = (B12 - B21, B20 - B02, B01 - B10) and the 3x3
    Hessian H = tr(B) I - (B + B^T) / 2, omega = -H^{-1} g / 4; if det H ~ 0
    omega = -g, and if omega is not an ascent direction (omega . g > 0)
    omega = -g / 8. The step is the unit quaternion
    ((1 - |omega|^2), 2 omega) / (1 + |omega|^2), applied on the right."""
    B = R.mT @ A
    g = torch.stack([B[..., 1, 2] - B[..., 2, 1], B[..., 2, 0] - B[..., 0, 2], B[..., 0, 1] - B[..., 1, 0]], -1)
    eye = torch.eye(3, dtype=A.dtype, device=A.device)
    H = _trace(B)[..., None, None] * eye - 0.5 * (B + B.mT)
    adj = _cofactor(H)  # H symmetric: adj(H) = cof(H)^T = cof(H)
    det = (H[..., :, 0] * adj[..., :, 0]).sum(-1)
    singular = det.abs() < 1e-9
    safe_det = torch.where(singular, torch.ones_like(det), det)
    omega = -0.25 * (adj @ g.unsqueeze(-1)).squeeze(-1) / safe_det.unsqueeze(-1)
    omega = torch.where(singular.unsqueeze(-1), -g, omega)
    omega = torch.where(((omega * g).sum(-1) > 0).unsqueeze(-1), -0.125 * g, omega)
    ww = (omega * omega).sum(-1, keepdim=True)
    step = torch.cat([1 - ww, 2 * omega], -1) / (1 + ww)
    return R @ quaternion_rotation(step)


def kugelstadt(M: Tensor, init: Tensor, *, max_iter: int = 1) -> Tensor:
    """Kugelstadt, Koschier & Bender (2018), "Fast corotated FEM using operator
    splitting", Alg. 3: Newton steps on tr(R^T M) from a warm start, in the
    rotation's local frame (the paper uses one step per solver iteration).

    The Newton step vector is the one of torchrot's ``variant="newton"`` (the
    Cayley step with c = tr S, Eq. 24 of Zhang et al.: z = 2 omega), but Alg. 3
    turns it into a rotation with the quaternion ((1 - |omega|^2), 2 omega) /
    (1 + |omega|^2), a rotation by 4 atan(|z| / 2) about z, where the Cayley
    map Q(z) rotates by 2 atan(|z|). The two results therefore agree to third
    order in the step, not to rounding: ~|z|^3 / 2 radians apart, 3e-7 for a one
    degree step, 1e-3 for 15 degrees (``tests/test_methods.py`` checks that relation
    to rounding). Alg. 3's guards (gradient steps where det H ~ 0 or the
    Newton step descends) are kept; M is first divided by its largest entry
    so the paper's absolute threshold det H < 1e-9 is meaningful for any
    scale (the Newton step itself is scale invariant). The quaternion of
    Alg. 3 is kept here as a rotation matrix (R <- R R(step)), as torchrot's
    warm start is.

    Args:
        M: ``(..., 3, 3)`` float32/float64.
        init: rotations broadcastable to M: the warm start (required).
        max_iter: number of Newton steps (default 1, as in the paper).
    Returns:
        ``(..., 3, 3)`` rotations (exact rotations to rounding).

    Accuracy: one step from init at angle theta from R* errs by O(theta^2)
    (quadratic convergence) times a constant that grows with M's anisotropy:
    from inits within 2 degrees of R* on condition-number-10 data, below
    1e-3; on the warm data (up to 15 degrees, condition number 1e3) median
    ~9e-5 but ~35% above 1e-3, and where the Newton model is not concave the
    guards' gradient steps leave errors up to 180 degrees. Useless for large
    remaining rotations (60 degrees: ~90% above 1e-3), like torchrot's
    ``variant="newton", max_iter=1``.
    """
    _check_matrices("kugelstadt", M, init, max_iter, init_required=True)
    if max_iter is None:
        raise ValueError("torchrot.methods.kugelstadt: max_iter must be an int >= 1 (Newton steps), got None")
    A, R = _flat(M, init)
    A = _max_normalized(A)
    for _ in range(max_iter):
        R = _kugelstadt_step(A, R)
    return R.reshape(M.shape)
