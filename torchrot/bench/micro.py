"""CPU microbenchmark: ns per matrix and accuracy of every method, same run.

Each row times one method on one data set of N matrices with
``torch.utils.benchmark`` (the median of several ``blocked_autorange`` runs,
each itself a median), beside ``torch.linalg.svd`` special Procrustes and a
plain ``copy_`` of the input into a preallocated tensor (the memory floor)
timed on the same data in the same run, and reports the accuracy of the same
call against float64 SVD. Data come from ``torchrot.testing``, the generators
the tests use, as (M, init) pairs of a local-global solver (``make_warm_start``).

Two parts:
  scaling: ns/matrix against N for the main methods (plotted log-log);
  methods: every method at one N, for each data set, dtype and thread count,
           torchrot at each instruction set, mode and variant, and the
           paper's comparison methods (``torchrot.methods``, group
           "paper method"), each with its failures shown, not hidden.
Beside them, each against its SVD counterpart in the same run: the
single-matrix call (single_matrix_overhead), a training step's rotation
layer (rotation_layer) and point-set registration (registration_rows).
"""
from __future__ import annotations

import json
import math
import os
import platform
import statistics
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import torch
import torch.utils.benchmark as tbench

import torchrot
from torchrot import baselines
from torchrot import methods as paper
from torchrot.reference import rigid_registration_svd, rotation_svd
from torchrot.testing import cpu_kernel, make_matrices, make_warm_start, registration_problem, soa_view

Tensor = torch.Tensor
ISAS = ("scalar", "default", "avx2", "avx512")
VARIANTS = ("newton", "conservative", "gershgorin")
WARM_DATA = ("warm", "warm_cond1e5")  # generated data whose init is close; recorded solver data pass warm=True
ACCURACY_SAMPLE = 1_000_000  # accuracy is measured on the first matrices of each data set
SLOW_MAX_N = 1_000_000  # SVD-based baselines are not run above this N
PAPER = "paper method"
FAILURE_THRESHOLD = 1e-3  # |R - R*|_F above this (or a non-finite result) counts as a failure
# Mueller et al.'s converged mode takes hundreds of steps per matrix (~1e5 ns/matrix in
# eager PyTorch, plus ~0.2 s per call of per-step overhead in its long tail): it is timed
# on the first matrices of each data set only, and with 1 thread only.
MUELLER_CONVERGED_SAMPLE_N = 2_000
# The comparison methods' default sample (all_methods): their ns/matrix is flat in N beyond ~1e4.
COMPARISON_N = 100_000


@dataclass
class Method:
    """A way to fit rotations, timed as ``run(M, init, out)``."""

    name: str
    run: Callable[[Tensor, Tensor, Tensor], Tensor]
    group: str  # "floor", "baseline", "torchrot" or "paper method"
    # what tables select on: "copy", "svd", "roma", "igl_double", "igl_single", "torchrot",
    # or the paper method's first author ("horn", "mueller", "higham", "fa3r", "kugelstadt")
    key: str = ""
    mode: str | None = None  # torchrot: "one_step", "converged_cold", "converged_warm", "one_step_new_output"
    variant: str | None = None  # torchrot's Cayley step estimate
    isa: str | None = None  # torchrot kernel to force (TORCHROT_CPU_CAPABILITY)
    warm_only: bool = False  # only meaningful where init is close (warm data)
    max_n: int | None = None
    float64_only: bool = False
    diagnostics: dict | None = None  # fit_rotation_info arguments: report iterations and fallbacks
    # Timed and measured on the first sample_n matrices where N is larger (for methods so
    # slow that ns/matrix no longer depends on N); the row reports the N actually used.
    sample_n: int | None = None
    # (M, init) -> (R, steps per matrix): the accuracy and the steps come from the same call
    iterations: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]] | None = None
    # Not re-run with more threads (a cost made of thousands of tiny-tensor steps only adds
    # thread-pool overhead there).
    max_threads: int | None = None
    # "aos": the data set's (N, 3, 3) tensors; "soa": the same values as structure-of-arrays
    # views (matrix index fastest, soa_view), made once per data set outside the timing
    layout: str = "aos"


