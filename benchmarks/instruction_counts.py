"""Exact instructions per matrix of torchrot's kernels, by single-stepping.

    python benchmarks/instruction_counts.py [--kernels avx512 avx2] [--sizes 512 1536]   (a few minutes)

The speed targets that do not hold are bounded by work (see speed_targets.py:
bytes, the computation alone, Cayley steps); this counts that work in
instructions, which this project's virtual machine cannot do with perf (no
hardware counters) and valgrind cannot do for AVX-512. A worker process runs
each call on two batch sizes under ``instruction_counter.c`` (ptrace
single-stepping, built here with the system C compiler) and the difference of
the two counts divided by the difference of the sizes is the cost per matrix
(per-call costs, Python's included, cancel). float32, one thread, warm data
recorded from the ARAP solver (the speed targets' data), cold fits on uniform
[0, 1] matrices; ``copy_`` for scale.
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
CASE_PREFIX = "case: "  # the worker names its cases on stderr, in the order it counts them
KERNEL_PREFIX = "kernel: "  # and the kernel each column ran on
# Below a few hundred matrices a call's own path differs with the size (e.g.
# copy_'s, or one block against several), so per-call costs no longer cancel
# (measured at 32 and 64: negative differences).
MIN_SIZE = 256

__all__ = ["MIN_SIZE", "main"]


def _cases(n: int) -> dict:
    """name -> a thunk running that call on the first n matrices (outputs preallocated)."""
    import torchrot
    from torchrot.bench import apps, data
    from torchrot.testing import make_matrices, soa_view

    M, init = data.pairs("arap", n, torch.float32, configs={"arap": apps.FULL.arap})
    M, init = M[:n].contiguous(), init[:n].contiguous()
    U = make_matrices("uniform", n, 0, torch.float32)
    G = make_matrices("gaussian", n, 1, torch.float32)
    R_u = torchrot.fit_rotation(U)
    M_soa, init_soa, out_soa = soa_view(M), soa_view(init), soa_view(torch.empty_like(M))
    out, buf = torch.empty_like(M), torch.empty_like(M)
    fit = torchrot.fit_rotation
    return {
        "copy_ of M": lambda: buf.copy_(M),
        "one-step, contiguous, out=": lambda: fit(M, init, max_iter=1, out=out),
        "one-step, SoA views, out=": lambda: fit(M_soa, init_soa, max_iter=1, out=out_soa),
        "warm-start check (out= calls), contiguous": lambda: torch.ops.torchrot_bench.count_bad_warm_starts(init),
        "warm-start check (out= calls), SoA views": lambda: torch.ops.torchrot_bench.count_bad_warm_starts(init_soa),
        "converged from the warm start": lambda: fit(M, init, out=out),
        "cold uniform, max_iter=1": lambda: fit(U, max_iter=1, out=out),
        "cold uniform, max_iter=2": lambda: fit(U, max_iter=2, out=out),
        "cold uniform, converged": lambda: fit(U, out=out),
        "backward (fit_rotation_backward)": lambda: torch.ops.torchrot.fit_rotation_backward(G, R_u, U, 1e-6),
    }


def _worker(kernels: list[str], sizes: list[int]) -> None:
    """Runs every case on every size between SIGUSR1 and SIGUSR2 (the counter's
    region markers), after a warm-up call. It names the cases and the kernels
    that ran (a kernel the CPU lacks is capped by cpu_kernel) on stderr."""
    from torchrot.testing.kernels import cpu_kernel

    # The counter reports its counts on the stdout this process inherited:
    # whatever the worker prints (the ARAP recording's progress on a machine
    # without the data cached) goes to stderr instead.
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    torch.set_num_threads(1)  # the kernel runs on the traced thread
    cases = {n: _cases(n) for n in sizes}
    for name in cases[sizes[0]]:
        print(CASE_PREFIX + name, file=sys.stderr, flush=True)
    pid = os.getpid()
    for kernel in kernels:
        with cpu_kernel(kernel) as actual:
            print(KERNEL_PREFIX + actual, file=sys.stderr, flush=True)
            for name in cases[sizes[0]]:
                for n in sizes:
                    fn = cases[n][name]
                    fn()
                    os.kill(pid, signal.SIGUSR1)
                    fn()
                    os.kill(pid, signal.SIGUSR2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kernels", nargs="+", default=None, help="default: the kernel this machine dispatches to")
    parser.add_argument("--sizes", type=int, nargs=2, default=[512, 1536])
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if min(args.sizes) < MIN_SIZE or args.sizes[0] >= args.sizes[1]:
        parser.error(f"--sizes N1 N2 needs {MIN_SIZE} <= N1 < N2")
    if args.worker:
        _worker(args.kernels, args.sizes)
        return
    import torchrot  # noqa: F401  (registers torch.ops.torchrot)

    kernels = args.kernels or [torch.ops.torchrot.cpu_kernel()]
    compiler = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    if compiler is None or not sys.platform.startswith("linux"):
        sys.exit("needs Linux (ptrace) and a C compiler")
    with tempfile.TemporaryDirectory() as tmp:
        counter = os.path.join(tmp, "instruction_counter")
        subprocess.run([compiler, "-O2", "-o", counter, os.path.join(HERE, "instruction_counter.c")], check=True)
        worker = [counter, sys.executable, os.path.abspath(__file__), "--worker", "--kernels", *kernels,
                  "--sizes", *map(str, args.sizes)]
        run = subprocess.run(worker, check=True, capture_output=True, text=True)
    counts = [int(line) for line in run.stdout.split()]
    case_names = [line[len(CASE_PREFIX):] for line in run.stderr.splitlines() if line.startswith(CASE_PREFIX)]
    ran = [line[len(KERNEL_PREFIX):] for line in run.stderr.splitlines() if line.startswith(KERNEL_PREFIX)]
    n1, n2 = args.sizes
    per_kernel = len(case_names) * 2
    if len(counts) != per_kernel * len(kernels):
        sys.exit(f"expected {per_kernel * len(kernels)} counts, got {len(counts)}")
    print(f"instructions per matrix, float32, 1 thread ((count at N = {n2} - count at N = {n1}) / {n2 - n1})")
    print("| call | " + " | ".join(f"{k} (ran: {r})" if r != k else k for k, r in zip(kernels, ran)) + " |\n|---|"
          + "---|" * len(kernels))
    table = {k: counts[i * per_kernel:(i + 1) * per_kernel] for i, k in enumerate(kernels)}
    for j, name in enumerate(case_names):
        cells = [f"{(table[k][2 * j + 1] - table[k][2 * j]) / (n2 - n1):.1f}" for k in kernels]
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
