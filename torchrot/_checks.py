"""Argument checks shared by the Python-side kernels (fake and pure PyTorch).

They mirror the checks of the C++ CPU operator (csrc/ops.cpp), so every device
and every tracing mode rejects the same arguments with the same message.
"""
from __future__ import annotations

import torch

OP_NAME = "torchrot.fit_rotation"
VARIANTS = ("newton", "conservative", "gershgorin")
SUPPORTED_DTYPES = (torch.float32, torch.float64, torch.float16, torch.bfloat16)


def check_matrix_arg(t: torch.Tensor, name: str, op: str = OP_NAME) -> None:
    """``t`` is a float32/float64/float16/bfloat16 tensor of shape (..., 3, 3);
    errors name the function ``op`` and the argument ``name``."""
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{op}: {name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() < 2 or t.shape[-1] != 3 or t.shape[-2] != 3:
        raise ValueError(f"{op}: {name} must have shape (..., 3, 3), got {list(t.shape)}")
    if t.dtype not in SUPPORTED_DTYPES:
        raise TypeError(
            f"{op}: {name} must be float32, float64, float16 or bfloat16, got {t.dtype}"
        )


# Largest step count accepted (csrc/ops.cpp kMaxIter): more steps never help,
# and on flat problems a lane steps until its cap (huge values hung).
MAX_ITER = 1000


def check_options(max_iter, variant) -> None:
    if max_iter is not None:
        if isinstance(max_iter, bool) or not isinstance(max_iter, int):
            raise TypeError(f"{OP_NAME}: max_iter must be None or an int >= 1, got {max_iter!r}")
        if not 1 <= max_iter <= MAX_ITER:
            raise ValueError(
                f"{OP_NAME}: max_iter must be None (iterate to convergence) or >= 1 and <= {MAX_ITER}, got {max_iter}"
            )
    if variant not in VARIANTS:
        raise ValueError(
            f"{OP_NAME}: variant must be one of 'newton', 'conservative', 'gershgorin', got {variant!r}"
        )


def check_device_dtype(t: torch.Tensor, name: str, ref: torch.Tensor, ref_name: str, op: str = OP_NAME) -> None:
    """t must be on ref's device and have ref's dtype."""
    if t.device != ref.device:
        raise ValueError(f"{op}: {name} must be on {ref_name}'s device ({ref.device}), got {t.device}")
    if t.dtype != ref.dtype:
        raise TypeError(f"{op}: {name} must have {ref_name}'s dtype ({ref.dtype}), got {t.dtype}")


def check_init(M: torch.Tensor, init: torch.Tensor | None) -> None:
    check_matrix_arg(M, "M")
    if init is None:
        return
    check_matrix_arg(init, "init")
    check_device_dtype(init, "init", M, "M")
    batch, init_batch = M.shape[:-2], init.shape[:-2]
    try:
        ok = len(init_batch) <= len(batch) and torch.broadcast_shapes(init_batch, batch) == batch
    except RuntimeError:
        ok = False
    if not ok:
        raise ValueError(
            f"{OP_NAME}: init of shape {list(init.shape)} must broadcast to M's shape {list(M.shape)}"
        )


def check_out(M: torch.Tensor, out: torch.Tensor) -> None:
    if not isinstance(out, torch.Tensor):
        raise TypeError(f"{OP_NAME}: out must be a torch.Tensor, got {type(out).__name__}")
    check_device_dtype(out, "out", M, "M")
    if out.shape != M.shape:
        raise ValueError(f"{OP_NAME}: out must have M's shape {list(M.shape)}, got {list(out.shape)}")


def check_all(M, init, max_iter, variant) -> None:
    check_init(M, init)
    check_options(max_iter, variant)


BACKWARD_NAME = "torchrot.fit_rotation_backward"


def check_backward(grad: torch.Tensor, R: torch.Tensor, M: torch.Tensor, gradient_eps) -> None:
    """Mirrors the checks of the C++ fit_rotation_backward (csrc/ops.cpp)."""
    for name, t in (("R", R), ("grad", grad), ("M", M)):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{BACKWARD_NAME}: {name} must be a torch.Tensor, got {type(t).__name__}")
        if t.dim() < 2 or t.shape[-1] != 3 or t.shape[-2] != 3:
            raise ValueError(f"{BACKWARD_NAME}: {name} must have shape (..., 3, 3), got {list(t.shape)}")
    if R.dtype not in SUPPORTED_DTYPES:
        raise TypeError(f"{BACKWARD_NAME}: R must be float32, float64, float16 or bfloat16, got {R.dtype}")
    for name, t in (("grad", grad), ("M", M)):
        check_device_dtype(t, name, R, "R", BACKWARD_NAME)
    if grad.shape != R.shape:
        raise ValueError(f"{BACKWARD_NAME}: grad must have R's shape {list(R.shape)}, got {list(grad.shape)}")
    try:
        ok = torch.broadcast_shapes(M.shape, R.shape) == R.shape
    except RuntimeError:
        ok = False
    if not ok:
        raise ValueError(f"{BACKWARD_NAME}: M of shape {list(M.shape)} must broadcast to R's shape {list(R.shape)}")
    check_gradient_eps(gradient_eps, BACKWARD_NAME)


# Largest damping accepted (csrc/ops.cpp kMaxGradientEps): beyond it the
# derivative is ~0 anyway, and the kernel's eps^4 terms would overflow float.
MAX_GRADIENT_EPS = 1e3


def check_gradient_eps(gradient_eps, name: str = OP_NAME) -> None:
    if isinstance(gradient_eps, bool) or not isinstance(gradient_eps, (int, float)):
        raise TypeError(f"{name}: gradient_eps must be a float >= 0, got {gradient_eps!r}")
    if not (0 <= gradient_eps <= MAX_GRADIENT_EPS):
        raise ValueError(
            f"{name}: gradient_eps must be a finite number >= 0 and <= {MAX_GRADIENT_EPS:g}, got {gradient_eps!r}"
        )
