"""The speed targets of the fast-path work, measured in one process.

float32, 1 thread. Part 1, on N matrices recorded from the ARAP solver (the
paper-scale recording of ``python -m torchrot bench --full``: 57k-vertex
capsule, ~1e6 matrices, cached in ~/.cache/torchrot) with their previous
rotations as warm starts, timed interleaved, median of ``--rounds`` rounds:
``copy_`` of M into a preallocated tensor, the one-step update on
structure-of-arrays views (the paper's layout, ``torchrot.testing.soa_view``),
on contiguous (N, 3, 3) tensors (``out=``, in place and into a new output) and the converged fit
from the warm start (exact: its failures against float64 SVD are counted).
Part 2: the converged cold fit on uniform [0, 1] matrices (N = 1e5) against
``torch.linalg.svd`` special Procrustes. Part 3: ``torchrot.nn.RotationFit``
forward + backward against SVD autograd (``torchrot.bench.micro.rotation_layer``).
Between parts 2 and 3, what bounds the targets: bytes moved, the computation
alone with the data in cache, and the cost and number of Cayley steps.

    python benchmarks/speed_targets.py [--n 1000000] [--rounds 9] [--layer-batches 64 100000]
"""
from __future__ import annotations

import argparse
import os
import statistics

import torch

import torchrot
from torchrot.bench import apps, data, micro
from torchrot.testing import make_matrices, soa_view

def _interleaved(methods: dict, rounds: int, min_time: float) -> dict[str, float]:
    """Median seconds per call of each method over ``rounds`` rounds, each
    round timing every method once (the suite's timer, micro.median_seconds)."""
    runs: dict[str, list[float]] = {name: [] for name in methods}
    for _ in range(rounds):
        for name, fn in methods.items():
            runs[name] += micro.median_seconds(fn, 1, min_time)
    return {name: statistics.median(r) for name, r in runs.items()}


def _failures(R: torch.Tensor, M: torch.Tensor) -> int:
    M64 = M.double()
    return micro.accuracy(R, M64, torchrot.rotation_svd(M64))["failures"]


# Matrices whose inputs and output stay in cache (3 x 590 KB in float32, within
# this VM's last-level cache) and whose per-call cost (~3 us) is small against
# the batch's: their timings are the computation alone.
CACHED_N = 16384


