"""Progress of a run: "[stage k/n, elapsed] title" lines (:class:`Progress`)
and progress within a long step (:func:`progress_bar`). Carriage-return
progress (a tqdm bar redrawn in place) only where a terminal shows it: a log
written to a file or a pipe gets plain lines."""
from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

__all__ = ["LinesProgress", "Progress", "progress_bar", "redraws_in_place"]


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


def redraws_in_place(stdout: TextIO | None = None, stderr: TextIO | None = None) -> bool:
    """Whether progress may redraw a line with carriage returns: only where
    both standard output (the log) and standard error (where tqdm draws) are
    terminals, so no saved log holds them."""
    stdout, stderr = stdout or sys.stdout, stderr or sys.stderr
    return all(getattr(stream, "isatty", lambda: False)() for stream in (stdout, stderr))


class LinesProgress:
    """A progress bar's ``update``/``close`` as plain lines on ``stream``: one
    at each quarter of ``total`` (``LINES`` in all), none redrawn."""

    LINES = 4

    def __init__(self, total: int, desc: str, stream: TextIO | None = None,
                 clock: Callable[[], float] = time.perf_counter):
        self.total, self.desc, self.stream, self.clock = max(total, 1), desc, stream or sys.stdout, clock
        self.done, self.printed, self.start = 0, 0, clock()

    def update(self, n: int = 1) -> None:
        self.done += n
        while self.printed < self.LINES and self.done * self.LINES >= (self.printed + 1) * self.total:
            self.printed += 1
            print(f"    {self.desc}: {self.done}/{self.total} in {self.clock() - self.start:.1f} s",
                  file=self.stream, flush=True)

    def close(self) -> None:
        pass


def progress_bar(total: int, desc: str, enabled: bool = True, stdout: TextIO | None = None,
                 stderr: TextIO | None = None):
    """An object with ``update(n)`` and ``close()`` for ``total`` steps: a tqdm
    bar where :func:`redraws_in_place` (and tqdm is installed, the "bench"
    extra), else :class:`LinesProgress` on ``stdout``; None if not ``enabled``."""
    if not enabled:
        return None
    if redraws_in_place(stdout, stderr):
        try:
            from tqdm.auto import tqdm
        except ImportError:
            pass
        else:
            return tqdm(total=total, desc=desc, unit="frame", leave=False, file=stderr or sys.stderr)
    return LinesProgress(total, desc, stdout)
