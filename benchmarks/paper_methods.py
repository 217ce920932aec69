"""The paper's comparison methods (torchrot.methods) beside torch.linalg.svd, the
memory copy and torchrot, timed in one run on the same data (docs/performance.md).

    python benchmarks/paper_methods.py                  # N = 1e5, float32, 1 thread
    python benchmarks/paper_methods.py --n 1e6 --data warm rot60 uniform --json out.json
    python benchmarks/paper_methods.py --wide           # and one line per method

Rows come from ``torchrot.bench.cases.run_checked_case`` (medians of ``--repeats``
``blocked_autorange`` medians; accuracy against float64 SVD on every matrix;
rows still suspicious after their re-timings marked as in the main job's
tables). Methods with ``sample_n`` (Mueller's converged mode) run on the
first matrices only; their N column says how many.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict

from torchrot.bench.cases import run_checked_case
from torchrot.bench.data import RECORDED, pairs
from torchrot.bench.machine import Load, load_average, machine_info
from torchrot.bench.options import DTYPES, data_sets, positive_int
from torchrot.bench.registry import PAPER, WARM_DATA, all_methods
from torchrot.bench.tables import fmt
from torchrot.bench.trust import MARKER, legend

__all__ = ["TORCHROT_MODES", "main", "selected_methods", "table", "wide_table"]

TORCHROT_MODES = ("one_step", "converged_cold", "converged_warm")  # conservative variant


def selected_methods():
    """copy_, torch.linalg.svd, three torchrot modes and every paper method."""
    return [m for m in all_methods(None, ("conservative",), first_touch=False, comparison_n=None)
            if m.group == PAPER or m.key in ("copy", "svd") or m.mode in TORCHROT_MODES]


def _marked(row) -> str:
    return f" {MARKER} {', '.join(row.suspicion)}" if row.suspicion else ""


def table(rows) -> str:
    lines = ["| data | method | N | ns/matrix | x SVD | x copy | max err | median err | share >1e-3 | failures "
             "| mean steps |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r.data} | {r.method} | {r.n:.0e} | {r.ns_per_matrix:.0f}{_marked(r)} | "
            f"{fmt(r.speedup_vs_svd, '.2f')} | {fmt(r.time_vs_copy, '.0f')} | {fmt(r.max_error, '.1e')} | "
            f"{fmt(r.median_error, '.1e')} | {fmt(r.share_above_1e3, '.2%')} | {fmt(r.failures, 'd')} | "
            f"{fmt(r.mean_iterations, '.1f')} |")
    return "\n".join(lines)


def wide_table(rows) -> str:
    """One line per method, per data set: ns/matrix, max error, failures (|R - R*|_F > 1e-3
    or non-finite: count and share); one line per method with --wide."""
    data_sets = list(dict.fromkeys(r.data for r in rows))
    by_method: dict[str, dict] = {}
    for r in rows:
        by_method.setdefault(r.method, {})[r.data] = r
    n_used = lambda r: "" if r.n == max(x.n for x in rows) else f" (N={r.n:.0e})"
    failed = lambda r: "-" if r.failures is None else (f"{r.failures}" if r.failures == 0 else
                                                        f"{r.failures} ({r.share_above_1e3:.2%})")
    lines = ["| method | " + " | ".join(f"{d} ns/matrix | {d} max err | {d} failures" for d in data_sets) + " |",
             "|---|" + "---|" * (3 * len(data_sets))]
    for method, by_data in by_method.items():
        cells = []
        for d in data_sets:
            r = by_data.get(d)
            cells += (["-"] * 3 if r is None else
                      [f"{r.ns_per_matrix:.0f}{n_used(r)}{_marked(r)}", fmt(r.max_error, ".0e"), failed(r)])
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=positive_int, default=100_000, help="matrices per data set")
    parser.add_argument("--data", nargs="+", default=["warm", "rot60", "uniform"], choices=data_sets(),
                        help="generated distributions or the recorded ARAP/elasticity data (recorded on first "
                             "use into $TORCHROT_CACHE, see torchrot.bench.data)")
    parser.add_argument("--dtype", default="float32", choices=sorted(DTYPES))
    parser.add_argument("--threads", type=positive_int, default=1)
    parser.add_argument("--repeats", type=positive_int, default=5)
    parser.add_argument("--min-run-time", type=float, default=0.1)
    parser.add_argument("--json", help="also write the rows and the machine to this JSON file")
    parser.add_argument("--wide", action="store_true", help="also print one line per method")
    args = parser.parse_args(argv)
    print(f"machine: {machine_info()} (shared machine: medians of runs)")
    before = load_average()
    rows = []
    for data in args.data:
        M, init = pairs(data, args.n, DTYPES[args.dtype])
        rows += run_checked_case("methods", data, M, init, args.threads, selected_methods(), args.repeats,
                                 args.min_run_time, log=lambda line: print(line, file=sys.stderr),
                                 warm=data in WARM_DATA or data in RECORDED)
    load = Load.around(before)
    print(load.line())
    print(table(rows))
    if args.wide:
        print()
        print(wide_table(rows))
    if any(r.suspicion for r in rows):
        print("\n" + legend())
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": machine_info(), "load_average_before": list(load.before),
                       "load_average_at_end": list(load.after), "args": vars(args),
                       "rows": [asdict(r) for r in rows]}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