@dataclass
class Row:
    part: str
    data: str
    method: str  # the display name; select rows on group, key, mode, variant and isa
    dtype: str
    n: int
    threads: int
    ns_per_matrix: float
    runs_ns: list = field(default_factory=list)
    isa: str | None = None
    group: str = ""
    key: str = ""
    mode: str | None = None
    variant: str | None = None
    layout: str = "aos"
    max_error: float | None = None  # max |R - R*|_F against float64 SVD
    median_error: float | None = None
    share_above_1e3: float | None = None  # share of matrices with |R - R*|_F > 1e-3 (or non-finite)
    failures: int | None = None  # number of matrices with |R - R*|_F > 1e-3 or a non-finite result
    max_shortfall: float | None = None  # max (tr(R*^T M) - tr(R^T M)) / |M|_F
    mean_iterations: float | None = None
    fallback_rate: float | None = None
    speedup_vs_svd: float | None = None
    time_vs_copy: float | None = None


def supported_isas() -> list[str]:
    """torchrot kernels this CPU can run, lowest first."""
    hardware = torch.backends.cpu.get_cpu_capability().lower()
    top = ISAS.index(hardware) if hardware in ISAS else 1
    return list(ISAS[: top + 1])


def forced_isa(isa: str | None):
    """Runs torchrot with kernel ``isa`` (None: the process default) in this thread."""
    return cpu_kernel(isa)


def _torchrot_methods(isa: str | None, label: str, variants: tuple[str, ...]) -> list[Method]:
    methods = []
    for variant in variants:
        methods.append(Method(
            f"torchrot 1-step warm, {variant}{label}",
            lambda M, init, out, v=variant: torchrot.fit_rotation(M, init, max_iter=1, variant=v, out=out),
            "torchrot", "torchrot", "one_step", variant, isa=isa, warm_only=True))
    for variant in variants:
        methods.append(Method(
            f"torchrot converged cold, {variant}{label}",
            lambda M, init, out, v=variant: torchrot.fit_rotation(M, variant=v, out=out),
            "torchrot", "torchrot", "converged_cold", variant, isa=isa,
            diagnostics={"variant": variant, "warm": False}))
    methods.append(Method(
        f"torchrot converged warm{label}",
        lambda M, init, out: torchrot.fit_rotation(M, init, out=out),
        "torchrot", "torchrot", "converged_warm", "conservative", isa=isa,
        diagnostics={"variant": "conservative", "warm": True}))
    return methods


def paper_methods(sample_n: int | None = None) -> list[Method]:
    """The comparison methods of the paper's Table 1 (``torchrot.methods``), batched
    PyTorch, same convention. Fixed-step warm starts only run on warm data, as
    torchrot's one-step rows; converged modes report their mean steps. ``sample_n``:
    run them on the first sample_n matrices of each data set only (a moderate N keeps
    the quick plan quick; they cost 0.5-5 us per matrix). They run with 1 thread only."""
    methods = [
        Method("Horn 1987 (eigh of 4x4 K)", lambda M, init, out: paper.horn(M), PAPER, max_n=SLOW_MAX_N),
        Method("Mueller 2016, 1 step from init", lambda M, init, out: paper.mueller(M, init, max_iter=1), PAPER,
               warm_only=True, max_n=SLOW_MAX_N),
        Method("Mueller 2016, 10 steps from init", lambda M, init, out: paper.mueller(M, init, max_iter=10),
               PAPER, warm_only=True, max_n=SLOW_MAX_N),
        Method(f"Mueller 2016, converged from init (cap {paper.MUELLER_CAP})",
               lambda M, init, out: paper.mueller(M, init), PAPER, sample_n=MUELLER_CONVERGED_SAMPLE_N,
               iterations=lambda M, init: paper.mueller(M, init, return_iterations=True), max_threads=1),
        Method("Higham 1986 polar, LU inverse", lambda M, init, out: paper.higham_polar(M), PAPER,
               max_n=SLOW_MAX_N, iterations=lambda M, init: paper.higham_polar(M, return_iterations=True)),
        Method("Higham 1986 polar, cofactor inverse", lambda M, init, out: paper.higham_polar(M, inverse="cofactor"),
               PAPER, max_n=SLOW_MAX_N,
               iterations=lambda M, init: paper.higham_polar(M, inverse="cofactor", return_iterations=True)),
        Method(f"FA3R 2018, {paper.FA3R_PAPER_ITERATIONS} steps (authors')", lambda M, init, out: paper.fa3r(M),
               PAPER, max_n=SLOW_MAX_N),
        Method("FA3R 2018, converged", lambda M, init, out: paper.fa3r(M, max_iter=None), PAPER, max_n=SLOW_MAX_N,
               iterations=lambda M, init: paper.fa3r(M, max_iter=None, return_iterations=True)),
        Method("Kugelstadt 2018, 1 Newton step from init", lambda M, init, out: paper.kugelstadt(M, init), PAPER,
               warm_only=True, max_n=SLOW_MAX_N),
    ]
    for method in methods:
        method.key = method.name.split()[0].lower()  # "horn", "mueller", "higham", "fa3r", "kugelstadt"
        # One thread: their cost is thousands of small batched tensor ops, which a
        # second thread only slows down (measured: Higham 1.3 -> 97 us per matrix).
        method.max_threads = 1
        if sample_n is not None:
            method.sample_n = sample_n if method.sample_n is None else min(sample_n, method.sample_n)
    return methods


