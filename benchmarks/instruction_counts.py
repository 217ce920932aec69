"""Exact instructions per matrix of torchrot's kernels, by single-stepping.

    python benchmarks/instruction_counts.py [--kernels avx512 avx2] [--sizes 512 1536] [--repeats 3]
        [--authors PATH/TO/fast-rotation-fitting [--march haswell]]   (a few minutes)

The speed targets that do not hold are bounded by work (see speed_targets.py:
bytes, the computation alone, Cayley steps); this counts that work in
instructions, which this project's virtual machine cannot do with perf (no
hardware counters) and valgrind cannot do for AVX-512. A worker process runs
each call on two batch sizes under ``instruction_counter.c`` (ptrace
single-stepping, built here with the system C compiler) and the difference of
the two counts divided by the difference of the sizes is the cost per matrix
(per-call costs, Python's included, cancel). Each region is counted
``--repeats`` times and the smallest count kept: the interpreter and torch
now and then execute thousands of instructions of their own in one region and
not the next (measured: ~16,000 in one N = 512 region, 16 per matrix too few
in its row), and such work only ever adds. float32, one thread, warm data
recorded from the ARAP solver (the speed targets' data), cold fits on uniform
[0, 1] matrices; ``copy_`` for scale. With ``--authors PATH`` (a checkout of
ErisZhang/fast-rotation-fitting; Eigen's headers, see authors_kernel.py) the
paper authors' AVX kernels are counted too, on the same data in their tiles,
built for ``--march`` (haswell: AVX2, as torchrot's AVX2 kernel).
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
AUTHORS_PREFIX = "paper authors: "  # the names of the cases of the authors' kernels (--authors)
# Below a few hundred matrices a call's own path differs with the size (e.g.
# copy_'s, or one block against several), so per-call costs no longer cancel
# (measured at 32 and 64: negative differences).
MIN_SIZE = 256

__all__ = ["AUTHORS_PREFIX", "CASE_PREFIX", "KERNEL_PREFIX", "MIN_SIZE", "build_counter", "main"]


def _cases(n: int, authors_library: str | None) -> dict:
    """name -> a thunk running that call on the first n matrices (outputs
    preallocated), or (prepare, thunk) where the call needs its input restored
    first (outside the counted region)."""
    import torchrot
    from torchrot.bench import apps, data
    from torchrot.testing import make_matrices, soa_view, tiled_view

    M, init = data.pairs("arap", n, torch.float32, configs={"arap": apps.FULL.arap})
    M, init = M[:n].contiguous(), init[:n].contiguous()
    U = make_matrices("uniform", n, 0, torch.float32)
    G = make_matrices("gaussian", n, 1, torch.float32)
    R_u = torchrot.fit_rotation(U)
    M_soa, init_soa, out_soa = soa_view(M), soa_view(init), soa_view(torch.empty_like(M))
    M_tiles, R_tiles = tiled_view(M, 8), tiled_view(init, 8)  # the paper authors' tiles of 8 (authors_kernel.py)
    out_tiles = tiled_view(torch.empty_like(M), 8)
    out, buf = torch.empty_like(M), torch.empty_like(M)
    fit = torchrot.fit_rotation
    cases = {
        "copy_ of M": lambda: buf.copy_(M),
        "one-step, contiguous, out=": lambda: fit(M, init, max_iter=1, out=out),
        "one-step, SoA views, out=": lambda: fit(M_soa, init_soa, max_iter=1, out=out_soa),
        "one-step, tiles of 8, in place": lambda: fit(M_tiles, R_tiles, max_iter=1, out=R_tiles),
        "warm-start check (out= calls), contiguous": lambda: torch.ops.torchrot_bench.count_bad_warm_starts(init),
        "warm-start check (out= calls), SoA views": lambda: torch.ops.torchrot_bench.count_bad_warm_starts(init_soa),
        "converged from the warm start": lambda: fit(M, init, out=out),
        "converged from the warm start, tiles of 8": lambda: fit(M_tiles, R_tiles, out=out_tiles),
        "cold uniform, max_iter=1": lambda: fit(U, max_iter=1, out=out),
        "cold uniform, max_iter=2": lambda: fit(U, max_iter=2, out=out),
        "cold uniform, converged": lambda: fit(U, out=out),
        "backward (fit_rotation_backward)": lambda: torch.ops.torchrot.fit_rotation_backward(G, R_u, U, 1e-6),
    }
    if authors_library is not None:
        import authors_kernel

        kernels, groups = authors_kernel.load(authors_library), n // authors_kernel.TILE
        M_blocks, R_blocks = authors_kernel.blocks(M), authors_kernel.blocks(init)
        # Their iterated kernel carries R^T in place: it starts from the warm starts at every call.
        R_start, R_iterated = authors_kernel.blocks(init.mT), authors_kernel.blocks(init.mT)
        cases[AUTHORS_PREFIX + "one-step, tiles of 8, in place"] = \
            lambda: kernels["one-step"](M_blocks.data_ptr(), R_blocks.data_ptr(), groups)
        cases[AUTHORS_PREFIX + "iterated to tan^2 < 1e-15, from the warm start"] = (
            lambda: R_iterated.copy_(R_start),
            lambda: kernels["iterated"](M_blocks.data_ptr(), R_iterated.data_ptr(), groups))
    return cases


def _worker(kernels: list[str], sizes: list[int], repeats: int, authors_library: str | None,
            only: str | None = None) -> None:
    """Runs every case (or the one named ``only``) on every size ``repeats``
    times between SIGUSR1 and SIGUSR2 (the counter's region markers), after a
    warm-up call. It names the cases and the kernels that ran (a kernel the CPU
    lacks is capped by cpu_kernel) on stderr."""
    from torchrot.testing.kernels import cpu_kernel

    # The counter reports its counts on the stdout this process inherited:
    # whatever the worker prints (the ARAP recording's progress on a machine
    # without the data cached) goes to stderr instead.
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    torch.set_num_threads(1)  # the kernel runs on the traced thread
    cases = {n: _cases(n, authors_library) for n in sizes}
    if only is not None:
        cases = {n: {name: case for name, case in named.items() if name == only} for n, named in cases.items()}
    for name in cases[sizes[0]]:
        print(CASE_PREFIX + name, file=sys.stderr, flush=True)
    pid = os.getpid()
    for kernel in kernels:
        with cpu_kernel(kernel) as actual:
            print(KERNEL_PREFIX + actual, file=sys.stderr, flush=True)
            for name in cases[sizes[0]]:
                for n in sizes:
                    prepare, fn = cases[n][name] if isinstance(cases[n][name], tuple) else (None, cases[n][name])
                    fn()
                    for _ in range(repeats):
                        if prepare is not None:
                            prepare()
                        os.kill(pid, signal.SIGUSR1)
                        fn()
                        os.kill(pid, signal.SIGUSR2)


def build_counter(folder: str) -> str:
    """instruction_counter.c compiled in ``folder`` with the system C compiler; its path."""
    compiler = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    if compiler is None or not sys.platform.startswith("linux"):
        sys.exit("needs Linux (ptrace) and a C compiler")
    counter = os.path.join(folder, "instruction_counter")
    subprocess.run([compiler, "-O2", "-o", counter, os.path.join(HERE, "instruction_counter.c")], check=True)
    return counter


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kernels", nargs="+", default=None, help="default: the kernel this machine dispatches to")
    parser.add_argument("--sizes", type=int, nargs=2, default=[512, 1536])
    parser.add_argument("--repeats", type=int, default=3, help="counts per region; the smallest is kept")
    parser.add_argument("--authors", metavar="PATH", help="a checkout of ErisZhang/fast-rotation-fitting: count "
                        "the paper authors' AVX kernels too (authors_kernel.py)")
    parser.add_argument("--eigen", default="/usr/include/eigen3")
    parser.add_argument("--march", default="haswell", help="the authors' kernels' -march (haswell: AVX2)")
    parser.add_argument("--authors-library", help=argparse.SUPPRESS)
    parser.add_argument("--only", help=argparse.SUPPRESS)  # the worker of instruction_profile.py: one case
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if min(args.sizes) < MIN_SIZE or args.sizes[0] >= args.sizes[1]:
        parser.error(f"--sizes N1 N2 needs {MIN_SIZE} <= N1 < N2")
    if args.authors is not None and any(n % 8 for n in args.sizes):
        parser.error("--authors: the authors' kernels take tiles of 8 matrices; --sizes must be multiples of 8")
    if args.repeats < 1:
        parser.error("--repeats needs at least 1")
    if args.worker:
        _worker(args.kernels, args.sizes, args.repeats, args.authors_library, args.only)
        return
    import torchrot  # noqa: F401  (registers torch.ops.torchrot)

    kernels = args.kernels or [torch.ops.torchrot.cpu_kernel()]
    with tempfile.TemporaryDirectory() as tmp:
        counter = build_counter(tmp)
        worker = [counter, sys.executable, os.path.abspath(__file__), "--worker", "--kernels", *kernels,
                  "--sizes", *map(str, args.sizes), "--repeats", str(args.repeats)]
        if args.authors is not None:
            import authors_kernel

            worker += ["--authors-library", authors_kernel.compile_library(args.authors, args.eigen, tmp, args.march)]
        run = subprocess.run(worker, check=True, capture_output=True, text=True)
    repeated = [int(line) for line in run.stdout.split()]
    case_names = [line[len(CASE_PREFIX):] for line in run.stderr.splitlines() if line.startswith(CASE_PREFIX)]
    ran = [line[len(KERNEL_PREFIX):] for line in run.stderr.splitlines() if line.startswith(KERNEL_PREFIX)]
    n1, n2 = args.sizes
    per_kernel = len(case_names) * 2
    if len(repeated) != per_kernel * len(kernels) * args.repeats:
        sys.exit(f"expected {per_kernel * len(kernels) * args.repeats} counts, got {len(repeated)}")
    counts = [min(repeated[i:i + args.repeats]) for i in range(0, len(repeated), args.repeats)]
    print(f"instructions per matrix, float32, 1 thread ((count at N = {n2} - count at N = {n1}) / {n2 - n1}, "
          f"each count the least of {args.repeats})")
    print("| call | " + " | ".join(f"{k} (ran: {r})" if r != k else k for k, r in zip(kernels, ran)) + " |\n|---|"
          + "---|" * len(kernels))
    table = {k: counts[i * per_kernel:(i + 1) * per_kernel] for i, k in enumerate(kernels)}
    for j, name in enumerate(case_names):
        cells = [f"{(table[k][2 * j + 1] - table[k][2 * j]) / (n2 - n1):.1f}" for k in kernels]
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
