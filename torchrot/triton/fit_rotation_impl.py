"""Algorithm 1 as a per-lane state machine, for a block of BLOCK matrices
(one per lane): the Triton twin of csrc/kernel/fit_rotation_impl.h
(Tolerances, begin_fit, can_take, take_step, advance, advance_one_step,
finish), with the same operations on each lane, so that each lane's result,
iteration count and status do not depend on its block.

The lane state is spelled out as values rather than a struct: ``A`` (M
scaled to max |entry| 1) and ``R`` (9-tuples), ``iterations``,
``attempt_steps`` and ``escapes`` (int32 counts) and the masks ``switched``,
``running``, ``fallback``, ``large_step`` (LaneState's fields; ``bad_init``
and ``non_finite`` only begin_fit and finish read).

One difference from the C++ kernel: finish() leaves the lanes that need the
Horn/Jacobi fallback (converged mode, rare) as they are, and the driver
(torchrot.triton.fit_rotation_kernel) solves them outside the kernel.
"""
from __future__ import annotations

import functools

import numpy as np
import torch
import triton
import triton.language as tl

from torchrot._constants import (
    ESTIMATE_SWITCH,
    GERSHGORIN_STEPS,
    INIT_CLEAN_EPS,
    INIT_CLEAN_STEPS,
    INIT_TOLERANCE,
    LARGE_STEP,
    MAX_CHECK_SLACK_EPS,
    MAX_ESCAPES,
    OBJECTIVE_LAGUERRE_STEPS,
    STEPS_WITHOUT_CLEAN_UP,
    UNDAMPED,
)
from torchrot.triton.cayley import (
    cayley_increment,
    cayley_step,
    objective_estimate,
    rotate_by,
    singular,
    smaller_than,
    trace,
)
from torchrot.triton.cold_start import best_start_rotation
from torchrot.triton.lanes import any, constant, is_finite, max_abs_entry, select
from torchrot.triton.mat3 import gram, reorthonormalize, times, transpose_times
from torchrot.triton.maximal_objective import maximal_objective
from torchrot.triton.optimality import check_warm_start, clean_warm_start, is_maximum
from torchrot.triton.saddle_escape import saddle_escape_rotation
from torchrot.triton.unit_scale import unit_scale

__all__ = ["tolerances", "constexprs_for", "begin_fit", "can_take", "take_step", "advance", "advance_one_step",
           "finish"]


