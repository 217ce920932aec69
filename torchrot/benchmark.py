"""CPU microbenchmark: ns per matrix and accuracy of every method, same run.

Each row times one method on one data set with ``torch.utils.benchmark``
(median of several blocked runs), beside ``torch.linalg.svd`` (special
Procrustes) and a plain ``copy_`` of the input into a preallocated tensor (the
memory floor), and reports the accuracy of the same call against float64 SVD.
Data come from ``torchrot.testing``, the generators the tests use.
"""
from __future__ import annotations

import json
import platform
import statistics
from dataclasses import asdict, dataclass, field
from typing import Callable

import torch
import torch.utils.benchmark as tbench

import torchrot
from torchrot.testing import make_warm_start, rotation_errors

# Data sets of the default run: warm-startable solver-like data and cold data.
DEFAULT_DATA = ("warm", "warm_cond1e5", "rot60", "uniform", "gaussian")
WARM_DATA = ("warm", "warm_cond1e5")


@dataclass
class Row:
    data: str
    method: str
    dtype: str
    n: int
    threads: int
    ns_per_matrix: float
    runs_ns: list = field(default_factory=list)
    max_error: float | None = None       # max |R - R*|_F vs float64 SVD
    median_error: float | None = None
    share_above_1e3: float | None = None  # share of matrices with |R - R*|_F > 1e-3
    max_shortfall: float | None = None   # max relative objective shortfall
    mean_iterations: float | None = None
    fallback_rate: float | None = None
    speedup_vs_svd: float | None = None
    time_vs_copy: float | None = None


@dataclass
class Method:
    name: str
    run: Callable[[], torch.Tensor]  # writes/returns rotations for the data set
    accuracy: bool = True
    info: Callable[[], tuple] | None = None  # (iterations, status) per matrix


def _median_seconds(fn: Callable[[], object], repeats: int, min_run_time: float) -> list[float]:
    """Per-call seconds of ``repeats`` independent blocked_autorange medians."""
    timer = tbench.Timer(stmt="fn()", globals={"fn": fn})
    return [timer.blocked_autorange(min_run_time=min_run_time).median for _ in range(repeats)]


def _methods(M: torch.Tensor, init: torch.Tensor, warm: bool) -> list[Method]:
    out = torch.empty_like(M)
    methods = [
        Method("copy_ (memory floor)", lambda: out.copy_(M), accuracy=False),
        Method("torch.linalg.svd", lambda: torchrot.rotation_svd(M)),
        Method(
            "torchrot converged, cold",
            lambda: torchrot.fit_rotation(M, out=out),
            info=lambda: torchrot.fit_rotation_info(M)[1:],
        ),
        Method(
            "torchrot converged, warm",
            lambda: torchrot.fit_rotation(M, init, out=out),
            info=lambda: torchrot.fit_rotation_info(M, init)[1:],
        ),
    ]
    if warm:
        for variant in ("newton", "conservative"):
            methods.append(
                Method(
                    f"torchrot 1-step warm ({variant})",
                    lambda variant=variant: torchrot.fit_rotation(M, init, max_iter=1, variant=variant, out=out),
                )
            )
    return methods


def run_benchmark(
    data: tuple[str, ...] = DEFAULT_DATA,
    n: int = 100_000,
    dtype: torch.dtype = torch.float32,
    threads: int = 1,
    repeats: int = 5,
    min_run_time: float = 0.2,
    log: Callable[[str], None] = print,
) -> list[Row]:
    """Times every method on every data set; returns one Row per (data, method)."""
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    rows: list[Row] = []
    try:
        for name in data:
            M, init = make_warm_start(name, n, seed=0, dtype=dtype)
            M64 = M.double()
            data_rows: list[Row] = []
            for method in _methods(M, init, warm=name in WARM_DATA):
                runs = _median_seconds(method.run, repeats, min_run_time)
                row = Row(name, method.name, str(dtype).replace("torch.", ""), n, threads,
                          ns_per_matrix=statistics.median(runs) / n * 1e9,
                          runs_ns=[r / n * 1e9 for r in runs])
                if method.accuracy:
                    err = rotation_errors(method.run(), M64)
                    dist = err["distance"]
                    row.max_error = dist.max().item()
                    row.median_error = dist.median().item()
                    row.share_above_1e3 = (dist > 1e-3).double().mean().item()
                    row.max_shortfall = err["shortfall"].max().item()
                if method.info is not None:
                    iterations, status = method.info()
                    row.mean_iterations = iterations.double().mean().item()
                    row.fallback_rate = (status == 1).double().mean().item()
                data_rows.append(row)
                log(f"  {name:14s} {method.name:34s} {row.ns_per_matrix:10.1f} ns/matrix")
            svd_ns = next(r.ns_per_matrix for r in data_rows if r.method == "torch.linalg.svd")
            copy_ns = next(r.ns_per_matrix for r in data_rows if r.method.startswith("copy_"))
            for row in data_rows:
                row.speedup_vs_svd = svd_ns / row.ns_per_matrix
                row.time_vs_copy = row.ns_per_matrix / copy_ns
            rows.extend(data_rows)
    finally:
        torch.set_num_threads(previous_threads)
    return rows


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def format_table(rows: list[Row]) -> str:
    """Markdown table of the rows (ns/matrix beside SVD and copy, accuracy)."""
    header = ("| data | method | ns/matrix | x SVD | x copy | max err | median err | >1e-3 | "
              "max shortfall | iters | fallback |")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in rows:
        lines.append(
            f"| {r.data} | {r.method} | {r.ns_per_matrix:.1f} | {r.speedup_vs_svd:.1f} | {r.time_vs_copy:.2f} | "
            f"{_fmt(r.max_error, '.1e')} | {_fmt(r.median_error, '.1e')} | {_fmt(r.share_above_1e3, '.2%')} | "
            f"{_fmt(r.max_shortfall, '.1e')} | {_fmt(r.mean_iterations, '.2f')} | {_fmt(r.fallback_rate, '.2%')} |"
        )
    return "\n".join(lines)


def machine_info() -> dict:
    return {
        "torch": torch.__version__,
        "torchrot": torchrot.__version__,
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
    }


def write_json(rows: list[Row], path: str) -> None:
    with open(path, "w") as f:
        json.dump({"machine": machine_info(), "rows": [asdict(r) for r in rows]}, f, indent=1)
