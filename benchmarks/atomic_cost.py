"""What making errors atomic costs the one-step warm start (issue: a call that
raises changes nothing).

``fit_rotation(M, init=R, max_iter=1, out=R)`` validates every warm start
before it writes (torch.ops.torchrot._count_bad_warm_starts, the same
vectorised check the fit applies) so that a bad one raises with R untouched;
when every warm start is clean the fit then skips its own check
(FitOptions::init_known_clean), so the pass replaces that check's work.
This times, interleaved in one process on the same data (warm, float32, N
matrices, 1 thread): a ``copy_`` of M into a preallocated tensor, the
validation pass alone, and the one-step update in place and into a separate
``out``; ns/matrix are medians of ``--repeats`` rounds.

    python benchmarks/atomic_cost.py [--n 1e6] [--repeats 9] [--dtype float32]
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import torch

import torchrot
from torchrot.testing import make_warm_start


def _seconds(fn, min_time: float = 0.2) -> float:
    """Median seconds of one call, over calls filling about min_time."""
    fn()
    times = []
    start = time.perf_counter()
    while time.perf_counter() - start < min_time or len(times) < 3:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=float, default=1e6)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    args = parser.parse_args()
    torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)
    n = int(args.n)
    M, R0 = make_warm_start("warm", n, 0, dtype)
    R = R0.clone()
    out = torch.empty_like(M)
    copy_target = torch.empty_like(M)
    cases = {"copy_ of M (memory floor)": lambda: copy_target.copy_(M)}
    if hasattr(torch.ops.torchrot, "_count_bad_warm_starts"):  # absent before the change: the "before" run
        cases["validation pass alone"] = lambda: torch.ops.torchrot._count_bad_warm_starts(R)
    cases |= {
        "one-step, in place (out=init)": lambda: torchrot.fit_rotation(M, R, max_iter=1, out=R),
        "one-step, out= separate": lambda: torchrot.fit_rotation(M, R0, max_iter=1, out=out),
    }
    samples = {name: [] for name in cases}
    for _ in range(args.repeats):
        for name, fn in cases.items():  # interleaved: every round times each case once
            R.copy_(R0)
            samples[name].append(_seconds(fn) / n * 1e9)
    print(f"{args.dtype}, N = {n:.0e}, 1 thread, kernel {torch.ops.torchrot.cpu_kernel()}, "
          f"load average {os.getloadavg()[0]:.1f}; median of {args.repeats} interleaved rounds")
    print("| case | ns/matrix |\n|---|---|")
    for name, values in samples.items():
        print(f"| {name} | {statistics.median(values):.2f} |")


if __name__ == "__main__":
    main()
