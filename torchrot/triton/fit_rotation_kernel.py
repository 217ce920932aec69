"""The batched fitting kernels: the Triton twin of csrc/cpu/fit_rotation_kernel.h
(fit_batch, count_bad_warm_starts). One program fits a block of BLOCK
matrices, one per lane, in registers: load, begin_fit, the Cayley steps
(advance, or advance_one_step for max_iter = 1), finish, store. Unlike the
CPU kernel, which saves the lanes still running after a pass and regroups
them into full blocks, a block here steps until its last lane stops: the
step budget bounds that (fit_rotation_impl.advance), and a GPU's many blocks
hide the rare long one.

Each launcher takes (n, 3, 3) views (any strides) and the options; the
compute dtype's tolerances are constexpr arguments (fit_rotation_impl.tolerances),
so a kernel is compiled once per dtype pair, variant and mode.
"""
from __future__ import annotations

import torch
import triton
import triton.language as tl

from torchrot._constants import CONVERGED_CAP, MAX_ESCAPES, FitStatus, compute_dtype
from torchrot.triton.block_io import block_lanes, load_block, store_block, store_lanes
from torchrot.triton.fit_rotation_impl import advance, advance_one_step, begin_fit, constexprs_for, finish
from torchrot.triton.optimality import check_warm_start, used_as_is

__all__ = ["BLOCK", "STEP_CAP", "COMPILE_OPTIONS", "fit_batch", "count_bad_warm_starts", "fit_batch_kernel",
           "count_bad_warm_starts_kernel", "fit_batch_constexprs", "count_bad_warm_starts_constexprs",
           "triton_dtype"]

#: Matrices per program (lanes of a block): a power of two. Each lane holds
#: M's scaled copy, R and a step's temporaries in registers.
BLOCK = 128
#: A lane's step count is capped here where max_iter is larger (the C++
#: kernel's float counters stop at 2^24; the budget max_iter still applies).
STEP_CAP = 1 << 24

#: Triton compile options of every torchrot kernel: no contraction of a * b + c
#: into a fused multiply-add where the C++ kernel rounds twice (mul_add.py).
COMPILE_OPTIONS = {"enable_fp_fusion": False}

_STATUS_CAYLEY, _STATUS_FALLBACK, _STATUS_BAD_INIT, _STATUS_NON_FINITE = (
    int(FitStatus.CAYLEY), int(FitStatus.FALLBACK), int(FitStatus.BAD_INIT), int(FitStatus.NON_FINITE))


@triton.jit
def fit_batch_kernel(M_ptr, m_stride_n, m_stride_r, m_stride_c, init_ptr, i_stride_n, i_stride_r, i_stride_c,
                     out_ptr, o_stride_n, o_stride_r, o_stride_c, iterations_ptr, status_ptr, n, budget, cap,
                     BLOCK: tl.constexpr, COMPUTE: tl.constexpr, HAS_INIT: tl.constexpr,
                     INIT_KNOWN_CLEAN: tl.constexpr, ONE_STEP: tl.constexpr, CONVERGE: tl.constexpr,
                     VARIANT: tl.constexpr, WRITE_ITERATIONS: tl.constexpr, WRITE_STATUS: tl.constexpr,
                     EPS: tl.constexpr, TINY: tl.constexpr, LIFT: tl.constexpr, STEP_FLOOR: tl.constexpr,
                     UNDAMPED: tl.constexpr, ESTIMATE_SWITCH: tl.constexpr, MAX_CHECK_SLACK: tl.constexpr,
                     INIT_TOLERANCE2: tl.constexpr, INIT_CLEAN2: tl.constexpr, LARGE_STEP: tl.constexpr,
                     OBJECTIVE_STEPS: tl.constexpr, GERSHGORIN_STEPS: tl.constexpr,
                     MAX_ESCAPES: tl.constexpr, INIT_CLEAN_STEPS: tl.constexpr,
                     STEPS_WITHOUT_CLEAN_UP: tl.constexpr, STATUS_CAYLEY: tl.constexpr, STATUS_FALLBACK: tl.constexpr,
                     STATUS_BAD_INIT: tl.constexpr, STATUS_NON_FINITE: tl.constexpr):
    """fit_range for one block: R (and the iteration counts and status codes
    where asked) of matrices [pid * BLOCK, pid * BLOCK + BLOCK) of the batch.
    Both inputs are in registers before ``out`` is written: out may be M or
    init itself."""
    lane, mask = block_lanes(n, BLOCK)
    M = load_block(M_ptr, lane, mask, m_stride_n, m_stride_r, m_stride_c, COMPUTE)
    if HAS_INIT:
        I = load_block(init_ptr, lane, mask, i_stride_n, i_stride_r, i_stride_c, COMPUTE)
    else:
        I = M
    A, R, running, bad_init, non_finite, objective = begin_fit(
        M, I, HAS_INIT, INIT_KNOWN_CLEAN, TINY, LIFT, UNDAMPED, OBJECTIVE_STEPS, INIT_TOLERANCE2, INIT_CLEAN2,
        INIT_CLEAN_STEPS)
    if ONE_STEP:
        R, iterations, large_step = advance_one_step(A, R, running, objective, VARIANT, not HAS_INIT, STEP_FLOOR,
                                                     LARGE_STEP)
        fallback = running & False
    else:
        switched = running & False
        if not HAS_INIT:
            switched = switched | True  # Gershgorin's bound is for the large first steps the cold start replaces
        R, iterations, fallback, large_step, running = advance(
            A, R, running, switched, objective, budget, cap, VARIANT, CONVERGE, not HAS_INIT, EPS, UNDAMPED,
            STEP_FLOOR, LARGE_STEP, ESTIMATE_SWITCH, GERSHGORIN_STEPS, MAX_CHECK_SLACK, MAX_ESCAPES)
    R = finish(R, large_step, iterations, non_finite | bad_init, STEPS_WITHOUT_CLEAN_UP)
    store_block(out_ptr, lane, mask, o_stride_n, o_stride_r, o_stride_c, R)
    if WRITE_ITERATIONS:
        store_lanes(iterations_ptr, lane, mask, iterations)
    if WRITE_STATUS:
        status = tl.where(fallback, STATUS_FALLBACK, STATUS_CAYLEY)
        status = tl.where(bad_init, STATUS_BAD_INIT, status)
        status = tl.where(non_finite, STATUS_NON_FINITE, status)
        store_lanes(status_ptr, lane, mask, status)


