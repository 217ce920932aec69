"""Pure-PyTorch implementations: the SVD reference and torchrot's algorithm.

``rotation_svd`` is the textbook answer (Eq. 4 of the paper), kept public as the
reference the tests measure against. ``fit_rotation_reference`` is the same
algorithm as the C++ kernel (csrc/kernel/), written once in
:mod:`torchrot.generic` as elementwise tensor operations over structure-of-arrays
components with per-matrix masks: it runs on any device and on ``meta``
tensors, and compiles without a graph break. It is the kernel of
``torch.ops.torchrot.fit_rotation`` on devices without a C++ or Triton kernel
(MPS; CUDA and XPU where Triton is missing: torchrot._device_kernels).

Convention everywhere: R (det R = +1) maximises tr(R^T M); for centred point
sets, M = sum_i w_i y_i x_i^T gives R x_i ~ y_i (column vectors).
"""
from __future__ import annotations

import torch

from torchrot._checks import bad_init_error, check_all, check_backward, check_matrix_arg
from torchrot._constants import GRADIENT_EPS
from torchrot.generic import quaternion as soa_quaternion
from torchrot.generic.driver import fit_rotation_backward_generic, fit_rotation_generic

__all__ = [
    "cayley_rotation",
    "fit_rotation_backward_reference",
    "fit_rotation_reference",
    "horn_matrix",
    "orthogonal_svd",
    "quaternion_rotation",
    "rigid_registration_svd",
    "rotation_svd",
]


def rotation_svd(M: torch.Tensor) -> torch.Tensor:
    """Rotation maximising tr(R^T M) by SVD: R = U diag(1, 1, det(U V^T)) V^T.

    The textbook answer (the paper's Eq. 4), computed in M's dtype by
    ``torch.linalg.svd``: pass float64 for a reference answer. Column-vector
    convention: for centred point sets ``M = sum_i w_i y_i x_i^T`` gives
    ``R x_i ~ y_i``.

    Args:
        M: ``(..., 3, 3)`` float32 or float64, any batch shape, on any device
            ``torch.linalg.svd`` supports. (float16/bfloat16 pass the checks,
            but torch.linalg.svd has no kernel for them: it raises.)

    Returns:
        ``(..., 3, 3)`` rotations (det R = +1) in M's dtype and on its device.
        Differentiable by autograd through the SVD (NaN/Inf where singular
        values repeat).

    Raises:
        TypeError: M is not a tensor, or not float32, float64, float16 or bfloat16.
        ValueError: M's shape is not ``(..., 3, 3)``.

    Examples:
        >>> M = torch.randn(5, 3, 3, dtype=torch.float64)
        >>> R = torchrot.rotation_svd(M)
        >>> R.shape, torch.allclose(R.det(), torch.ones(5, dtype=torch.float64))
        (torch.Size([5, 3, 3]), True)
        >>> torch.allclose(R, torchrot.fit_rotation(M))
        True
    """
    check_matrix_arg(M, "M", op="torchrot.rotation_svd")
    U, _, Vh = torch.linalg.svd(M)
    d = torch.linalg.det(U @ Vh)
    D = torch.ones(M.shape[:-1], dtype=M.dtype, device=M.device)
    D[..., 2] = d
    return (U * D.unsqueeze(-2)) @ Vh


def orthogonal_svd(M: torch.Tensor) -> torch.Tensor:
    """Orthogonal matrix maximising tr(Q^T M) by SVD: the polar factor Q = U V^T.

    The reference of :func:`torchrot.fit_orthogonal` (det Q = +1 or -1, the
    sign of det M), computed in M's dtype by ``torch.linalg.svd``: pass
    float64 for a reference answer. Column-vector convention as
    :func:`rotation_svd`.

    Args:
        M: ``(..., 3, 3)`` float32 or float64, any batch shape, on any device
            ``torch.linalg.svd`` supports.

    Returns:
        ``(..., 3, 3)`` orthogonal matrices in M's dtype and on its device.

    Raises:
        TypeError: M is not a tensor, or not float32, float64, float16 or bfloat16.
        ValueError: M's shape is not ``(..., 3, 3)``.

    Examples:
        >>> from torchrot.reference import orthogonal_svd
        >>> F = torch.diag(torch.tensor([2.0, 1.0, -0.5], dtype=torch.float64))
        >>> orthogonal_svd(F).diagonal().tolist()
        [1.0, 1.0, -1.0]
    """
    check_matrix_arg(M, "M", op="torchrot.reference.orthogonal_svd")
    U, _, Vh = torch.linalg.svd(M)
    return U @ Vh