@functools.cache
def tolerances(compute: torch.dtype) -> dict:
    """Tolerances<T> for compute dtype ``compute`` (float32 or float64), as
    the kernels' constexpr arguments: each threshold computed in that dtype
    as the C++ kernel computes it (e.g. kInitTolerance squared in float), so
    that every comparison is the same. From torchrot._constants (csrc/limits.h)
    and torch.finfo; computed once per dtype (every launch reads it): do not
    modify the returned dict."""
    T = np.float32 if compute == torch.float32 else np.float64
    finfo = torch.finfo(compute)
    eps, tiny = T(finfo.eps), T(finfo.tiny)
    name = str(compute).removeprefix("torch.")
    init_tolerance, init_clean = T(INIT_TOLERANCE), T(INIT_CLEAN_EPS) * eps
    values = {
        "EPS": eps,                                        # converged: s < eps
        "TINY": tiny,                                      # the smallest normal number
        "LIFT": T(np.ldexp(1.0, np.finfo(T).nmant + 1)),   # 2^digits (unit_scale.h)
        "STEP_FLOOR": tiny / (eps * eps),                  # can_take's floor of d^2 + w.w
        "UNDAMPED": T(UNDAMPED[name]),                     # sqrt(eps)
        "ESTIMATE_SWITCH": T(ESTIMATE_SWITCH),
        "MAX_CHECK_SLACK": T(MAX_CHECK_SLACK_EPS) * eps,
        "INIT_TOLERANCE2": init_tolerance * init_tolerance,
        "INIT_CLEAN2": init_clean * init_clean,
        "LARGE_STEP": T(LARGE_STEP),
        "HUGE": T(finfo.max),                              # the largest finite number
        "HALF_RANGE": T(np.ldexp(1.0, np.finfo(T).maxexp // 2)),  # 2^(max_exponent / 2) (rotation_gradient.h)
    }
    constants = {key: float(value) for key, value in values.items()}
    constants.update(OBJECTIVE_STEPS=OBJECTIVE_LAGUERRE_STEPS, GERSHGORIN_STEPS=GERSHGORIN_STEPS,
                     MAX_ESCAPES=MAX_ESCAPES, INIT_CLEAN_STEPS=INIT_CLEAN_STEPS,
                     STEPS_WITHOUT_CLEAN_UP=STEPS_WITHOUT_CLEAN_UP)
    return constants


def constexprs_for(kernel, compute: torch.dtype) -> dict:
    """The tolerances (see :func:`tolerances`) that ``kernel`` takes, by name."""
    return {key: value for key, value in tolerances(compute).items() if key in kernel.arg_names}


@triton.jit
def begin_fit(M, I, HAS_INIT: tl.constexpr, INIT_KNOWN_CLEAN: tl.constexpr, TINY: tl.constexpr,
              LIFT: tl.constexpr, UNDAMPED: tl.constexpr, OBJECTIVE_STEPS: tl.constexpr,
              INIT_TOLERANCE2: tl.constexpr, INIT_CLEAN2: tl.constexpr, INIT_CLEAN_STEPS: tl.constexpr):
    """Normalises M and picks the start: the warm start I (HAS_INIT; cleaned
    up to the compute precision unless INIT_KNOWN_CLEAN) or the cold start.
    Returns (A, R, running, bad_init, non_finite, objective): lanes whose M
    or I are unusable, and M = 0, do not run; ``objective`` is the cold
    start's maximal objective (the first step's estimate c; unused warm)."""
    max_abs = max_abs_entry(M)  # NaN if any entry is NaN
    finite = is_finite(max_abs)
    zero = max_abs == 0.0
    A, lift, inv = unit_scale(M, max_abs, TINY, LIFT)
    bad_init = zero & False
    if HAS_INIT:
        if INIT_KNOWN_CLEAN:
            R = I
        else:
            init_finite, bad_init, deviation2 = check_warm_start(I, INIT_TOLERANCE2)
            finite = finite & init_finite
            R = clean_warm_start(I, init_finite, bad_init, deviation2, INIT_CLEAN2, INIT_CLEAN_STEPS)
        objective = max_abs
    else:
        # The first step from the cube start takes c = lambda itself (Horn's eigenproblem).
        R, start_objective = best_start_rotation(A)
        objective = maximal_objective(A, start_objective, UNDAMPED, OBJECTIVE_STEPS)
    running = finite & ~zero & ~bad_init
    return A, R, running, bad_init, ~finite, objective


@triton.jit
def can_take(step, STEP_FLOOR: tl.constexpr):
    """Whether a lane can take ``step``: H not singular, the step finite, and
    d^2 + w.w above STEP_FLOOR (T_min / eps^2; see fit_rotation_impl.h)."""
    norm2 = step[5] + step[4]
    return (step[5] > 0.0) & is_finite(norm2) & (norm2 > STEP_FLOOR)


@triton.jit
def take_step(R, running, iterations, attempt_steps, large_step, step, valid, LARGE_STEP: tl.constexpr):
    """Applies ``step`` to the running lanes that can take it, counts it and
    notes a large one. Returns (R, iterations, attempt_steps, large_step,
    stepping)."""
    stepping = running & valid
    R = select(stepping, rotate_by(R, cayley_increment(step)), R)
    large_step = large_step | (stepping & ~smaller_than(step, LARGE_STEP))
    taken = stepping.to(tl.int32)
    return R, iterations + taken, attempt_steps + taken, large_step, stepping


@triton.jit
def advance(A, R, running, switched, objective, budget, cap, VARIANT: tl.constexpr, CONVERGE: tl.constexpr,
            COLD: tl.constexpr, EPS: tl.constexpr, UNDAMPED: tl.constexpr, STEP_FLOOR: tl.constexpr,
            LARGE_STEP: tl.constexpr, ESTIMATE_SWITCH: tl.constexpr, GERSHGORIN_STEPS: tl.constexpr,
            MAX_CHECK_SLACK: tl.constexpr, MAX_ESCAPES: tl.constexpr):
    """Up to ``budget`` Cayley steps on the running lanes (each stops at its
    own convergence, at ``cap`` steps per start or escape, or stalls), the
    first with c = ``objective`` where COLD. Converged mode (CONVERGE): the
    maximum check of each converged lane, saddle escapes, and the lanes for
    the fallback. Returns (R, iterations, fallback, large_step, running)."""
    iterations = tl.zeros(running.shape, tl.int32)
    attempt_steps = tl.zeros(running.shape, tl.int32)
    escapes = tl.zeros(running.shape, tl.int32)
    fallback = running & False
    large_step = running & False
    b = 0
    while (b < budget) & any(running):
        S = transpose_times(R, A)
        t = trace(S)
        c = objective_estimate(S, VARIANT)
        if CONVERGE and VARIANT == "gershgorin":
            c = tl.where(switched, objective_estimate(S, "conservative"), c)
        if COLD:
            c = tl.where(b == 0, objective, c)
        step = cayley_step(S, c)
        valid = can_take(step, STEP_FLOOR)
        stalled = running & ~valid
        R, iterations, attempt_steps, large_step, stepping = take_step(R, running, iterations, attempt_steps,
                                                                       large_step, step, valid, LARGE_STEP)
        # An undamped step below eps: converged.
        undamped = ~(c - t > UNDAMPED * tl.abs(t))
        finished = stepping & undamped & smaller_than(step, EPS)
        if CONVERGE:
            if VARIANT == "gershgorin":  # the only variant that reads `switched`
                switch_now = smaller_than(step, ESTIMATE_SWITCH) | ~(attempt_steps < GERSHGORIN_STEPS)
                switched = switched | (stepping & switch_now)
            if any(finished):
                # Unless the step is small only because H is singular: stalled.
                singular_lanes = finished & singular(step, EPS)
                stalled = stalled | singular_lanes
                finished = finished & ~singular_lanes
                # The maximum, or a saddle? Saddles are escaped by a half-turn and iterate again.
                at_maximum = finished & is_maximum(S, MAX_CHECK_SLACK)
                saddle = finished & ~at_maximum
                escape = saddle & (escapes < MAX_ESCAPES)
                fallback = fallback | (saddle & ~escape)
                if any(escape):
                    R = select(escape, times(R, saddle_escape_rotation(transpose_times(R, A))), R)
                    large_step = large_step | escape
                    escapes = escapes + escape.to(tl.int32)
                    attempt_steps = tl.where(escape, 0, attempt_steps)
                    switched = switched & ~escape
                    finished = finished & ~escape
            # Not converged within the cap, or stalled: the fallback decides.
            exhausted = stepping & ~finished & ~(attempt_steps < cap)
            fallback = fallback | exhausted | stalled
            finished = finished | exhausted | stalled
        else:
            finished = finished | stalled | ~(attempt_steps < cap)
        running = running & ~finished
        b += 1
    return R, iterations, fallback, large_step, running


@triton.jit
def advance_one_step(A, R, running, objective, VARIANT: tl.constexpr, COLD: tl.constexpr,
                     STEP_FLOOR: tl.constexpr, LARGE_STEP: tl.constexpr):
    """advance(budget 1) for max_iter = 1 (the paper's one-step update): the
    same operations on the running lanes, without the bookkeeping of the
    convergence decision. Returns (R, iterations, large_step)."""
    S = transpose_times(R, A)
    if COLD:
        c = objective
    else:
        c = objective_estimate(S, VARIANT)
    step = cayley_step(S, c)
    zeros = tl.zeros(running.shape, tl.int32)
    R, iterations, _, large_step, _ = take_step(R, running, zeros, zeros, running & False, step,
                                                can_take(step, STEP_FLOOR), LARGE_STEP)
    return R, iterations, large_step


@triton.jit
def finish(R, large_step, iterations, nan_lanes, STEPS_WITHOUT_CLEAN_UP: tl.constexpr):
    """The result of every lane: one Newton-Schulz step where a step was
    large or a saddle was escaped, or after more than STEPS_WITHOUT_CLEAN_UP
    steps (fit_rotation_impl.h's finish explains why the others need none);
    NaN on ``nan_lanes`` (M or init not finite, or a bad warm start).
    Fallback lanes are left to the driver."""
    clean_up = large_step | ~(iterations < STEPS_WITHOUT_CLEAN_UP + 1)
    if any(clean_up):
        R = select(clean_up, reorthonormalize(R, gram(R)), R)
    if any(nan_lanes):
        nan = constant(R[0], float("nan"))
        R = select(nan_lanes, (nan, nan, nan, nan, nan, nan, nan, nan, nan), R)
    return R
