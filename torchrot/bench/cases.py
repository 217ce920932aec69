"""Timing one table: every applicable method on one data set ``(M, init)``,
beside ``torch.linalg.svd`` and the interleaved ``copy_`` (the memory
floor), with each row's accuracy against float64 SVD and the machine's load
(:func:`run_case`); and the same with its suspicious rows re-timed
(:func:`run_checked_case`, see :mod:`torchrot.bench.trust`)."""
from __future__ import annotations

import functools
import statistics
from collections.abc import Callable

import torch
import torch.utils.benchmark as tbench

from torchrot.bench.accuracy import ACCURACY_SAMPLE, accuracy
from torchrot.bench.machine import Load, load_average
from torchrot.bench.registry import WARM_DATA, Method, forced_isa
from torchrot.bench.rows import Row
from torchrot.bench.timing import interleaved_seconds, median_seconds
from torchrot.bench.trust import MAX_RETIMES, relate_to_baselines, retime_suspicious
from torchrot.fitting import fit_rotation_info
from torchrot.reference import rotation_svd
from torchrot.testing.data import soa_view

__all__ = ["run_case", "run_checked_case"]

Tensor = torch.Tensor


def _applicable(method: Method, warm: bool, n: int, dtype: torch.dtype, threads: int = 1) -> bool:
    if method.warm_only and not warm:
        return False
    if method.max_n is not None and n > method.max_n:
        return False
    if method.max_threads is not None and threads > method.max_threads:
        return False
    return not (method.float64_only and dtype != torch.float64)


def run_case(part: str, data: str, M: Tensor, init: Tensor, threads: int, methods: list[Method],
             repeats: int, min_run_time: float, log: Callable[[str], None] = print,
             warm: bool | None = None, slow_repeats: int | None = None) -> list[Row]:
    """Times every applicable method on one data set ``(M, init)`` ``(N, 3, 3)``
    named ``data`` (its rows' label); SVD and copy included. ``warm``: whether
    init is close to the answer, so the warm-start-only methods run (default:
    ``data in WARM_DATA``; recorded solver data are warm). ``slow_repeats``:
    timed runs of the methods with a ``sample_n`` (seconds per call; None: ``repeats``).
    Each row records the load averages before and after the table.

    The copy (key ``"copy"``) is timed interleaved: one sample after each
    other method (interleaved_seconds), its row the median of those samples,
    so that it meets the caches as the fits do. Timed back to back, a small
    batch's copy would run within the last-level cache whatever the methods
    around it leave there (benchmarks/lab_notes.md)."""
    load_before = load_average()
    n, dtype = M.shape[0], M.dtype
    warm = data in WARM_DATA if warm is None else warm
    out = torch.empty_like(M)
    layouts = {"aos": (M, init, out)}
    k = min(n, ACCURACY_SAMPLE)
    M64 = M[:k].double()
    R_star = rotation_svd(M64)
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    copy_method = next((m for m in methods if m.key == "copy"), None)
    copy_runs: list[float] = []  # one copy call after each other method
    # The copy last (a stable sort), so that its samples are in when its row is
    # made; each row is placed at its method's index, so the rows keep the methods' order.
    timed = sorted(enumerate(methods), key=lambda indexed: indexed[1] is copy_method)
    placed: dict[int, Row] = {}
    try:
        for index, method in timed:
            if not _applicable(method, warm, n, dtype, threads):
                continue
            # slow methods run on the first sample_n matrices (their ns/matrix is flat in N)
            used = n if method.sample_n is None else min(n, method.sample_n)
            if method.layout not in layouts:
                layouts[method.layout] = tuple(soa_view(x) for x in (M, init, out))
            M_used, init_used, out_used = (x[:used] for x in layouts[method.layout])
            k_used = min(k, used)
            with forced_isa(method.isa):
                # methods with a sample_n (the comparison methods, up to seconds per call): slow_repeats runs
                method_repeats = repeats if method.sample_n is None or slow_repeats is None else slow_repeats
                steps = None
                if method_repeats == 1 and method.iterations is not None and k_used == used:
                    # one call gives the time, the result and the steps (Mueller's converged mode: seconds)
                    timer = tbench.Timer(stmt="out.append(fn())", globals={
                        "fn": functools.partial(method.iterations, M_used, init_used), "out": (result := [])},
                        num_threads=threads)
                    runs = [timer.timeit(1).median]
                    R, steps = result[-1]
                elif method is copy_method and copy_runs:
                    runs = copy_runs
                else:
                    runs = median_seconds(functools.partial(method.run, M_used, init_used, out_used),
                                          method_repeats, min_run_time, threads)
                    if method.iterations is not None and k_used == used:
                        R, steps = method.iterations(M_used, init_used)
                    else:
                        R = method.run(M_used, init_used, out_used)
                        if method.iterations is not None:
                            steps = method.iterations(M[:k_used], init[:k_used])[1]
                info = None
                if method.diagnostics is not None:
                    start = init[:k] if method.diagnostics["warm"] else None
                    info = fit_rotation_info(M[:k], start, variant=method.diagnostics["variant"])
            row = Row(part, data, method.name, str(dtype).replace("torch.", ""), used, threads,
                      ns_per_matrix=statistics.median(runs) / used * 1e9, runs_ns=[r / used * 1e9 for r in runs],
                      isa=method.isa, group=method.group, key=method.key, mode=method.mode,
                      variant=method.variant, layout=method.layout)
            if method.group != "floor":
                for key, value in accuracy(R[:k_used], M64[:k_used], R_star[:k_used]).items():
                    setattr(row, key, value)
            if info is not None:
                row.mean_iterations = info.iterations.double().mean().item()
                row.fallback_rate = (info.status == 1).double().mean().item()
            if steps is not None:
                row.mean_iterations = steps.double().mean().item()
            placed[index] = row
            log(f"  {part:7s} {data:13s} {row.dtype:7s} N={n:<9d} {threads}T  {method.name:48s} "
                f"{row.ns_per_matrix:10.2f} ns/matrix")
            if copy_method is not None and method is not copy_method:
                copy_runs.append(interleaved_seconds(lambda: copy_method.run(M, init, out)))
    finally:
        torch.set_num_threads(previous_threads)
    rows: list[Row] = [placed[i] for i in sorted(placed)]
    relate_to_baselines(rows)
    load = Load.around(load_before)
    for row in rows:
        row.load_before, row.load_after, row.cpus = list(load.before), list(load.after), load.cpus
    return rows


def run_checked_case(part: str, data: str, M: Tensor, init: Tensor, threads: int, methods: list[Method],
                     repeats: int, min_run_time: float, log: Callable[[str], None] = print,
                     warm: bool | None = None, slow_repeats: int | None = None,
                     one_thread: dict[tuple, float] | None = None, max_retimes: int = MAX_RETIMES) -> list[Row]:
    """:func:`run_case`, then its suspicious rows re-timed on the same data
    (:func:`torchrot.bench.trust.retime_suspicious`; ``one_thread``: the
    1-thread rows' times, :func:`torchrot.bench.trust.one_thread_times`,
    for the check of tables with more threads)."""
    def timed(subset: list[Method]) -> list[Row]:
        return run_case(part, data, M, init, threads, subset, repeats, min_run_time, log, warm, slow_repeats)

    def retime(names: list[str]) -> list[Row]:
        return timed([m for m in methods if m.name in names])

    return retime_suspicious(timed(methods), retime, one_thread, max_retimes, log)
