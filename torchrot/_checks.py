"""Argument checks of the Python-side kernels (fake, device-generic) and of
the Python API while traced.

They mirror the checks of the C++ CPU operator (csrc/ops/checks.cpp) in
order, type and message: TypeError for a wrong type or dtype, ValueError for
a wrong value, shape or device, with the message templates the C++ side
defines (csrc/messages.h, through torchrot._constants.MESSAGES). So every
device and tracing mode rejects the same arguments with the same words
(tests/test_errors.py runs every case on every path). Limits, variants and
dtypes come from torchrot._constants.
"""
from __future__ import annotations

import numpy as np
import torch

from torchrot._constants import MAX_GRADIENT_EPS, MAX_ITER, MESSAGES, SUPPORTED_DTYPES, VARIANTS

__all__ = [
    "BACKWARD_NAME",
    "OP_NAME",
    "ORTHOGONAL_NAME",
    "broadcast_shapes",
    "check_all",
    "check_backward",
    "check_gradient_eps",
    "check_gradient_eps_type",
    "check_init",
    "check_matrix_arg",
    "check_max_iter",
    "check_max_iter_type",
    "check_out",
    "check_out_autograd",
    "check_tensor",
    "check_variant",
    "check_variant_type",
    "bad_init_error",
    "not_orthogonal_error",
]

OP_NAME = MESSAGES["OP_NAME"]
BACKWARD_NAME = MESSAGES["BACKWARD_NAME"]
ORTHOGONAL_NAME = MESSAGES["ORTHOGONAL_NAME"]


def _message(key: str, op: str = OP_NAME, **fields) -> str:
    return MESSAGES[key].format(op=op, **fields)


def broadcast_shapes(*shapes: torch.Size) -> torch.Size:
    """torch.broadcast_shapes, without its cost (more than a small fit's:
    benchmarks/lab_notes.md) where the shapes are equal, the common call."""
    if all(shape == shapes[0] for shape in shapes[1:]):
        return torch.Size(shapes[0])
    return torch.broadcast_shapes(*shapes)


def check_tensor(t, name: str, op: str = OP_NAME) -> None:
    if not isinstance(t, torch.Tensor):
        raise TypeError(_message("NOT_A_TENSOR", op, name=name, type=type(t).__name__))


def check_matrix_shape(t, name: str, op: str = OP_NAME) -> None:
    """``t`` is a tensor of shape (..., 3, 3)."""
    check_tensor(t, name, op)
    if t.dim() < 2 or t.shape[-1] != 3 or t.shape[-2] != 3:
        raise ValueError(_message("MATRIX_SHAPE", op, name=name, shape=list(t.shape)))


def check_matrix_arg(t, name: str, op: str = OP_NAME) -> None:
    """``t`` is a float32/float64/float16/bfloat16 tensor of shape (..., 3, 3);
    errors name the function ``op`` and the argument ``name``."""
    check_matrix_shape(t, name, op)
    if t.dtype not in SUPPORTED_DTYPES:
        raise TypeError(_message("MATRIX_DTYPE", op, name=name, dtype=t.dtype))


def _check_like(t: torch.Tensor, name: str, ref: torch.Tensor, ref_name: str, op: str = OP_NAME) -> None:
    """t must be on ref's device and have ref's dtype."""
    if t.device != ref.device:
        raise ValueError(_message("DEVICE_LIKE", op, name=name, ref=ref_name, device=ref.device, got=t.device))
    if t.dtype != ref.dtype:
        raise TypeError(_message("DTYPE_LIKE", op, name=name, ref=ref_name, dtype=ref.dtype, got=t.dtype))


def check_max_iter_type(max_iter, op: str = OP_NAME) -> None:
    """The type of max_iter, and that the operator's int64 holds it (a larger
    int raises check_max_iter's ValueError rather than a schema error)."""
    if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, int)):
        raise TypeError(_message("MAX_ITER_TYPE", op, value=repr(max_iter)))  # bool: an int to the schema
    if max_iter is not None and not -(2**63) <= max_iter < 2**63:
        raise ValueError(_message("MAX_ITER_RANGE", op, value=max_iter))


def check_max_iter(max_iter, op: str = OP_NAME) -> None:
    check_max_iter_type(max_iter, op)
    if max_iter is not None and not 1 <= max_iter <= MAX_ITER:
        raise ValueError(_message("MAX_ITER_RANGE", op, value=max_iter))


def check_variant_type(variant, op: str = OP_NAME) -> None:
    if not isinstance(variant, str):
        raise TypeError(_message("VARIANT_TYPE", op, type=type(variant).__name__))


def check_variant(variant, op: str = OP_NAME) -> None:
    check_variant_type(variant, op)
    if variant not in VARIANTS:
        raise ValueError(_message("VARIANT_VALUE", op, value=variant))


