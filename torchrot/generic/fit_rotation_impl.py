"""Algorithm 1 as a per-lane state machine on structure-of-arrays lanes: the
Python twin of csrc/kernel/fit_rotation_impl.h (Tolerances, LaneState,
begin_fit's normalisation, advance, finish), each step spelled out entry by
entry with per-lane masks instead of branches.

The lane state is a dict: ``A`` (M scaled to max |entry| 1) and ``R`` (the
current rotation), 9 tensors each, and the per-lane entries of
torchrot.generic.control_flow._LANE_KEYS. Unlike the kernel, a lane that
stops at a saddle point is marked ``pending`` and escapes at the end of the
step (_apply_pending_escapes), so that the escapes can be deferred past the
whole-batch steps (torchrot.generic.schedule).
"""
from __future__ import annotations

import torch

from torchrot._constants import (
    ESTIMATE_SWITCH,
    GERSHGORIN_STEPS,
    LARGE_STEP,
    MAX_CHECK_SLACK_EPS,
    MAX_ESCAPES,
    STEPS_WITHOUT_CLEAN_UP,
    UNDAMPED,
    dtype_name,
)
from torchrot.generic.cayley import (
    cayley_increment,
    cayley_step,
    objective_estimate,
    rotate_by,
    skew_vector,
    trace,
)
from torchrot.generic.control_flow import _INT, _any, _compiling, _masked_update, _repeat
from torchrot.generic.horn_fallback import horn_rotation
from torchrot.generic.lanes import select
from torchrot.generic.mat3 import reorthonormalize, times, transpose_times
from torchrot.generic.optimality import is_maximum
from torchrot.generic.saddle_escape import saddle_escape_rotation

__all__ = ["can_take", "take_step", "advance", "finish", "_step", "_apply_pending_escapes", "_cleaned_up"]


def _step(st, variant, converge, cap, eps, objective=None):
    """One masked Cayley step of the kernel's advance() on the lane state
    (with c = ``objective`` if given: the first step from the cold start).

    A lane that stops at a saddle point (converged mode) with escapes left is
    marked ``pending`` and stops running; _apply_pending_escapes applies the
    escape and restarts it, as the kernel does within the same step."""
    A, R = st["A"], st["R"]
    running, fallback, switched = st["running"], st["fallback"], st["switched"]
    iterations, attempt, escapes = st["iterations"], st["attempt"], st["escapes"]
    finfo = torch.finfo(A[0].dtype)
    step_floor = finfo.tiny / finfo.eps**2  # can_take's floor of d^2 + w.w
    undamped_tol = UNDAMPED[dtype_name(A[0].dtype)]
    S = transpose_times(R, A)
    t = trace(S)
    m = skew_vector(S)
    mm = m[0] * m[0] + m[1] * m[1] + m[2] * m[2]
    if objective is not None:
        c = objective
    else:
        c = objective_estimate(S, t, mm, variant)
        if converge and variant == "gershgorin":
            c = torch.where(switched, objective_estimate(S, t, mm, "conservative"), c)
    w, d, ww, dd, hh = cayley_step(S, t, m, c)
    valid = can_take(dd, ww, step_floor)
    stalled = running & ~valid
    R, iterations, attempt, large, stepping = take_step(st, (w, d, ww, dd), valid)
    undamped = ~(c - t > undamped_tol * t.abs())
    finished = stepping & undamped & (ww < eps * dd)
    pending = st["pending"]
    if converge:
        singular = finished & ~(mm < eps * hh)  # CayleyStep::singular (cayley.h)
        stalled = stalled | singular
        finished = finished & ~singular
        switch_now = (ww < ESTIMATE_SWITCH * dd) | (attempt >= GERSHGORIN_STEPS)
        switched = switched | (stepping & switch_now)
        saddle = finished & ~is_maximum(S, MAX_CHECK_SLACK_EPS * eps)
        escape = saddle & (escapes < MAX_ESCAPES)
        fallback = fallback | (saddle & ~escape)
        pending = pending | escape
        exhausted = stepping & ~finished & (attempt >= cap)
        fallback = fallback | exhausted | stalled
        finished = finished | exhausted | stalled
    else:
        finished = finished | stalled | (attempt >= cap)
    return dict(st, R=R, running=running & ~finished, fallback=fallback, switched=switched,
                iterations=iterations, attempt=attempt, pending=pending, large=large)


def can_take(dd, ww, step_floor):
    """Whether a lane can take the step (d, w): H not singular, the step
    finite, d^2 + w.w above ``step_floor`` (T_min / eps^2; fit_rotation_impl.h)."""
    norm2 = dd + ww
    return (dd > 0) & torch.isfinite(norm2) & (norm2 > step_floor)


def take_step(st, step, valid):
    """Applies the step (w, d, w.w, d^2) to the running lanes that can take it
    (``valid``), counts it and notes a large one: (R, iterations, attempt,
    large, stepping)."""
    w, d, ww, dd = step
    stepping = st["running"] & valid
    safe_d = torch.where(stepping, d, 1.0)
    safe_dd = torch.where(stepping, dd, 1.0)
    safe_w = [torch.where(stepping, x, 0.0) for x in w]
    # Lanes not stepping get K = 0 exactly (w = 0, d = 1): R + R K = R, no select needed.
    R = rotate_by(st["R"], cayley_increment(safe_w, safe_d, torch.where(stepping, ww, 0.0), safe_dd))
    large = st["large"] | (stepping & ~(ww < LARGE_STEP * dd))
    step_i = stepping.to(_INT)
    return R, st["iterations"] + step_i, st["attempt"] + step_i, large, stepping


def _apply_pending_escapes(st):
    """The saddle escape (saddle_escape.h) of the pending lanes, which then run again."""
    pending = st["pending"]
    if not _compiling() and not _any(pending):
        return st
    escaped = lambda *RA: times(list(RA[:9]), saddle_escape_rotation(transpose_times(list(RA[:9]), list(RA[9:]))))
    R = _masked_update(pending, escaped, st["R"], (*st["R"], *st["A"]))
    return dict(st, R=R, running=st["running"] | pending, pending=pending & False, large=st["large"] | pending,
                escapes=st["escapes"] + pending.to(_INT), attempt=torch.where(pending, 0, st["attempt"]),
                switched=st["switched"] & ~pending)


def _cleaned_up(st):
    """finish()'s Newton-Schulz step, on the lanes that took a large step or
    a saddle escape, or more than STEPS_WITHOUT_CLEAN_UP steps."""
    clean_up = st["large"] | (st["iterations"] > STEPS_WITHOUT_CLEAN_UP)
    return select(clean_up, reorthonormalize(st["R"]), st["R"])


def advance(st, steps, variant, converge, cap, eps):
    """Pending escapes, then up to ``steps`` Cayley steps on the running lanes
    of ``st`` (each with its escapes): the lane state after them."""
    st = _apply_pending_escapes(st)
    return _repeat(lambda s: _apply_pending_escapes(_step(s, variant, converge, cap, eps)), st, steps)


def finish(st, converge):
    """The result R of every lane that is not running: the Newton-Schulz
    clean-up and, in converged mode, the Horn fallback of the fallback lanes
    (the C++ finish's solve_fallback_lanes). NaN lanes are the driver's."""
    R = _cleaned_up(st)
    if converge:
        R = _masked_update(st["fallback"], lambda *A: horn_rotation(list(A)), R, st["A"])
    return R
