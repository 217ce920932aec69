"""Command line: ``python -m torchrot bench [--full] [options]``."""
from __future__ import annotations

import argparse
import dataclasses
import sys

import torch

from torchrot.benchmark import FULL, QUICK, format_table, machine_info, run_plan, single_matrix_overhead, write_results
from torchrot.testing import DISTRIBUTIONS

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def _positive_int(text: str) -> int:
    value = int(float(text))  # accepts 1e5
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


def _data_set(text: str) -> str:
    if text not in DISTRIBUTIONS:
        raise argparse.ArgumentTypeError(f"unknown data set {text!r}; known: {', '.join(sorted(DISTRIBUTIONS))}")
    return text


def _bench(args: argparse.Namespace) -> int:
    plan = FULL if args.full else QUICK
    overrides = {
        "scaling_n": tuple(args.scaling_n) if args.scaling_n else None,
        "methods_n": args.n,
        "methods_data": tuple(args.data) if args.data else None,
        "dtypes": tuple(DTYPES[d] for d in args.dtype) if args.dtype else None,
        "threads": tuple(args.threads) if args.threads else None,
        "repeats": args.repeats,
    }
    plan = dataclasses.replace(plan, **{k: v for k, v in overrides.items() if v is not None})
    print(f"torchrot benchmark ({'full' if args.full else 'quick'}): {machine_info()}")
    print(f"plan: {plan}")
    rows = run_plan(plan)
    overhead = single_matrix_overhead()
    print("\nSingle-matrix call (us):")
    for name, us in overhead.items():
        print(f"  {name:58s} {us:7.2f}")
    for part in ("scaling", "methods"):
        print(f"\n## {part}\n")
        print(format_table([r for r in rows if r.part == part]))
    if args.output:
        for path in write_results(rows, overhead, args.output):
            print(f"wrote {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torchrot")
    sub = parser.add_subparsers(dest="command", required=True)
    bench = sub.add_parser("bench", help="accuracy/speed tables on built-in generated data",
                           description="Times torchrot beside torch.linalg.svd, the memory copy and the "
                                       "installed baselines (roma, libigl); the default quick plan takes a "
                                       "few minutes, --full the complete grid (N up to 1e7, every kernel, "
                                       "both dtypes).")
    bench.add_argument("--full", action="store_true", help="the complete grid (about 40 minutes on 2 cores)")
    bench.add_argument("--n", type=_positive_int, help="matrices per data set in the method tables")
    bench.add_argument("--scaling-n", type=_positive_int, nargs="+", help="N values of the scaling sweep")
    bench.add_argument("--data", type=_data_set, nargs="+", help="data sets of the method tables")
    bench.add_argument("--dtype", nargs="+", choices=sorted(DTYPES))
    bench.add_argument("--threads", type=_positive_int, nargs="+")
    bench.add_argument("--repeats", type=_positive_int, help="timed runs per row; the median is reported")
    bench.add_argument("--output", default="results", help="folder for bench.json/.md/.png ('' to skip)")
    args = parser.parse_args(argv)
    return _bench(args)


if __name__ == "__main__":
    sys.exit(main())
