"""Control flow of the device-generic kernel: data-dependent loops and
branches over lanes, eager or compiled. No C++ header counterpart: the C++
kernel branches per block (``L::any``) and loops with ``for``
(csrc/kernel/fit_rotation_impl.h); here those decisions are tensor masks.

Eager, the loops stop as soon as no lane runs and the rare pieces (saddle
escapes, the Horn fallback, the overflow pass) run only when some lane needs
them: one host read of a mask each (free on CPU). Compiled, the same
decisions are graph operations (torch.while_loop, torch.cond), traced once
each: no graph break, no unrolling (the graph stays small enough to compile
in about two minutes). Both spellings take the same decisions, so results do
not depend on the mode.

The lane state the loops carry is a dict: ``A`` and ``R`` (9 tensors each,
torchrot.generic.mat3) and the per-lane entries _LANE_KEYS (LaneState of
fit_rotation_impl.h), counters in _INT.
"""
from __future__ import annotations

import torch

from torchrot.generic.lanes import select

__all__ = ["_INT", "_LANE_KEYS", "UNROLL_MAX_STEPS", "_compiling", "_any", "_masked_update", "_repeat"]

#: The dtype of the per-lane counters (iterations, attempt, escapes).
_INT = torch.int32

#: The lane state's per-lane entries besides ``A`` and ``R``, in the order loops carry them.
_LANE_KEYS = ("running", "fallback", "switched", "iterations", "attempt", "escapes", "pending", "large")

#: Compiled, loops of at most this many steps are unrolled (the one-step warm start).
UNROLL_MAX_STEPS = 2


def _compiling() -> bool:
    return torch.compiler.is_compiling()


def _any(mask: torch.Tensor) -> bool:
    """Eager only: whether some lane of ``mask`` is set (``meta``: assume so)."""
    return mask.device.type == "meta" or bool(mask.any())


def _masked_update(mask, fn, R, operands):
    """R (9 tensors) with the lanes of ``mask`` replaced by ``fn(*operands)``,
    which is computed only when some lane is set."""
    if not _compiling():  # only the lanes of mask, gathered
        if mask.device.type == "meta":
            return select(mask, fn(*operands), R)
        idx = mask.nonzero().squeeze(1)
        if idx.numel() == 0:
            return R
        return [r.index_put((idx,), v) for r, v in zip(R, fn(*(x[idx] for x in operands)))]
    k = len(R)

    def replace(mask, *xs):
        return tuple(select(mask, fn(*xs[k:]), list(xs[:k])))

    def keep(mask, *xs):
        return tuple(x.clone() for x in xs[:k])

    return list(torch.cond(mask.any(), replace, keep, (mask, *R, *operands)))


def _repeat(step, st, steps, unroll=True):
    """Up to ``steps`` applications of ``step`` to the lane state ``st``
    (a dict: ``A``, ``R`` and _LANE_KEYS), stopping once no lane runs.
    Compiled, ``unroll`` lets a loop of at most UNROLL_MAX_STEPS steps be
    unrolled; otherwise it is a while_loop."""
    if steps <= 0:
        return st
    if not _compiling():
        for _ in range(steps):
            if not _any(st["running"]):
                break
            st = step(st)
            if st["running"].device.type == "meta":  # one step gives the shapes and dtypes of all
                break
        return st
    if unroll and steps <= UNROLL_MAX_STEPS:
        # A short fixed loop fuses into one kernel (finished lanes' steps are no-ops).
        for _ in range(steps):
            st = step(st)
        return st
    A = st["A"]
    # The lane flags travel through the loop as int32 0/1: inductor's CPU code
    # loads and stores bool buffers byte by byte (a branch per lane), which
    # made a step several times slower (benchmarks/lab_notes.md); int32 lanes
    # load and store as vectors.
    flags = {k for k in _LANE_KEYS if st[k].dtype == torch.bool}
    pack = lambda s: (*s["R"], *(s[k].to(_INT) if k in flags else s[k] for k in _LANE_KEYS))

    def unpack(xs):
        lanes = {k: (x != 0 if k in flags else x) for k, x in zip(_LANE_KEYS, xs[9:])}
        return {"A": A, "R": list(xs[:9]), **lanes}

    def cond(i, *xs):
        return (i < steps) & (xs[9] != 0).any()  # xs[9]: running

    def body(i, *xs):
        out = pack(step(unpack(xs)))
        return (i + 1, *(o.clone() if any(o is x for x in xs) else o for o in out))

    carried = []
    for x in pack(st):  # while_loop rejects carried inputs that alias each other
        carried.append(x.clone() if any(x is y for y in carried) else x)
    counter = torch.zeros((), dtype=torch.int64, device=A[0].device)
    return unpack(torch.while_loop(cond, body, (counter, *carried))[1:])
