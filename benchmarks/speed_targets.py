"""The speed targets of the fast-path work, measured in one process.

float32, 1 thread. Part 1, on N matrices recorded from the ARAP solver (the
paper-scale recording of ``python -m torchrot bench --full``: 57k-vertex
capsule, ~1e6 matrices, cached in ~/.cache/torchrot) with their previous
rotations as warm starts, timed interleaved, median of ``--rounds`` rounds:
``copy_`` of M into a preallocated tensor, the one-step update on
structure-of-arrays views (the paper's layout, ``torchrot.testing.soa_view``),
on contiguous (N, 3, 3) tensors (``out=``, in place and into a new output), the
converged fit from the warm start (exact: its failures against float64 SVD are
counted), ``torch.add(M, init, out=)``, which moves a warm-start call's
bytes, and the check of the warm starts that ``out=`` calls make before
writing. Part 2: the cold fit on uniform [0, 1] matrices (N = 1e5; converged,
and one and two steps) against ``torch.linalg.svd`` special Procrustes. Part 3: ``torchrot.nn.RotationFit``
forward + backward against SVD autograd (``torchrot.bench.workloads.rotation_layer``).
Between parts 2 and 3, what bounds the targets, from those timings (bytes
moved, the cost and number of Cayley steps) and from the computation alone
with the data in cache, timed there.

    python benchmarks/speed_targets.py [--n 1000000] [--rounds 9] [--layer-batches 64 100000]
"""
from __future__ import annotations

import argparse

import torch

import torchrot
from torchrot.bench import apps, data
from torchrot.bench.accuracy import FAILURE_THRESHOLD, accuracy
from torchrot.bench.machine import Load, load_average, machine_info
from torchrot.bench.tables import format_layer_table
from torchrot.bench.timing import interleaved_median_seconds
from torchrot.bench.workloads import rotation_layer
from torchrot.testing import make_matrices, soa_view

__all__ = ["main"]


def _failures(R: torch.Tensor, M64: torch.Tensor, R_svd: torch.Tensor) -> int:
    """Failures of R against the float64 SVD solution R_svd of M64 (torchrot.bench.accuracy)."""
    return accuracy(R, M64, R_svd)["failures"]


# The timings parts 1 and 2 share with _bounds and the target table.
COPY = "copy_ of M (memory floor)"
ADD = "torch.add(M, init, out=) (a warm call's bytes)"
VALIDATE = "warm-start check before writing (in out= calls)"
ONE_STEP = "one-step, contiguous, out="
CONVERGED = "converged from the warm start, contiguous"
SVD, COLD = "svd", "torchrot"
COLD_1, COLD_2 = (f"torchrot, max_iter={k}" for k in (1, 2))


# Matrices whose inputs and output stay in cache (3 x 590 KB in float32, within
# a last-level cache of a few MB) and whose per-call cost (~3 us) is small against
# the batch's: their timings are the computation alone.
CACHED_N = 16384


