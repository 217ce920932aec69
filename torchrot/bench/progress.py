"""Overall progress of a run: "[stage k/n, elapsed] title" lines."""
from __future__ import annotations

import time
from typing import Callable


class Progress:
    """Numbers the stages of a run of ``total`` stages and prints each with the
    time elapsed since the start; :meth:`note` prints a line inside a stage."""

    def __init__(self, total: int, log: Callable[[str], None] = print, clock: Callable[[], float] = time.perf_counter):
        self.total, self.log, self.clock = total, log, clock
        self.done = 0
        self.start = clock()

    def elapsed(self) -> float:
        return self.clock() - self.start

    def stage(self, title: str) -> None:
        self.done += 1
        self.log(f"\n[stage {self.done}/{self.total}, {self.elapsed():5.1f} s] {title}")

    def note(self, text: str) -> None:
        self.log(f"  [{self.elapsed():5.1f} s] {text}")
