"""Times torchrot.rigid_registration beside the same closed form by SVD
(torchrot.bench.workloads.registration_rows, whose table the main job prints at
its small shapes): interleaved in one process, median of several rounds, us per call,
1 thread, scale=True, on the tests' problems, with a copy_ of x and y (the
floor of reading the points once) and torchrot's largest rotation error
against the float64 SVD answer.

    python benchmarks/registration.py [--shapes 1x100 64x64 16x1000 1024x64 1x100000] [--dtype float32 float64]
"""
from __future__ import annotations

import argparse

import torch

from torchrot.bench.machine import Load, load_average
from torchrot.bench.options import DTYPES, positive_int
from torchrot.bench.plans import FULL
from torchrot.bench.tables import format_registration_table
from torchrot.bench.workloads import registration_rows

__all__ = ["main"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", nargs="+", default=[f"{p}x{n}" for p, n in FULL.registration_shapes],
                        help="problems x points per problem")
    parser.add_argument("--dtype", nargs="+", default=sorted(DTYPES), choices=sorted(DTYPES))
    parser.add_argument("--rounds", type=positive_int, default=FULL.registration_rounds)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"rigid_registration(x, y, scale=True), 1 thread, median of {args.rounds} interleaved rounds "
          "(us per call)", flush=True)
    before = load_average()
    shapes = [tuple(int(v) for v in shape.split("x")) for shape in args.shapes]
    rows = registration_rows(shapes, [DTYPES[d] for d in args.dtype], args.rounds)
    print(Load.around(before).line() + "\n\n" + format_registration_table(rows))


if __name__ == "__main__":
    main()