def _bounds(ns: dict[str, float], cold_ns: dict[str, float], M: torch.Tensor, init: torch.Tensor,
            warm_steps: torch.Tensor, U: torch.Tensor, rounds: int, min_time: float) -> None:
    """Prints what bounds the copy_-relative and SVD-relative targets from the
    timings of parts 1 and 2 (``ns``, ``cold_ns``: ns/matrix; ``warm_steps``:
    part 1's converged fit's steps per matrix): bytes
    (``torch.add(M, init, out=)`` moves what a warm-start call moves), the
    check of the warm starts that out= calls make before writing, Cayley
    steps (the cost of one, from cold fits of max_iter = 2 against 1, and the
    steps a converged call takes against those its matrices need), and, timed
    here, the computation alone (data in cache)."""
    Mc, Ic = M[:CACHED_N].clone(), init[:CACHED_N].clone()
    buf_c, out_c = torch.empty_like(Mc), torch.empty_like(Mc)
    fit = torchrot.fit_rotation
    cached = {
        "copy_ of M": lambda: buf_c.copy_(Mc),
        "one-step": lambda: fit(Mc, Ic, max_iter=1, out=out_c),
        "converged warm": lambda: fit(Mc, Ic, out=out_c),
    }
    ns_c = {k: v / CACHED_N * 1e9 for k, v in interleaved_median_seconds(cached, rounds, min_time).items()}
    copy, add, elem = ns[COPY], ns[ADD], M.element_size() * 9
    print(f"\nWhat bounds them (this run, ns/matrix):\n- bytes: a warm-start call reads M and init and writes R, "
          f"{3 * elem} B/matrix against copy_'s {2 * elem} B; torch.add(M, init, out=) moves the same bytes in "
          f"{add:.2f} ns = {add / copy:.2f}x copy_ ({copy:.2f}), both from part 1. A call with out= first checks "
          f"every warm start, so that one that raises leaves out as it was: {ns[VALIDATE]:.2f} of the one-step's "
          f"{ns[ONE_STEP]:.2f} (it reads init once more; the fit then skips its own check).")
    print(f"- the computation alone (N = {CACHED_N:,}, data in cache): copy_ {ns_c['copy_ of M']:.2f}, one-step "
          f"{ns_c['one-step']:.2f} = {ns_c['one-step'] / copy:.2f}x the copy_ at N = {M.shape[0]:,}, converged warm "
          f"{ns_c['converged warm']:.2f} = {ns_c['converged warm'] / copy:.2f}x.")
    warm_steps = warm_steps.float()
    cold_steps = torchrot.fit_rotation_info(U)[1].float()
    step = cold_ns[COLD_2] - cold_ns[COLD_1]
    single = (warm_steps < 2).float().mean().item()
    extra = ns[CONVERGED] - ns[ONE_STEP]
    print(f"- Cayley steps: a step costs {step:.2f} (cold, max_iter 2 against 1: one more step, with the step loop's "
          f"bookkeeping; max_iter=1 runs the one-step's inlined path).")
    print(f"  Warm (recorded ARAP): its matrices need {warm_steps.mean().item():.2f} steps on average, but only "
          f"{single:.1%} need one, so a SIMD block all but always takes two; converged "
          f"{ns[CONVERGED]:.2f} = the one-step {ns[ONE_STEP]:.2f} "
          f"+ {extra / step:.2f} step-equivalents (the second step, and the convergence and maximum checks of each).")
    print(f"  Cold (uniform [0, 1]): its matrices need {cold_steps.mean().item():.2f} steps on average "
          f"({(cold_steps > 2).float().mean().item():.1%} more than two: the first step, with the maximal objective "
          f"as its estimate, lands on the maximum and the second confirms); max_iter=1 {cold_ns[COLD_1]:.2f} (the "
          f"cube start, the maximal objective and that step), max_iter=2 {cold_ns[COLD_2]:.2f}, converged "
          f"{cold_ns[COLD]:.2f} (max_iter=2 and converged mode's maximum check and bookkeeping).")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--min-time", type=float, default=0.1)
    parser.add_argument("--layer-batches", type=int, nargs="+", default=[64, 100_000])
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"machine: {machine_info()}")
    before = load_average()

    M, init = data.pairs("arap", args.n, torch.float32, configs={"arap": apps.FULL.arap})
    n = M.shape[0]
    M_soa, init_soa = soa_view(M), soa_view(init)
    buf, out, out_soa, R = torch.empty_like(M), torch.empty_like(M), soa_view(torch.empty_like(M)), init.clone()
    methods = {
        COPY: lambda: buf.copy_(M),
        ADD: lambda: torch.add(M, init, out=buf),
        VALIDATE: lambda: torch.ops.torchrot_bench.count_bad_warm_starts(init),
        "one-step, SoA views, out=": lambda: torchrot.fit_rotation(M_soa, init_soa, max_iter=1, out=out_soa),
        ONE_STEP: lambda: torchrot.fit_rotation(M, init, max_iter=1, out=out),
        "one-step, contiguous, in place (out=init)": lambda: torchrot.fit_rotation(M, R, max_iter=1, out=R),
        "one-step, contiguous, new output": lambda: torchrot.fit_rotation(M, init, max_iter=1),
        CONVERGED: lambda: torchrot.fit_rotation(M, init, out=out),
        "converged from the warm start, SoA views": lambda: torchrot.fit_rotation(M_soa, init_soa, out=out_soa),
    }
    ns = {k: v / n * 1e9 for k, v in interleaved_median_seconds(methods, args.rounds, args.min_time).items()}
    copy = ns[COPY]
    print(f"\nrecorded ARAP data (57k-vertex capsule), N = {n:,}, float32, 1 thread, median of {args.rounds} rounds; "
          f"{Load.around(before).line()}")
    print(f"{'method':44s} {'ns/matrix':>10s} {'x copy_':>8s}")
    for name, v in ns.items():
        print(f"{name:44s} {v:10.2f} {v / copy:8.2f}")
    M64 = M.double()
    R_svd = torchrot.rotation_svd(M64)
    R_converged, warm_steps, _ = torchrot.fit_rotation_info(M, init)
    converged_failures = _failures(R_converged, M64, R_svd)
    one_step_failures = _failures(torchrot.fit_rotation(M, init, max_iter=1), M64, R_svd)
    print(f"failures (|R - R*|_F > {FAILURE_THRESHOLD:g} or non-finite): one-step {one_step_failures:,} "
          f"({one_step_failures / n:.2%}), converged {converged_failures}")

    U = make_matrices("uniform", 100_000, 0, torch.float32)
    cold_calls = {SVD: lambda: torchrot.rotation_svd(U), COLD: lambda: torchrot.fit_rotation(U),
                  COLD_1: lambda: torchrot.fit_rotation(U, max_iter=1),
                  COLD_2: lambda: torchrot.fit_rotation(U, max_iter=2)}
    cold = interleaved_median_seconds(cold_calls, args.rounds, args.min_time)
    cold_ns = {k: v / U.shape[0] * 1e9 for k, v in cold.items()}
    print(f"\nuniform [0, 1], N = 100,000, converged cold: torchrot {cold_ns[COLD]:.1f} ns/matrix, "
          f"torch.linalg.svd {cold_ns[SVD]:.1f}: {cold[SVD] / cold[COLD]:.1f}x")

    _bounds(ns, cold_ns, M, init, warm_steps, U, args.rounds, args.min_time)

    layer = rotation_layer(tuple(args.layer_batches), min_run_time=args.min_time)
    print("\nnn.RotationFit forward + backward (us), float32, 1 thread:\n" + format_layer_table(layer))

    rows = [
        ("one-step on SoA views <= 1.0x copy_", ns["one-step, SoA views, out="] / copy, 1.0),
        ("one-step on contiguous tensors <= 1.3x copy_", ns[ONE_STEP] / copy, 1.3),
        ("converged from the warm start, exact, <= 1.5x copy_", ns[CONVERGED] / copy, 1.5),
    ]
    print("\n| target | measured | holds |\n|---|---|---|")
    for name, value, bound in rows:
        print(f"| {name} | {value:.2f}x | {'yes' if value <= bound else '**no**'} |")
    print(f"| converged exact: 0 failures | {converged_failures} | "
          f"{'yes' if converged_failures == 0 else '**no**'} |")
    speedup = cold[SVD] / cold[COLD]
    print(f"| converged cold, uniform, N = 1e5, >= 100x SVD | {speedup:.1f}x | "
          f"{'yes' if speedup >= 100 else '**no**'} |")
    for r in layer:
        if r["batch"] == 64:
            print(f"| nn.RotationFit fwd+bwd, batch 64, <= 60 us and <= 0.15x SVD autograd | "
                  f"{r['torchrot_us']:.0f} us, "
                  f"{r['torchrot_vs_svd']:.3f}x (a clone in its place: {r['autograd_floor_us']:.0f} us) | "
                  f"{'yes' if r['torchrot_us'] <= 60 and r['torchrot_vs_svd'] <= 0.15 else '**no**'} |")
        if r["batch"] == 100_000:
            x = 1 / r["torchrot_vs_svd"]
            print(f"| nn.RotationFit fwd+bwd, batch 1e5, >= 60x faster than SVD autograd | {x:.1f}x | "
                  f"{'yes' if x >= 60 else '**no**'} |")


if __name__ == "__main__":
    main()
