"""How the benchmark measures time: medians of ``torch.utils.benchmark``
runs, interleaved rounds, single interleaved samples, and the solvers'
per-phase timer. Every timing of ``python -m torchrot bench`` and of the
scripts in ``benchmarks/`` goes through these functions."""
from __future__ import annotations

import contextlib
import math
import statistics
import time
from collections import defaultdict
from collections.abc import Callable, Iterator

import torch.utils.benchmark as tbench

__all__ = ["INTERLEAVED_MIN_SECONDS", "PhaseTimer", "device_median_seconds", "interleaved_median_seconds",
           "interleaved_seconds", "median_seconds"]

#: An interleaved sample lasts at least this long (seconds): shorter calls are
#: repeated back to back, so that the sample does not time the clock (a copy
#: of 1e3 float32 matrices takes ~1 us; their 72 KB stay in cache either way).
INTERLEAVED_MIN_SECONDS = 50e-6


def median_seconds(fn: Callable[[], object], repeats: int, min_run_time: float, threads: int = 1) -> list[float]:
    """Per-call seconds of ``repeats`` independent ``blocked_autorange`` medians
    (the Timer sets the thread count itself: it defaults to 1). A call that
    alone takes ``min_run_time`` or more is timed one call at a time instead
    (``blocked_autorange`` would spend a first call estimating its block size)."""
    timer = tbench.Timer(stmt="fn()", globals={"fn": fn}, num_threads=threads)
    first = timer.timeit(1).median
    if first >= min_run_time:
        return [first] + [timer.timeit(1).median for _ in range(repeats - 1)]
    return [timer.blocked_autorange(min_run_time=min_run_time).median for _ in range(repeats)]


def interleaved_median_seconds(calls: dict[str, Callable[[], object]], rounds: int,
                               min_run_time: float) -> dict[str, float]:
    """Median seconds per call of each of ``calls`` over ``rounds`` rounds, each
    round timing every call once with median_seconds, so that slow drifts of a
    shared machine's load meet every call alike."""
    runs: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(rounds):
        for name, fn in calls.items():
            runs[name] += median_seconds(fn, 1, min_run_time)
    return {name: statistics.median(r) for name, r in runs.items()}


def interleaved_seconds(fn: Callable[[], object]) -> float:
    """Seconds per call of ``fn`` where it is called (no warm-up): one call,
    or, if that took less than INTERLEAVED_MIN_SECONDS, the mean of enough
    further calls back to back to last that long. Runs at the caller's
    thread count."""
    start = time.perf_counter()
    fn()
    first = time.perf_counter() - start
    if first >= INTERLEAVED_MIN_SECONDS:
        return first
    calls = math.ceil(INTERLEAVED_MIN_SECONDS / max(first, 1e-9))
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls


def device_median_seconds(calls: dict[str, Callable[[], object]], synchronize: Callable[[], None], rounds: int,
                          min_run_time: float) -> dict[str, float]:
    """Median seconds per call of each of ``calls`` on an accelerator (whose
    work is asynchronous): each round times every call in turn over enough
    calls back to back to last ``min_run_time``, from a synchronised device to
    the device synchronised after the last call (the work itself, launches
    included, not only the launches)."""
    runs: dict[str, list[float]] = {name: [] for name in calls}
    repeats = {}
    for name, fn in calls.items():  # warm-up (first calls compile) and the repeat count
        fn()
        synchronize()
        start = time.perf_counter()
        fn()
        synchronize()
        repeats[name] = max(1, math.ceil(min_run_time / max(time.perf_counter() - start, 1e-9)))
    for _ in range(rounds):
        for name, fn in calls.items():
            synchronize()
            start = time.perf_counter()
            for _ in range(repeats[name]):
                fn()
            synchronize()
            runs[name].append((time.perf_counter() - start) / repeats[name])
    return {name: statistics.median(r) for name, r in runs.items()}


class PhaseTimer:
    """Collects seconds per named phase, one entry per call.

    ``with timer.phase("fit"): ...`` appends the time of the block to
    ``timer.seconds["fit"]``; a disabled timer (``enabled=False``) costs nothing.
    """

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.seconds: dict[str, list[float]] = defaultdict(list)

    @contextlib.contextmanager
    def phase(self, name: str) -> Iterator[None]:
        if not self.enabled:
            yield
            return
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name].append(time.perf_counter() - start)

    def median_ms(self) -> dict[str, float]:
        """Median milliseconds per phase."""
        return {name: statistics.median(values) * 1e3 for name, values in self.seconds.items() if values}

    def total(self) -> float:
        """Seconds summed over every phase and call."""
        return sum(sum(v) for v in self.seconds.values())
