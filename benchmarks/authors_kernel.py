"""The paper authors' one-step AVX kernel beside torchrot, in one process.

Builds ``fit_rotation_small_avx`` (the one-step warm-start update of Zhang,
Jacobson & Alexa's public code, ``src/fit_rotation_avx.cpp`` of a checkout of
github.com/ErisZhang/fast-rotation-fitting, which you provide: nothing of it
is in torchrot) with that repository's release flags, and times it on its own
layout, tiles of 8 float32 matrices in structure of arrays (``(N / 8, 9, 8)``,
updated in place), against a ``copy_`` of M and torchrot's one-step fit on
the same memory (``torchrot.testing.tiled_view``: the ``(N / 8, 8, 3, 3)``
view), on contiguous ``(N, 3, 3)`` tensors, and the authors' kernel with the
shuffles of such tensors into and out of its layout. float32, 1 thread,
``make_warm_start("warm")`` data, medians of ``--rounds`` interleaved rounds.
Also prints how far each one-step result is from the exact fit (float64).

    python benchmarks/authors_kernel.py --source PATH/TO/fast-rotation-fitting [--eigen /usr/include/eigen3]

Needs g++ and Eigen's headers (the file includes them; Debian: libeigen3-dev).
"""
from __future__ import annotations

import argparse
import ctypes
import os
import subprocess
import tempfile

import torch

import torchrot
from torchrot.bench.machine import Load, load_average, machine_info
from torchrot.bench.timing import interleaved_median_seconds
from torchrot.testing import make_warm_start, tiled_view

__all__ = ["FLAGS", "SYMBOL", "TILE", "blocks", "build", "main"]

TILE = 8  # the authors' AVX blocks: 8 float32 matrices
SYMBOL = "_Z22fit_rotation_small_avxPfS_i"  # int fit_rotation_small_avx(float* M, float* R, int groups)
# The repository's CMakeLists.txt: Release, -mavx2 -march=native -mfpmath=sse, C++11.
FLAGS = ["-O3", "-DNDEBUG", "-std=c++11", "-mavx2", "-march=native", "-mfpmath=sse", "-w"]


def build(source: str, eigen: str, folder: str):
    """The authors' kernel, compiled into a shared library in ``folder``."""
    library = os.path.join(folder, "fit_rotation_avx.so")
    subprocess.run(["g++", *FLAGS, "-fPIC", "-shared", f"-I{eigen}", "-o", library,
                    os.path.join(source, "src", "fit_rotation_avx.cpp")], check=True)
    kernel = getattr(ctypes.CDLL(library), SYMBOL)
    kernel.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
    return kernel


def blocks(t: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) -> the authors' (N / 8, 9, 8) layout (a copy; their kernel's
    aligned loads need 32-byte alignment, which torch's allocations have)."""
    b = t.reshape(-1, TILE, 9).transpose(1, 2).contiguous()
    assert b.data_ptr() % 32 == 0
    return b


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", required=True, help="a checkout of ErisZhang/fast-rotation-fitting")
    parser.add_argument("--eigen", default="/usr/include/eigen3")
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--min-time", type=float, default=0.3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    n = args.n - args.n % TILE
    groups = n // TILE
    M, init = make_warm_start("warm", n, seed=0, dtype=torch.float32)
    with tempfile.TemporaryDirectory() as folder:
        kernel = build(args.source, args.eigen, folder)

        # What each computes, once from init, against the exact fit.
        exact = torchrot.fit_rotation(M.double())
        M_blocks, R_authors = blocks(M), blocks(init)
        kernel(M_blocks.data_ptr(), R_authors.data_ptr(), groups)
        R_authors = R_authors.transpose(1, 2).reshape(n, 3, 3)
        R_torchrot = torchrot.fit_rotation(M, init, max_iter=1)
        for name, R in (("authors' one-step", R_authors), ("torchrot one-step", R_torchrot)):
            error = (R.double() - exact).abs().amax((-2, -1))
            print(f"{name}: max |R - R*| {error.max().item():.1e}, "
                  f"off by > 1e-3: {(error > 1e-3).float().mean().item():.2%}")

        M_blocks, R_blocks = blocks(M), blocks(init)
        M_tiles, R_tiles = tiled_view(M, TILE), tiled_view(init, TILE)  # torchrot's views of the same layout
        buffer, out = torch.empty_like(M), init.clone()
        M_shuffled, R_shuffled = torch.empty_like(M_blocks), torch.empty_like(R_blocks)

        def authors_with_shuffles():
            M_shuffled.copy_(M.view(groups, TILE, 9).transpose(1, 2))
            R_shuffled.copy_(out.view(groups, TILE, 9).transpose(1, 2))
            kernel(M_shuffled.data_ptr(), R_shuffled.data_ptr(), groups)
            out.view(groups, TILE, 9).copy_(R_shuffled.transpose(1, 2))

        fit, check = torchrot.fit_rotation, torch.ops.torchrot_bench.count_bad_warm_starts
        calls = {
            "copy_ of M": lambda: buffer.copy_(M),
            "authors' one-step AVX, their layout, in place":
                lambda: kernel(M_blocks.data_ptr(), R_blocks.data_ptr(), groups),
            "torchrot one-step, the same layout (tiled views), in place":
                lambda: fit(M_tiles, R_tiles, max_iter=1, out=R_tiles),
            # An out= call first checks every warm start, so that one that raises leaves out as it was.
            "of which: torchrot's check of the warm starts before writing": lambda: check(R_tiles),
            "authors' one-step incl. shuffling (N, 3, 3) in and out": authors_with_shuffles,
            "torchrot one-step, (N, 3, 3), in place": lambda: fit(M, out, max_iter=1, out=out),
        }
        before = load_average()
        seconds = interleaved_median_seconds(calls, args.rounds, args.min_time)
        load = Load.around(before)
    copy, authors = seconds["copy_ of M"], seconds["authors' one-step AVX, their layout, in place"]
    print(f"\nN = {n:,} float32 matrices, 1 thread, medians of {args.rounds} interleaved rounds (kernel "
          f"{machine_info()['torchrot_kernel']}); {load.line()}:\n")
    print("| call | ns/matrix | x copy_ | x authors' |\n|---|---|---|---|")
    for name, s in seconds.items():
        print(f"| {name} | {s / n * 1e9:.2f} | {s / copy:.2f} | {s / authors:.2f} |")


if __name__ == "__main__":
    main()
