"""Thread-count independence at every CPU kernel (instruction set): 1, 2 and
3 threads give bit-identical R, iterations and status on a large batch split
at boundaries inside SIMD blocks, and the single-threaded result is the
"scalar" build's (for the kernels that round like it,
torchrot.testing.rounds_like_scalar).
"""
from __future__ import annotations

import functools

import pytest
import torch
from isa_helpers import (
    ALL_ISA_PARAMS,
    DTYPES,
    HARDWARE_ISA,
    _cpu_kernel,
    _describe,
    _info,
    _run_info,
    _same,
    _scatter_non_finite,
)

from torchrot.testing import dtype_id, make_warm_start, rounds_like_scalar

# ---------------------------------------------------------------------------
# 5. Thread-count independence
# ---------------------------------------------------------------------------

N_THREADED = 50_001  # odd: 2 or 3 threads split it at boundaries inside SIMD blocks


@functools.cache
def _large_batch(dtype):
    """(M, init): N_THREADED warm-start pairs from several distributions, with
    NaN/Inf matrices, shuffled."""
    names = ("warm", "gaussian", "rank1", "ill_conditioned", "rot180_exact", "det_negative")
    per = N_THREADED // len(names)
    Ms, inits = [], []
    for j, name in enumerate(names):
        M, init = make_warm_start(name, per, 100 + j, dtype)
        Ms.append(M)
        inits.append(init)
    rest = N_THREADED - per * len(names)
    M, init = make_warm_start("gaussian", rest, 200, dtype)
    Ms.append(M)
    inits.append(init)
    M, init = torch.cat(Ms), torch.cat(inits)
    gen = torch.Generator().manual_seed(300)
    idx = torch.randperm(N_THREADED, generator=gen)[:500]
    M[idx] = _scatter_non_finite(M[idx], gen)
    perm = torch.randperm(N_THREADED, generator=gen)
    return M[perm].contiguous(), init[perm].contiguous()


_THREAD_CASES = {  # name -> (warm start?, max_iter, variant)
    "cold-converged-conservative": (False, None, "conservative"),
    "warm-iter1-gershgorin": (True, 1, "gershgorin"),
    "warm-converged-newton": (True, None, "newton"),
}


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", [pytest.param(None, id="unset")] + ALL_ISA_PARAMS)
def test_thread_count_independence(isa, dtype, use_isa, restore_threads):
    """At the default kernel (variable unset: the hardware level) and at each
    kernel by name, 1, 2 and 3 threads give bit-identical R, iterations and
    status, in converged cold, one-step warm and converged warm mode; the
    single-threaded result also equals the scalar kernel's on these 50k
    matrices (for the kernels that round like it, rounds_like_scalar)."""
    M, init = _large_batch(dtype)
    expected_kernel = HARDWARE_ISA if isa is None else isa
    results = {}
    for threads in (1, 2, 3):
        torch.set_num_threads(threads)
        assert torch.get_num_threads() == threads
        for name, (warm, k, v) in _THREAD_CASES.items():
            with use_isa(isa):
                assert _cpu_kernel() == expected_kernel
                results[threads, name] = _info(M, init if warm else None, k, v)
    torch.set_num_threads(1)
    failures = []
    for name, (warm, k, v) in _THREAD_CASES.items():
        for threads in (2, 3):
            if not _same(results[threads, name], results[1, name]):
                failures.append(
                    f"{name}: {threads} threads vs 1:\n"
                    + _describe(results[threads, name], results[1, name], M, init if warm else None)
                )
        if not rounds_like_scalar(expected_kernel):
            continue  # test_two_rounding_kernel_meets_criteria
        ref = _run_info(use_isa, "scalar", M, init if warm else None, k, v)
        if not _same(results[1, name], ref):
            failures.append(f"{name}: 1 thread vs the scalar kernel:\n" + _describe(
                results[1, name], ref, M, init if warm else None))
    assert not failures, f"{expected_kernel} {dtype_id(dtype)}:\n" + "\n".join(failures)
    assert (results[1, "cold-converged-conservative"][2] == 3).any()
