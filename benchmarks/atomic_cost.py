"""What making errors atomic costs the one-step warm start (issue: a call that
raises changes nothing).

``fit_rotation(M, init=R, max_iter=1, out=R)`` validates every warm start
before it writes (torch.ops.torchrot_bench.count_bad_warm_starts, the same
vectorised check the fit applies) so that a bad one raises with R untouched;
when every warm start is clean the fit then skips its own check
(FitOptions::init_known_clean), so the pass replaces that check's work.
This times, interleaved in one process on the same data (warm, float32, N
matrices, 1 thread): a ``copy_`` of M into a preallocated tensor, the
validation pass alone, and the one-step update in place and into a separate
``out``; ns/matrix are medians of ``--repeats`` interleaved rounds
(``torchrot.bench.timing.interleaved_median_seconds``).

    python benchmarks/atomic_cost.py [--n 1e6] [--repeats 9] [--dtype float32]
"""
from __future__ import annotations

import argparse

import torch

import torchrot
from torchrot.bench.machine import Load, load_average
from torchrot.bench.options import DTYPES, positive_int
from torchrot.bench.timing import interleaved_median_seconds
from torchrot.testing import make_warm_start

__all__ = ["main"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=positive_int, default=1_000_000)
    parser.add_argument("--repeats", type=positive_int, default=9)
    parser.add_argument("--min-time", type=float, default=0.2, help="seconds of calls per sample")
    parser.add_argument("--dtype", choices=sorted(DTYPES), default="float32")
    args = parser.parse_args()
    torch.set_num_threads(1)
    dtype = DTYPES[args.dtype]
    n = args.n
    M, R0 = make_warm_start("warm", n, 0, dtype)
    R = R0.clone()
    out = torch.empty_like(M)
    copy_target = torch.empty_like(M)
    cases = {"copy_ of M (memory floor)": lambda: copy_target.copy_(M)}
    if hasattr(torch.ops.torchrot_bench, "count_bad_warm_starts"):  # absent before the change: the "before" run
        cases["validation pass alone"] = lambda: torch.ops.torchrot_bench.count_bad_warm_starts(R)
    cases |= {
        "one-step, in place (out=init)": lambda: torchrot.fit_rotation(M, R, max_iter=1, out=R),
        "one-step, out= separate": lambda: torchrot.fit_rotation(M, R0, max_iter=1, out=out),
    }
    before = load_average()
    seconds = interleaved_median_seconds(cases, args.repeats, args.min_time)
    print(f"{args.dtype}, N = {n:.0e}, 1 thread, kernel {torch.ops.torchrot.cpu_kernel()}; median of "
          f"{args.repeats} interleaved rounds; {Load.around(before).line()}")
    print("| case | ns/matrix |\n|---|---|")
    for name, s in seconds.items():
        print(f"| {name} | {s / n * 1e9:.2f} |")


if __name__ == "__main__":
    main()
