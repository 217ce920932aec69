"""The machine a run measures: what it is (:func:`machine_info`) and how
busy it was while a table was timed (:class:`Load`)."""
from __future__ import annotations

import datetime
import os
import platform
import shlex
import sys
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version

import torch

__all__ = ["Load", "load_average", "machine_info"]


def _torchrot_version() -> str:
    # The package metadata, where torchrot.__version__ comes from too (read here
    # so that no benchmark module imports the package root).
    try:
        return version("torchrot")
    except PackageNotFoundError:  # a source tree that was never installed
        return "unknown"


def machine_info() -> dict:
    """torch and torchrot versions, the torchrot CPU kernel that runs, ATen's
    CPU capability, the CPU count, processor and Python version, and the run:
    its date (UTC) and command line, so that every results file says which
    version, machine and command wrote it, and when."""
    return {
        "torch": torch.__version__,
        "torchrot": _torchrot_version(),
        "torchrot_kernel": torch.ops.torchrot.cpu_kernel(),
        "aten_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "cores": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "date": datetime.datetime.now(datetime.UTC).date().isoformat(),
        # As typed (sys.orig_argv keeps "-m torchrot", where sys.argv has the module's path),
        # quoted where an argument needs it, so that it can be pasted into a shell.
        "command": shlex.join(["python", *sys.orig_argv[1:]]),
    }


def load_average() -> tuple[float, float, float]:
    """The system's 1, 5 and 15 minute load averages (``os.getloadavg``)."""
    return os.getloadavg()


@dataclass(frozen=True)
class Load:
    """The load averages (1, 5, 15 min) just before and just after a table
    was timed, and the CPU count. The load counts every runnable thread, this
    run's own included: a 1-thread table alone on the machine reads about 1."""

    before: tuple[float, float, float]
    after: tuple[float, float, float]
    cpus: int

    @classmethod
    def around(cls, before: tuple[float, float, float]) -> Load:
        """The load from ``before`` (taken when the table started) to now."""
        return cls(tuple(before), load_average(), os.cpu_count() or 1)

    def line(self) -> str:
        """One line for the tables: the 1-minute averages and the CPU count."""
        busy = max(self.before[0], self.after[0]) >= self.cpus
        return (f"load average (1 min, this run included) {self.before[0]:.2f} -> {self.after[0]:.2f} on "
                f"{self.cpus} CPUs" + (" (at or above the CPU count)" if busy else ""))
