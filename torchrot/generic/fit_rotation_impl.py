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

import math

import torch

from torchrot._constants import (
    ESTIMATE_SWITCH,
    GERSHGORIN_STEPS,
    LARGE_STEP,
    MAX_CHECK_SLACK_EPS,
    MAX_ESCAPES,
    STEPS_WITHOUT_CLEAN_UP,
    UNDAMPED,
)
from torchrot.generic.cayley import (
    _cayley_increment,
    _cayley_step,
    _objective_estimate,
    _rotate_by,
    _skew_vector,
    _trace,
)
from torchrot.generic.control_flow import _INT, _any, _compiling, _masked_update, _repeat
from torchrot.generic.horn_fallback import _horn_rotation
from torchrot.generic.mat3 import _mul, _reorthonormalize, _tmul, _where
from torchrot.generic.optimality import _is_maximum
from torchrot.generic.saddle_escape import _saddle_escape_rotation

__all__ = ["_dtype_name", "_normalized", "_step", "_apply_pending_escapes", "_advance_and_finish", "_cleaned_up"]


def _dtype_name(dtype: torch.dtype) -> str:
    """"float32" for torch.float32: the key of torchrot._constants' per-dtype
    tables (the kernel's Tolerances<T>)."""
    return str(dtype).removeprefix("torch.")


def _normalized(M):
    """M / max|M| entrywise, as the kernel scales it (csrc/kernel/unit_scale.h):
    a maximum outside the normal range, whose reciprocal is not a normal
    number, is first lifted by 2^digits (subnormal) or dropped by 2^-digits
    (above 1 / tiny): (A, max_abs, zero, lift, inv) with A = (M lift) inv."""
    max_abs = M[0].abs()
    for x in M[1:]:
        max_abs = torch.maximum(max_abs, x.abs())  # NaN propagates
    finfo = torch.finfo(M[0].dtype)
    digits = round(-math.log2(finfo.eps)) + 1
    ones = torch.ones_like(max_abs)
    lift = torch.where(max_abs < finfo.tiny, float(2**digits),
                       torch.where(max_abs > 1 / finfo.tiny, float(2**-digits), ones))
    zero = max_abs == 0
    inv = torch.where(zero, 0.0, 1 / torch.where(zero, 1.0, max_abs * lift))
    return [(x * lift) * inv for x in M], max_abs, zero, lift, inv


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
    undamped_tol = UNDAMPED[_dtype_name(A[0].dtype)]
    S = _tmul(R, A)
    t = _trace(S)
    m = _skew_vector(S)
    mm = m[0] * m[0] + m[1] * m[1] + m[2] * m[2]
    if objective is not None:
        c = objective
    else:
        c = _objective_estimate(S, t, mm, variant)
        if converge and variant == "gershgorin":
            c = torch.where(switched, _objective_estimate(S, t, mm, "conservative"), c)
    w, d, ww, dd, hh = _cayley_step(S, t, m, c)
    norm2 = dd + ww
    valid = (dd > 0) & torch.isfinite(norm2) & (norm2 > step_floor)  # can_take
    stepping = running & valid
    stalled = running & ~valid
    safe_d = torch.where(stepping, d, 1.0)
    safe_dd = torch.where(stepping, dd, 1.0)
    safe_w = [torch.where(stepping, x, 0.0) for x in w]
    # Lanes not stepping get K = 0 exactly (w = 0, d = 1): R + R K = R, no select needed.
    R = _rotate_by(R, _cayley_increment(safe_w, safe_d, torch.where(stepping, ww, 0.0), safe_dd))
    large = st["large"] | (stepping & ~(ww < LARGE_STEP * dd))  # take_step's LaneState::large_step
    step_i = stepping.to(_INT)
    iterations = iterations + step_i
    attempt = attempt + step_i
    undamped = ~(c - t > undamped_tol * t.abs())
    finished = stepping & undamped & (ww < eps * dd)
    pending = st["pending"]
    if converge:
        singular = finished & ~(mm < eps * hh)  # CayleyStep::singular (cayley.h)
        stalled = stalled | singular
        finished = finished & ~singular
        switch_now = (ww < ESTIMATE_SWITCH * dd) | (attempt >= GERSHGORIN_STEPS)
        switched = switched | (stepping & switch_now)
        saddle = finished & ~_is_maximum(S, MAX_CHECK_SLACK_EPS * eps)
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


def _apply_pending_escapes(st):
    """The saddle escape (saddle_escape.h) of the pending lanes, which then run again."""
    pending = st["pending"]
    if not _compiling() and not _any(pending):
        return st
    R = _masked_update(pending,
                       lambda *RA: _mul(list(RA[:9]), _saddle_escape_rotation(_tmul(list(RA[:9]), list(RA[9:])))),
                       st["R"], (*st["R"], *st["A"]))
    return dict(st, R=R, running=st["running"] | pending, pending=pending & False, large=st["large"] | pending,
                escapes=st["escapes"] + pending.to(_INT), attempt=torch.where(pending, 0, st["attempt"]),
                switched=st["switched"] & ~pending)


def _cleaned_up(st):
    """finish()'s Newton-Schulz step, on the lanes that took a large step or
    a saddle escape, or more than STEPS_WITHOUT_CLEAN_UP steps."""
    clean_up = st["large"] | (st["iterations"] > STEPS_WITHOUT_CLEAN_UP)
    return _where(clean_up, _reorthonormalize(st["R"]), st["R"])


def _advance_and_finish(st, steps, variant, converge, cap, eps):
    """Pending escapes, up to ``steps`` more Cayley steps on the lanes of
    ``st``, then finish(): the Newton-Schulz clean-up and, in converged mode,
    the Horn fallback. Returns (R, final state)."""
    st = _apply_pending_escapes(st)
    st = _repeat(lambda s: _apply_pending_escapes(_step(s, variant, converge, cap, eps)), st, steps)
    R = _cleaned_up(st)
    if converge:
        R = _masked_update(st["fallback"], lambda *A: _horn_rotation(list(A)), R, st["A"])
    return R, st