def rigid_registration_svd(x: torch.Tensor, y: torch.Tensor, weights: torch.Tensor | None = None,
                           scale: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Umeyama's closed form (IEEE TPAMI 1991) by SVD, written plainly: the
    reference for :func:`torchrot.rigid_registration` and its baseline in
    ``benchmarks/registration.py``. Differentiable by autograd (through the SVD).

    Args:
        x: ``(..., N, 3)`` source points, float32 or float64.
        y: ``(..., N, 3)`` target points, x's dtype (column vectors:
            ``y ~ s R x + t``).
        weights: optional ``(..., N)`` non-negative weights; None: all ones.
        scale: also fit Umeyama's scale s; False: s = 1.

    Returns:
        ``(R, t, s)``: ``(..., 3, 3)``, ``(..., 3)`` and ``(...)``, in the inputs'
        dtype (pass float64 for a reference answer). No argument checks: use
        :func:`torchrot.rigid_registration` for checked input.

    Examples:
        >>> from torchrot.reference import rigid_registration_svd
        >>> from torchrot.testing import registration_problem
        >>> x, y, (R_true, t_true, s_true) = registration_problem(n=20, seed=0)  # y = s R x + t
        >>> R, t, s = rigid_registration_svd(x, y, scale=True)
        >>> torch.allclose(R, R_true), torch.allclose(t, t_true), torch.allclose(s, s_true)
        (True, True, True)
    """
    if weights is None:
        weights = torch.ones(x.shape[:-1], dtype=x.dtype, device=x.device)
    p = weights / weights.sum(-1, keepdim=True)
    x_mean = (p.unsqueeze(-1) * x).sum(-2)
    y_mean = (p.unsqueeze(-1) * y).sum(-2)
    xc, yc = x - x_mean.unsqueeze(-2), y - y_mean.unsqueeze(-2)
    M = torch.einsum("...n,...ni,...nj->...ij", p, yc, xc)
    R = rotation_svd(M)
    if scale:
        # tr(R^T M): the sign-corrected sum of M's singular values.
        s = (R * M).sum((-2, -1)) / (p * xc.square().sum(-1)).sum(-1)
    else:
        s = torch.ones(M.shape[:-2], dtype=M.dtype, device=M.device)
    t = y_mean - s.unsqueeze(-1) * (R @ x_mean.unsqueeze(-1)).squeeze(-1)
    return R, t, s


def _fraction_rotation(w, d):
    """Eq. 10 for z = -w / d, multiplied through by d^2 (one division). Not
    torchrot.generic.cayley's cayley_increment, which computes Q - I for the
    fits (other roundings): cayley_rotation makes the test data
    (torchrot.testing.data), whose bits stay as they were."""
    ww = (w * w).sum(-1)[..., None, None]
    dd = (d * d)[..., None, None]
    x, y, v = w.unbind(-1)
    zero = torch.zeros_like(x)
    cross = torch.stack([zero, -v, y, v, zero, -x, -y, x, zero], -1).reshape(w.shape + (3,))
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return ((dd - ww) * eye + 2 * w.unsqueeze(-1) * w.unsqueeze(-2) - 2 * d[..., None, None] * cross) / (dd + ww)


def cayley_rotation(z: torch.Tensor) -> torch.Tensor:
    """The rotation ((1 - z.z) I + 2 z z^T + 2 [z]x) / (1 + z.z) (paper Eq. 10).

    Args:
        z: ``(..., 3)`` Cayley parameters, z = tan(theta / 2) * axis (Eq. 7),
            floating point.

    Returns:
        ``(..., 3, 3)`` rotations by theta about the axis, z's dtype and device.

    Examples:
        >>> from torchrot.reference import cayley_rotation
        >>> cayley_rotation(torch.tensor([0.0, 0.0, 1.0]))  # tan(45 degrees) = 1: 90 degrees about z
        tensor([[ 0., -1.,  0.],
                [ 1.,  0.,  0.],
                [ 0.,  0.,  1.]])
    """
    return _fraction_rotation(-z, torch.ones_like(z[..., 0]))  # z = -w / d with d = 1


def quaternion_rotation(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of unit quaternions (torchrot.generic.quaternion's entries, stacked).

    Args:
        q: ``(..., 4)`` unit quaternions ordered (w, x, y, z), floating point
            (not normalised here).

    Returns:
        ``(..., 3, 3)`` rotations, q's dtype and device; q and -q give the same R.

    Examples:
        >>> from torchrot.reference import quaternion_rotation
        >>> quaternion_rotation(torch.tensor([0.0, 0.0, 0.0, 1.0]))  # 180 degrees about z
        tensor([[-1.,  0.,  0.],
                [ 0., -1.,  0.],
                [ 0.,  0.,  1.]])
    """
    return torch.stack(soa_quaternion.quaternion_rotation(*q.unbind(-1)), -1).reshape(q.shape[:-1] + (3, 3))


