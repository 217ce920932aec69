"""The device-generic kernel, structure of arrays: torchrot's algorithm for
any device, written as elementwise tensor operations. It is the body of
:func:`torchrot.fit_rotation_reference`, the kernel of the operators on
every device without a C++ or Triton one (MPS; CUDA and XPU where Triton is
missing), run eagerly there.

Every matrix is held as 9 separate ``(n,)`` tensors (its entries, row-major),
and every step of the C++ kernel is spelled out entry by entry, with
per-matrix masks instead of branches, so each lane executes the kernel's
state machine: in float64 the same iteration counts and status codes
(tests/test_generic_path.py), but on the rare lane where rounding decides (a
degenerate maximum or a saddle): the kernel rounds a * b + c once
(csrc/kernel/mul_add.h), torch's ops twice.

One module per header of csrc/kernel/ that has a Python counterpart, named
after it, and one per job that has none:

======================  ==============================================  ==================================
module                  what                                            mirrors
======================  ==============================================  ==================================
``lanes``               select, max |entry| per lane                    csrc/kernel/lanes.h
``mat3``                3x3 algebra on lists of 9 tensors               csrc/kernel/mat3.h
``unit_scale``          M scaled to max |entry| 1, exactly              csrc/kernel/unit_scale.h
``cayley``              trace, m, the estimate c, Algorithm 2, Eq. 10   csrc/kernel/cayley.h
``cold_start``          the best of the 24 rotations of the cube        csrc/kernel/cold_start.h
``maximal_objective``   K's largest eigenvalue (Laguerre)               csrc/kernel/maximal_objective.h
``optimality``          maximum check, warm-start check and clean-up    csrc/kernel/optimality.h
``saddle_escape``       the half-turn out of a saddle                   csrc/kernel/saddle_escape.h
``quaternion``          R(q) and Horn's K                               csrc/kernel/quaternion.h
``horn_fallback``       the guaranteed fallback (eigh)                  csrc/kernel/horn_fallback.h
``rotation_gradient``   the derivative's tangent                        csrc/kernel/rotation_gradient.h
``fit_rotation_impl``   the lane state machine: step, escapes, finish   csrc/kernel/fit_rotation_impl.h
``control_flow``        loops and branches over lanes, eager/compiled   (none: torch.while_loop, cond)
``schedule``            whole-batch steps, straggler compaction         (none: csrc/cpu's regrouping)
``driver``              _fit_core and the entry points                   (none)
======================  ==============================================  ==================================

(force_inline.h and mul_add.h have no counterpart: torch's ops are neither
inlined nor fused by hand. Each module's functions carry the header's names;
tests/test_mirrors.py holds the correspondence, with the C++ functions that
have no twin here and why.)

Schedule (converged mode, torchrot.generic.schedule): the whole batch takes
up to ``full_steps(dtype, cold)`` masked Cayley steps (most matrices converge
within them), saddle escapes deferred; the matrices still running, pending
an escape or needing the fallback are then compacted and take the rest of
the kernel's step budget (escapes included) and the Horn fallback (float64
eigh) there; results are scattered back. Eagerly the compaction is exact (a
host read) and loops stop when no lane runs. Compiled, there is no
data-dependent shape and no graph break (for callers that compile it): the buffer has the static size
``straggler_capacity(n)`` (cumsum + scatter), lanes that do not fit take the
rest on the whole batch, masked, and the loops and the rare pieces are
``while_loop`` / ``cond`` graph operations (torchrot.generic.control_flow), so
``torch.compile(fullgraph=True)`` compiles the whole algorithm as one graph
(minutes: the operators no longer compile it; CUDA and XPU run torchrot.triton).
Their predicates (whether any lane still runs) are the only values the host
reads: one flag per loop iteration (about a dozen per call), instead of
running the whole step budget on every lane.

The names below are the package's entry points and tunables; the code
reads its tunables from the submodule that defines them, so patch them
there: ``torchrot.generic.schedule`` (STRAGGLER_MIN, STRAGGLER_DIVISOR,
FULL_STEPS, ...).

Speed: benchmarks/generic_path.py.
"""
from __future__ import annotations

from torchrot.generic.driver import (
    STATUS_BAD_INIT,
    STATUS_CAYLEY,
    STATUS_FALLBACK,
    STATUS_NON_FINITE,
    fit_rotation_backward_generic,
    fit_rotation_generic,
)
from torchrot.generic.rotation_gradient import rotation_tangent
from torchrot.generic.schedule import (
    COLD_FULL_STEPS,
    FULL_STEPS,
    FULL_STEPS_MAX_ITER,
    STRAGGLER_DIVISOR,
    STRAGGLER_MIN,
    fit_soa,
    full_steps,
    straggler_capacity,
)

__all__ = [
    "COLD_FULL_STEPS",
    "FULL_STEPS",
    "FULL_STEPS_MAX_ITER",
    "STATUS_BAD_INIT",
    "STATUS_CAYLEY",
    "STATUS_FALLBACK",
    "STATUS_NON_FINITE",
    "STRAGGLER_DIVISOR",
    "STRAGGLER_MIN",
    "fit_rotation_backward_generic",
    "fit_rotation_generic",
    "fit_soa",
    "full_steps",
    "rotation_tangent",
    "straggler_capacity",
]
