"""The complete CPU benchmark grid, written to benchmarks/results/.

    python benchmarks/run_full_suite.py          # about 40 minutes on 2 cores

Same as ``python -m torchrot bench --full --output benchmarks/results``: the
scaling sweep (N = 1e3 ... 1e7, float32, 1 thread) and the method tables at
N = 1e6 (every torchrot kernel, mode and variant; float32 and float64; 1 and
2 threads) beside torch.linalg.svd, the memory copy, RoMa and libigl.
"""
import os
import sys

from torchrot.__main__ import main

if __name__ == "__main__":
    results = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
    sys.exit(main(["bench", "--full", "--output", results, *sys.argv[1:]]))
