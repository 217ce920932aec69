"""The complete CPU benchmark grid, written to benchmarks/results/.

    python benchmarks/run_full_suite.py          # torchrot.bench.cli.FULL_RUN_MINUTES on 2 cores

Same as ``python -m torchrot bench --full --output benchmarks/results``: the
scaling sweep (N = 1e2 ... 1e7, float32, 1 thread) and the method tables at
N = 1e6 (every torchrot kernel, mode and variant; float32 and float64; 1 and
2 threads) beside torch.linalg.svd, the memory copy, RoMa and libigl, then the
applications part at paper scale (57k-vertex ARAP, 24k-tet elasticity, 1e6
recorded matrices per table).
"""
import os
import sys

from torchrot.bench.cli import main

__all__: list[str] = []  # a script

if __name__ == "__main__":
    results = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
    sys.exit(main(["bench", "--full", "--output", results, *sys.argv[1:]]))