def all_methods(isas: list[str] | None = None, variants: tuple[str, ...] = VARIANTS,
                first_touch: bool = True, comparison: bool = True,
                comparison_n: int | None = COMPARISON_N) -> list[Method]:
    """The floor, the baselines that are installed, torchrot per kernel and (with
    ``comparison``) the paper's comparison methods, on at most ``comparison_n``
    matrices per data set (None: all)."""
    methods = [
        Method("copy_ (memory floor)", lambda M, init, out: out.copy_(M), "floor", "copy"),
        Method("torch.linalg.svd", lambda M, init, out: rotation_svd(M), "baseline", "svd", max_n=SLOW_MAX_N),
    ]
    if baselines.available("roma"):
        methods.append(Method("roma.special_procrustes", lambda M, init, out: baselines.roma_special_procrustes(M),
                              "baseline", "roma", max_n=SLOW_MAX_N))
    if baselines.available("igl"):
        methods.append(Method("igl.fit_rotations (double)", lambda M, init, out: baselines.igl_fit_rotations(M),
                              "baseline", "igl_double", max_n=SLOW_MAX_N))
        methods.append(Method("igl.fit_rotations (single)",
                              lambda M, init, out: baselines.igl_fit_rotations(M, single_precision=True),
                              "baseline", "igl_single", max_n=SLOW_MAX_N))
    if isas is None:
        methods += _torchrot_methods(None, "", variants)
    else:
        for isa in isas:
            methods += _torchrot_methods(isa, f" [{isa}]", variants)
    # The paper's own layout: matrix index fastest (a solver's (3, 3, N) covariances).
    methods.append(Method("torchrot 1-step warm, conservative, SoA views",
                          lambda M, init, out: torchrot.fit_rotation(M, init, max_iter=1, out=out), "torchrot",
                          "torchrot", "one_step", "conservative", warm_only=True, layout="soa"))
    methods.append(Method("torchrot converged warm, SoA views", lambda M, init, out: torchrot.fit_rotation(
        M, init, out=out), "torchrot", "torchrot", "converged_warm", "conservative", layout="soa"))
    if first_touch:
        # Without out=: every call allocates a new output and pays its first-touch page faults
        # (fewer where it is on transparent huge pages, see csrc/cpu/huge_pages.h).
        methods.append(Method("torchrot 1-step warm, conservative, new output",
                              lambda M, init, out: torchrot.fit_rotation(M, init, max_iter=1), "torchrot",
                              "torchrot", "one_step_new_output", "conservative", warm_only=True))
    if comparison:
        methods += paper_methods(comparison_n)
    return methods


def median_seconds(fn: Callable[[], object], repeats: int, min_run_time: float, threads: int = 1) -> list[float]:
    """Per-call seconds of ``repeats`` independent ``blocked_autorange`` medians
    (the Timer sets the thread count itself: it defaults to 1). A call that
    alone takes ``min_run_time`` or more is timed one call at a time instead
    (``blocked_autorange`` would spend a first call estimating its block size)."""
    timer = tbench.Timer(stmt="fn()", globals={"fn": fn}, num_threads=threads)
    first = timer.timeit(1).median
    if first >= min_run_time:
        return [first] + [timer.timeit(1).median for _ in range(repeats - 1)]
    return [timer.blocked_autorange(min_run_time=min_run_time).median for _ in range(repeats)]


def interleaved_median_seconds(calls: dict[str, Callable[[], object]], rounds: int,
                               min_run_time: float) -> dict[str, float]:
    """Median seconds per call of each of ``calls`` over ``rounds`` rounds, each
    round timing every call once with median_seconds, so that slow drifts of a
    shared machine's load meet every call alike."""
    runs: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(rounds):
        for name, fn in calls.items():
            runs[name] += median_seconds(fn, 1, min_run_time)
    return {name: statistics.median(r) for name, r in runs.items()}


