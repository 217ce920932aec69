"""Argument checks of the Python-side kernels (fake and pure PyTorch).

They mirror the checks of the C++ CPU operator (csrc/ops.cpp) in order, type
and message: TypeError for a wrong type or dtype, ValueError for a wrong value,
shape or device. So every device and tracing mode rejects the same arguments
with the same error (tests/test_errors.py runs every case on every path).
Limits come from torchrot._limits (csrc/limits.h).
"""
from __future__ import annotations

import numpy as np
import torch

from torchrot._limits import INIT_TOLERANCE, MAX_GRADIENT_EPS, MAX_ITER, MESSAGES

OP_NAME = MESSAGES["OP_NAME"]
BACKWARD_NAME = MESSAGES["BACKWARD_NAME"]
OUT_AUTOGRAD = MESSAGES["OUT_AUTOGRAD"]
OUT_INFERENCE = MESSAGES["OUT_INFERENCE"]
VARIANTS = ("newton", "conservative", "gershgorin")
SUPPORTED_DTYPES = (torch.float32, torch.float64, torch.float16, torch.bfloat16)


def broadcast_shapes(*shapes: torch.Size) -> torch.Size:
    """torch.broadcast_shapes, without its cost (~7 us, more than a small fit)
    where the shapes are equal, the common call."""
    if all(shape == shapes[0] for shape in shapes[1:]):
        return torch.Size(shapes[0])
    return torch.broadcast_shapes(*shapes)


def check_tensor(t, name: str, op: str = OP_NAME) -> None:
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{op}: {name} must be a torch.Tensor, got {type(t).__name__}")


def check_matrix_shape(t, name: str, op: str = OP_NAME) -> None:
    """``t`` is a tensor of shape (..., 3, 3)."""
    check_tensor(t, name, op)
    if t.dim() < 2 or t.shape[-1] != 3 or t.shape[-2] != 3:
        raise ValueError(f"{op}: {name} must have shape (..., 3, 3), got {list(t.shape)}")


def check_matrix_arg(t, name: str, op: str = OP_NAME) -> None:
    """``t`` is a float32/float64/float16/bfloat16 tensor of shape (..., 3, 3);
    errors name the function ``op`` and the argument ``name``."""
    check_matrix_shape(t, name, op)
    if t.dtype not in SUPPORTED_DTYPES:
        raise TypeError(f"{op}: {name} must be float32, float64, float16 or bfloat16, got {t.dtype}")


def check_device_dtype(t: torch.Tensor, name: str, ref: torch.Tensor, ref_name: str, op: str = OP_NAME) -> None:
    """t must be on ref's device and have ref's dtype."""
    if t.device != ref.device:
        raise ValueError(f"{op}: {name} must be on {ref_name}'s device ({ref.device}), got {t.device}")
    if t.dtype != ref.dtype:
        raise TypeError(f"{op}: {name} must have {ref_name}'s dtype ({ref.dtype}), got {t.dtype}")


def check_max_iter_type(max_iter) -> None:
    """The type of max_iter, and that the operator's int64 holds it (a larger
    int raises check_max_iter's ValueError rather than a schema error)."""
    if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, int)):
        raise TypeError(f"{OP_NAME}: max_iter must be None or an int >= 1, got {max_iter!r}")  # bool: an int to the schema
    if max_iter is not None and not -(2**63) <= max_iter < 2**63:
        _raise_max_iter_range(max_iter)


def check_max_iter(max_iter) -> None:
    check_max_iter_type(max_iter)
    if max_iter is not None and not 1 <= max_iter <= MAX_ITER:
        _raise_max_iter_range(max_iter)


def _raise_max_iter_range(max_iter: int) -> None:
    raise ValueError(
        f"{OP_NAME}: max_iter must be None (iterate to convergence) or an int >= 1 and <= {MAX_ITER}, got {max_iter}"
    )


def check_variant_type(variant) -> None:
    if not isinstance(variant, str):
        raise TypeError(f"{OP_NAME}: variant must be a str, got {type(variant).__name__}")


def check_variant(variant) -> None:
    check_variant_type(variant)
    if variant not in VARIANTS:
        raise ValueError(f"{OP_NAME}: variant must be one of 'newton', 'conservative', 'gershgorin', got '{variant}'")


def check_options(max_iter, variant) -> None:
    check_max_iter(max_iter)
    check_variant(variant)


