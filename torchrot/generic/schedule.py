"""The schedule of the device-generic kernel: which lanes take which steps
on which tensors, and the compaction of the stragglers. No counterpart in
csrc/kernel/: the CPU kernel saves its unfinished lanes and regroups them
into full blocks between passes (csrc/cpu/fit_rotation_kernel.h); this is
its batched-tensor equivalent.

Converged mode: the whole batch takes up to ``full_steps(dtype, cold)``
masked Cayley steps (most matrices converge within them), saddle escapes
deferred; the matrices still running, pending an escape or needing the
fallback are then compacted and take the rest of the kernel's step budget
(escapes included) and the Horn fallback there; results are scattered back.
Eagerly the compaction is exact (a host read). Compiled, there is no
data-dependent shape: the buffer has the static size
``straggler_capacity(n)`` (cumsum + scatter), and lanes that do not fit take
the rest on the whole batch, masked. Each lane executes the kernel's state
machine, so results do not depend on the tiering.

The tunables (FULL_STEPS, COLD_FULL_STEPS, FULL_STEPS_MAX_ITER,
STRAGGLER_DIVISOR, STRAGGLER_MIN) are read from this module at each call:
patch them here (torchrot.generic.schedule), not on the package.
"""
from __future__ import annotations

import torch

from torchrot._constants import CONVERGED_CAP, MAX_ESCAPES
from torchrot.generic.control_flow import _INT, _LANE_KEYS, _any, _compiling, _repeat
from torchrot.generic.fit_rotation_impl import _cleaned_up, _step, advance, finish
from torchrot.generic.lanes import select

__all__ = [
    "FULL_STEPS",
    "COLD_FULL_STEPS",
    "FULL_STEPS_MAX_ITER",
    "STRAGGLER_DIVISOR",
    "STRAGGLER_MIN",
    "full_steps",
    "straggler_capacity",
    "fit_soa",
    "_compact_indices",
    "_gather",
    "_scatter_back",
    "_masked_lanes",
]

#: Masked Cayley steps every matrix of the batch takes before the stragglers
#: are compacted (converged mode), by compute dtype, from a warm start (see
#: full_steps); with max_iter=k <= FULL_STEPS_MAX_ITER all k steps run on the
#: whole batch. The Newton steps converge quadratically, so float64 needs one
#: more. From testing.make_warm_start (N = 1e5), float32: 7.1% of "warm"
#: lanes take 3 steps, none more; 1.6% of rot60's take 4; float64 rot60:
#: 0.004% take 5. Each whole-batch step costs the whole batch; a straggler
#: step only the buffer.
FULL_STEPS = {torch.float32: 4, torch.float64: 5}
#: The same from the cold start, both dtypes: its first step is exact (c is the
#: maximal objective) and the second confirms, so uniform and Gaussian lanes
#: take 2 steps (N = 1e5: 34 float32 uniform lanes and 15 Gaussian take 3 or
#: 4, no float64 lane more than 2); the few others finish in the buffer.
#: Against 4 whole-batch steps, float32 converged fits ran faster, eagerly and
#: compiled, and float64 (no third steps) as fast (benchmarks/lab_notes.md).
COLD_FULL_STEPS = 2
FULL_STEPS_MAX_ITER = 8
#: Compiled, the straggler buffer holds 1/STRAGGLER_DIVISOR of the batch (at
#: least STRAGGLER_MIN lanes, at most the batch); more stragglers than that
#: take the rest of their steps on the whole batch.
STRAGGLER_DIVISOR = 8
STRAGGLER_MIN = 1024


def full_steps(dtype: torch.dtype, cold: bool) -> int:
    """Whole-batch steps before compaction for compute dtype ``dtype``, from
    the cold start (``cold``) or a warm one."""
    return COLD_FULL_STEPS if cold else FULL_STEPS[dtype]


