"""Every Triton kernel of torchrot compiles, with Triton's own compiler, for
NVIDIA (Hopper, Ampere) and AMD (MI300) GPUs, down to machine code, on a
machine without a GPU (torchrot.triton.ahead_of_time); NVIDIA's assembly
divides and takes square roots correctly rounded, as the C++ kernel does
(the interpreter cannot show that: NumPy rounds correctly whatever the
kernel asks for)."""
from __future__ import annotations

import pytest
from kernel_paths import TRITON_MARKS

pytestmark = list(TRITON_MARKS)


def _specializations():
    from torchrot.testing import triton_interpreter_unavailable

    if triton_interpreter_unavailable() is not None and "not installed" in triton_interpreter_unavailable():
        return []
    from torchrot.triton.ahead_of_time import specializations

    return specializations()


SPECIALIZATIONS = _specializations()


@pytest.mark.parametrize("target", ["sm90", "sm80", "gfx942"])
@pytest.mark.parametrize("specialization", SPECIALIZATIONS, ids=[s.name for s in SPECIALIZATIONS])
def test_compiles_correctly_rounded(specialization, target):
    from torchrot.triton.ahead_of_time import approximate_instructions, compile_for

    compiled, _ = compile_for(specialization, target)
    binary = compiled.asm.get("cubin") or compiled.asm.get("hsaco")
    assert binary, f"no machine code for {target}"
    assert approximate_instructions(compiled) == []