def check_init(M: torch.Tensor, init: torch.Tensor | None, op: str = OP_NAME) -> None:
    check_matrix_arg(M, "M", op)
    if init is None:
        return
    check_matrix_arg(init, "init", op)
    # any float dtype: a warm start of another precision is cast to M's compute dtype
    if init.device != M.device:
        raise ValueError(_message("DEVICE_LIKE", op, name="init", ref="M", device=M.device, got=init.device))
    batch, init_batch = M.shape[:-2], init.shape[:-2]
    try:
        ok = len(init_batch) <= len(batch) and broadcast_shapes(init_batch, batch) == batch
    except RuntimeError:
        ok = False
    if not ok:
        raise ValueError(_message("INIT_BROADCAST", op, shape=list(init.shape), m_shape=list(M.shape)))


def has_overlapping_elements(t: torch.Tensor) -> bool:
    """Whether two distinct elements of ``t`` share memory (as
    csrc/ops/overlap.cpp: nested strides at once, others by sorting the
    element offsets)."""
    dims = sorted((abs(st), sz) for st, sz in zip(t.stride(), t.shape) if sz > 1)
    extent, nested = 1, True
    for stride, size in dims:
        if stride == 0:
            return True
        nested = nested and stride >= extent
        extent += (size - 1) * stride
    if nested:
        return False
    # NumPy, not torch: this also runs on fake tensors (no data) under tracing.
    offsets = np.zeros((), dtype=np.int64)
    for d, (size, stride) in enumerate(zip(t.shape, t.stride())):
        shape = [1] * t.dim()
        shape[d] = int(size)
        offsets = offsets + (np.arange(int(size), dtype=np.int64) * int(stride)).reshape(shape)
    ordered = np.sort(offsets, axis=None)
    return bool((ordered[1:] == ordered[:-1]).any())


def check_out(M: torch.Tensor, out, op: str = OP_NAME) -> None:
    check_tensor(out, "out", op)
    _check_like(out, "out", M, "M", op)
    if out.shape != M.shape:
        raise ValueError(_message("OUT_SHAPE", op, m_shape=list(M.shape), shape=list(out.shape)))
    if has_overlapping_elements(out):
        raise ValueError(_message("OUT_OVERLAP", op))
    # (Not while dynamo traces, which cannot: the fake kernel checks it then.)
    if not torch.compiler.is_compiling() and out.is_inference() and not torch.is_inference_mode_enabled():
        raise ValueError(_message("OUT_INFERENCE", op))


def check_out_autograd(M: torch.Tensor, out: torch.Tensor, op: str = OP_NAME) -> None:
    """torch's rule for out= operators, which the operator's Autograd kernel
    applies (csrc/autograd.cpp): no call that would record a derivative."""
    reverse = torch.is_grad_enabled() and (M.requires_grad or out.requires_grad)
    if reverse or _has_tangent(M) or _has_tangent(out):
        raise ValueError(_message("OUT_AUTOGRAD", op))


def _has_tangent(t: torch.Tensor) -> bool:
    return torch.autograd.forward_ad.unpack_dual(t).tangent is not None


def check_all(M, init, max_iter, variant, op: str = OP_NAME) -> None:
    """M and init, then max_iter and variant: the operator's order."""
    check_init(M, init, op)
    check_max_iter(max_iter, op)
    check_variant(variant, op)


def check_gradient_eps_type(gradient_eps, op: str = OP_NAME) -> None:
    if isinstance(gradient_eps, bool) or not isinstance(gradient_eps, (int, float)):
        raise TypeError(_message("GRADIENT_EPS_TYPE", op, value=repr(gradient_eps)))


def check_gradient_eps(gradient_eps, op: str = OP_NAME) -> None:
    check_gradient_eps_type(gradient_eps, op)
    if not (0 <= gradient_eps <= MAX_GRADIENT_EPS):
        raise ValueError(_message("GRADIENT_EPS_RANGE", op, value=f"{gradient_eps:g}"))


def bad_init_error(bad: int, n: int) -> ValueError:
    """The error for ``bad`` of ``n`` warm starts that are not rotations."""
    return ValueError(_message("INIT_NOT_ROTATIONS", bad=bad, n=n))


def not_orthogonal_error(bad: int, n: int, op: str) -> ValueError:
    """The error for ``bad`` of ``n`` warm starts of an orthogonal fit that
    are not orthogonal matrices."""
    return ValueError(_message("INIT_NOT_ORTHOGONAL", op, bad=bad, n=n))


def check_backward(grad, R, M, gradient_eps) -> None:
    """Mirrors the checks of the C++ fit_rotation_backward (csrc/ops/checks.cpp)."""
    check_matrix_arg(R, "R", BACKWARD_NAME)
    for name, t in (("grad", grad), ("M", M)):
        check_matrix_shape(t, name, BACKWARD_NAME)
        _check_like(t, name, R, "R", BACKWARD_NAME)
    if grad.shape != R.shape:
        raise ValueError(_message("GRAD_SHAPE", BACKWARD_NAME, r_shape=list(R.shape), shape=list(grad.shape)))
    try:
        ok = broadcast_shapes(M.shape, R.shape) == R.shape
    except RuntimeError:
        ok = False
    if not ok:
        raise ValueError(_message("BACKWARD_BROADCAST", BACKWARD_NAME, shape=list(M.shape), r_shape=list(R.shape)))
    check_gradient_eps(gradient_eps, BACKWARD_NAME)
