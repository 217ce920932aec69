"""a * b + c rounded once: the Triton twin of csrc/kernel/mul_add.h.

Triton lowers ``tl.fma`` to the hardware's fused multiply-add (CUDA's
``fma.rn``, Triton's interpreter to a correctly rounded fma), which is what
the scalar CPU kernel's ``std::fma`` computes, so every ``mul_add`` of the
C++ kernel rounds alike here. The kernels are compiled with
``enable_fp_fusion=False`` (torchrot.triton.launch), so that no other
product and sum is fused behind the code's back.
"""
from __future__ import annotations

import triton
import triton.language as tl

__all__ = ["mul_add"]


@triton.jit
def mul_add(a, b, c):
    return tl.fma(a, b, c)
