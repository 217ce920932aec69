"""The applications part of ``python -m torchrot bench``: the paper's
Tables 1-2 and Figs. 5-7 on the built-in solver data.

:func:`apps_cases` lists its stages: record (or load from the cache) the
"arap" and "elasticity" data sets and compute their Fig. 5 statistics, time
every benchmark method on them (Tables 1 and 2), run the solver experiments
(Figs. 6 and 7, the libigl validation); :func:`run_apps` runs them all.
:func:`write_apps` writes ``apps.json`` (every number), ``apps.md`` and
``fig5_data.png``, ``fig6_local_global.png``, ``fig7_energy_time.png``.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from torchrot.apps.meshes import capsule, load_surface, octopus
from torchrot.bench import data, experiments, figures, report
from torchrot.bench.cases import run_checked_case
from torchrot.bench.registry import Method, all_methods, supported_isas
from torchrot.bench.rows import Row, row_value
from torchrot.bench.sessions import DropScript, HandleScript
from torchrot.bench.statistics import recording_statistics
from torchrot.bench.tables import for_terminal, group_tables, table_load
from torchrot.bench.trust import legend

__all__ = ["AppsPlan", "FULL", "QUICK", "apps_cases", "markdown", "print_summary", "rewrite", "run_apps", "run_table",
           "table_methods", "write_apps"]


@dataclass
class AppsPlan:
    """What the applications part runs.

    arap, elasticity: the recorded data sets' configurations.
    table_n, dtypes, repeats, min_run_time: the Tables 1-2 benchmark
        (N matrices drawn from each recording; 1 thread, as the paper);
        comparison_n: the paper's comparison methods (batched PyTorch, slow,
        ns/matrix flat in N) run on the first comparison_n of them.
    timing_frames, timing_iterations: ARAP Fig. 6 frames x iterations;
    elasticity_timing_frames: time steps timed for elasticity's Fig. 6.
    trace_iterations, trace_reference_iterations: ARAP Fig. 7;
    elasticity_trace_iterations: iterations of elasticity's Fig. 7 time step.
    validation_resolution, validation_iterations: the libigl comparison's
        capsule and iteration count (converged to ~1e-10 relative change).
    threads: torch threads of the solver experiments.
    local_dtypes: precisions of the local step timed for Fig. 6 (float32 is
        the paper's; Fig. 7 and the validation run in float64).
    """

    arap: data.ArapDataConfig = field(default_factory=data.ArapDataConfig)
    elasticity: data.ElasticityDataConfig = field(default_factory=data.ElasticityDataConfig)
    table_n: int = 100_000
    dtypes: tuple[torch.dtype, ...] = (torch.float32,)
    repeats: int = 5
    min_run_time: float = 0.1
    all_isas: bool = False
    comparison_n: int | None = 20_000
    slow_repeats: int | None = None  # timed runs of the comparison methods (None: repeats)
    statistics_sample: int = 200_000
    timing_frames: int = 6
    timing_iterations: int = 4
    elasticity_timing_frames: int = 8
    trace_iterations: int = 40
    trace_reference_iterations: int = 60
    elasticity_trace_iterations: int = 30
    validation_resolution: int = 12
    validation_iterations: int = 600
    threads: int = 1
    local_dtypes: tuple[torch.dtype, ...] = (torch.float32, torch.float64)


#: The default run: the same stages at small sizes (a 14k-vertex capsule, a 3k-tet octopus,
#: 5e3 matrices per table); ``--full``: the paper-scale run (57k vertices, 24k tets, 1e6 matrices).
QUICK = AppsPlan(arap=data.ArapDataConfig(resolution=32, frames=16, iterations=3, max_per_step=1_000),
                 elasticity=data.ElasticityDataConfig(resolution=12, frames=24, iterations=4, max_per_step=400),
                 table_n=5_000, repeats=3, min_run_time=0.02, comparison_n=500, slow_repeats=1,
                 statistics_sample=40_000,
                 timing_frames=3, timing_iterations=3, elasticity_timing_frames=3, trace_iterations=15,
                 trace_reference_iterations=30, elasticity_trace_iterations=12, validation_resolution=6,
                 validation_iterations=300)
FULL = AppsPlan(arap=data.ArapDataConfig(frames=60, max_per_step=6_000),  # 1.08M matrices
                elasticity=data.ElasticityDataConfig(frames=90, max_per_step=2_400),  # 1.08M matrices
                table_n=1_000_000, dtypes=(torch.float32, torch.float64), all_isas=True, comparison_n=100_000,
                timing_frames=10,
                elasticity_timing_frames=16, trace_iterations=200, trace_reference_iterations=800,
                elasticity_trace_iterations=60, validation_resolution=24, validation_iterations=3000)


def _arap_mesh(plan: AppsPlan):
    return load_surface(plan.arap.mesh_path) if plan.arap.mesh_path else capsule(plan.arap.resolution)


def table_methods(plan: AppsPlan) -> list[Method]:
    """Every benchmark method; torchrot with its scalar kernel (Table 1, the
    paper's non-vectorized code) and its best kernel (Table 2), or every kernel."""
    isas = supported_isas()
    kernels = isas if plan.all_isas else ["scalar", isas[-1]]
    return all_methods(kernels, ("newton", "conservative"), comparison_n=plan.comparison_n)


def run_table(plan: AppsPlan, name: str, dtype: torch.dtype, cache: str | None,
              log: Callable[[str], None] = print, methods: list[Method] | None = None) -> list[Row]:
    """Tables 1 and 2 rows of recorded data set ``name``: ``plan.table_n``
    matrices drawn from it, every method, 1 thread (as the paper); suspicious
    rows re-timed (:func:`torchrot.bench.cases.run_checked_case`)."""
    M, init = data.pairs(name, plan.table_n, dtype, configs={"arap": plan.arap, "elasticity": plan.elasticity},
                         cache=cache)
    return run_checked_case("apps", name, M, init, 1, methods or table_methods(plan), plan.repeats,
                            plan.min_run_time, log, warm=True, slow_repeats=plan.slow_repeats)


def _label(dtype: torch.dtype) -> str:
    return str(dtype).replace("torch.", "")


def apps_cases(plan: AppsPlan, cache: str | None = None, tables: bool = True, log: Callable[[str], None] = print,
               progress: bool = True) -> tuple[list[tuple[str, Callable[[], None]]], dict, list]:
    """The applications part as stages: (title, run) pairs to run in order,
    which fill the returned ``results`` dict and ``rows`` list."""
    results: dict = {"plan": _plain_plan(plan), "datasets": {}, "statistics": {}, "timings": {}}
    rows: list = []
    configs = {"arap": plan.arap, "elasticity": plan.elasticity}
    cases: list[tuple[str, Callable[[], None]]] = []
    clock: dict = {}

    def start() -> None:
        clock["start"] = time.perf_counter()
        results["load_average_at_start"] = list(os.getloadavg())

    def record(name: str) -> None:
        if not clock:
            start()
        folder = data.dataset_folder(name, configs[name], cache)
        cached = data.is_complete(folder)
        log(f"  {'loading' if cached else 'recording'} {folder}")
        recording = data.load_dataset(name, configs[name], cache, progress)
        results["datasets"][name] = recording.manifest
        log(f"  {len(recording):,} recorded matrices ({recording.manifest['steps']} local steps); Fig. 5 statistics")
        results["statistics"][name] = recording_statistics(recording, sample=plan.statistics_sample)

    for name in data.RECORDED:
        cases.append((f"data set {name!r}: record (or load from the cache), Fig. 5 statistics",
                      lambda name=name: record(name)))
    if tables:
        methods = table_methods(plan)
        for dtype in plan.dtypes:
            for name in data.RECORDED:
                cases.append((f"Tables 1-2: every method on {name} data, {_label(dtype)}, N = {plan.table_n:,}",
                              lambda name=name, dtype=dtype: rows.extend(
                                  run_table(plan, name, dtype, cache, log, methods))))
    meshes: dict = {}

    def mesh_pair():
        if not meshes:
            meshes["arap"], meshes["elasticity"] = _arap_mesh(plan), octopus(plan.elasticity.resolution)
        return meshes["arap"], meshes["elasticity"]

    script, drop = HandleScript(frames=plan.arap.frames), DropScript(frames=plan.elasticity.frames)

    def fig6(dtype: torch.dtype) -> None:
        mesh, tets = mesh_pair()
        log(f"  ARAP on {mesh.name} ({len(mesh.V):,} vertices), elasticity on {tets.name} ({len(tets.F):,} tets)")
        results["timings"][_label(dtype)] = {
            "arap": experiments.arap_phase_times(mesh, script, plan.timing_frames, plan.timing_iterations,
                                                 threads=plan.threads, dtype=dtype),
            "elasticity": experiments.elasticity_phase_times(tets, drop, frames=plan.elasticity_timing_frames,
                                                             threads=plan.threads, dtype=dtype)}

    for dtype in plan.local_dtypes:
        cases.append((f"Fig. 6: local vs global step per iteration, {_label(dtype)} local step",
                      lambda dtype=dtype: fig6(dtype)))

    def fig7() -> None:
        mesh, tets = mesh_pair()
        results["traces"] = {
            "arap": experiments.arap_energy_trace(mesh, script, iterations=plan.trace_iterations,
                                                  reference_iterations=plan.trace_reference_iterations,
                                                  threads=plan.threads),
            "elasticity": experiments.elasticity_energy_trace(tets, drop, iterations=plan.elasticity_trace_iterations,
                                                              threads=plan.threads),
        }

    cases.append(("Fig. 7: energy against solver time, same start for every fit", fig7))

    def validation() -> None:
        small = capsule(plan.validation_resolution)
        log(f"  {small.name} ({len(small.V):,} vertices), {plan.validation_iterations} iterations")
        results["validation"] = experiments.validate_arap_against_libigl(
            small, HandleScript(frames=plan.arap.frames), plan.validation_iterations, threads=plan.threads)
        results["seconds"] = time.perf_counter() - clock.get("start", time.perf_counter())
        results["load_average_at_end"] = list(os.getloadavg())

    cases.append(("ARAP against igl.arap_solve: converged energies", validation))
    return cases, results, rows


def run_apps(plan: AppsPlan = QUICK, cache: str | None = None, tables: bool = True,
             log: Callable[[str], None] = print, progress: bool = True) -> tuple[dict, list]:
    """Runs every stage of :func:`apps_cases`; returns (results, benchmark rows)."""
    cases, results, rows = apps_cases(plan, cache, tables, log, progress)
    for title, run in cases:
        log(title)
        run()
    return results, rows


def _plain_plan(plan: AppsPlan) -> dict:
    out = dataclasses.asdict(plan)
    for key in ("dtypes", "local_dtypes"):
        out[key] = [str(d).replace("torch.", "") for d in getattr(plan, key)]
    return out


def _json_default(x):
    """JSON for what json does not know: dtypes and NumPy scalars/arrays."""
    if isinstance(x, torch.dtype):
        return str(x).replace("torch.", "")
    if hasattr(x, "tolist"):
        return x.tolist()
    raise TypeError(f"not JSON serializable: {type(x).__name__}")


def markdown(results: dict, rows: list, machine: dict | None = None) -> str:
    """The applications report (Markdown)."""
    parts = ["# torchrot applications: the paper's tables and figures on built-in solver data", ""]
    if machine:
        parts += [f"Machine: {machine}", ""]
    parts += [f"Load average (1, 5, 15 min) at the start: {results['load_average_at_start']}, at the end: "
              f"{results['load_average_at_end']} (other processes share this machine: timings are medians).", ""]
    parts += ["## Recorded data (Fig. 5)", "", report.statistics_table(results["statistics"]), "",
              "![Fig. 5](fig5_data.png)", ""]
    dtypes = sorted({r["dtype"] if isinstance(r, dict) else r.dtype for r in rows})
    for dtype in dtypes:
        parts += [f"## Table 1 analogue ({dtype}, 1 thread): speed-up over torch.linalg.svd, "
                  "torchrot's scalar kernel", "", report.table1(rows, dtype=dtype), "",
                  f"## Table 2 analogue ({dtype}, 1 thread): vectorized torchrot over torch.linalg.svd and "
                  "libigl's McAdams et al. SVD", "", report.table2(rows, dtype=dtype), ""]
    for key, table in group_tables(rows).items():
        load = table_load(table)
        if load:
            parts.append(f"- {key[1]}, {key[2]}: {load.line()}")
    parts += [""] + ([legend(), ""] if any(row_value(r, "suspicion") for r in rows) else [])
    parts += ["## Local vs global step (Fig. 6)", ""]
    for label, timings in results["timings"].items():
        parts += [f"Local step in {label}:", "", report.phase_table(timings), ""]
    parts += [
              "![Fig. 6](fig6_local_global.png)", "", "## Energy against time (Fig. 7)", "",
              "![Fig. 7](fig7_energy_time.png)", ""]
    validation = results["validation"]
    parts += ["## ARAP against libigl", "",
              f"{validation['mesh']} ({validation['vertices']:,} vertices), {validation['iterations']} iterations "
              f"from frame {validation['start_frame']} with the handles {validation['jump_frames']} frames ahead:", "",
              "| solver | energy | relative difference to libigl | last relative change |", "|---|---|---|---|"]
    for fit, v in validation["fits"].items():
        parts.append(f"| {fit} | {v['energy']:.12g} | {v['relative_difference_to_libigl']:.1e} | "
                     f"{v['last_relative_change']:.1e} |")
    parts += [f"| igl.arap_solve | {validation['libigl']['energy']:.12g} | 0 | - |", ""]
    return "\n".join(parts)


def print_summary(results: dict, rows: list, log: Callable[[str], None] = print,
                  report_path: str | None = None) -> None:
    """Prints the tables (those wider than the terminal as a pointer to
    ``report_path``, the apps.md that holds them) and the libigl comparison."""
    where = report_path or "apps.md (--output)"
    log("\n## Recorded data (Fig. 5)\n")
    log(for_terminal(report.statistics_table(results["statistics"]), where))
    for dtype in sorted({r.dtype for r in rows}):
        log(f"\n## Table 1 analogue ({dtype}, 1 thread, recorded data): speed-up over torch.linalg.svd\n")
        log(for_terminal(report.table1(rows, dtype=dtype, narrow=True), where))
        log(f"\n## Table 2 analogue ({dtype}, 1 thread): vectorized torchrot\n")
        log(for_terminal(report.table2(rows, dtype=dtype, narrow=True), where))
    if any(r.suspicion for r in rows):
        log(legend())
    for label, timings in results["timings"].items():
        log(f"\n## Local vs global step per iteration, ms (Fig. 6), local step in {label}\n")
        log(for_terminal(report.phase_table(timings), where))
    validation = results["validation"]
    log(f"\n## ARAP against igl.arap_solve ({validation['mesh']}, {validation['vertices']:,} vertices), "
        "relative energy difference\n")
    for fit, v in validation["fits"].items():
        log(f"  {fit:10s} {v['relative_difference_to_libigl']:+.1e}")


def write_apps(results: dict, rows: list, folder: str, machine: dict | None = None) -> list[str]:
    """apps.json, apps.md and the three PNGs in ``folder``; returns the paths."""
    os.makedirs(folder, exist_ok=True)
    paths = {name: os.path.join(folder, name) for name in
             ("apps.json", "apps.md", "fig5_data.png", "fig6_local_global.png", "fig7_energy_time.png")}
    with open(paths["apps.json"], "w") as f:
        json.dump({"machine": machine, **results,
                   "rows": [r if isinstance(r, dict) else dataclasses.asdict(r) for r in rows]}, f, indent=1,
                  default=_json_default)
    with open(paths["apps.md"], "w") as f:
        f.write(markdown(results, rows, machine))
    try:
        figures.plot_fig5(results["statistics"], paths["fig5_data.png"])
        figures.plot_fig6(results["timings"], paths["fig6_local_global.png"])
        figures.plot_fig7(results["traces"], paths["fig7_energy_time.png"])
    except ImportError:
        print("matplotlib is not installed (pip install 'torchrot[bench]'): no figures written")
        return [paths["apps.json"], paths["apps.md"]]
    return list(paths.values())


def rewrite(folder: str) -> list[str]:
    """Writes apps.md and the PNGs again from ``folder``/apps.json (no timing is re-run)."""
    with open(os.path.join(folder, "apps.json")) as f:
        saved = json.load(f)
    machine, rows = saved.pop("machine", None), saved.pop("rows", [])
    return write_apps(saved, rows, folder, machine)


if __name__ == "__main__":
    import sys

    for path in rewrite(sys.argv[1] if len(sys.argv) > 1 else "results"):
        print(f"wrote {path}")
