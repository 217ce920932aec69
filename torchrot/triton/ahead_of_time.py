"""torchrot's Triton kernels compiled for a GPU that this machine need not
have: Triton's own compiler (``triton.compile``) for a named target, down to
the device's machine code (cubin for NVIDIA, hsaco for AMD). The tests check
with it that every kernel compiles for NVIDIA and AMD GPUs, and for NVIDIA
with correctly rounded divisions and square roots; the device benchmark reports how long
the compilations of a first call take.

Each entry of :func:`specializations` is one kernel as the operators launch
it (one compilation on a device's first call with those arguments).
"""
from __future__ import annotations

import time
from typing import NamedTuple

import torch

__all__ = ["TARGETS", "Specialization", "specializations", "compile_for", "approximate_instructions"]

#: name -> (backend, architecture, warp size) of triton.backends.compiler.GPUTarget:
#: NVIDIA Hopper (H100, H200) and Ampere (A100), AMD CDNA 3 (MI300).
TARGETS = {"sm90": ("cuda", 90, 32), "sm80": ("cuda", 80, 32), "gfx942": ("hip", "gfx942", 64)}

# PTX instructions that round worse than IEEE arithmetic (AMD's assembly
# builds correctly rounded division from v_rcp_f32 and corrections: names tell nothing there).
_APPROXIMATE = ("div.full", "div.approx", "sqrt.approx", "rcp.approx", "rsqrt.approx", "ex2.approx", "lg2.approx")


class Specialization(NamedTuple):
    name: str          # e.g. "fit float32 converged warm"
    kernel: object     # the triton.jit function
    constexprs: dict   # its constexpr arguments
    pointers: dict     # pointer argument -> the dtype it points to


def specializations() -> list[Specialization]:
    """The kernels a program meets: the fit in each mode (converged cold and
    warm with diagnostics, max_iter = 3, the one-step update cold and warm)
    in both dtypes, the warm-start check and the derivative."""
    from torchrot.triton.fit_rotation_kernel import (
        count_bad_warm_starts_constexprs,
        count_bad_warm_starts_kernel,
        fit_batch_constexprs,
        fit_batch_kernel,
    )
    from torchrot.triton.rotation_gradient_kernel import tangent_batch_constexprs, tangent_batch_kernel

    found = []
    for dtype in (torch.float32, torch.float64):
        name = str(dtype).removeprefix("torch.")
        matrices = {"M_ptr": dtype, "init_ptr": dtype, "out_ptr": dtype, "iterations_ptr": torch.int32,
                    "status_ptr": torch.uint8}
        for mode, has_init, max_iter, info in (("converged cold", False, None, True),
                                               ("converged warm", True, None, True),
                                               ("max_iter=3 warm", True, 3, False),
                                               ("one step cold", False, 1, False),
                                               ("one step warm", True, 1, False)):
            constexprs = fit_batch_constexprs(dtype, has_init, max_iter, "conservative", write_iterations=info,
                                              write_status=info or max_iter is None)
            found.append(Specialization(f"fit {name} {mode}", fit_batch_kernel, constexprs, matrices))
        found.append(Specialization(f"warm-start check {name}", count_bad_warm_starts_kernel,
                                    count_bad_warm_starts_constexprs(dtype),
                                    {"init_ptr": dtype, "counts_ptr": torch.int64}))
        found.append(Specialization(f"derivative {name}", tangent_batch_kernel, tangent_batch_constexprs(dtype),
                                    {"X_ptr": dtype, "R_ptr": dtype, "M_ptr": dtype, "out_ptr": dtype,
                                     "damping_ptr": dtype}))
    return found


_POINTEE = {torch.float32: "*fp32", torch.float64: "*fp64", torch.int32: "*i32", torch.int64: "*i64",
            torch.uint8: "*u8"}


def compile_for(specialization: Specialization, target: str = "sm90"):
    """(compiled kernel, seconds): ``specialization`` compiled by Triton for
    TARGETS[target] with the operators' compile options; integers as int64."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from torchrot.triton.fit_rotation_kernel import COMPILE_OPTIONS

    kernel = specialization.kernel
    signature = {}
    for name in kernel.arg_names:
        if name in specialization.constexprs:
            signature[name] = "constexpr"
        elif name in specialization.pointers:
            signature[name] = _POINTEE[specialization.pointers[name]]
        else:
            signature[name] = "i64"
    source = ASTSource(fn=kernel, signature=signature, constexprs=dict(specialization.constexprs))
    start = time.perf_counter()
    compiled = triton.compile(source, target=GPUTarget(*TARGETS[target]), options=dict(COMPILE_OPTIONS))
    return compiled, time.perf_counter() - start


def approximate_instructions(compiled) -> list[str]:
    """The approximating instructions in a kernel compiled for NVIDIA (its
    PTX): none where every division and root is correctly rounded."""
    assembly = compiled.asm.get("ptx", "")
    return sorted({op for op in _APPROXIMATE if op in assembly})
