"""Run-time choice of the CPU kernel (instruction set): the kernel is forced
per thread with ``torchrot.testing.cpu_kernel(name)`` (scalar | default |
avx2 | avx512), capped at the hardware level; the process default is
TORCHROT_CPU_CAPABILITY, read once at import (tested in subprocesses). A bad
name raises, in a request and in the variable.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch
from isa_helpers import ALL_ISA_PARAMS, HARDWARE_ISA, ISA_LEVEL, ISAS, _cpu_kernel, _supported

import torchrot
from torchrot.testing import make_matrices

ENV = "TORCHROT_CPU_CAPABILITY"


# ---------------------------------------------------------------------------
# 1. the kernel follows the request (per thread) and TORCHROT_CPU_CAPABILITY
#    (at import), capped at the hardware
# ---------------------------------------------------------------------------


def test_unset_selects_hardware_level(use_isa):
    with use_isa(None):
        assert _cpu_kernel() == HARDWARE_ISA
    with use_isa(""):  # empty counts as unset
        assert _cpu_kernel() == HARDWARE_ISA


@pytest.mark.parametrize("isa", ALL_ISA_PARAMS)
def test_cpu_kernel_follows_request(isa, use_isa):
    for spelling in (isa, isa.upper(), isa.capitalize()):  # case-insensitive
        with use_isa(spelling) as used:
            assert _cpu_kernel() == used == isa, f"cpu_kernel({spelling!r})"
    # switching back and forth takes effect at once, and requests nest
    for other in ISAS:
        if not _supported(other):
            continue
        with use_isa(other):
            assert _cpu_kernel() == other
            with use_isa(isa):
                assert _cpu_kernel() == isa
            assert _cpu_kernel() == other
    assert _cpu_kernel() == HARDWARE_ISA


def test_request_above_hardware_is_capped(use_isa):
    above = [isa for isa in ISAS if not _supported(isa)]
    if not above:
        pytest.skip(f"this CPU supports every kernel ({HARDWARE_ISA}); see the ATEN_CPU_CAPABILITY test")
    M = make_matrices("gaussian", 37, 0)
    for isa in above:
        with use_isa(isa):
            assert _cpu_kernel() == HARDWARE_ISA, f"cpu_kernel({isa!r})"
            # and it computes (no illegal instruction)
            assert torch.isfinite(torchrot.fit_rotation(M)).all()


def test_request_is_per_thread(use_isa):
    """A kernel forced in one thread does not change another thread's."""
    import threading

    seen = {}
    entered, release = threading.Event(), threading.Event()

    def other():
        with use_isa("scalar"):
            seen["inside"] = _cpu_kernel()
            entered.set()
            release.wait(30)

    thread = threading.Thread(target=other)
    thread.start()
    assert entered.wait(30)
    seen["main"] = _cpu_kernel()
    release.set()
    thread.join()
    assert seen == {"inside": "scalar", "main": HARDWARE_ISA}


_ENV_SCRIPT = r"""
import json, os, torch, torchrot
first = torch.ops.torchrot.cpu_kernel()
os.environ["TORCHROT_CPU_CAPABILITY"] = "sse2"  # read once, at import: no effect now
print(json.dumps([first, torch.ops.torchrot.cpu_kernel()]))
"""


def _run_with_env(script: str, **env_vars) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != ENV}
    env.update(env_vars)
    return subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)


@pytest.mark.slow
@pytest.mark.parametrize("isa", ["scalar", "default", "AVX2", "avx512", ""])
def test_environment_variable_is_read_once_at_import(isa):
    proc = _run_with_env(_ENV_SCRIPT, **{ENV: isa})
    assert proc.returncode == 0, proc.stderr[-3000:]
    expected = ISAS[min(ISA_LEVEL[isa.lower()], ISA_LEVEL[HARDWARE_ISA])] if isa else HARDWARE_ISA
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == [expected, expected]


_CAP_SCRIPT = r"""
import json, torch, torchrot
from torchrot.testing import cpu_kernel, rounding_reference
out = {"aten": torch.backends.cpu.get_cpu_capability(), "kernels": {}, "same_as_reference": {}}
M = torch.randn(53, 3, 3, generator=torch.Generator().manual_seed(3))
for req in ("scalar", "default", "avx2", "avx512", "AVX512"):
    with cpu_kernel(req) as used:
        out["kernels"][req] = used
        got = torchrot.fit_rotation_info(M)
    with cpu_kernel(rounding_reference(req)):
        ref = torchrot.fit_rotation_info(M)
    out["same_as_reference"][req] = all(torch.equal(a, b) for a, b in zip(got, ref))
out["kernels"]["<unset>"] = torch.ops.torchrot.cpu_kernel()
print(json.dumps(out))
"""


@pytest.mark.slow
@pytest.mark.parametrize("aten_level", ["default", "avx2"])
def test_request_above_lowered_hardware_level_is_capped(aten_level):
    """With ATen's level lowered by ATEN_CPU_CAPABILITY (read once at start-up,
    hence a subprocess), every request above it is capped to it."""
    if not _supported(aten_level):
        pytest.skip(f"CPU supports up to {HARDWARE_ISA}")
    proc = _run_with_env(_CAP_SCRIPT, ATEN_CPU_CAPABILITY=aten_level)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["aten"] == aten_level.upper()
    expected = {
        req: ISAS[min(ISA_LEVEL[req.lower()], ISA_LEVEL[aten_level])]
        for req in ("scalar", "default", "avx2", "avx512", "AVX512")
    }
    expected["<unset>"] = aten_level
    assert result["kernels"] == expected
    assert all(result["same_as_reference"].values()), result["same_as_reference"]


@pytest.mark.parametrize("value", ["sse4", "avx-512", "avx512 ", " avx2", "AVX2x", "none", "1", "neon"])
def test_invalid_request_raises(value, use_isa):
    """A bad name raises ValueError naming it, and changes nothing."""
    with pytest.raises(ValueError, match=r"scalar, default, avx2, avx512; got") as excinfo:
        with use_isa(value):
            pass
    assert f"'{value}'" in str(excinfo.value)
    assert _cpu_kernel() == HARDWARE_ISA


@pytest.mark.slow
@pytest.mark.parametrize("value", ["sse4", "avx-512", "neon"])
def test_invalid_environment_variable_fails_the_import(value):
    proc = _run_with_env("import torchrot", **{ENV: value})
    assert proc.returncode != 0
    assert f"ValueError: {ENV} must be one of scalar, default, avx2, avx512; got '{value}'" in proc.stderr