#: An interleaved sample lasts at least this long (seconds): shorter calls are
#: repeated back to back, so that the sample does not time the clock (a copy
#: of 1e3 float32 matrices takes ~1 us; their 72 KB stay in cache either way).
INTERLEAVED_MIN_SECONDS = 50e-6


def _interleaved_seconds(fn: Callable[[], object]) -> float:
    """Seconds per call of ``fn`` where it is called (no warm-up): one call,
    or, if that took less than INTERLEAVED_MIN_SECONDS, the mean of enough
    further calls back to back to last that long. Runs at the caller's
    thread count."""
    start = time.perf_counter()
    fn()
    first = time.perf_counter() - start
    if first >= INTERLEAVED_MIN_SECONDS:
        return first
    calls = math.ceil(INTERLEAVED_MIN_SECONDS / max(first, 1e-9))
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls


def accuracy(R: Tensor, M64: Tensor, R_star: Tensor) -> dict:
    """max/median |R - R*|_F, the share and number of failures (> FAILURE_THRESHOLD
    or non-finite) and the largest objective shortfall relative to |M|_F, against
    R* = rotation_svd(M64) (float64)."""
    # A non-finite result counts as infinitely wrong (a NaN would drop out of max and share).
    dist = torch.nan_to_num((R.double() - R_star).norm(dim=(-2, -1)), nan=math.inf)
    norm = M64.norm(dim=(-2, -1)).clamp_min(torch.finfo(torch.float64).tiny)
    shortfall = torch.nan_to_num(((R_star - R.double()) * M64).sum((-2, -1)) / norm, nan=math.inf)
    failed = dist > FAILURE_THRESHOLD
    return {
        "max_error": dist.max().item(),
        "median_error": dist.median().item(),
        "share_above_1e3": failed.double().mean().item(),
        "failures": int(failed.sum()),
        "max_shortfall": shortfall.max().item(),
    }


def _applicable(method: Method, warm: bool, n: int, dtype: torch.dtype, threads: int = 1) -> bool:
    if method.warm_only and not warm:
        return False
    if method.max_n is not None and n > method.max_n:
        return False
    if method.max_threads is not None and threads > method.max_threads:
        return False
    return not (method.float64_only and dtype != torch.float64)


