"""Wall-clock time of the phases of each solver iteration."""
from __future__ import annotations

import contextlib
import statistics
import time
from collections import defaultdict
from typing import Iterator


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