def horn_matrix(M: torch.Tensor) -> torch.Tensor:
    """Horn's symmetric 4x4 K with tr(R(q)^T M) = q^T K q for unit q (w, x, y, z)
    (torchrot.generic.quaternion's entries, stacked).

    Args:
        M: ``(..., 3, 3)`` floating point.

    Returns:
        ``(..., 4, 4)`` symmetric matrices, M's dtype and device; the
        eigenvector of the largest eigenvalue is the quaternion of the
        rotation maximising tr(R^T M).

    Examples:
        >>> from torchrot.reference import horn_matrix, quaternion_rotation
        >>> M = torch.randn(3, 3, dtype=torch.float64)
        >>> q = torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=torch.float64) / 30 ** 0.5
        >>> torch.allclose(q @ horn_matrix(M) @ q, (quaternion_rotation(q) * M).sum())
        True
    """
    return torch.stack(soa_quaternion.horn_matrix(list(M.flatten(-2).unbind(-1))), -1).reshape(M.shape[:-2] + (4, 4))


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
    maximising tr(R^T M), column-vector convention (``M = sum_i w_i y_i x_i^T``
    gives ``R x_i ~ y_i``). Agrees with the C++ kernel to rounding (the same
    iterations and status codes in float64; tests/test_generic_path.py). Runs
    where M is, as elementwise tensor operations: on CUDA, XPU or MPS tensors
    too, and on ``meta`` tensors (shapes only). Autograd through it
    differentiates the iterations themselves; :func:`torchrot.fit_rotation`'s
    derivative is that of the exact maximiser (the optimality condition).

    Args:
        M: ``(..., 3, 3)`` float32 or float64 (float16/bfloat16 are computed in
            float32 and returned in their dtype); any batch shape.
        init: optional ``(..., 3, 3)`` rotations broadcastable to M, on M's
            device, of any float dtype (cast to the compute dtype): the warm
            start. ``None``: a cold start.
        max_iter: ``None`` (default) to converge each matrix (with the
            Horn/Jacobi fallback); ``k >= 1`` (at most 1000) for at most k
            Cayley steps.
        variant: ``"newton"``, ``"conservative"`` (the default) or
            ``"gershgorin"`` (paper Sec. 4.2).
        return_info: also return per-matrix iteration counts and status codes.

    Returns:
        R ``(..., 3, 3)`` in M's dtype, or, if ``return_info``, ``(R,
        iterations, status)`` with iterations ``(...)`` int32 and status
        ``(...)`` uint8 (:class:`torchrot.FitStatus` codes), as
        :func:`torchrot.fit_rotation_info` returns them. All on M's device.

    Raises:
        TypeError: M or init not a tensor, or not float32, float64, float16 or
            bfloat16; max_iter not an int or None; variant not a str.
        ValueError: M not ``(..., 3, 3)``; init not broadcastable to M or on
            another device; an unknown variant; max_iter out of range; a
            finite ``init`` that is not a rotation (not checked on ``meta``
            tensors, whose values are unknown).

    Examples:
        >>> M = torch.randn(6, 3, 3, dtype=torch.float64)
        >>> R, iterations, status = torchrot.fit_rotation_reference(M, return_info=True)
        >>> torch.allclose(R, torchrot.fit_rotation(M)), iterations.shape, status.dtype
        (True, torch.Size([6]), torch.uint8)
        >>> torchrot.fit_rotation_reference(M.to("meta")).shape  # shapes only, no data
        torch.Size([6, 3, 3])
    """
    check_all(M, init, max_iter, variant)
    return fit_rotation_generic(M, init, max_iter, variant, return_info, bad_init_error)


def fit_rotation_backward_reference(
    grad: torch.Tensor, R: torch.Tensor, M: torch.Tensor, gradient_eps: float = GRADIENT_EPS
) -> torch.Tensor:
    """dL/dM from dL/dR = ``grad`` at R = fit_rotation(M), in batched PyTorch.

    The fitted R makes S = R^T M symmetric; differentiating that condition
    (csrc/kernel/rotation_gradient.h has the derivation) gives
    dL/dM = R [u]x with (tr(S) I - S) u = vex(R^T G - G^T R), solved with
    Tikhonov damping ``lambda = gradient_eps |M|_F``:
    u = (A^2 + lambda^2 I)^-1 A g, evaluated as Re (A + i lambda I)^-1 g by
    the 3x3 adjugate, as the CPU kernel (forming A^2 would square A's
    condition number: ~3 digits lost in float32), elementwise over the 9
    entries (torchrot.generic.rotation_gradient.rotation_tangent). The map is
    self-adjoint, so with ``grad = dM`` this returns the forward-mode tangent dR.

    Convention: R (det +1) maximises tr(R^T M); M = sum_i w_i y_i x_i^T gives
    R x_i ~ y_i (column vectors).

    Args:
        grad: ``(..., 3, 3)`` with R's shape, dtype and device.
        R: ``(..., 3, 3)`` the fitted rotations, float32, float64, float16 or bfloat16.
        M: ``(..., 3, 3)`` the fitted matrices, broadcastable to R, R's dtype and device.
        gradient_eps: damping, a finite float from 0 (undamped) to 1000.

    Returns:
        ``(..., 3, 3)`` in R's dtype (reduced precision computed in float32).

    Raises:
        TypeError: an argument not a tensor, R not float32, float64, float16 or
            bfloat16, grad or M not of R's dtype; gradient_eps not a float or int.
        ValueError: shapes other than ``(..., 3, 3)``, grad not of R's shape, M
            not broadcastable to R, a tensor on another device than R;
            gradient_eps out of range.

    Examples:
        >>> from torchrot.reference import fit_rotation_backward_reference
        >>> M = torch.randn(4, 3, 3, dtype=torch.float64, requires_grad=True)
        >>> R = torchrot.fit_rotation(M)
        >>> grad = torch.randn(4, 3, 3, dtype=torch.float64)
        >>> R.backward(grad)
        >>> torch.allclose(fit_rotation_backward_reference(grad, R.detach(), M.detach()), M.grad)
        True
    """
    check_backward(grad, R, M, gradient_eps)
    return fit_rotation_backward_generic(grad, R, M, gradient_eps)
