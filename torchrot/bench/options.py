"""The command-line vocabulary that ``python -m torchrot bench`` and the
scripts in ``benchmarks/`` share: the dtypes and data sets a benchmark can
run, thread counts, and counts written as ``1e5``. ``--help`` texts and
argument checks read these, so they list exactly what the code accepts."""
from __future__ import annotations

import argparse
import os

import torch

from torchrot.bench.data import RECORDED
from torchrot.testing.data import DISTRIBUTIONS

__all__ = ["DTYPES", "data_sets", "dtype_name", "max_threads", "positive_int"]

#: The dtypes the benchmarks time, by name.
DTYPES = {"float32": torch.float32, "float64": torch.float64}


def dtype_name(dtype: torch.dtype) -> str:
    """"float32" for torch.float32."""
    return str(dtype).removeprefix("torch.")


def data_sets() -> list[str]:
    """Every data set a benchmark can run: the generated distributions of
    ``torchrot.testing`` and the recorded solver data (``torchrot.bench.data``)."""
    return sorted(DISTRIBUTIONS) + list(RECORDED)


def max_threads() -> int:
    """The most threads a table is timed with: this machine's CPUs (more
    threads than CPUs would time the scheduler, not the method)."""
    return os.cpu_count() or 1


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1, also written as a float (``1e5``)."""
    value = int(float(text))
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value
