"""``python -m torchrot bench [--full] [options]``: the microbenchmark, then
the applications part, as numbered stages with the elapsed time; the report
(narrow tables on the terminal, every column in the files) ends with a
headline of at most :data:`torchrot.bench.summary.MAX_LINES` lines."""
from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import os
import sys
import time

import torch

from torchrot.bench import data
from torchrot.bench.machine import Load, load_average, machine_info
from torchrot.bench.options import DTYPES, data_sets, dtype_name, max_threads, positive_int
from torchrot.bench.plans import FULL, QUICK, plan_cases
from torchrot.bench.progress import Progress
from torchrot.bench.registry import WARM_DATA
from torchrot.bench.results import write_results
from torchrot.bench.summary import headline, write_summary
from torchrot.bench.tables import for_terminal, format_layer_table, format_registration_table, format_tables_narrow
from torchrot.bench.workloads import registration_rows, rotation_layer, single_matrix_overhead

__all__ = ["FULL_RUN_MINUTES", "bench", "main", "parser"]

#: The paper-scale run's (--full) wall time on 2 cores, as --help states it
#: (its measurement: benchmarks/lab_notes.md).
FULL_RUN_MINUTES = 80


def _folder_size(folder: str) -> int:
    total = 0
    for root, _, files in os.walk(folder):
        for name in files:
            try:
                total += os.path.getsize(os.path.join(root, name))
            except OSError:
                pass
    return total


def _missing_app_modules() -> list[str]:
    return [m for m in ("scipy", "igl") if importlib.util.find_spec(m) is None]


def _choices(values) -> str:
    return ", ".join(str(v) for v in values)


def _data_set(text: str) -> str:
    if text not in data_sets():
        raise argparse.ArgumentTypeError(f"unknown data set {text!r}; known: {_choices(data_sets())}")
    return text


def _thread_count(text: str) -> int:
    threads = positive_int(text)
    if threads > max_threads():
        raise argparse.ArgumentTypeError(f"at most {max_threads()} (this machine's CPUs), got {text}")
    return threads


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(prog="python -m torchrot")
    sub = top.add_subparsers(dest="command", required=True)
    bench = sub.add_parser(
        "bench", help="accuracy/speed tables on generated and recorded solver data",
        description="Times torchrot beside torch.linalg.svd, the memory copy, the installed baselines (roma, "
                    "libigl) and the paper's comparison methods on generated data, then the applications part: "
                    "records (or loads from the cache) the ARAP and elasticity data sets and prints the paper's "
                    "Tables 1-2 analogues and writes Figs. 5-7. The default run takes about a minute on 2 cores "
                    "(every part at small sizes); --full is the paper-scale run (N up to 1e7, every kernel, both "
                    f"dtypes, 57k-vertex and 24k-tet solvers: about {FULL_RUN_MINUTES} minutes).")
    bench.add_argument("--full", action="store_true",
                       help=f"the paper-scale run (about {FULL_RUN_MINUTES} minutes on 2 cores)")
    bench.add_argument("--n", type=positive_int, help="matrices per data set in the method tables (default "
                                                      f"{QUICK.methods_n:,}; --full {FULL.methods_n:,})")
    bench.add_argument("--scaling-n", type=positive_int, nargs="+", metavar="N",
                       help=f"N values of the scaling sweep (default {_choices(QUICK.scaling_n)}; --full "
                            f"{_choices(FULL.scaling_n)})")
    bench.add_argument("--data", type=_data_set, nargs="+", metavar="NAME",
                       help=f"data sets of the method tables, any of: {_choices(data_sets())} (default "
                            f"{_choices(QUICK.methods_data)})")
    bench.add_argument("--dtype", type=str, nargs="+", choices=sorted(DTYPES), metavar="DTYPE",
                       help=f"dtypes, any of: {_choices(sorted(DTYPES))} (default "
                            f"{_choices(dtype_name(d) for d in QUICK.dtypes)}; --full "
                            f"{_choices(dtype_name(d) for d in FULL.dtypes)})")
    bench.add_argument("--threads", type=_thread_count, nargs="+", metavar="T",
                       help=f"thread counts of the method tables, each 1 to {max_threads()} (this machine's CPUs; "
                            f"default {_choices(QUICK.threads)})")
    bench.add_argument("--repeats", type=positive_int, help="timed runs per row; the median is reported (default "
                                                            f"{QUICK.repeats}; --full {FULL.repeats})")
    bench.add_argument("--output", default="results",
                       help="folder for bench.json/.md/.png and apps.json/.md/fig*.png (default: ./results; "
                            "'' to write nothing)")
    bench.add_argument("--no-apps", action="store_true",
                       help="skip the applications part (ARAP/elasticity data, Tables 1-2, Figs. 5-7)")
    bench.add_argument("--apps-only", action="store_true", help="run only the applications part")
    bench.add_argument("--mesh", help="an OBJ/OFF/PLY/STL surface for the ARAP data set and experiments "
                                      "(default: the built-in capsule)")
    bench.add_argument("--device", help="the device job instead: torchrot's operators on this device's tensors "
                                        "(cuda, xpu, mps; cpu checks the job itself) beside torch.linalg.svd, RoMa "
                                        "and copy_ on the same device, and a first call's latency; writes "
                                        "device.json/.md")
    bench.add_argument("--device-n", type=positive_int, nargs="+", metavar="N",
                       help="with --device: matrices per row (default "
                            "1000 10000 100000 1000000 10000000)")
    bench.add_argument("--svd-max-n", type=positive_int, metavar="N",
                       help="with --device: time torch.linalg.svd, RoMa and the rotation layer up to N matrices "
                            "(default 1000000)")
    bench.add_argument("--cache", help="folder of the recorded data sets (default: $TORCHROT_CACHE, else "
                                       "$XDG_CACHE_HOME/torchrot, else ~/.cache/torchrot); a second run loads "
                                       "them from there")
    return top


