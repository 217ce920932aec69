"""Shared by the tests of the run-time choice of the CPU kernel (instruction
set), tests/test_isa_*.py: the kernels this CPU runs and their parameter
lists, bitwise comparison of results with a precise failure message, running
fit_rotation_info on a named kernel (checking with
``torch.ops.torchrot.cpu_kernel()`` that it is the one that ran, so an ignored
request cannot make a test pass vacuously), and the test data.

Results are compared bit for bit (integer views of the floats): NaN payloads
and signed zeros count, as "bit-identical" promises.
"""
from __future__ import annotations

import functools
import math

import pytest
import torch

import torchrot
from torchrot._constants import CPU_KERNELS
from torchrot.testing import (
    DISTRIBUTIONS,
    bits,
    edge_case_matrices,
    make_matrices,
    make_warm_start,
    random_rotations,
    rounds_like_scalar,
)

DTYPES = (torch.float32, torch.float64)

ISAS = CPU_KERNELS  # lowest to highest
ISA_LEVEL = {name: level for level, name in enumerate(ISAS)}
SIMD_ISAS = ISAS[1:]


def _hardware_isa() -> str:
    """The level the dispatch caps requests at (ATen's, as dispatch.cpp maps it)."""
    cap = torch.backends.cpu.get_cpu_capability()
    return {"AVX512": "avx512", "AVX2": "avx2"}.get(cap, "default")


HARDWARE_ISA = _hardware_isa()


def _supported(isa: str) -> bool:
    return ISA_LEVEL[isa] <= ISA_LEVEL[HARDWARE_ISA]


# Only the kernels this CPU runs are parametrized: a request above the hardware
# is capped to a lower kernel (tested on its own in tests/test_isa_dispatch.py), so its cases would
# always skip here.
ALL_ISA_PARAMS = [pytest.param(i, id=i) for i in ISAS if _supported(i)]
SIMD_ISA_PARAMS = [pytest.param(i, id=i) for i in SIMD_ISAS if _supported(i)]
# The kernels of this CPU that round a * b + c twice (x86-64's default):
# checked against the accuracy criteria, not the scalar kernel's bits; the others
# are checked bit for bit.
TWO_ROUNDING_ISAS = [i for i in SIMD_ISAS if _supported(i) and not rounds_like_scalar(i)]
SCALAR_ROUNDING_ISA_PARAMS = [p for p in SIMD_ISA_PARAMS if rounds_like_scalar(p.values[0])]


def _cpu_kernel() -> str:
    return torch.ops.torchrot.cpu_kernel()


# ---------------------------------------------------------------------------
# Helpers: bitwise comparison with a precise failure message
# ---------------------------------------------------------------------------

def _bad_matrices(got, ref) -> torch.Tensor:
    """Bool (n,) mask of the matrices whose R, iterations or status differ."""
    R, R_ref = got[0], ref[0]
    n = R_ref.reshape(-1, 9).shape[0]
    bad = (bits(R).reshape(n, 9) != bits(R_ref).reshape(n, 9)).any(1)
    if len(got) > 1:
        bad |= got[1].reshape(n) != ref[1].reshape(n)
        bad |= got[2].reshape(n) != ref[2].reshape(n)
    return bad


def _same(got, ref) -> bool:
    """``got`` and ``ref`` (R, or (R, iterations, status)) are bit-identical."""
    got = got if isinstance(got, tuple) else (got,)
    ref = ref if isinstance(ref, tuple) else (ref,)
    if len(got) != len(ref):
        return False
    for a, b in zip(got, ref):
        if a.shape != b.shape or a.dtype != b.dtype or not torch.equal(bits(a), bits(b)):
            return False
    return True


def _describe(got, ref, M, init=None, limit=3) -> str:
    got = got if isinstance(got, tuple) else (got,)
    ref = ref if isinstance(ref, tuple) else (ref,)
    if any(a.shape != b.shape or a.dtype != b.dtype for a, b in zip(got, ref)):
        return f"shape/dtype differ: {[(a.shape, a.dtype) for a in got]} vs {[(b.shape, b.dtype) for b in ref]}"
    bad = _bad_matrices(got, ref).nonzero().flatten().tolist()
    lines = [f"{len(bad)} of {ref[0].reshape(-1, 9).shape[0]} matrices differ, first at {bad[:10]}"]
    M9 = M.reshape(-1, 9)
    for i in bad[:limit]:
        line = f"  [{i}] M={M9[i].tolist()}"
        if init is not None:
            line += f" init={init.reshape(-1, 9)[i].tolist()}"
        line += f"\n       R={got[0].reshape(-1, 9)[i].tolist()}\n   R_ref={ref[0].reshape(-1, 9)[i].tolist()}"
        gb, rb = bits(got[0]).reshape(-1, 9)[i], bits(ref[0]).reshape(-1, 9)[i]
        width = 2 * got[0].element_size()
        diffs = [f"{k}: {int(g) & (1 << 4 * width) - 1:0{width}x} vs {int(r) & (1 << 4 * width) - 1:0{width}x}"
                 for k, (g, r) in enumerate(zip(gb.tolist(), rb.tolist())) if g != r]
        if diffs:
            line += "\n       bits differ at entries " + ", ".join(diffs)
        if len(got) > 1:
            line += (
                f"\n       iterations={int(got[1].reshape(-1)[i])} (ref {int(ref[1].reshape(-1)[i])}),"
                f" status={int(got[2].reshape(-1)[i])} (ref {int(ref[2].reshape(-1)[i])})"
            )
        lines.append(line)
    return "\n".join(lines)


