"""Times the device-generic path (torchrot.fit_rotation_reference) on CPU tensors.

Interleaved in one process, median of several runs, ns per matrix, 1 thread,
N = 1e5 uniform float32 (torchrot.testing.make_matrices("uniform", ...)):
copy_ of M into a preallocated tensor (memory floor), torch.linalg.svd special
Procrustes (torchrot.rotation_svd), fit_rotation_reference eager (the masked
(..., 3, 3) implementation), the structure-of-arrays path torchrot.generic
eager and under torch.compile(fullgraph=True) (max_iter=1 warm start; the
converged graph only with --compile-converged: inductor needs >10 min for it),
and the C++ kernel (torchrot.fit_rotation).

    python benchmarks/generic_path.py [--n 100000] [--runs 7] [--dtype float32]
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import torch

import torchrot
from torchrot import generic
from torchrot.testing import make_matrices


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--n", type=int, default=100_000)
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--distribution", default="uniform")
    parser.add_argument("--compile", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--compile-converged", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)
    M = make_matrices(args.distribution, args.n, 0, dtype)
    buf = torch.empty_like(M)
    init = torchrot.fit_rotation(M)
    methods = {
        "copy_ (memory floor)": lambda: buf.copy_(M),
        "torch.linalg.svd (rotation_svd)": lambda: torchrot.rotation_svd(M),
        "fit_rotation_reference eager": lambda: torchrot.fit_rotation_reference(M),
        "generic.fit_rotation eager (SoA)": lambda: generic.fit_rotation(M),
        "SoA eager, init, max_iter=1": lambda: generic.fit_rotation(M, init, max_iter=1),
        "C++ kernel (fit_rotation)": lambda: torchrot.fit_rotation(M),
        "C++ kernel, init, max_iter=1": lambda: torchrot.fit_rotation(M, init, max_iter=1),
    }
    if args.compile:
        one_step = torch.compile(generic.fit_rotation, fullgraph=True, dynamic=False)
        methods["SoA compiled, init, max_iter=1"] = lambda: one_step(M, init, max_iter=1)
    if args.compile_converged:  # inductor takes >10 min on the unrolled converged graph
        compiled = torch.compile(generic.fit_rotation, fullgraph=True, dynamic=False)
        methods["SoA compiled (converged)"] = lambda: compiled(M)
    t0 = time.perf_counter()
    for f in methods.values():  # warm-up (and compilation)
        f()
    compile_s = time.perf_counter() - t0
    times = {k: [] for k in methods}
    for _ in range(args.runs):
        for name, f in methods.items():
            t = time.perf_counter()
            f()
            times[name].append(time.perf_counter() - t)
    load = os.getloadavg()
    print(f"N={args.n} {args.distribution} {args.dtype}, 1 thread, median of {args.runs} interleaved runs;"
          f" load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; warm-up incl. compile {compile_s:.1f} s")
    svd = statistics.median(times["torch.linalg.svd (rotation_svd)"])
    print(f"{'method':34s} {'ns/matrix':>10s} {'x faster than SVD':>18s}")
    for name, ts in times.items():
        med = statistics.median(ts)
        print(f"{name:34s} {med / args.n * 1e9:10.1f} {svd / med:18.2f}")


if __name__ == "__main__":
    main()