@triton.jit
def count_bad_warm_starts_kernel(init_ptr, stride_n, stride_r, stride_c, counts_ptr, n, BLOCK: tl.constexpr,
                                 COMPUTE: tl.constexpr, INIT_TOLERANCE2: tl.constexpr, INIT_CLEAN2: tl.constexpr):
    """count_bad_warm_starts for one block: adds its warm starts that are not
    rotations to counts[0], and those the fit would not use as they are to
    counts[1]."""
    lane, mask = block_lanes(n, BLOCK)
    R0 = load_block(init_ptr, lane, mask, stride_n, stride_r, stride_c, COMPUTE)
    finite, bad, deviation2 = check_warm_start(R0, INIT_TOLERANCE2)
    unclean = ~used_as_is(finite, bad, deviation2, INIT_CLEAN2)
    tl.atomic_add(counts_ptr, tl.sum((bad & mask).to(tl.int64), 0))
    tl.atomic_add(counts_ptr + 1, tl.sum((unclean & mask).to(tl.int64), 0))


def triton_dtype(dtype: torch.dtype):
    """tl.float32 or tl.float64 for a compute dtype."""
    return tl.float64 if dtype == torch.float64 else tl.float32


def _grid(n: int):
    return (triton.cdiv(n, BLOCK),)


def fit_batch_constexprs(compute: torch.dtype, has_init: bool, max_iter: int | None, variant: str, *,
                         init_known_clean: bool = False, write_iterations: bool = False,
                         write_status: bool = False) -> dict:
    """fit_batch_kernel's constexpr arguments for a call: one compiled kernel each."""
    return dict(BLOCK=BLOCK, COMPUTE=triton_dtype(compute), HAS_INIT=has_init, INIT_KNOWN_CLEAN=init_known_clean,
                ONE_STEP=max_iter == 1, CONVERGE=max_iter is None, VARIANT=variant,
                WRITE_ITERATIONS=write_iterations, WRITE_STATUS=write_status, STATUS_CAYLEY=_STATUS_CAYLEY,
                STATUS_FALLBACK=_STATUS_FALLBACK, STATUS_BAD_INIT=_STATUS_BAD_INIT,
                STATUS_NON_FINITE=_STATUS_NON_FINITE, **constexprs_for(fit_batch_kernel, compute))


def count_bad_warm_starts_constexprs(compute: torch.dtype) -> dict:
    """count_bad_warm_starts_kernel's constexpr arguments."""
    return dict(BLOCK=BLOCK, COMPUTE=triton_dtype(compute), **constexprs_for(count_bad_warm_starts_kernel, compute))


def fit_batch(M: torch.Tensor, init: torch.Tensor | None, out: torch.Tensor, max_iter: int | None, variant: str, *,
              init_known_clean: bool = False, iterations: torch.Tensor | None = None,
              status: torch.Tensor | None = None) -> None:
    """Fits the (n, 3, 3) views M (and init, broadcast to M) into the (n, 3, 3)
    view ``out`` (which may be M or init itself, not overlap them otherwise),
    with the (n,) int32 ``iterations`` and uint8 ``status`` if given.
    Fallback lanes are left for the caller (status FALLBACK)."""
    n = M.shape[0]
    if n == 0:
        return
    converge = max_iter is None
    # Converged mode: at most CONVERGED_CAP steps per start or escape (Tolerances::converged_budget).
    budget = (MAX_ESCAPES + 1) * CONVERGED_CAP if converge else max_iter
    cap = CONVERGED_CAP if converge else min(max_iter, STEP_CAP)
    I = init if init is not None else M
    constexprs = fit_batch_constexprs(compute_dtype(M.dtype), init is not None, max_iter, variant,
                                      init_known_clean=init_known_clean, write_iterations=iterations is not None,
                                      write_status=status is not None)
    fit_batch_kernel[_grid(n)](
        M, *M.stride(), I, *I.stride(), out, *out.stride(),
        iterations if iterations is not None else out, status if status is not None else out, n, budget, cap,
        **constexprs, **COMPILE_OPTIONS)


def count_bad_warm_starts(init: torch.Tensor, compute: torch.dtype) -> tuple[int, int]:
    """(bad, unclean) among the (n, 3, 3) view ``init``'s warm starts, checked
    in ``compute`` (one pass, one read of the two counts by the host)."""
    n = init.shape[0]
    if n == 0:
        return 0, 0
    counts = torch.zeros(2, dtype=torch.int64, device=init.device)
    count_bad_warm_starts_kernel[_grid(n)](init, *init.stride(), counts, n, **count_bad_warm_starts_constexprs(compute),
                                           **COMPILE_OPTIONS)
    bad, unclean = counts.tolist()
    return bad, unclean
