"""Times the device-generic path (torchrot.fit_rotation_reference, torchrot.generic).

Interleaved in one process, median of several rounds
(``torchrot.bench.timing.interleaved_median_seconds``; ``torch.utils.benchmark``
synchronizes the accelerator around each timing), ns per matrix, N uniform
matrices (torchrot.testing.make_matrices("uniform", ...)), 1 thread on CPU:
copy_ of M into a preallocated tensor (the memory floor), torch.linalg.svd
special Procrustes (torchrot.rotation_svd), fit_rotation_reference eager and
under torch.compile(fullgraph=True) (converged, cold start; and the one-step
warm start, max_iter=1), and, on CPU, the C++ kernel (torchrot.fit_rotation).
The compiled converged graph takes about 2 minutes to compile here.

    python benchmarks/generic_path.py [--n 100000] [--runs 7] [--min-time 0.05] [--dtype float32] [--no-compile]
    python benchmarks/generic_path.py --device cuda --n 1000 10000 100000 1000000 10000000
"""
from __future__ import annotations

import argparse
import time

import torch

import torchrot
from torchrot.bench.machine import Load, load_average
from torchrot.bench.options import DTYPES, dtype_name, positive_int
from torchrot.bench.timing import interleaved_median_seconds
from torchrot.testing import make_matrices

__all__ = ["main", "run"]


def _methods(M: torch.Tensor, init: torch.Tensor, compile_: bool) -> dict:
    buf = torch.empty_like(M)
    methods = {
        "copy_ (memory floor)": lambda: buf.copy_(M),
        "torch.linalg.svd (rotation_svd)": lambda: torchrot.rotation_svd(M),
        "generic eager, converged": lambda: torchrot.fit_rotation_reference(M),
        "generic eager, init, max_iter=1": lambda: torchrot.fit_rotation_reference(M, init, max_iter=1),
    }
    if compile_:
        compiled = torch.compile(torchrot.fit_rotation_reference, fullgraph=True, dynamic=False)
        methods["generic compiled, converged"] = lambda: compiled(M)
        methods["generic compiled, init, max_iter=1"] = lambda: compiled(M, init, max_iter=1)
    if M.device.type == "cpu":
        methods["C++ kernel, converged"] = lambda: torchrot.fit_rotation(M)
        methods["C++ kernel, init, max_iter=1"] = lambda: torchrot.fit_rotation(M, init, max_iter=1)
    return methods


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def run(n: int, device: torch.device, dtype: torch.dtype, distribution: str, runs: int, compile_: bool,
        min_time: float) -> None:
    M = make_matrices(distribution, n, 0, dtype).to(device)
    init = torchrot.fit_rotation(M.cpu()).to(device)
    methods = _methods(M, init, compile_)
    t0 = time.perf_counter()
    for f in methods.values():  # warm-up (and compilation)
        f()
    _sync(device)
    warm_up_s = time.perf_counter() - t0
    before = load_average()
    seconds = interleaved_median_seconds(methods, runs, min_time)
    threads = f"{torch.get_num_threads()} thread(s)" if device.type == "cpu" else str(device)
    print(f"\nN={n:,} {distribution} {dtype_name(dtype)}, {threads}, median of {runs} interleaved rounds; "
          f"{Load.around(before).line()}; warm-up incl. compile {warm_up_s:.1f} s")
    svd = seconds["torch.linalg.svd (rotation_svd)"]
    print(f"{'method':36s} {'ns/matrix':>10s} {'x faster than SVD':>18s}")
    for name, median in seconds.items():
        print(f"{name:36s} {median / n * 1e9:10.1f} {svd / median:18.2f}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--n", type=positive_int, nargs="+", default=[100_000])
    parser.add_argument("--runs", type=positive_int, default=7, help="interleaved rounds")
    parser.add_argument("--min-time", type=float, default=0.05, help="seconds of calls per sample")
    parser.add_argument("--dtype", default="float32", choices=sorted(DTYPES))
    parser.add_argument("--distribution", default="uniform")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=positive_int, default=1, help="CPU threads (default 1)")
    parser.add_argument("--compile", action=argparse.BooleanOptionalAction, default=True)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    for n in args.n:
        run(n, torch.device(args.device), DTYPES[args.dtype], args.distribution, args.runs, args.compile,
            args.min_time)


if __name__ == "__main__":
    main()