def run_case(part: str, data: str, M: Tensor, init: Tensor, threads: int, methods: list[Method],
             repeats: int, min_run_time: float, log: Callable[[str], None] = print,
             warm: bool | None = None, slow_repeats: int | None = None) -> list[Row]:
    """Times every applicable method on one data set ``(M, init)`` ``(N, 3, 3)``
    named ``data`` (its rows' label); SVD and copy included. ``warm``: whether
    init is close to the answer, so the warm-start-only methods run (default:
    ``data in WARM_DATA``; recorded solver data are warm). ``slow_repeats``:
    timed runs of the methods with a ``sample_n`` (seconds per call; None: ``repeats``).

    The copy (key ``"copy"``) is timed interleaved: one sample after each
    other method (_interleaved_seconds), its row the median of those samples,
    so that it meets the caches as the fits do. Timed back to back, it would
    run within this VM's 32 MB last-level cache whatever the methods around
    it leave there (measured, N = 1e5 float32: back to back 0.83-1.03 ns per
    matrix; interleaved 0.85-4.4, depending on the method before it)."""
    n, dtype = M.shape[0], M.dtype
    warm = data in WARM_DATA if warm is None else warm
    out = torch.empty_like(M)
    layouts = {"aos": (M, init, out)}
    k = min(n, ACCURACY_SAMPLE)
    M64 = M[:k].double()
    R_star = rotation_svd(M64)
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    copy_method = next((m for m in methods if m.key == "copy"), None)
    copy_runs: list[float] = []  # one copy call after each other method
    # The copy last (a stable sort), so that its samples are in when its row is
    # made; each row is placed at its method's index, so the rows keep the methods' order.
    timed = sorted(enumerate(methods), key=lambda indexed: indexed[1] is copy_method)
    placed: dict[int, Row] = {}
    try:
        for index, method in timed:
            if not _applicable(method, warm, n, dtype, threads):
                continue
            # slow methods run on the first sample_n matrices (their ns/matrix is flat in N)
            used = n if method.sample_n is None else min(n, method.sample_n)
            if method.layout not in layouts:
                layouts[method.layout] = tuple(soa_view(x) for x in (M, init, out))
            M_used, init_used, out_used = (x[:used] for x in layouts[method.layout])
            k_used = min(k, used)
            with forced_isa(method.isa):
                # methods with a sample_n (the comparison methods, up to seconds per call): slow_repeats runs
                method_repeats = repeats if method.sample_n is None or slow_repeats is None else slow_repeats
                steps = None
                if method_repeats == 1 and method.iterations is not None and k_used == used:
                    # one call gives the time, the result and the steps (Mueller's converged mode: seconds)
                    timer = tbench.Timer(stmt="out.append(fn())", globals={"fn": lambda: method.iterations(
                        M_used, init_used), "out": (result := [])}, num_threads=threads)
                    runs = [timer.timeit(1).median]
                    R, steps = result[-1]
                elif method is copy_method and copy_runs:
                    runs = copy_runs
                else:
                    runs = median_seconds(lambda: method.run(M_used, init_used, out_used), method_repeats,
                                           min_run_time, threads)
                    if method.iterations is not None and k_used == used:
                        R, steps = method.iterations(M_used, init_used)
                    else:
                        R = method.run(M_used, init_used, out_used)
                        if method.iterations is not None:
                            steps = method.iterations(M[:k_used], init[:k_used])[1]
                info = None
                if method.diagnostics is not None:
                    start = init[:k] if method.diagnostics["warm"] else None
                    info = torchrot.fit_rotation_info(M[:k], start, variant=method.diagnostics["variant"])
            row = Row(part, data, method.name, str(dtype).replace("torch.", ""), used, threads,
                      ns_per_matrix=statistics.median(runs) / used * 1e9, runs_ns=[r / used * 1e9 for r in runs],
                      isa=method.isa, group=method.group, key=method.key, mode=method.mode,
                      variant=method.variant, layout=method.layout)
            if method.group != "floor":
                for key, value in accuracy(R[:k_used], M64[:k_used], R_star[:k_used]).items():
                    setattr(row, key, value)
            if info is not None:
                row.mean_iterations = info.iterations.double().mean().item()
                row.fallback_rate = (info.status == 1).double().mean().item()
            if steps is not None:
                row.mean_iterations = steps.double().mean().item()
            placed[index] = row
            log(f"  {part:7s} {data:13s} {row.dtype:7s} N={n:<9d} {threads}T  {method.name:48s} "
                f"{row.ns_per_matrix:10.2f} ns/matrix")
            if copy_method is not None and method is not copy_method:
                copy_runs.append(_interleaved_seconds(lambda: copy_method.run(M, init, out)))
    finally:
        torch.set_num_threads(previous_threads)
    rows: list[Row] = [placed[i] for i in sorted(placed)]
    by_key = {r.key: r for r in rows if r.key in ("svd", "copy")}
    svd, copy = by_key.get("svd"), by_key.get("copy")
    for row in rows:
        row.speedup_vs_svd = svd.ns_per_matrix / row.ns_per_matrix if svd else None
        row.time_vs_copy = row.ns_per_matrix / copy.ns_per_matrix if copy else None
    return rows


@dataclass
class Plan:
    """What to run: the scaling sweep and the method matrix."""

    scaling_data: tuple[str, ...] = ("warm", "uniform")
    scaling_n: tuple[int, ...] = (1_000, 3_000, 10_000)
    methods_data: tuple[str, ...] = ("warm", "warm_cond1e5", "rot60", "uniform")
    methods_n: int = 4_000
    dtypes: tuple[torch.dtype, ...] = (torch.float32,)
    threads: tuple[int, ...] = (1, 2)
    all_isas: bool = False
    variants: tuple[str, ...] = ("newton", "conservative")
    repeats: int = 3
    min_run_time: float = 0.02
    # the paper's comparison methods run on at most this many matrices per data set (None: methods_n);
    # their ns/matrix is flat in N from ~1e4 on (0.5-5 us per matrix of batched tensor ops)
    comparison_n: int | None = 500
    layer_batches: tuple[int, ...] = (64, 10_000)  # rotation_layer: nn.RotationFit forward + backward
    slow_repeats: int | None = 1  # timed runs of the comparison methods (up to seconds per call; None: repeats)
    overhead_run_time: float = 0.05  # min_run_time of the single-matrix call timings
    # registration_rows: rigid_registration against the SVD closed form, (problems, points)
    registration_shapes: tuple[tuple[int, int], ...] = ((1, 100), (64, 64), (1024, 64))
    registration_rounds: int = 5


