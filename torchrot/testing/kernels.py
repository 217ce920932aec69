"""Which kernel runs: the CPU kernel objects (forced per thread) and the
device-generic kernels run on CPU tensors, so that the same tests check
every path on any machine."""
from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator

import torch

from torchrot._constants import CPU_KERNELS
from torchrot.testing.triton_interpreter import (
    fma_rounded_once,
    triton_interpreter,
    triton_interpreter_unavailable,
)

__all__ = ['CPU_KERNELS', 'rounds_like_scalar', 'rounding_reference', 'cpu_kernel', 'available_cpu_kernels',
           'generic_kernel', 'triton_kernel', 'triton_interpreter_unavailable']


def rounds_like_scalar(name: str) -> bool:
    """Whether CPU kernel ``name`` (capped at this CPU, as :func:`cpu_kernel`
    caps it) gives the scalar kernel's results bit for bit: it rounds
    ``a * b + c`` once, as the scalar kernel does. False only for x86-64's
    "default" kernel, the one for CPUs without AVX2 and FMA
    (csrc/kernel/mul_add.h); it meets the same accuracy criteria and is
    bit-identical across its own batch sizes, layouts and threads.

    Raises:
        ValueError: ``name`` is not one of CPU_KERNELS.

    Examples:
        >>> from torchrot.testing import rounds_like_scalar
        >>> rounds_like_scalar("scalar")
        True
    """
    with cpu_kernel(name):
        return bool(torch.ops.torchrot._cpu_kernel_fuses_multiply_add())

def rounding_reference(name: str) -> str:
    """The kernel whose results CPU kernel ``name`` reproduces bit for bit:
    "scalar", or ``name`` itself where it rounds differently
    (:func:`rounds_like_scalar`).

    Raises:
        ValueError: ``name`` is not one of CPU_KERNELS.

    Examples:
        >>> from torchrot.testing import rounding_reference
        >>> rounding_reference("scalar")
        'scalar'
    """
    return "scalar" if rounds_like_scalar(name) else name

@contextlib.contextmanager
def cpu_kernel(name: str | None) -> Iterator[str]:
    """``with cpu_kernel("scalar") as used: ...`` runs the calling thread's
    torchrot calls on the CPU kernel object ``name`` (one of CPU_KERNELS,
    case-insensitive), capped at what this CPU supports; ``None`` runs the
    process-wide choice. ``used`` is the kernel that runs
    (``torch.ops.torchrot.cpu_kernel()``). Other threads keep theirs: the
    choice is per thread, so this is safe in multi-threaded tests. Nests.

    The process-wide choice is the environment variable
    TORCHROT_CPU_CAPABILITY, read once when torchrot is imported.

    Raises:
        ValueError: ``name`` is not one of CPU_KERNELS.

    Examples:
        >>> from torchrot.testing import cpu_kernel
        >>> M = torch.randn(8, 3, 3)
        >>> with cpu_kernel("scalar") as used:
        ...     R_scalar = torchrot.fit_rotation(M)
        >>> used, torch.allclose(R_scalar, torchrot.fit_rotation(M), atol=1e-5)
        ('scalar', True)
    """
    previous = torch.ops.torchrot._set_cpu_kernel(name or "")
    try:
        yield torch.ops.torchrot.cpu_kernel()
    finally:
        torch.ops.torchrot._set_cpu_kernel(previous)

def available_cpu_kernels() -> tuple[str, ...]:
    """The CPU kernel objects of CPU_KERNELS that this machine runs: those its
    build has (scalar and default everywhere, AVX2 and AVX-512 on x86-64) up
    to the highest its CPU supports, lowest first (a tuple of str).

    Examples:
        >>> from torchrot.testing import CPU_KERNELS, available_cpu_kernels
        >>> kernels = available_cpu_kernels()
        >>> kernels[0], set(kernels) <= set(CPU_KERNELS)
        ('scalar', True)
    """
    found = []
    for name in CPU_KERNELS:
        with cpu_kernel(name) as used:
            if used == name:
                found.append(name)
    return tuple(found)

@contextlib.contextmanager
def _cpu_kernels_shadowed_by(kernels: dict) -> Iterator[None]:
    """Registers ``kernels`` (operator name -> Python kernel) as the CPU
    kernels of torch.ops.torchrot.* while it lasts; leaving restores the C++ ones."""
    library = torch.library.Library("torchrot", "IMPL")
    try:
        with warnings.catch_warnings():
            # "Overriding a previously registered kernel": that is the point.
            warnings.filterwarnings(
                "ignore", message=".*(Overriding a previously registered kernel|operators may also be overridden)")
            for name, kernel in kernels.items():
                library.impl(name, kernel, "CPU")
        yield
    finally:
        library._destroy()


@contextlib.contextmanager
def generic_kernel() -> Iterator[None]:
    """``with generic_kernel(): ...`` runs ``torch.ops.torchrot.*`` on CPU
    tensors with the device-generic kernels (pure PyTorch, what MPS tensors
    run, and CUDA and XPU tensors where Triton is missing) instead of the C++
    ones, so that the same tests check both paths on any machine.
    Process-wide while it lasts (it registers CPU kernels that shadow the C++
    ones; leaving restores them): not for multi-threaded use.

    Examples:
        >>> from torchrot.testing import generic_kernel
        >>> M = torch.randn(8, 3, 3, dtype=torch.float64)
        >>> with generic_kernel():
        ...     R_generic = torchrot.fit_rotation(M)
        >>> torch.allclose(R_generic, torchrot.fit_rotation(M))
        True
    """
    from torchrot._device_kernels import GENERIC_KERNELS

    with _cpu_kernels_shadowed_by(GENERIC_KERNELS):
        yield


@contextlib.contextmanager
def triton_kernel() -> Iterator[None]:
    """``with triton_kernel(): ...`` runs ``torch.ops.torchrot.*`` on CPU
    tensors with torchrot's Triton kernels (what CUDA and XPU tensors run)
    under Triton's interpreter, instead of the C++ ones, so that the same
    tests check the accelerator kernels on any machine with Triton
    installed. The interpreter runs each block with NumPy: slow, for small
    batches; where it would round ``tl.fma`` twice (Triton 3.6), the C
    library's fma rounds it once, as a GPU does. Process-wide while it lasts,
    like :func:`generic_kernel`; it imports the Triton kernels interpreted,
    so a process that uses it cannot also run them compiled on a GPU
    (:func:`triton_interpreter_unavailable`).

    Raises:
        RuntimeError: :func:`triton_interpreter_unavailable` gives a reason.

    Examples:
        >>> from torchrot.testing import triton_kernel, triton_interpreter_unavailable
        >>> M = torch.randn(8, 3, 3, dtype=torch.float64)
        >>> if triton_interpreter_unavailable() is None:
        ...     with triton_kernel():
        ...         R_triton = torchrot.fit_rotation(M)
        ...     assert torch.equal(R_triton, torchrot.fit_rotation(M))
    """
    reason = triton_interpreter_unavailable()
    if reason is not None:
        raise RuntimeError(f"torchrot.testing.triton_kernel: {reason}")
    import numpy as np

    # np.errstate: the interpreter computes with NumPy, which warns where the
    # kernels divide by zero or meet NaN (as they do, silently, on a GPU).
    with triton_interpreter(), np.errstate(all="ignore"), fma_rounded_once():
        from torchrot.triton.operators import TRITON_KERNELS

        with _cpu_kernels_shadowed_by(TRITON_KERNELS):
            yield
