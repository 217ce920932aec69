"""The operators' kernels on Triton devices: the Triton twin of
csrc/ops/fit_rotation_cpu.cpp. The same checks (torchrot._checks, in the C++
operator's order), then the batched Triton kernels on (n, 3, 3) views of
the tensors, the results laid out as the CPU kernel lays them out.

What a call reads back on the host (a device synchronisation): the warm-start
counts of ``fit_rotation_out`` with ``init`` (validated before ``out`` is
written, so that a call that raises leaves it as it was), and in converged
mode or with a warm start, two counts of the status codes (the lanes that need
the Horn fallback, which is solved outside the kernel by the pure-PyTorch
path, and the warm starts that are not rotations, which make the call raise).
The one-step update of ``fit_rotation_out`` reads back only its validation,
and a cold fit with ``max_iter`` nothing.
"""
from __future__ import annotations

import contextlib
import math

import torch

from torchrot._checks import bad_init_error, check_all, check_backward, check_gradient_eps, check_out
from torchrot._constants import DEFAULT_VARIANT, GRADIENT_EPS, FitStatus, compute_dtype
from torchrot._layout import empty_result
from torchrot.generic.driver import _components
from torchrot.generic.horn_fallback import horn_rotation
from torchrot.generic.lanes import max_abs_entry
from torchrot.generic.unit_scale import unit_scale
from torchrot.triton.fit_rotation_kernel import count_bad_warm_starts, fit_batch
from torchrot.triton.rotation_gradient_kernel import tangent_batch

__all__ = ["TRITON_KERNELS"]


def _batch_view(t: torch.Tensor, shape: torch.Size) -> torch.Tensor:
    """``t`` broadcast to ``shape`` (..., 3, 3) as an (n, 3, 3) tensor: a view
    where its batch flattens to one stride, a copy otherwise (inputs only)."""
    return t.expand(shape).reshape(-1, 3, 3)


def _writable_view(t: torch.Tensor) -> torch.Tensor | None:
    """``t`` as an (n, 3, 3) view that writes through to it, or None."""
    try:
        return t.view(-1, 3, 3)
    except RuntimeError:
        return None


def _memory_range(t: torch.Tensor) -> tuple[int, int]:
    low = high = t.data_ptr()
    for size, stride in zip(t.shape, t.stride()):
        reach = (size - 1) * stride * t.element_size()
        low, high = min(low, low + reach), max(high, high + reach)
    return low, high + t.element_size()


def _overlaps_other_than_identity(out: torch.Tensor, t: torch.Tensor | None) -> bool:
    """Whether writing ``out`` could change ``t`` before it is read
    (csrc/ops/overlap.h): any shared memory but the exact identity (the same
    elements in the same layout, which the kernels allow: a block's inputs
    are in registers before its result is stored). Conservative: memory
    ranges, not elements."""
    if t is None or t.numel() == 0 or out.numel() == 0:
        return False
    if (out.data_ptr() == t.data_ptr() and out.dtype == t.dtype and out.shape == t.shape
            and out.stride() == t.stride()):
        return False
    (low, high), (t_low, t_high) = _memory_range(out), _memory_range(t)
    return low < t_high and t_low < high


def _on(device: torch.device):
    """The context that makes ``device`` current, where Triton launches its
    kernels (an accelerator's device guard; nothing for CPU tensors, which
    only Triton's interpreter runs)."""
    module = getattr(torch, device.type, None)
    if device.type == "cpu" or module is None or not hasattr(module, "device"):
        return contextlib.nullcontext()
    return module.device(device)