def _info(M, init, max_iter, variant):
    return tuple(torchrot.fit_rotation_info(M, init, max_iter=max_iter, variant=variant))


def _run_info(use_isa, isa, M, init, max_iter, variant):
    """fit_rotation_info under kernel ``isa``, checking that it is the one used."""
    with use_isa(isa):
        assert _cpu_kernel() == isa, f"cpu_kernel({isa!r}) selected kernel {_cpu_kernel()!r}"
        return _info(M, init, max_iter, variant)


# ---------------------------------------------------------------------------
# Test data: every distribution, the edge cases and NaN/Inf entries, both in
# homogeneous SIMD blocks (ordered) and mixed into the same blocks (shuffled)
# ---------------------------------------------------------------------------

REQUIRED_DISTRIBUTIONS = (
    "warm", "gaussian", "uniform", "rank1", "ill_conditioned", "symmetric", "det_negative", "rot180_exact",
)
assert set(REQUIRED_DISTRIBUTIONS) <= set(DISTRIBUTIONS)
PER_DISTRIBUTION = 19  # not a multiple of any width: blocks straddle distributions
N_NON_FINITE = 48


def _scatter_non_finite(A: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Copy of A (k, 3, 3) with NaN / +Inf / -Inf at one random entry of each
    matrix; every 8th matrix gets two entries, every 12th is all NaN."""
    A = A.clone()
    k = A.shape[0]
    flat = A.view(k, 9)
    vals = torch.tensor([math.nan, math.inf, -math.inf], dtype=A.dtype)
    rows = torch.arange(k)
    flat[rows, torch.randint(0, 9, (k,), generator=gen)] = vals[rows % 3]
    two = rows[rows % 8 == 5]
    flat[two, torch.randint(0, 9, (len(two),), generator=gen)] = vals[(two + 1) % 3]
    flat[rows[rows % 12 == 7]] = math.nan
    return A


@functools.cache
def mixed_batch(dtype: torch.dtype, warm: bool, seed: int = 0):
    """``(M, init)`` (init None when cold): all DISTRIBUTIONS, the edge cases
    and matrices with NaN/Inf entries (in M, and for warm also in init), once
    in order and once shuffled; contiguous, 662 (cold) or 686 (warm) matrices."""
    Ms, inits = [], []
    for j, name in enumerate(DISTRIBUTIONS):
        if warm:
            M, init = make_warm_start(name, PER_DISTRIBUTION, seed + 31 * j, dtype)
            inits.append(init)
        else:
            M = make_matrices(name, PER_DISTRIBUTION, seed + 31 * j, dtype)
        Ms.append(M)
    edge = edge_case_matrices(dtype)
    Ms.append(edge)
    if warm:
        # the edge cases as given (M = 0 returns init, ...) with random warm starts
        inits.append(random_rotations(len(edge), torch.Generator().manual_seed(seed + 5)).to(dtype))
    gen = torch.Generator().manual_seed(seed + 11)
    finite = make_matrices("gaussian", N_NON_FINITE, seed + 13, dtype)
    Ms.append(_scatter_non_finite(finite, gen))
    if warm:
        inits.append(random_rotations(N_NON_FINITE, torch.Generator().manual_seed(seed + 17)).to(dtype))
        # and finite M with a non-finite warm start
        M_bad_init, bad_init = make_warm_start("warm", N_NON_FINITE // 4, seed + 23, dtype)
        Ms.append(M_bad_init)
        inits.append(_scatter_non_finite(bad_init, gen))
    M = torch.cat(Ms)
    init = torch.cat(inits) if warm else None
    perm = torch.randperm(M.shape[0], generator=torch.Generator().manual_seed(seed + 19))
    M = torch.cat([M, M[perm]]).contiguous()
    if warm:
        init = torch.cat([init, init[perm]]).contiguous()
    return M, init


# The pool of tests/test_isa_layouts.py and tests/test_isa_out_aliasing.py.
@functools.cache
def _tail_pool(dtype):
    """70 (M, init) pairs mixing distributions, edge cases and NaN/Inf, from
    the shuffled half of the warm mixed batch."""
    M, init = mixed_batch(dtype, True)
    half = M.shape[0] // 2
    pool_M, pool_init = M[half:half + 70].clone(), init[half:half + 70].clone()
    assert (~torch.isfinite(pool_M)).any() and pool_M.shape[0] == 70
    return pool_M, pool_init