def _bounds(M: torch.Tensor, init: torch.Tensor, U: torch.Tensor, rounds: int, min_time: float) -> None:
    """Prints what bounds the copy_-relative and SVD-relative targets, measured
    in this run: bytes (``torch.add(M, init, out=)`` moves what a warm-start
    call moves), the computation alone (data in cache), and Cayley steps (the
    cost of one, from max_iter = 3 against max_iter = 1, and how many a
    converged call executes against how many its matrices need)."""
    buf, out, out_u = torch.empty_like(M), torch.empty_like(M), torch.empty_like(U)
    Mc, Ic = M[:CACHED_N].clone(), init[:CACHED_N].clone()
    buf_c, out_c = torch.empty_like(Mc), torch.empty_like(Mc)
    fit = torchrot.fit_rotation
    big = {
        "copy_ of M": lambda: buf.copy_(M),
        "torch.add(M, init, out=)": lambda: torch.add(M, init, out=buf),
        "warm, max_iter=1": lambda: fit(M, init, max_iter=1, out=out),
        "warm, max_iter=3": lambda: fit(M, init, max_iter=3, out=out),
        "warm, converged": lambda: fit(M, init, out=out),
    }
    cached = {
        "copy_ of M": lambda: buf_c.copy_(Mc),
        "one-step": lambda: fit(Mc, Ic, max_iter=1, out=out_c),
        "converged warm": lambda: fit(Mc, Ic, out=out_c),
    }
    cold = {
        "cold, max_iter=1": lambda: fit(U, max_iter=1, out=out_u),
        "cold, max_iter=3": lambda: fit(U, max_iter=3, out=out_u),
        "cold, converged": lambda: fit(U, out=out_u),
    }
    ns = {k: v / M.shape[0] * 1e9 for k, v in _interleaved(big, rounds, min_time).items()}
    ns_c = {k: v / CACHED_N * 1e9 for k, v in _interleaved(cached, rounds, min_time).items()}
    ns_u = {k: v / U.shape[0] * 1e9 for k, v in _interleaved(cold, max(3, rounds // 3), min_time).items()}
    copy, elem = ns["copy_ of M"], M.element_size() * 9
    print(f"\nWhat bounds them (this run, ns/matrix):\n- bytes: a warm-start call reads M and init and writes R, "
          f"{3 * elem} B/matrix against copy_'s {2 * elem} B; torch.add(M, init, out=) moves the same bytes in "
          f"{ns['torch.add(M, init, out=)']:.2f} ns = {ns['torch.add(M, init, out=)'] / copy:.2f}x copy_ ({copy:.2f}).")
    print(f"- the computation alone (N = {CACHED_N:,}, data in cache): copy_ {ns_c['copy_ of M']:.2f}, one-step "
          f"{ns_c['one-step']:.2f} = {ns_c['one-step'] / copy:.2f}x the copy_ at N = {M.shape[0]:,}, converged warm "
          f"{ns_c['converged warm']:.2f} = {ns_c['converged warm'] / copy:.2f}x.")
    for name, t1, t3, conv, iters in (
        ("warm (recorded ARAP)", ns["warm, max_iter=1"], ns["warm, max_iter=3"], ns["warm, converged"],
         torchrot.fit_rotation_info(M, init)[1]),
        ("cold (uniform [0, 1])", ns_u["cold, max_iter=1"], ns_u["cold, max_iter=3"], ns_u["cold, converged"],
         torchrot.fit_rotation_info(U)[1]),
    ):
        step = (t3 - t1) / 2
        fixed = t1 - step
        print(f"- Cayley steps, {name}: a step costs {step:.2f} (max_iter 3 against 1), the rest of a call {fixed:.2f}; "
              f"converged {conv:.2f} = {fixed:.2f} + {(conv - fixed) / step:.2f} step-equivalents, while its matrices "
              f"need {iters.float().mean().item():.2f} steps on average (SIMD blocks step until their slowest lane "
              f"converges; the rest is the convergence and maximum checks).")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--min-time", type=float, default=0.1)
    parser.add_argument("--layer-batches", type=int, nargs="+", default=[64, 100_000])
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"machine: {micro.machine_info()}; load average {os.getloadavg()}")

    M, init = data.pairs("arap", args.n, torch.float32, configs={"arap": apps.FULL.arap})
    n = M.shape[0]
    M_soa, init_soa = soa_view(M), soa_view(init)
    buf, out, out_soa, R = torch.empty_like(M), torch.empty_like(M), soa_view(torch.empty_like(M)), init.clone()
    methods = {
        "copy_ of M (memory floor)": lambda: buf.copy_(M),
        "one-step, SoA views, out=": lambda: torchrot.fit_rotation(M_soa, init_soa, max_iter=1, out=out_soa),
        "one-step, contiguous, out=": lambda: torchrot.fit_rotation(M, init, max_iter=1, out=out),
        "one-step, contiguous, in place (out=init)": lambda: torchrot.fit_rotation(M, R, max_iter=1, out=R),
        "one-step, contiguous, new output": lambda: torchrot.fit_rotation(M, init, max_iter=1),
        "converged from the warm start, contiguous": lambda: torchrot.fit_rotation(M, init, out=out),
        "converged from the warm start, SoA views": lambda: torchrot.fit_rotation(M_soa, init_soa, out=out_soa),
    }
    ns = {k: v / n * 1e9 for k, v in _interleaved(methods, args.rounds, args.min_time).items()}
    copy = ns["copy_ of M (memory floor)"]
    print(f"\nrecorded ARAP data (57k-vertex capsule), N = {n:,}, float32, 1 thread, median of {args.rounds} rounds")
    print(f"{'method':44s} {'ns/matrix':>10s} {'x copy_':>8s}")
    for name, v in ns.items():
        print(f"{name:44s} {v:10.2f} {v / copy:8.2f}")
    converged_failures = _failures(torchrot.fit_rotation(M, init), M)
    one_step_failures = _failures(torchrot.fit_rotation(M, init, max_iter=1), M)
    print(f"failures (|R - R*|_F > {micro.FAILURE_THRESHOLD:g} or non-finite): one-step {one_step_failures:,} "
          f"({one_step_failures / n:.2%}), converged {converged_failures}")

    U = make_matrices("uniform", 100_000, 0, torch.float32)
    cold = _interleaved({"svd": lambda: torchrot.rotation_svd(U), "torchrot": lambda: torchrot.fit_rotation(U)},
                        max(3, args.rounds // 3), args.min_time)
    print(f"\nuniform [0, 1], N = 100,000, converged cold: torchrot {cold['torchrot'] / 1e5 * 1e9:.1f} ns/matrix, "
          f"torch.linalg.svd {cold['svd'] / 1e5 * 1e9:.1f}: {cold['svd'] / cold['torchrot']:.1f}x")

    _bounds(M, init, U, args.rounds, args.min_time)

    layer = micro.rotation_layer(tuple(args.layer_batches), min_run_time=args.min_time)
    print("\nnn.RotationFit forward + backward (us), float32, 1 thread:\n" + micro.format_layer_table(layer))

    rows = [
        ("one-step on SoA views <= 1.0x copy_", ns["one-step, SoA views, out="] / copy, 1.0),
        ("one-step on contiguous tensors <= 1.3x copy_", ns["one-step, contiguous, out="] / copy, 1.3),
        ("converged from the warm start, exact, <= 1.5x copy_", ns["converged from the warm start, contiguous"] / copy,
         1.5),
    ]
    print("\n| target | measured | holds |\n|---|---|---|")
    for name, value, bound in rows:
        print(f"| {name} | {value:.2f}x | {'yes' if value <= bound else '**no**'} |")
    print(f"| converged exact: 0 failures | {converged_failures} | {'yes' if converged_failures == 0 else '**no**'} |")
    speedup = cold["svd"] / cold["torchrot"]
    print(f"| converged cold, uniform, N = 1e5, >= 100x SVD | {speedup:.1f}x | {'yes' if speedup >= 100 else '**no**'} |")
    for r in layer:
        if r["batch"] == 64:
            print(f"| nn.RotationFit fwd+bwd, batch 64, <= 60 us and <= 0.15x SVD autograd | {r['torchrot_us']:.0f} us, "
                  f"{r['torchrot_vs_svd']:.3f}x | "
                  f"{'yes' if r['torchrot_us'] <= 60 and r['torchrot_vs_svd'] <= 0.15 else '**no**'} |")
        if r["batch"] == 100_000:
            x = 1 / r["torchrot_vs_svd"]
            print(f"| nn.RotationFit fwd+bwd, batch 1e5, >= 60x faster than SVD autograd | {x:.1f}x | "
                  f"{'yes' if x >= 60 else '**no**'} |")


if __name__ == "__main__":
    main()