def _check_warm_starts(init: torch.Tensor, compute: torch.dtype) -> bool:
    """Raises (ValueError) if a warm start of ``init``, in its own shape, is
    not a rotation; returns whether every one is clean (init_known_clean)."""
    bad, unclean = count_bad_warm_starts(init.reshape(-1, 3, 3), compute)
    if bad:
        raise bad_init_error(bad, init.numel() // 9)
    return unclean == 0


def solve_fallback_lanes(M: torch.Tensor, out: torch.Tensor, lanes: torch.Tensor) -> None:
    """The fallback lanes of ``out`` (n, 3, 3), solved exactly: Horn's method
    on M scaled as the kernel scales it (torchrot.generic.horn_fallback)."""
    k = lanes.numel()
    M_lanes = _components(M[lanes].to(compute_dtype(M.dtype)), k)
    A = unit_scale(M_lanes, max_abs_entry(M_lanes))[0]
    out[lanes] = torch.stack(horn_rotation(A), -1).reshape(k, 3, 3).to(out.dtype)


def _run_fit(M, init, out, max_iter, variant, callers_out, iterations=None, status=None):
    """run_fit on M's device (see _fit)."""
    with _on(M.device):
        _fit(M, init, out, max_iter, variant, callers_out, iterations, status)


def _fit(M, init, out, max_iter, variant, callers_out, iterations=None, status=None):
    """run_fit: fits M (broadcasting init to it) into ``out`` of M's shape; a
    caller's ``out`` is written only once the call can no longer fail."""
    n = M.numel() // 9
    if n == 0:
        return
    compute = compute_dtype(M.dtype)
    init_known_clean = False
    if init is not None and callers_out:
        init_known_clean = _check_warm_starts(init, compute)
    m_view = _batch_view(M, M.shape)
    init_view = _batch_view(init, M.shape) if init is not None else None
    # Reduced precision is computed into a float32 buffer, which torch rounds
    # to out's dtype (as the C++ operator does).
    through_temporary = compute != out.dtype or (callers_out and (_overlaps_other_than_identity(out, M)
                                                                  or _overlaps_other_than_identity(out, init)))
    out_view = None if through_temporary else _writable_view(out)
    temporary = out_view is None
    if temporary:
        out_view = torch.empty((n, 3, 3), dtype=compute, device=out.device)
    converge = max_iter is None
    check_inits = init is not None and not callers_out
    if status is None and (converge or check_inits):
        status = torch.empty(n, dtype=torch.uint8, device=M.device)
    fit_batch(m_view, init_view, out_view, max_iter, variant, init_known_clean=init_known_clean,
              iterations=iterations, status=status)
    if status is not None and (converge or check_inits):
        fallback = status == int(FitStatus.FALLBACK)
        fallbacks, bad = torch.stack([fallback.sum(), (status == int(FitStatus.BAD_INIT)).sum()]).tolist()
        if bad:  # only a fresh out has been written; the error counts init in its own shape
            _check_warm_starts(init, compute)
            raise bad_init_error(bad, n)  # not reached: the same check found them
        if fallbacks:
            solve_fallback_lanes(m_view, out_view, fallback.nonzero().squeeze(1))
    if temporary:
        out.copy_(out_view.view(out.shape))


def _fit_rotation(M, init=None, max_iter=None, variant=DEFAULT_VARIANT, gradient_eps=GRADIENT_EPS):
    check_all(M, init, max_iter, variant)  # in the C++ operator's order
    check_gradient_eps(gradient_eps)
    out = empty_result(M)
    _run_fit(M, init, out, max_iter, variant, callers_out=False)
    return out


def _fit_rotation_out(M, init, max_iter, variant, out):
    check_all(M, init, max_iter, variant)
    check_out(M, out)
    _run_fit(M, init, out, max_iter, variant, callers_out=True)


def _fit_rotation_info(M, init=None, max_iter=None, variant=DEFAULT_VARIANT):
    check_all(M, init, max_iter, variant)
    out = empty_result(M)
    batch = M.shape[:-2]
    iterations = torch.empty(batch, dtype=torch.int32, device=M.device)
    status = torch.empty(batch, dtype=torch.uint8, device=M.device)
    _run_fit(M, init, out, max_iter, variant, callers_out=False, iterations=iterations.view(-1),
             status=status.view(-1))
    return out, iterations, status


def _fit_rotation_backward(grad, R, M, gradient_eps=GRADIENT_EPS):
    """dL/dM for dL/dR = grad at R = fit_rotation(M); with grad = dM, the
    forward-mode dR (the map is self-adjoint: csrc/kernel/rotation_gradient.h)."""
    check_backward(grad, R, M, gradient_eps)
    out = empty_result(R)
    if math.prod(R.shape[:-2]) == 0:
        return out
    compute = compute_dtype(R.dtype)
    out_view = _writable_view(out) if compute == R.dtype else None
    target = out_view if out_view is not None else torch.empty(R.shape, dtype=compute, device=R.device).view(-1, 3, 3)
    with _on(R.device):
        tangent_batch(_batch_view(grad, R.shape), _batch_view(R, R.shape), _batch_view(M, R.shape), target,
                      gradient_eps)
    if out_view is None:
        out.copy_(target.view(R.shape))
    return out


#: operator name -> its Triton kernel (torchrot._device_kernels registers
#: them; torchrot.testing.triton_kernel runs them on CPU tensors).
TRITON_KERNELS = {
    "fit_rotation": _fit_rotation,
    "fit_rotation_out": _fit_rotation_out,
    "fit_rotation_backward": _fit_rotation_backward,
    "fit_rotation_info": _fit_rotation_info,
}