#: The default ``python -m torchrot bench``: every part at small sizes (well under 2 minutes with
#: the applications part on 2 cores). ``--full``: the paper-scale grid.
QUICK = Plan()
FULL = Plan(scaling_n=(1_000, 10_000, 100_000, 1_000_000, 10_000_000), methods_n=1_000_000,
            dtypes=(torch.float32, torch.float64), all_isas=True, variants=VARIANTS, repeats=5, min_run_time=0.2,
            comparison_n=COMPARISON_N, slow_repeats=None, overhead_run_time=0.5, layer_batches=(64, 100_000),
            registration_shapes=((1, 100), (64, 64), (16, 1000), (1024, 64), (1, 100_000)), registration_rounds=9)


def make_pairs(data: str, n: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``(M, init)`` of a generated data set (``torchrot.testing.make_warm_start``, seed 0)."""
    return make_warm_start(data, n, seed=0, dtype=dtype)


def plan_cases(plan: Plan, pairs: Callable[[str, int, torch.dtype], tuple[Tensor, Tensor]] = make_pairs,
               warm: Callable[[str], bool] = WARM_DATA.__contains__,
               log: Callable[[str], None] = print) -> list[tuple[str, Callable[[], list[Row]]]]:
    """The plan as a list of (title, run) cases, each ``run()`` returning its
    rows: the scaling sweep (one case per data set) and the method matrix (one
    per dtype, thread count and data set). ``pairs(data, n, dtype)`` makes the
    data (default: generated); ``warm(data)`` says whether its init is close."""
    cases = []
    scaling = [m for m in all_methods(None, ("conservative",), first_touch=False, comparison=False)
               if m.mode != "one_step" or m.variant != "newton"]

    def sweep(data: str) -> list[Row]:
        rows = []
        for n in plan.scaling_n:
            M, init = pairs(data, n, torch.float32)
            rows += run_case("scaling", data, M, init, 1, scaling, plan.repeats, plan.min_run_time, log, warm(data),
                             plan.slow_repeats)
        return rows

    for data in plan.scaling_data:
        cases.append((f"scaling sweep, {data} data, N = {', '.join(f'{n:,}' for n in plan.scaling_n)}",
                      lambda data=data: sweep(data)))
    methods = all_methods(supported_isas() if plan.all_isas else None, plan.variants, comparison_n=plan.comparison_n)

    def matrix(data: str, dtype: torch.dtype, threads: int) -> list[Row]:
        M, init = pairs(data, plan.methods_n, dtype)
        return run_case("methods", data, M, init, threads, methods, plan.repeats, plan.min_run_time, log, warm(data),
                        plan.slow_repeats)

    for dtype in plan.dtypes:
        for threads in plan.threads:
            for data in plan.methods_data:
                cases.append((f"every method, {data} data, {str(dtype).replace('torch.', '')}, "
                              f"N = {plan.methods_n:,}, {threads} thread{'s' * (threads > 1)}",
                              lambda data=data, dtype=dtype, threads=threads: matrix(data, dtype, threads)))
    return cases


def run_plan(plan: Plan, log: Callable[[str], None] = print) -> list[Row]:
    """Every case of :func:`plan_cases` on generated data."""
    return [row for _, run in plan_cases(plan, log=log) for row in run()]


def single_matrix_overhead(min_run_time: float = 0.5) -> dict[str, float]:
    """Microseconds per call on one (3, 3) matrix, beside empty custom ops."""
    M = torch.randn(3, 3)
    R = torchrot.fit_rotation(M)
    out = torch.empty(3, 3)
    calls = {
        "empty custom op (1 argument)": lambda: torch.ops.torchrot._empty_op(M),
        "empty custom op (fit_rotation's signature and output)":
            lambda: torch.ops.torchrot._empty_fit_rotation(M, None, None, "conservative"),
        "torchrot.fit_rotation(M)": lambda: torchrot.fit_rotation(M),
        "torch.ops.torchrot.fit_rotation(M)": lambda: torch.ops.torchrot.fit_rotation(M),
        "torchrot.fit_rotation(M, out=out)": lambda: torchrot.fit_rotation(M, out=out),
        "torchrot.fit_rotation(M, R, max_iter=1, out=R)": lambda: torchrot.fit_rotation(M, R, max_iter=1, out=R),
        "torch.linalg.svd special Procrustes": lambda: rotation_svd(M),
    }
    return {name: statistics.median(median_seconds(fn, 3, min_run_time)) * 1e6 for name, fn in calls.items()}


def rotation_layer(batches: tuple[int, ...], min_run_time: float = 0.05, repeats: int = 3) -> list[dict]:
    """A training step's rotation layer: microseconds per forward + backward of
    ``torchrot.nn.RotationFit`` on a float32 ``(B, 3, 3)`` batch (gaussian
    network outputs), beside the same through SVD autograd (rotation_svd), the
    same step with a ``clone`` in the layer's place (what PyTorch's autograd
    engine and the loss's own ops cost: the floor of any layer) and a ``copy_``
    of the batch, timed in the same run, in interleaved rounds; 1 thread."""
    layer = torchrot.nn.RotationFit()
    results = []
    for batch in batches:
        M = make_matrices("gaussian", batch, 0, torch.float32).requires_grad_()
        G = make_matrices("gaussian", batch, 1, torch.float32)
        buffer = torch.empty_like(M)

        def step(fit):
            M.grad = None
            (fit(M) * G).sum().backward()

        calls = {"copy_": lambda: buffer.copy_(M.detach()), "svd": lambda: step(rotation_svd),
                 "floor": lambda: step(torch.clone), "torchrot": lambda: step(layer)}
        us = {name: seconds * 1e6 for name, seconds in interleaved_median_seconds(calls, repeats, min_run_time).items()}
        results.append({"batch": batch, "copy_us": us["copy_"], "svd_autograd_us": us["svd"],
                        "autograd_floor_us": us["floor"], "torchrot_us": us["torchrot"],
                        "torchrot_vs_svd": us["torchrot"] / us["svd"]})
    return results


def format_layer_table(results: list[dict]) -> str:
    lines = ["| batch | nn.RotationFit fwd+bwd (us) | SVD autograd fwd+bwd (us) | torchrot / SVD | "
             "clone in its place (us) | copy_ (us) |",
             "|---|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['batch']:,} | {r['torchrot_us']:.1f} | {r['svd_autograd_us']:.1f} | "
                     f"{r['torchrot_vs_svd']:.3f}x ({1 / r['torchrot_vs_svd']:.1f}x faster) | "
                     f"{r['autograd_floor_us']:.1f} | {r['copy_us']:.2f} |")
    return "\n".join(lines)


# Point-set registration: torchrot.rigid_registration beside the same closed
# form by SVD (torchrot.reference.rigid_registration_svd: Umeyama by
# torch.linalg.svd, as one writes it in PyTorch today), scale=True, on the
# tests' problems (torchrot.testing.registration_problem, noise 0.1), with a
# copy_ of x and y into preallocated tensors (the floor of reading the points
# once), timed in interleaved rounds at the caller's thread count; each row
# also gives torchrot's largest |R - R*| against the float64 SVD answer.
def registration_row(problems: int, points: int, dtype: torch.dtype, rounds: int,
                     min_run_time: float = 0.05) -> dict:
    """One row: us per call of each method (median of ``rounds`` interleaved
    rounds) and torchrot's largest rotation error against float64 SVD."""
    x, y, _ = registration_problem((problems,), n=points, seed=0, noise=0.1, dtype=dtype)
    x_copy, y_copy = torch.empty_like(x), torch.empty_like(y)
    calls = {
        "copy_": lambda: (x_copy.copy_(x), y_copy.copy_(y)),
        "svd": lambda: rigid_registration_svd(x, y, scale=True),
        "torchrot": lambda: torchrot.rigid_registration(x, y, scale=True),
    }
    for call in calls.values():  # warm-up
        call()
    us = {name: s * 1e6 for name, s in interleaved_median_seconds(calls, rounds, min_run_time).items()}
    reference, _, _ = rigid_registration_svd(x.double(), y.double(), scale=True)
    error = (torchrot.rigid_registration(x, y, scale=True).R.double() - reference).abs().max().item()
    return {"problems": problems, "points": points, "dtype": str(dtype).removeprefix("torch."),
            "copy_us": us["copy_"], "svd_us": us["svd"], "torchrot_us": us["torchrot"],
            "speedup_vs_svd": us["svd"] / us["torchrot"], "max_r_error": error}


def registration_rows(shapes, dtypes=(torch.float32,), rounds: int = 5, min_run_time: float = 0.05) -> list[dict]:
    """:func:`registration_row` for every dtype and (problems, points) shape
    (the main job's: ``Plan.registration_shapes``)."""
    return [registration_row(problems, points, dtype, rounds, min_run_time)
            for dtype in dtypes for problems, points in shapes]


def format_registration_table(rows: list[dict]) -> str:
    lines = ["| problems x points | dtype | copy_ of x, y | SVD closed form | torchrot | faster than SVD | max R error |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['problems']:,} x {r['points']:,} | {r['dtype']} | {r['copy_us']:.1f} | {r['svd_us']:.1f} "
                     f"| {r['torchrot_us']:.1f} | {r['speedup_vs_svd']:.1f}x | {r['max_r_error']:.1e} |")
    return "\n".join(lines)


def machine_info() -> dict:
    return {
        "torch": torch.__version__,
        "torchrot": torchrot.__version__,
        "torchrot_kernel": torch.ops.torchrot.cpu_kernel(),
        "aten_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "cores": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
    }


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def format_table(rows: list[Row]) -> str:
    """Markdown table: ns/matrix beside SVD and copy of the same run, accuracy."""
    header = ("| data | dtype | N | threads | method | ns/matrix | speedup vs SVD | time vs copy | max err | "
              "median err | share >1e-3 | failures | max shortfall | mean iters | fallback |")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in rows:
        lines.append(
            f"| {r.data} | {r.dtype} | {r.n:.0e} | {r.threads} | {r.method} | {r.ns_per_matrix:.2f} | "
            f"{_fmt(r.speedup_vs_svd, '.1f')} | {_fmt(r.time_vs_copy, '.2f')} | {_fmt(r.max_error, '.1e')} | "
            f"{_fmt(r.median_error, '.1e')} | {_fmt(r.share_above_1e3, '.2%')} | {_fmt(r.failures, 'd')} | "
            f"{_fmt(r.max_shortfall, '.1e')} | "
            f"{_fmt(r.mean_iterations, '.2f')} | {_fmt(r.fallback_rate, '.3%')} |"
        )
    return "\n".join(lines)


def plot_scaling(rows: list[Row], path: str) -> None:
    """PNG: ns/matrix against N (log-log), one line per method, a panel per data set."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scaling = [r for r in rows if r.part == "scaling"]
    data_sets = sorted({r.data for r in scaling}, key=[r.data for r in scaling].index)
    fig, axes = plt.subplots(1, len(data_sets), figsize=(6.5 * len(data_sets), 5), squeeze=False)
    for ax, data in zip(axes[0], data_sets):
        methods = sorted({r.method for r in scaling if r.data == data},
                         key=[r.method for r in scaling].index)
        for method in methods:
            pts = sorted((r.n, r.ns_per_matrix) for r in scaling if r.data == data and r.method == method)
            style = "--" if any(r.key == "copy" for r in scaling if r.method == method) else "-"
            ax.plot([p[0] for p in pts], [p[1] for p in pts], style, marker="o", label=method)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("N (matrices per call)")
        ax.set_ylabel("ns per matrix (median)")
        ax.set_title(f"{data} data, float32, 1 thread")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"torchrot vs baselines ({machine_info()['aten_cpu_capability']}, "
                 f"{machine_info()['processor']})")
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.1, top=0.86, wspace=0.2)  # tight_layout: seconds
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_results(rows: list[Row], overhead: dict[str, float], folder: str, layer: list[dict] | None = None,
                  registration: list[dict] | None = None) -> list[str]:
    """bench.json, bench.md and bench_scaling.png in ``folder``; returns the paths."""
    os.makedirs(folder, exist_ok=True)
    paths = [os.path.join(folder, name) for name in ("bench.json", "bench.md", "bench_scaling.png")]
    with open(paths[0], "w") as f:
        json.dump({"machine": machine_info(), "single_matrix_us": overhead, "rotation_layer": layer or [],
                   "registration": registration or [], "rows": [asdict(r) for r in rows]}, f, indent=1)
    with open(paths[1], "w") as f:
        f.write(f"# torchrot benchmark\n\nMachine: {machine_info()}\n\n")
        f.write("## Single-matrix call (microseconds)\n\n")
        for name, us in overhead.items():
            f.write(f"- {name}: {us:.2f}\n")
        if layer:
            f.write("\n## Rotation layer: forward + backward, float32, 1 thread\n\n" + format_layer_table(layer) + "\n")
        if registration:
            f.write("\n## Point-set registration: rigid_registration(x, y, scale=True), us per call, 1 thread\n\n"
                    + format_registration_table(registration) + "\n")
        for part in ("scaling", "methods"):
            part_rows = [r for r in rows if r.part == part]
            if part_rows:
                f.write(f"\n## {part}\n\n{format_table(part_rows)}\n")
    try:
        plot_scaling(rows, paths[2])
    except ImportError:
        print("matplotlib is not installed (pip install 'torchrot[bench]'): no plot written")
        paths.pop()
    return paths
