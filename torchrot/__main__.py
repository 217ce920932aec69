"""Command line: ``python -m torchrot bench [--full] [options]``."""
from __future__ import annotations

import argparse
import dataclasses
import sys

import torch

from torchrot.benchmark import FULL, QUICK, format_table, machine_info, run_plan, single_matrix_overhead, write_results
from torchrot.apps.datasets import RECORDED
from torchrot.testing import DISTRIBUTIONS

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def _positive_int(text: str) -> int:
    value = int(float(text))  # accepts 1e5
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


def _data_set(text: str) -> str:
    known = sorted(DISTRIBUTIONS) + list(RECORDED)
    if text not in known:
        raise argparse.ArgumentTypeError(f"unknown data set {text!r}; known: {', '.join(known)}")
    return text


def _apps(args: argparse.Namespace) -> None:
    """The applications part: recorded solver data, Tables 1-2, Figs. 5-7, targets."""
    import importlib.util

    missing = [m for m in ("scipy", "igl") if importlib.util.find_spec(m) is None]
    if missing:
        print(f"\napplications part skipped: {', '.join(missing)} not installed (pip install 'torchrot[bench]')")
        return
    from torchrot.apps import reproduce

    plan = reproduce.FULL if args.full else reproduce.QUICK
    overrides = {"table_n": args.n, "dtypes": tuple(DTYPES[d] for d in args.dtype) if args.dtype else None,
                 "repeats": args.repeats}
    plan = dataclasses.replace(plan, **{k: v for k, v in overrides.items() if v is not None})
    if args.mesh:
        plan = dataclasses.replace(plan, arap=dataclasses.replace(plan.arap, mesh_path=args.mesh))
    print(f"\n# Applications: ARAP and co-rotational elasticity data (cache: "
          f"{reproduce.datasets.cache_root(args.cache)})")
    results, rows = reproduce.run_apps(plan, args.cache)
    reproduce.print_summary(results, rows)
    print(f"\napplications part: {results['seconds']:.0f} s")
    if args.output:
        for path in reproduce.write_apps(results, rows, args.output, machine_info()):
            print(f"wrote {path}")


def _bench(args: argparse.Namespace) -> int:
    if args.apps_only:
        _apps(args)
        return 0
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
    if not args.no_apps:
        _apps(args)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torchrot")
    sub = parser.add_subparsers(dest="command", required=True)
    bench = sub.add_parser("bench", help="accuracy/speed tables on built-in generated data",
                           description="Times torchrot beside torch.linalg.svd, the memory copy and the "
                                       "installed baselines (roma, libigl); the default quick plan takes a "
                                       "few minutes, --full the complete grid (N up to 1e7, every kernel, "
                                       "both dtypes). Then the applications part: records (or loads) the "
                                       "ARAP and elasticity data sets, prints the paper's Tables 1-2 "
                                       "analogues and writes Figs. 5-7.")
    bench.add_argument("--full", action="store_true", help="the complete grid (about 40 minutes on 2 cores)")
    bench.add_argument("--n", type=_positive_int, help="matrices per data set in the method tables")
    bench.add_argument("--scaling-n", type=_positive_int, nargs="+", help="N values of the scaling sweep")
    bench.add_argument("--data", type=_data_set, nargs="+", help="data sets of the method tables")
    bench.add_argument("--dtype", nargs="+", choices=sorted(DTYPES))
    bench.add_argument("--threads", type=_positive_int, nargs="+")
    bench.add_argument("--repeats", type=_positive_int, help="timed runs per row; the median is reported")
    bench.add_argument("--output", default="results",
                       help="folder for bench.json/.md/.png and apps.json/.md/fig*.png ('' to skip)")
    bench.add_argument("--no-apps", action="store_true",
                       help="skip the applications part (ARAP/elasticity data, Tables 1-2, Figs. 5-7)")
    bench.add_argument("--apps-only", action="store_true", help="run only the applications part")
    bench.add_argument("--mesh", help="an OBJ/OFF/PLY/STL surface for the ARAP data set and experiments "
                                      "(default: the built-in 57,346-vertex capsule)")
    bench.add_argument("--cache", help="folder of the recorded data sets (default: $TORCHROT_CACHE, else "
                                       "~/.cache/torchrot); a second run loads them from there")
    args = parser.parse_args(argv)
    return _bench(args)


if __name__ == "__main__":
    sys.exit(main())
