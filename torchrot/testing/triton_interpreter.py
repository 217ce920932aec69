"""Triton's interpreter as torchrot's tests use it (torchrot.testing.triton_kernel):
turning it on where Triton reads the switch, telling whether a process can
still use it, and a once-rounded ``tl.fma`` where the installed Triton's
interpreter rounds it twice (Triton 3.6; 3.9 rounds once), so that the
interpreted kernels round as a GPU does. Triton's private interpreter
classes (``InterpretedFunction``, ``InterpreterBuilder``, ``TensorHandle``,
``interpreter_builder``) are used here and nowhere else;
tests/test_triton_operators.py checks them on the installed Triton."""
from __future__ import annotations

import contextlib
import functools
import importlib.util
import os
import sys
from collections.abc import Iterator

__all__ = ["triton_interpreter_unavailable", "triton_interpreter", "fma_rounds_once", "fma_rounded_once"]

_TRITON_MODULE = "torchrot.triton.mul_add"  # imported by every Triton kernel of torchrot


def triton_interpreter_unavailable() -> str | None:
    """Why :func:`triton_kernel` cannot run in this process (a str), or None:
    Triton is not installed, or torchrot's Triton kernels, or Triton itself,
    were already imported compiled (for a GPU) in this process.

    Examples:
        >>> from torchrot.testing import triton_interpreter_unavailable
        >>> isinstance(triton_interpreter_unavailable(), (str, type(None)))
        True
    """
    if importlib.util.find_spec("triton") is None:
        return "Triton is not installed (pip install triton; no wheel for this platform)"
    language, module = sys.modules.get("triton.language"), sys.modules.get(_TRITON_MODULE)
    if language is not None or module is not None:
        from triton.runtime.interpreter import InterpretedFunction

        if module is not None and not isinstance(module.mul_add, InterpretedFunction):
            return ("torchrot's Triton kernels were imported compiled in this process; run the interpreter "
                    "in another process, or with TRITON_INTERPRET=1 set before they are imported")
        # Triton's own library functions (tl.max, tl.zeros, ...) are interpreted or compiled as Triton is
        # first imported (importing torch._dynamo imports it).
        if language is not None and not isinstance(language.max, InterpretedFunction):
            return ("Triton was imported without its interpreter in this process (torch.compile's modules "
                    "import it); run the interpreter in another process, or with TRITON_INTERPRET=1 set "
                    "before Triton is imported")
    return None


@contextlib.contextmanager
def triton_interpreter() -> Iterator[None]:
    """TRITON_INTERPRET=1 while it lasts (Triton reads it where a
    @triton.jit function is decorated: torchrot's kernels, and Triton's own
    library functions where Triton is first imported); the previous value
    afterwards."""
    previous = os.environ.get("TRITON_INTERPRET")
    os.environ["TRITON_INTERPRET"] = "1"
    try:
        yield
    finally:
        if previous is None:
            del os.environ["TRITON_INTERPRET"]
        else:
            os.environ["TRITON_INTERPRET"] = previous


def fma_rounds_once(builder) -> bool:
    """Whether Triton's interpreter rounds ``tl.fma`` once, as a GPU does.
    Older releases (3.6) compute ``a * b + c`` with NumPy, two roundings
    (fixed by triton-lang/triton#11424 and #11611); each probe is exact
    only where it is rounded once."""
    import numpy as np
    import triton.language as tl
    from triton.runtime.interpreter import TensorHandle

    for dtype, a, c, fused in ((tl.float32, 1 + 2.0**-12, -(1 + 2.0**-11), 2.0**-24),
                               (tl.float32, 4097.0, 2.0**-30, 16785410.0),  # no float64 intermediate either
                               (tl.float64, 1 + 2.0**-27, -(1 + 2.0**-26), 2.0**-54)):
        np_dtype = np.float32 if dtype == tl.float32 else np.float64
        a, c = TensorHandle(np.array([a], np_dtype), dtype), TensorHandle(np.array([c], np_dtype), dtype)
        if builder.create_fma(a, a, c).data[0] != fused:
            return False
    return True


@functools.cache
def _c_fma() -> dict:
    """NumPy dtype -> the C library's ``fma``/``fmaf`` (rounded once) as a
    NumPy ufunc, element by element (Triton runs on Linux only: glibc)."""
    import ctypes

    import numpy as np

    libm = ctypes.CDLL("libm.so.6")
    found = {}
    for name, dtype, c_type in (("fma", np.float64, ctypes.c_double), ("fmaf", np.float32, ctypes.c_float)):
        function = getattr(libm, name)
        function.restype, function.argtypes = c_type, [c_type] * 3
        found[np.dtype(dtype)] = np.frompyfunc(function, 3, 1)
    return found


@contextlib.contextmanager
def fma_rounded_once() -> Iterator[None]:
    """While it lasts, Triton's interpreter computes ``tl.fma`` in float32
    and float64 with the C library's fma (:func:`_c_fma`), where it would
    round twice (:func:`fma_rounds_once`): slower, as a GPU rounds."""
    import numpy as np
    from triton.runtime.interpreter import InterpreterBuilder, TensorHandle, interpreter_builder

    if fma_rounds_once(interpreter_builder):
        yield
        return
    fused = _c_fma()
    two_roundings = InterpreterBuilder.create_fma

    def create_fma(self, x, y, z):
        function = fused.get(z.data.dtype)
        if function is None:
            return two_roundings(self, x, y, z)
        result = function(*np.broadcast_arrays(x.data, y.data, z.data))
        return TensorHandle(np.asarray(result, dtype=z.data.dtype), z.dtype.scalar)

    InterpreterBuilder.create_fma = create_fma
    try:
        yield
    finally:
        InterpreterBuilder.create_fma = two_roundings