def check_init(M: torch.Tensor, init: torch.Tensor | None) -> None:
    check_matrix_arg(M, "M")
    if init is None:
        return
    check_matrix_arg(init, "init")
    # any float dtype: a warm start of another precision is cast to M's compute dtype
    if init.device != M.device:
        raise ValueError(f"{OP_NAME}: init must be on M's device ({M.device}), got {init.device}")
    batch, init_batch = M.shape[:-2], init.shape[:-2]
    try:
        ok = len(init_batch) <= len(batch) and broadcast_shapes(init_batch, batch) == batch
    except RuntimeError:
        ok = False
    if not ok:
        raise ValueError(f"{OP_NAME}: init of shape {list(init.shape)} must broadcast to M's shape {list(M.shape)}")


def has_overlapping_elements(t: torch.Tensor) -> bool:
    """Whether two distinct elements of ``t`` share memory (as ops.cpp's
    has_overlapping_elements: nested strides at once, others by sorting the
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


def check_out(M: torch.Tensor, out) -> None:
    check_tensor(out, "out")
    check_device_dtype(out, "out", M, "M")
    if out.shape != M.shape:
        raise ValueError(f"{OP_NAME}: out must have M's shape {list(M.shape)}, got {list(out.shape)}")
    if has_overlapping_elements(out):
        raise ValueError(f"{OP_NAME}: out must not have overlapping elements (e.g. an expanded tensor)")
    # (Not while dynamo traces, which cannot: the fake kernel checks it then.)
    if not torch.compiler.is_compiling() and out.is_inference() and not torch.is_inference_mode_enabled():
        raise ValueError(OP_NAME + OUT_INFERENCE)


def check_out_autograd(M: torch.Tensor, out: torch.Tensor) -> None:
    """torch's rule for out= operators, which the operator's Autograd kernel
    applies (csrc/autograd.cpp): no call that would record a derivative."""
    reverse = torch.is_grad_enabled() and (M.requires_grad or out.requires_grad)
    if reverse or _has_tangent(M) or _has_tangent(out):
        raise ValueError(OP_NAME + OUT_AUTOGRAD)


def _has_tangent(t: torch.Tensor) -> bool:
    return torch.autograd.forward_ad.unpack_dual(t).tangent is not None


def check_all(M, init, max_iter, variant) -> None:
    check_init(M, init)
    check_options(max_iter, variant)


def check_gradient_eps_type(gradient_eps, name: str = OP_NAME) -> None:
    if isinstance(gradient_eps, bool) or not isinstance(gradient_eps, (int, float)):
        raise TypeError(f"{name}: gradient_eps must be a float >= 0, got {gradient_eps!r}")


def check_gradient_eps(gradient_eps, name: str = OP_NAME) -> None:
    check_gradient_eps_type(gradient_eps, name)
    if not (0 <= gradient_eps <= MAX_GRADIENT_EPS):
        raise ValueError(
            f"{name}: gradient_eps must be a finite number >= 0 and <= {MAX_GRADIENT_EPS:g}, got {gradient_eps:g}"
        )


def bad_init_error(bad: int, n: int) -> ValueError:
    """The error for ``bad`` of ``n`` warm starts that are not rotations."""
    return ValueError(
        f"{OP_NAME}: init must hold rotations (|R^T R - I|_F < {INIT_TOLERANCE:g} and det R > 0; rotations of any"
        f" float dtype qualify); {bad} of {n} are not: pass rotations, or no init for a cold start"
    )


def check_backward(grad, R, M, gradient_eps) -> None:
    """Mirrors the checks of the C++ fit_rotation_backward (csrc/ops.cpp)."""
    check_matrix_arg(R, "R", BACKWARD_NAME)
    for name, t in (("grad", grad), ("M", M)):
        check_matrix_shape(t, name, BACKWARD_NAME)
        check_device_dtype(t, name, R, "R", BACKWARD_NAME)
    if grad.shape != R.shape:
        raise ValueError(f"{BACKWARD_NAME}: grad must have R's shape {list(R.shape)}, got {list(grad.shape)}")
    try:
        ok = broadcast_shapes(M.shape, R.shape) == R.shape
    except RuntimeError:
        ok = False
    if not ok:
        raise ValueError(f"{BACKWARD_NAME}: M of shape {list(M.shape)} must broadcast to R's shape {list(R.shape)}")
    check_gradient_eps(gradient_eps, BACKWARD_NAME)
