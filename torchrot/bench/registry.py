"""The methods the microbenchmark times: the memory floor, the baselines
that are installed (torch.linalg.svd, RoMa, libigl), torchrot in each mode,
variant, kernel and layout, and the paper's comparison methods
(``torchrot.methods``). Each is a :class:`Method`, timed as
``run(M, init, out)`` on ``(N, 3, 3)`` tensors."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchrot._constants import VARIANTS
from torchrot.baselines import available, igl_fit_rotations, roma_special_procrustes
from torchrot.fitting import fit_rotation
from torchrot.methods import FA3R_PAPER_ITERATIONS, MUELLER_CAP, fa3r, higham_polar, horn, kugelstadt, mueller
from torchrot.reference import rotation_svd
from torchrot.testing.kernels import available_cpu_kernels, cpu_kernel

__all__ = ["COMPARISON_N", "MUELLER_CONVERGED_SAMPLE_N", "Method", "PAPER", "SLOW_MAX_N", "VARIANTS", "WARM_DATA",
           "all_methods", "forced_isa", "paper_methods", "supported_isas"]

Tensor = torch.Tensor
WARM_DATA = ("warm", "warm_cond1e5")  # generated data whose init is close; recorded solver data pass warm=True
SLOW_MAX_N = 1_000_000  # SVD-based baselines are not run above this N
PAPER = "paper method"
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


def supported_isas() -> list[str]:
    """torchrot kernels this machine runs, lowest first."""
    return list(available_cpu_kernels())


def forced_isa(isa: str | None):
    """Runs torchrot with kernel ``isa`` (None: the process default) in this thread."""
    return cpu_kernel(isa)


def _torchrot_methods(isa: str | None, label: str, variants: tuple[str, ...]) -> list[Method]:
    methods = []
    for variant in variants:
        methods.append(Method(
            f"torchrot 1-step warm, {variant}{label}",
            lambda M, init, out, v=variant: fit_rotation(M, init, max_iter=1, variant=v, out=out),
            "torchrot", "torchrot", "one_step", variant, isa=isa, warm_only=True))
    for variant in variants:
        methods.append(Method(
            f"torchrot converged cold, {variant}{label}",
            lambda M, init, out, v=variant: fit_rotation(M, variant=v, out=out),
            "torchrot", "torchrot", "converged_cold", variant, isa=isa,
            diagnostics={"variant": variant, "warm": False}))
    methods.append(Method(
        f"torchrot converged warm{label}",
        lambda M, init, out: fit_rotation(M, init, out=out),
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
        Method("Horn 1987 (eigh of 4x4 K)", lambda M, init, out: horn(M), PAPER, max_n=SLOW_MAX_N),
        Method("Mueller 2016, 1 step from init", lambda M, init, out: mueller(M, init, max_iter=1), PAPER,
               warm_only=True, max_n=SLOW_MAX_N),
        Method("Mueller 2016, 10 steps from init", lambda M, init, out: mueller(M, init, max_iter=10),
               PAPER, warm_only=True, max_n=SLOW_MAX_N),
        Method(f"Mueller 2016, converged from init (cap {MUELLER_CAP})",
               lambda M, init, out: mueller(M, init), PAPER, sample_n=MUELLER_CONVERGED_SAMPLE_N,
               iterations=lambda M, init: mueller(M, init, return_iterations=True), max_threads=1),
        Method("Higham 1986 polar, LU inverse", lambda M, init, out: higham_polar(M), PAPER,
               max_n=SLOW_MAX_N, iterations=lambda M, init: higham_polar(M, return_iterations=True)),
        Method("Higham 1986 polar, cofactor inverse", lambda M, init, out: higham_polar(M, inverse="cofactor"),
               PAPER, max_n=SLOW_MAX_N,
               iterations=lambda M, init: higham_polar(M, inverse="cofactor", return_iterations=True)),
        Method(f"FA3R 2018, {FA3R_PAPER_ITERATIONS} steps (authors')", lambda M, init, out: fa3r(M),
               PAPER, max_n=SLOW_MAX_N),
        Method("FA3R 2018, converged", lambda M, init, out: fa3r(M, max_iter=None), PAPER, max_n=SLOW_MAX_N,
               iterations=lambda M, init: fa3r(M, max_iter=None, return_iterations=True)),
        Method("Kugelstadt 2018, 1 Newton step from init", lambda M, init, out: kugelstadt(M, init), PAPER,
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
    if available("roma"):
        methods.append(Method("roma.special_procrustes", lambda M, init, out: roma_special_procrustes(M),
                              "baseline", "roma", max_n=SLOW_MAX_N))
    if available("igl"):
        methods.append(Method("igl.fit_rotations (double)", lambda M, init, out: igl_fit_rotations(M),
                              "baseline", "igl_double", max_n=SLOW_MAX_N))
        methods.append(Method("igl.fit_rotations (single)",
                              lambda M, init, out: igl_fit_rotations(M, single_precision=True),
                              "baseline", "igl_single", max_n=SLOW_MAX_N))
    if isas is None:
        methods += _torchrot_methods(None, "", variants)
    else:
        for isa in isas:
            methods += _torchrot_methods(isa, f" [{isa}]", variants)
    # The paper's own layout: matrix index fastest (a solver's (3, 3, N) covariances).
    methods.append(Method("torchrot 1-step warm, conservative, SoA views",
                          lambda M, init, out: fit_rotation(M, init, max_iter=1, out=out), "torchrot",
                          "torchrot", "one_step", "conservative", warm_only=True, layout="soa"))
    methods.append(Method("torchrot converged warm, SoA views", lambda M, init, out: fit_rotation(
        M, init, out=out), "torchrot", "torchrot", "converged_warm", "conservative", layout="soa"))
    if first_touch:
        # Without out=: every call allocates a new output and pays its first-touch page faults
        # (fewer where it is on transparent huge pages, see csrc/cpu/huge_pages.h).
        methods.append(Method("torchrot 1-step warm, conservative, new output",
                              lambda M, init, out: fit_rotation(M, init, max_iter=1), "torchrot",
                              "torchrot", "one_step_new_output", "conservative", warm_only=True))
    if comparison:
        methods += paper_methods(comparison_n)
    return methods