def straggler_capacity(n: int) -> int:
    """Lanes of the compiled straggler buffer for a batch of n (integer
    arithmetic, so that a symbolic n of a dynamic-shape graph stays symbolic)."""
    return min(n, max(STRAGGLER_MIN, -(-n // STRAGGLER_DIVISOR)))


def _compact_indices(sel, capacity):
    """Indices (capacity,) of the first `capacity` set lanes of `sel`, padded
    with n (no host sync), the valid mask, and the lanes that did not fit."""
    n = sel.shape[0]
    pos = torch.cumsum(sel.to(torch.int64), 0) - 1
    take = sel & (pos < capacity)
    dest = torch.where(take, pos, capacity)
    idx = torch.full((capacity + 1,), n, dtype=torch.int64, device=sel.device)
    idx = idx.scatter(0, dest, torch.arange(n, device=sel.device))[:capacity]
    return idx, idx < n, sel & ~take


def _gather(x, idx, n):
    return x.index_select(0, idx.clamp(max=n - 1))


def _scatter_back(x, sub, idx, valid):
    n = x.shape[0]
    dest = torch.where(valid, idx, n)
    full = torch.cat([x, x[:1]])
    return full.scatter(0, dest, sub)[:n]


def _masked_lanes(st, mask):
    """``st`` restricted to the lanes of ``mask`` (the others neither run nor fall back)."""
    return dict(st, running=st["running"] & mask, fallback=st["fallback"] & mask, pending=st["pending"] & mask)


def fit_soa(A, R, running, variant, max_iter, eps, objective=None):
    """Runs advance + finish on SoA state; returns (R list, iterations, fallback).
    ``objective``: the first step's estimate c (cold starts: the maximal objective).

    Schedule: every lane takes up to full_steps(dtype, cold) steps on the whole batch
    (saddle escapes deferred); the lanes still running, falling back or
    pending an escape are then compacted into a buffer of
    straggler_capacity(n) lanes that takes the rest of the step budget and
    the fallback; lanes that did not fit (more stragglers than the buffer
    holds: rare) take it on the whole batch, masked. Each lane executes the
    kernel's state machine, so results do not depend on the tiering."""
    n = running.shape[0]
    converge = max_iter is None
    cap = CONVERGED_CAP if converge else max_iter
    budget = CONVERGED_CAP * (MAX_ESCAPES + 1) if converge else max_iter
    zeros_b = torch.zeros_like(running)
    zeros_i = torch.zeros(running.shape, dtype=_INT, device=running.device)
    # After an exact first step (cold starts) the Gershgorin variant goes on with the conservative estimate.
    cold = objective is not None
    st = {"A": A, "R": R, "running": running, "fallback": zeros_b,
          "switched": ~zeros_b if cold else zeros_b,
          "iterations": zeros_i, "attempt": zeros_i, "escapes": zeros_i, "pending": zeros_b, "large": zeros_b}
    full = budget if (not converge and max_iter <= FULL_STEPS_MAX_ITER) else min(full_steps(A[0].dtype, cold), budget)
    # A lane pending an escape after step k <= full needs at most
    # MAX_ESCAPES * CONVERGED_CAP more steps (<= budget - full).
    if cold:  # every lane's first step (full >= 1)
        st = _step(st, variant, converge, cap, eps, objective)
    # Compiled, steps unrolled after the exact first step fuse with it and
    # made the fit slower, the more so the more steps (benchmarks/lab_notes.md),
    # so there they stay a while_loop.
    st = _repeat(lambda s: _step(s, variant, converge, cap, eps), st, full - 1 if cold else full,
                 unroll=not cold)
    rest = budget - full
    capacity = straggler_capacity(n) if n > 0 else 0
    R = _cleaned_up(st)
    if capacity == 0 or (rest == 0 and not converge):
        return R, st["iterations"], st["fallback"]
    sel = st["running"] | st["fallback"] | st["pending"]
    if not _compiling():
        # Eager: host reads are allowed, so the stragglers are compacted exactly.
        if not _any(sel):
            return R, st["iterations"], st["fallback"]
        if sel.device.type != "meta":
            idx = sel.nonzero().squeeze(1)
            sub = {"A": [a[idx] for a in st["A"]], "R": [r[idx] for r in st["R"]],
                   **{k: st[k][idx] for k in _LANE_KEYS}}
            sub = advance(sub, rest, variant, converge, cap, eps)
            R_sub = finish(sub, converge)
            put = lambda x, y: x.index_put((idx,), y)
            return ([put(r, rs) for r, rs in zip(R, R_sub)], put(st["iterations"], sub["iterations"]),
                    put(st["fallback"], sub["fallback"]))
    idx, valid, overflow = _compact_indices(sel, capacity)
    sub = {"A": [_gather(a, idx, n) for a in st["A"]], "R": [_gather(r, idx, n) for r in st["R"]]}
    for k in _LANE_KEYS:
        sub[k] = _gather(st[k], idx, n)
    sub = advance(_masked_lanes(sub, valid), rest, variant, converge, cap, eps)
    R_sub = finish(sub, converge)
    R = [_scatter_back(r, rs, idx, valid) for r, rs in zip(R, R_sub)]
    iterations = _scatter_back(st["iterations"], sub["iterations"], idx, valid)
    fallback = _scatter_back(st["fallback"], sub["fallback"], idx, valid)
    if _compiling() or _any(overflow):
        # The lanes that did not fit, on the whole batch, masked (eager:
        # only when there are such lanes; compiled: its loop stops at once).
        ov = advance(_masked_lanes(st, overflow), rest, variant, converge, cap, eps)
        R_ov = finish(ov, converge)
        R = select(overflow, R_ov, R)
        iterations = torch.where(overflow, ov["iterations"], iterations)
        fallback = torch.where(overflow, ov["fallback"], fallback)
    return R, iterations, fallback
