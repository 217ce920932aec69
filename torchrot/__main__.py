"""Command line: ``python -m torchrot bench [options]``."""
from __future__ import annotations

import argparse
import os
import sys

import torch

from torchrot.benchmark import DEFAULT_DATA, format_table, machine_info, run_benchmark, write_json
from torchrot.testing import DISTRIBUTIONS

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def _positive_int(text: str) -> int:
    value = int(float(text))  # accepts 1e5
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


def _bench(args: argparse.Namespace) -> int:
    unknown = [d for d in args.data if d not in DISTRIBUTIONS]
    if unknown:
        print(f"unknown data set(s) {unknown}; known: {sorted(DISTRIBUTIONS)}", file=sys.stderr)
        return 2
    print(f"torchrot benchmark: {machine_info()}")
    rows = []
    for dtype in args.dtype:
        for threads in args.threads:
            print(f"{dtype}, N = {args.n}, {threads} thread(s):")
            rows += run_benchmark(tuple(args.data), args.n, DTYPES[dtype], threads, args.repeats, args.min_run_time)
    print()
    print(format_table(rows))
    if args.output:
        os.makedirs(args.output, exist_ok=True)
        path = os.path.join(args.output, "bench.json")
        write_json(rows, path)
        print(f"\nwrote {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torchrot", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    bench = sub.add_parser("bench", help="accuracy/speed table on built-in generated data")
    bench.add_argument("--n", type=_positive_int, default=100_000, help="matrices per data set (default 1e5)")
    bench.add_argument("--dtype", nargs="+", choices=sorted(DTYPES), default=["float32"])
    bench.add_argument("--threads", nargs="+", type=_positive_int, default=[1])
    bench.add_argument("--data", nargs="+", default=list(DEFAULT_DATA), help="data sets (torchrot.testing)")
    bench.add_argument("--repeats", type=_positive_int, default=5, help="timed runs per row; the median is reported")
    bench.add_argument("--min-run-time", type=float, default=0.2, help="seconds per timed run")
    bench.add_argument("--output", default="results", help="folder for bench.json ('' to skip)")
    args = parser.parse_args(argv)
    return _bench(args)


if __name__ == "__main__":
    sys.exit(main())
