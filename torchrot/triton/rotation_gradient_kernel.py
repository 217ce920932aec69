"""The batched derivative kernel: the Triton twin of
csrc/cpu/rotation_gradient_kernel.h: out[i] = R[i] [u_i]x, the damped
solution of the optimality condition's linearisation
(torchrot.triton.rotation_gradient) for X[i] = dL/dR (the backward) or dM
(forward mode), a block of BLOCK matrices per program."""
from __future__ import annotations

import torch
import triton
import triton.language as tl

from torchrot._constants import compute_dtype
from torchrot.triton.block_io import block_lanes, load_block, store_block
from torchrot.triton.fit_rotation_impl import constexprs_for
from torchrot.triton.fit_rotation_kernel import BLOCK, COMPILE_OPTIONS, triton_dtype
from torchrot.triton.rotation_gradient import rotation_tangent

__all__ = ["tangent_batch", "tangent_batch_kernel", "tangent_batch_constexprs"]


@triton.jit
def tangent_batch_kernel(X_ptr, x_stride_n, x_stride_r, x_stride_c, R_ptr, r_stride_n, r_stride_r, r_stride_c,
                         M_ptr, m_stride_n, m_stride_r, m_stride_c, out_ptr, o_stride_n, o_stride_r, o_stride_c,
                         damping_ptr, n, BLOCK: tl.constexpr, COMPUTE: tl.constexpr, TINY: tl.constexpr,
                         LIFT: tl.constexpr, HUGE: tl.constexpr, HALF_RANGE: tl.constexpr):
    """tangent_range for one block. All inputs are in registers before
    ``out`` is written: out may alias X."""
    lane, mask = block_lanes(n, BLOCK)
    X = load_block(X_ptr, lane, mask, x_stride_n, x_stride_r, x_stride_c, COMPUTE)
    R = load_block(R_ptr, lane, mask, r_stride_n, r_stride_r, r_stride_c, COMPUTE)
    M = load_block(M_ptr, lane, mask, m_stride_n, m_stride_r, m_stride_c, COMPUTE)
    damping = tl.load(damping_ptr)
    T = rotation_tangent(X, R, M, damping, TINY, LIFT, HUGE, HALF_RANGE)
    store_block(out_ptr, lane, mask, o_stride_n, o_stride_r, o_stride_c, T)


def tangent_batch(X: torch.Tensor, R: torch.Tensor, M: torch.Tensor, out: torch.Tensor, damping: float) -> None:
    """out = the rotational tangent for the (n, 3, 3) views X, R, M (R's dtype
    decides the compute dtype; ``damping`` is rounded to it, as the C++
    kernel's argument is)."""
    n = R.shape[0]
    if n == 0:
        return
    compute = compute_dtype(R.dtype)
    damping_value = torch.full((1,), damping, dtype=compute, device=R.device)
    tangent_batch_kernel[(triton.cdiv(n, BLOCK),)](
        X, *X.stride(), R, *R.stride(), M, *M.stride(), out, *out.stride(), damping_value, n,
        **tangent_batch_constexprs(compute), **COMPILE_OPTIONS)


def tangent_batch_constexprs(compute: torch.dtype) -> dict:
    """tangent_batch_kernel's constexpr arguments."""
    return dict(BLOCK=BLOCK, COMPUTE=triton_dtype(compute), **constexprs_for(tangent_batch_kernel, compute))