def _plans(args: argparse.Namespace):
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
    if _missing_app_modules():
        return plan, None
    from torchrot.bench import apps  # the solvers need scipy and igl

    apps_plan = apps.FULL if args.full else apps.QUICK
    overrides = {"table_n": args.n, "dtypes": tuple(DTYPES[d] for d in args.dtype) if args.dtype else None,
                 "repeats": args.repeats}
    apps_plan = dataclasses.replace(apps_plan, **{k: v for k, v in overrides.items() if v is not None})
    if args.mesh:
        apps_plan = dataclasses.replace(apps_plan, arap=dataclasses.replace(apps_plan.arap, mesh_path=args.mesh))
    return plan, apps_plan


def _with_load(run, loads: dict, key: str):
    """``run`` as a stage that records the machine's load around it in ``loads[key]``."""
    def stage():
        before = load_average()
        run()
        loads[key] = Load.around(before)
    return stage


def _device_job(args: argparse.Namespace, log) -> int:
    from torchrot.bench import device

    device.device_bench(args.device, tuple(args.device_n or device.DEVICE_N),
                        tuple(DTYPES[d] for d in args.dtype) if args.dtype else (torch.float32, torch.float64),
                        rounds=args.repeats or 5, svd_max_n=args.svd_max_n or device.SVD_MAX_N,
                        output=os.path.abspath(args.output) if args.output else None,
                        command="python -m torchrot " + " ".join(sys.argv[1:]), log=log)
    return 0


