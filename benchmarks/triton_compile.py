"""How long a first call on a GPU compiles: every Triton kernel of torchrot,
as the operators launch it, compiled by Triton for NVIDIA Hopper (sm_90),
Ampere (sm_80) and AMD MI300 (gfx942) on this machine's CPU, without a GPU
(torchrot.triton.ahead_of_time). A first call compiles the kernels it needs
once; Triton caches them on disk for later processes.

    python benchmarks/triton_compile.py [--rounds 3] > benchmarks/results/triton_compile.md

Each figure is the median of --rounds compilations, each from an empty
Triton cache. Writes Markdown to stdout.
"""
from __future__ import annotations

import argparse
import os
import statistics
import tempfile

from torchrot.bench.machine import machine_info
from torchrot.bench.options import positive_int
from torchrot.triton.ahead_of_time import TARGETS, compile_for, specializations

__all__ = ["main"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=positive_int, default=3)
    rounds = parser.parse_args().rounds
    import triton

    print(f"# Triton compile time of each kernel\n\nMachine: {machine_info()}, Triton {triton.__version__}\n")
    print(f"Seconds per compilation on this CPU (median of {rounds}, each from an empty Triton cache).\n")
    targets = list(TARGETS)
    print("| kernel | " + " | ".join(targets) + " |")
    print("|---|" + "---:|" * len(targets))
    totals = dict.fromkeys(targets, 0.0)
    for specialization in specializations():
        cells = []
        for target in targets:
            seconds = []
            for _ in range(rounds):
                with tempfile.TemporaryDirectory() as cache:
                    os.environ["TRITON_CACHE_DIR"] = cache
                    seconds.append(compile_for(specialization, target)[1])
            totals[target] += statistics.median(seconds)
            cells.append(f"{statistics.median(seconds):.2f}")
        print(f"| {specialization.name} | " + " | ".join(cells) + " |")
    print("| all of the above | " + " | ".join(f"{totals[t]:.1f}" for t in targets) + " |")


if __name__ == "__main__":
    main()
