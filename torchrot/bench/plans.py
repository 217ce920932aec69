"""What the microbenchmark runs (:class:`Plan`: :data:`QUICK` by default,
:data:`FULL` with ``--full``) and the plan as stages (:func:`plan_cases`).

Each row times one method on one data set of N matrices with
``torch.utils.benchmark`` (the median of several ``blocked_autorange`` runs,
each itself a median), beside ``torch.linalg.svd`` special Procrustes and a
plain ``copy_`` of the input into a preallocated tensor (the memory floor)
timed on the same data in the same run, and reports the accuracy of the same
call against float64 SVD. Data come from ``torchrot.testing``, the generators
the tests use, as (M, init) pairs of a local-global solver (``make_warm_start``).

Two parts:
  scaling: ns/matrix against N for the main methods (plotted log-log);
  methods: every method at one N, for each data set, dtype and thread count,
           torchrot at each instruction set, mode and variant, and the
           paper's comparison methods (``torchrot.methods``, group
           "paper method"), each with its failures shown, not hidden.
Every table's suspicious rows are re-timed and, if they stay suspicious,
marked (:mod:`torchrot.bench.trust`). Beside them, each against its SVD
counterpart in the same run (:mod:`torchrot.bench.workloads`): the
single-matrix call, a training step's rotation layer and point-set registration.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchrot.bench.cases import run_checked_case
from torchrot.bench.registry import COMPARISON_N, VARIANTS, WARM_DATA, all_methods, supported_isas
from torchrot.bench.rows import Row
from torchrot.bench.trust import one_thread_times
from torchrot.testing.data import make_warm_start

__all__ = ["FULL", "Plan", "QUICK", "SCALING_N", "make_pairs", "plan_cases", "run_plan"]

Tensor = torch.Tensor

#: N of the full scaling sweep: five decades, from calls that per-call costs
#: dominate to batches far beyond the last-level cache.
SCALING_N = (100, 1_000, 10_000, 100_000, 1_000_000, 10_000_000)


@dataclass
class Plan:
    """What to run: the scaling sweep and the method matrix."""

    scaling_data: tuple[str, ...] = ("warm", "uniform")
    # the default run's sweep: the full sweep's sizes up to 1e4 (1e5 and up take seconds per SVD row)
    scaling_n: tuple[int, ...] = tuple(n for n in SCALING_N if n <= 10_000)
    methods_data: tuple[str, ...] = ("warm", "warm_cond1e5", "rot60", "uniform")
    methods_n: int = 4_000
    dtypes: tuple[torch.dtype, ...] = (torch.float32,)
    threads: tuple[int, ...] = (1, 2)
    all_isas: bool = False
    variants: tuple[str, ...] = ("newton", "conservative")
    repeats: int = 3
    min_run_time: float = 0.02
    # the paper's comparison methods run on at most this many matrices per data set (None: methods_n);
    # their ns/matrix is flat in N from ~1e4 on (0.5-5 us per matrix of batched tensor ops)
    comparison_n: int | None = 500
    layer_batches: tuple[int, ...] = (64, 10_000)  # rotation_layer: nn.RotationFit forward + backward
    slow_repeats: int | None = 1  # timed runs of the comparison methods (up to seconds per call; None: repeats)
    overhead_run_time: float = 0.05  # min_run_time of the single-matrix call timings
    # registration_rows: rigid_registration against the SVD closed form, (problems, points)
    registration_shapes: tuple[tuple[int, int], ...] = ((1, 100), (64, 64), (1024, 64))
    registration_rounds: int = 5


#: The default ``python -m torchrot bench``: every part at small sizes (about a minute with
#: the applications part on 2 cores). ``--full``: the paper-scale grid.
QUICK = Plan()
FULL = Plan(scaling_n=SCALING_N, methods_n=1_000_000,
            dtypes=(torch.float32, torch.float64), all_isas=True, variants=VARIANTS, repeats=5, min_run_time=0.2,
            comparison_n=COMPARISON_N, slow_repeats=None, overhead_run_time=0.5, layer_batches=(64, 100_000),
            registration_shapes=((1, 100), (64, 64), (16, 1000), (1024, 64), (1, 100_000)), registration_rounds=9)


def make_pairs(data: str, n: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``(M, init)`` of a generated data set (``torchrot.testing.make_warm_start``, seed 0)."""
    return make_warm_start(data, n, seed=0, dtype=dtype)


def plan_cases(plan: Plan, pairs: Callable[[str, int, torch.dtype], tuple[Tensor, Tensor]] = make_pairs,
               warm: Callable[[str], bool] = WARM_DATA.__contains__,
               log: Callable[[str], None] = print) -> list[tuple[str, Callable[[], list[Row]]]]:
    """The plan as a list of (title, run) cases, each ``run()`` returning its
    rows: the scaling sweep (one case per data set) and the method matrix (one
    per dtype, thread count and data set; the 1-thread tables first, the
    references of the tables with more threads). ``pairs(data, n, dtype)``
    makes the data (default: generated); ``warm(data)`` says whether its init is close."""
    cases = []
    scaling = [m for m in all_methods(None, ("conservative",), first_touch=False, comparison=False)
               if m.mode != "one_step" or m.variant != "newton"]

    def sweep(data: str) -> list[Row]:
        rows = []
        for n in plan.scaling_n:
            M, init = pairs(data, n, torch.float32)
            rows += run_checked_case("scaling", data, M, init, 1, scaling, plan.repeats, plan.min_run_time, log,
                                     warm(data), plan.slow_repeats)
        return rows

    for data in plan.scaling_data:
        cases.append((f"scaling sweep, {data} data, N = {', '.join(f'{n:,}' for n in plan.scaling_n)}",
                      lambda data=data: sweep(data)))
    methods = all_methods(supported_isas() if plan.all_isas else None, plan.variants, comparison_n=plan.comparison_n)
    one_thread: dict[tuple, float] = {}  # filled by the 1-thread tables, read by those with more threads

    def matrix(data: str, dtype: torch.dtype, threads: int) -> list[Row]:
        M, init = pairs(data, plan.methods_n, dtype)
        rows = run_checked_case("methods", data, M, init, threads, methods, plan.repeats, plan.min_run_time, log,
                                warm(data), plan.slow_repeats, one_thread)
        one_thread.update(one_thread_times(rows))
        return rows

    for dtype in plan.dtypes:
        for threads in sorted(plan.threads):
            for data in plan.methods_data:
                cases.append((f"every method, {data} data, {str(dtype).replace('torch.', '')}, "
                              f"N = {plan.methods_n:,}, {threads} thread{'s' * (threads > 1)}",
                              lambda data=data, dtype=dtype, threads=threads: matrix(data, dtype, threads)))
    return cases


def run_plan(plan: Plan, log: Callable[[str], None] = print) -> list[Row]:
    """Every case of :func:`plan_cases` on generated data."""
    return [row for _, run in plan_cases(plan, log=log) for row in run()]