def bench(args: argparse.Namespace, log=print) -> int:
    if args.device:
        return _device_job(args, log)
    clock = time.perf_counter()
    plan, apps_plan = _plans(args)
    output = os.path.abspath(args.output) if args.output else None
    cache = data.cache_root(args.cache)
    missing = _missing_app_modules()
    run_micro, run_apps = not args.apps_only, not args.no_apps and not missing
    log(f"torchrot benchmark ({'full' if args.full else 'quick; --full for the paper-scale run'}): "
        f"{machine_info()}")
    log(f"results:  {output + os.sep if output else 'not written (--output ' + repr(args.output) + ')'}")
    if run_apps or (run_micro and set(plan.methods_data) & set(data.RECORDED)):
        log(f"data set cache: {cache}{os.sep} (recorded solver data, {_folder_size(cache) / 1e6:.0f} MB now; "
            "--cache or $TORCHROT_CACHE to move it)")
    if missing and not args.no_apps:
        log(f"applications part skipped: {', '.join(missing)} not installed (pip install 'torchrot[bench]')")

    stages: list[tuple[str, object]] = []
    rows: list = []
    overhead: dict = {}
    layer: list = []
    registration: list = []
    loads: dict = {}  # the load around each workload table, by its key in bench.json
    if run_micro:
        def pairs(name: str, n: int, dtype: torch.dtype):
            configs = {} if apps_plan is None else {"arap": apps_plan.arap, "elasticity": apps_plan.elasticity}
            return data.pairs(name, n, dtype, configs=configs, cache=args.cache)

        def warm(name: str) -> bool:
            return name in WARM_DATA or name in data.RECORDED

        for title, run in plan_cases(plan, pairs, warm, log):
            stages.append((title, lambda run=run: rows.extend(run())))
        stages.append(("single-matrix call overhead", _with_load(lambda: overhead.update(
            single_matrix_overhead(plan.overhead_run_time)), loads, "single_matrix_us")))
        stages.append((f"rotation layer (nn.RotationFit forward + backward), batch "
                       f"{', '.join(f'{b:,}' for b in plan.layer_batches)}",
                       _with_load(lambda: layer.extend(rotation_layer(plan.layer_batches, plan.overhead_run_time)),
                                  loads, "rotation_layer")))
        stages.append((f"point-set registration (rigid_registration against the SVD closed form), problems x "
                       f"points {', '.join(f'{p:,} x {n:,}' for p, n in plan.registration_shapes)}, "
                       f"{', '.join(dtype_name(d) for d in plan.dtypes)}",
                       _with_load(lambda: registration.extend(registration_rows(
                           plan.registration_shapes, plan.dtypes, plan.registration_rounds, plan.overhead_run_time)),
                           loads, "registration")))
    apps_results: dict = {}
    apps_rows: list = []
    if run_apps:
        from torchrot.bench import apps

        cases, apps_results, apps_rows = apps.apps_cases(apps_plan, args.cache, log=log)
        stages += cases
    stages.append(("writing the results" if output else "summary", None))

    progress = Progress(len(stages), log)
    # Everything outside the timed rows (data generation and recording, reference SVDs, statistics) runs
    # on 1 thread, as the solver experiments do: on a shared machine a second intra-op thread that waits
    # for a busy core slows the small sparse products and fits of the recording ten-fold. The rows set
    # their own thread count (run_case).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for title, run in stages[:-1]:
            progress.stage(title)
            run()
    finally:
        torch.set_num_threads(threads)
    progress.stage(stages[-1][0])
    written: list[str] = []
    bench_md = os.path.join(output, "bench.md") if output else "bench.md (--output)"
    if run_micro:
        log("\nSingle-matrix call (us)" + (f"\n{loads['single_matrix_us'].line()}:" if overhead else ":"))
        for name, us in overhead.items():
            log(f"  {name:58s} {us:7.2f}")
        log(f"\nRotation layer, forward + backward (us)\n{loads['rotation_layer'].line()}:\n"
            + for_terminal(format_layer_table(layer), bench_md))
        log(f"\nPoint-set registration, rigid_registration(x, y, scale=True) (us per call)\n"
            f"{loads['registration'].line()}:\n" + for_terminal(format_registration_table(registration), bench_md))
        for part in ("scaling", "methods"):
            log(f"\n## {part} (every column: {bench_md})\n")
            log(for_terminal(format_tables_narrow([r for r in rows if r.part == part]), bench_md))
        if output:
            written += write_results(rows, overhead, output, layer, registration, loads)
    if run_apps:
        from torchrot.bench import apps

        apps.print_summary(apps_results, apps_rows, log, os.path.join(output, "apps.md") if output else None)
        if output:
            written += apps.write_apps(apps_results, apps_rows, output, machine_info())
    log("")
    for path in written:
        log(f"wrote {path}")
    log(f"\ndone in {time.perf_counter() - clock:.0f} s.")
    if run_apps or (run_micro and set(plan.methods_data) & set(data.RECORDED)):
        log(f"data set cache: {cache}{os.sep} ({_folder_size(cache) / 1e6:.0f} MB; delete it to re-record)")
    log("")
    # (The folder as given: the summary file names it, and the README quotes that file.)
    summary = headline(rows, layer, registration, apps_rows, args.output or None, torch.ops.torchrot.cpu_kernel())
    for line in summary:
        log(line)
    if output:
        log(f"wrote {write_summary(summary, output)}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    return bench(args)


if __name__ == "__main__":
    sys.exit(main())
