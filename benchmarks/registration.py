"""Times torchrot.rigid_registration beside the same closed form by SVD
(torchrot.bench.micro.registration_rows, whose table the main job prints at
its small shapes): interleaved in one process, median of several rounds, us per call,
1 thread, scale=True, on the tests' problems, with a copy_ of x and y (the
floor of reading the points once) and torchrot's largest rotation error
against the float64 SVD answer.

    python benchmarks/registration.py [--shapes 1x100 64x64 16x1000 1024x64 1x100000] [--dtype float32 float64]
"""
from __future__ import annotations

import argparse
import os

import torch

from torchrot.bench.micro import FULL, format_registration_table, registration_rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", nargs="+", default=[f"{p}x{n}" for p, n in FULL.registration_shapes],
                        help="problems x points per problem")
    parser.add_argument("--dtype", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    parser.add_argument("--rounds", type=int, default=9)
    args = parser.parse_args()
    torch.set_num_threads(1)
    load = os.getloadavg()
    print(f"rigid_registration(x, y, scale=True), 1 thread, median of {args.rounds} interleaved rounds (us per call); "
          f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}", flush=True)
    shapes = [tuple(int(v) for v in shape.split("x")) for shape in args.shapes]
    rows = registration_rows(shapes, [getattr(torch, d) for d in args.dtype], args.rounds)
    print(format_registration_table(rows))


if __name__ == "__main__":
    main()
