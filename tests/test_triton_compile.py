"""Every Triton kernel of torchrot compiles, with Triton's own compiler, for
NVIDIA (Hopper, Ampere) and AMD (MI300) GPUs, down to machine code, on a
machine without a GPU (torchrot.triton.ahead_of_time); NVIDIA's assembly
divides and takes square roots correctly rounded, as the C++ kernel does
(the interpreter cannot show that: NumPy rounds correctly whatever the
kernel asks for). Compiled in a child process: this one runs the kernels
under Triton's interpreter (torchrot.testing.triton_kernel), and a process
holds them, and Triton's own library functions, either interpreted or
compiled."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from kernel_paths import TRITON_MARKS

pytestmark = list(TRITON_MARKS)

# Prints {specialization: [machine code?, approximate instructions]} for the target argv[1].
_COMPILE = """
import json, sys
from torchrot.triton.ahead_of_time import approximate_instructions, compile_for, specializations

found = {}
for specialization in specializations():
    compiled, _ = compile_for(specialization, sys.argv[1])
    binary = compiled.asm.get("cubin") or compiled.asm.get("hsaco")
    found[specialization.name] = [bool(binary), approximate_instructions(compiled)]
print(json.dumps(found))
"""


@pytest.mark.parametrize("target", ["sm90", "sm80", "gfx942"])
def test_compiles_correctly_rounded(target):
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    proc = subprocess.run([sys.executable, "-c", _COMPILE, target], env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    found = json.loads(proc.stdout)
    assert found
    assert {name: result for name, result in found.items() if result != [True, []]} == {}, (
        f"{target}: [machine code?, approximate instructions]")
