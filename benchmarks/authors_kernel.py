"""The paper authors' AVX kernels beside torchrot, in one process, and the speed targets they set.

Builds the paper authors' two float32 AVX kernels from ``src/fit_rotation_avx.cpp`` of a
checkout of github.com/ErisZhang/fast-rotation-fitting, which you provide (nothing of it is in
torchrot), with that repository's release flags:

- ``fit_rotation_small_avx``, the one-step warm-start update (the paper's mode), and
- ``fit_rotation_avx``, the same Cayley steps iterated until every matrix of a tile of 8 has
  tan^2(theta/2) < 1e-15 (at most 500 steps),

and times them on their own layout, tiles of 8 float32 matrices in structure of arrays
(``(N / 8, 9, 8)``, updated in place), beside torchrot on the same memory
(``torchrot.testing.tiled_view``: the ``(N / 8, 8, 3, 3)`` view), on structure-of-arrays
views (``soa_view``) and on contiguous ``(N, 3, 3)`` tensors, with a ``copy_`` of M (the
memory floor) and the check of the warm starts that every ``out=`` call makes before it
writes (so that a call that raises leaves ``out`` as it was). float32, 1 thread, medians of
``--rounds`` interleaved rounds. The data: the ARAP solver's recorded covariances and the
rotations it had for them (``--data arap``, the default: the paper-scale recording of
``python -m torchrot bench --full``, ~1e6 matrices, recorded on first use and cached, see
``torchrot.bench.data``), or any distribution of ``torchrot.testing.make_warm_start``.

Prints the timings, the accuracy of each computation against the float64 SVD, the table of
targets: each ratio against the authors' one-step, its limit, whether it holds, and what it
would be without the warm-start check (what keeping "an error changes nothing" costs), and what
the guarantees that the timings pay for buy (``authors_guarantees.py``): inputs made from the
data (M at other scales, M = 0 in some matrices, warm starts slightly off orthonormal or
reflected) through both one-steps. The authors' kernels are timed twice: in the caller's
floating-point mode, as they ship, and with subnormal numbers flushed to zero
(``torch.set_flush_denormal(True)`` around each call: FTZ and DAZ). Recorded solver data make
subnormal numbers inside a step, which some x86 cores compute through slow microcode assists
(benchmarks/lab_notes.md); torchrot's kernels flush subnormal results themselves
(``csrc/cpu/flush_to_zero.h``). The unit of every ratio is the faster of the two, so that no
core's subnormal arithmetic flatters torchrot.

    python benchmarks/authors_kernel.py --source PATH/TO/fast-rotation-fitting [--kernels avx2 avx512] [--n 1000000]

Needs g++ and Eigen's headers (the file includes them; Debian: libeigen3-dev). Every
instruction set of ``--kernels`` (default: each of avx2 and avx512 this CPU runs) is timed in
the same run, interleaved: torchrot's kernel for it (``torchrot.testing.cpu_kernel``) beside the
authors' kernels built for it (``KERNEL_MARCH``: ``-march=haswell`` for AVX2, their own
``-march=native`` for AVX-512, where it gets AVX-512VL's 32 vector registers), each ratio
against the authors' one-step of its own instruction set.
"""
from __future__ import annotations

import argparse
import ctypes
import functools
import os
import subprocess
import tempfile

import authors_guarantees
import torch

import torchrot
from torchrot.bench import apps, data
from torchrot.bench.accuracy import FAILURE_THRESHOLD, accuracy
from torchrot.bench.machine import Load, load_average, machine_info
from torchrot.bench.timing import interleaved_median_seconds
from torchrot.testing import available_cpu_kernels, cpu_kernel, rotation_svd, soa_view, tiled_view

__all__ = ["FLAGS", "ONE_STEP", "ITERATED", "KERNEL_MARCH", "TARGETS", "TARGET_LIMITS",
           "TILE", "authors_unit", "blocks", "build", "compile_library", "load", "main", "one_step"]

TILE = 8  # the authors' AVX blocks: 8 float32 matrices
ONE_STEP = "_Z22fit_rotation_small_avxPfS_i"  # int fit_rotation_small_avx(float* M, float* R, int groups)
ITERATED = "_Z16fit_rotation_avxPfS_i"  # int fit_rotation_avx(float* M, float* R, int groups)
# The repository's CMakeLists.txt: Release, -mavx2 -march=native -mfpmath=sse, C++11.
FLAGS = ["-O3", "-DNDEBUG", "-std=c++11", "-mavx2", "-march=native", "-mfpmath=sse", "-w"]
#: torchrot's CPU kernel -> the -march its rows' authors' kernels are built with: their AVX code
#: for an AVX2-only machine (haswell: 16 vector registers), and their own build (native), which
#: gets AVX-512VL's 32 registers on an AVX-512 machine.
KERNEL_MARCH = {"avx2": "haswell", "avx512": "native"}

# The rows of each instruction set; the authors' one-step on its own layout is the unit of its targets.
COPY = "copy_ of M (memory floor)"
AUTHORS = "authors' one-step, their tiles, in place"
AUTHORS_FLUSHED = "authors' one-step, subnormal numbers flushed to zero"
AUTHORS_ITERATED = "authors' iterated (to tan^2 < 1e-15), their tiles, from the warm starts (copied in)"
AUTHORS_ITERATED_FLUSHED = "authors' iterated, subnormal numbers flushed to zero"
#: The authors' calls timed twice, as they ship and flushed (_flushed): row -> its flushed row.
FLUSHED = {AUTHORS: AUTHORS_FLUSHED, AUTHORS_ITERATED: AUTHORS_ITERATED_FLUSHED}
TILES = "torchrot one-step, the same tiles (tiled views), in place"
SOA = "torchrot one-step, SoA views, in place"
OUT = "torchrot one-step, contiguous (N, 3, 3), out="
FRESH = "torchrot one-step, contiguous, a new result"
CONVERGED_TILES = "torchrot converged from the warm start, tiles, out="
CONVERGED_OUT = "torchrot converged from the warm start, contiguous, out="
CHECK_TILES = "of which: the warm-start check before writing (tiles)"
CHECK = "of which: the warm-start check before writing (contiguous)"

#: target: (row, the row of its warm-start check), each with a limit per instruction set below.
TARGETS = {
    "one-step in place on the authors' tiles": (TILES, CHECK_TILES),
    "one-step in place on SoA views": (SOA, CHECK),
    "one-step, contiguous, out=": (OUT, CHECK),
    "converged from the warm start (tiles, out=)": (CONVERGED_TILES, CHECK_TILES),
    "converged from the warm start (contiguous, out=)": (CONVERGED_OUT, CHECK),
}
#: torchrot's CPU kernel -> the limits of TARGETS, in order, as multiples of the authors' one-step built
#: for the same instruction set (issue #44; AVX2 holds 8 floats per register as their AVX code does, in
#: 16 registers; AVX-512 has 16 floats and 32 registers).
TARGET_LIMITS = {
    "avx2": (1.3, 1.4, 1.6, 2.5, 2.5),
    "avx512": (1.0, 1.1, 1.3, 1.8, 1.8),
}


def compile_library(source: str, eigen: str, folder: str, march: str = "native", debug_info: bool = False) -> str:
    """The path of the authors' kernels compiled into a shared library in
    ``folder``, for ``-march=march`` (their build: native), with debug
    information if asked (the same code: instruction_profile.py reads it);
    one library per ``march``, so that builds for two instruction sets load
    side by side."""
    library = os.path.join(folder, f"fit_rotation_avx_{march}.so")
    flags = [f"-march={march}" if flag == "-march=native" else flag for flag in FLAGS] + (["-g"] if debug_info else [])
    subprocess.run(["g++", *flags, "-fPIC", "-shared", f"-I{eigen}", "-o", library,
                    os.path.join(source, "src", "fit_rotation_avx.cpp")], check=True)
    return library


def load(library: str) -> dict:
    """The kernels of a library of compile_library: ``{"one-step": fn, "iterated": fn}``,
    each ``fn(M_blocks, R_blocks, groups)`` on data pointers of the (N / 8, 9, 8) layout."""
    kernels = {}
    for name, symbol in (("one-step", ONE_STEP), ("iterated", ITERATED)):
        kernel = getattr(ctypes.CDLL(library), symbol)
        kernel.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
        kernels[name] = kernel
    return kernels


def build(source: str, eigen: str, folder: str, march: str = "native") -> dict:
    """The authors' kernels, compiled (compile_library) and loaded (load)."""
    return load(compile_library(source, eigen, folder, march))


def blocks(t: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) -> the authors' (N / 8, 9, 8) layout (a copy; their kernel's
    aligned loads need 32-byte alignment, which torch's allocations have)."""
    b = t.reshape(-1, TILE, 9).transpose(1, 2).contiguous()
    assert b.data_ptr() % 32 == 0
    return b


def unblock(b: torch.Tensor) -> torch.Tensor:
    """The authors' (N / 8, 9, 8) layout -> (N, 3, 3) (a copy)."""
    return b.transpose(1, 2).reshape(-1, 3, 3).contiguous()


def iterated_fit(kernel, M_blocks: torch.Tensor, init: torch.Tensor) -> torch.Tensor:
    """The authors' iterated kernel's rotations from warm starts ``init`` ``(N, 3, 3)``.
    It reads its warm start transposed (its loop carries R^T, the rotation of
    M^T) and stores the transpose of what it carries, R itself."""
    R = blocks(init.mT)
    kernel(M_blocks.data_ptr(), R.data_ptr(), M_blocks.shape[0])
    return unblock(R)


def one_step(kernels, M: torch.Tensor, init: torch.Tensor) -> torch.Tensor:
    """The authors' one-step rotations ``(N, 3, 3)`` of M from warm starts
    ``init`` (N a multiple of TILE), through copies in their layout."""
    M_blocks, R_blocks = blocks(M), blocks(init)
    kernels["one-step"](M_blocks.data_ptr(), R_blocks.data_ptr(), M_blocks.shape[0])
    return unblock(R_blocks)


def _accuracy_rows(kernels, M: torch.Tensor, init: torch.Tensor) -> dict[str, dict]:
    """What each computation gives, once, from the same warm starts, against the float64 SVD
    (torchrot on the calling thread's CPU kernel)."""
    M64 = M.double()
    exact = rotation_svd(M64)
    results = {
        "authors' one-step": one_step(kernels, M, init),
        "authors' iterated": iterated_fit(kernels["iterated"], blocks(M), init),
        "torchrot one-step": torchrot.fit_rotation(M, init, max_iter=1),
        "torchrot converged from the warm start": torchrot.fit_rotation(M, init),
    }
    rows = {}
    for name, R in results.items():
        row = accuracy(R, M64, exact)
        gram = R.double().mT @ R.double() - torch.eye(3, dtype=torch.float64)
        row["orthonormality"] = gram.norm(dim=(-2, -1)).max().item()
        rows[name] = row
    rows["torchrot converged from the warm start"]["steps"] = \
        torchrot.fit_rotation_info(M, init).iterations.double().mean().item()
    return rows


def _authors_calls(kernels, M: torch.Tensor, init: torch.Tensor) -> dict:
    """The timed calls of the authors' kernels (their one-step in place, fed
    back as a local-global solver's loop does; their iterated kernel from the
    same warm starts at every call, copied into its buffer first), each on
    memory of its own."""
    groups = M.shape[0] // TILE
    M_blocks, R_blocks = blocks(M), blocks(init)
    R_iterated_start, R_iterated = blocks(init.mT), blocks(init.mT)
    return {
        AUTHORS: lambda: kernels["one-step"](M_blocks.data_ptr(), R_blocks.data_ptr(), groups),
        AUTHORS_ITERATED: lambda: (R_iterated.copy_(R_iterated_start),
                                   kernels["iterated"](M_blocks.data_ptr(), R_iterated.data_ptr(), groups)),
    }


def _calls(kernels, M: torch.Tensor, init: torch.Tensor) -> dict:
    """The timed calls of one instruction set (torchrot's on the calling
    thread's CPU kernel), each on memory of its own, ``copy_`` included. The
    one-step updates in place feed their results back, as a local-global
    solver's loop does; the converged fits start from the same warm starts at
    every call. The authors' calls (_authors_calls) twice: as they ship and
    flushed (FLUSHED)."""
    fit, check = torchrot.fit_rotation, torch.ops.torchrot_bench.count_bad_warm_starts
    M_tiles, R_tiles = tiled_view(M, TILE), tiled_view(init, TILE)
    R_tiles_start, R_tiles_converged = tiled_view(init, TILE), tiled_view(init, TILE)
    M_soa, R_soa = soa_view(M), soa_view(init)
    buffer, out, out_converged = torch.empty_like(M), init.clone(), init.clone()
    flushed = {FLUSHED[row]: _flushed(call) for row, call in _authors_calls(kernels, M, init).items()}
    return {
        COPY: lambda: buffer.copy_(M),
        **_authors_calls(kernels, M, init),
        **flushed,
        TILES: lambda: fit(M_tiles, R_tiles, max_iter=1, out=R_tiles),
        SOA: lambda: fit(M_soa, R_soa, max_iter=1, out=R_soa),
        OUT: lambda: fit(M, init, max_iter=1, out=out),
        FRESH: lambda: fit(M, init, max_iter=1),
        CONVERGED_TILES: lambda: fit(M_tiles, R_tiles_start, out=R_tiles_converged),
        CONVERGED_OUT: lambda: fit(M, init, out=out_converged),
        CHECK_TILES: lambda: check(R_tiles),
        CHECK: lambda: check(init),
    }


def _flushed(call):
    """``call`` run with subnormal numbers flushed to zero (FTZ and DAZ, in this thread), then the
    caller's mode (torch's default: off) back."""
    def run():
        torch.set_flush_denormal(True)
        try:
            return call()
        finally:
            torch.set_flush_denormal(False)
    return run


def authors_unit(times: dict[str, float]) -> float:
    """The unit of the targets in ``times`` (row -> time, one instruction set): the authors'
    one-step, the faster of its two floating-point modes."""
    return min(times[AUTHORS], times[AUTHORS_FLUSHED])


def _on_kernel(kernel: str, call):
    """``call`` run on torchrot's CPU kernel ``kernel`` (in this thread)."""
    def run():
        with cpu_kernel(kernel):
            return call()
    return run


def _print_targets(ns: dict[str, dict[str, float]], accuracy_rows: dict[str, dict[str, dict]]) -> None:
    print("\n| target | kernel | ns/matrix | x authors' one-step | limit | holds | without the warm-start check |")
    print("|---|---|---|---|---|---|---|")
    for kernel, times in ns.items():
        converged = accuracy_rows[kernel]["torchrot converged from the warm start"]
        unit = authors_unit(times)
        for (target, (row, check)), limit in zip(TARGETS.items(), TARGET_LIMITS[kernel], strict=True):
            ratio = times[row] / unit
            holds = ratio <= limit and (converged["failures"] == 0 or "converged" not in target)
            without = (times[row] - times[check]) / unit
            print(f"| {target} | {kernel} | {times[row]:.2f} | {ratio:.2f} | {limit:.1f} | {'yes' if holds else 'no'} "
                  f"| {without:.2f} |")
    for kernel, rows in accuracy_rows.items():
        converged = rows["torchrot converged from the warm start"]
        print(f"\n{kernel}: converged fits' failures (|R - R*|_F > {FAILURE_THRESHOLD:g} against the float64 SVD): "
              f"{converged['failures']}; they take {converged['steps']:.2f} Cayley steps per matrix on average (the "
              "one-step: 1) and verify the maximum.")
    print("\nThe drift bound (1,000 chained in-place one-steps stay rotations to working precision) is a test: "
          "tests/test_warm_start_precision.py.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", required=True, help="a checkout of ErisZhang/fast-rotation-fitting")
    parser.add_argument("--eigen", default="/usr/include/eigen3")
    parser.add_argument("--data", default="arap",
                        help="arap (recorded, paper-scale; the default), elasticity, or a distribution of "
                             "torchrot.testing.make_warm_start (e.g. warm)")
    parser.add_argument("--kernels", nargs="+", choices=sorted(KERNEL_MARCH),
                        help="torchrot's CPU kernels to time, each beside the authors' kernels built for its "
                             "instruction set (KERNEL_MARCH), all in one run; default: those this CPU runs")
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--min-time", type=float, default=0.3)
    args = parser.parse_args()
    available = available_cpu_kernels()
    kernel_names = args.kernels or [kernel for kernel in KERNEL_MARCH if kernel in available]
    if not kernel_names:
        parser.error(f"this CPU runs none of torchrot's kernels {sorted(KERNEL_MARCH)} (it runs {available})")
    missing = [kernel for kernel in kernel_names if kernel not in available]
    if missing:
        parser.error(f"--kernels: this CPU does not run {missing} (it runs {list(available)})")
    torch.set_num_threads(1)  # every call runs in this thread, in its floating-point mode and on its kernel
    if not torch.set_flush_denormal(False):
        parser.error("this CPU has no flush-to-zero mode (the authors' kernels are timed with it too)")
    n = args.n - args.n % TILE
    M, init = data.pairs(args.data, n, torch.float32, configs={"arap": apps.FULL.arap})
    calls, accuracy_rows = {}, {}
    with tempfile.TemporaryDirectory() as folder:
        for kernel in kernel_names:
            kernels = build(args.source, args.eigen, folder, KERNEL_MARCH[kernel])
            with cpu_kernel(kernel):
                accuracy_rows[kernel] = _accuracy_rows(kernels, M, init)
                if kernel == kernel_names[0]:
                    guarantee_rows = authors_guarantees.rows(functools.partial(one_step, kernels), M, init)
            for row, call in _calls(kernels, M, init).items():
                calls[(kernel, row)] = _on_kernel(kernel, call)
        before = load_average()
        seconds = interleaved_median_seconds(calls, args.rounds, args.min_time)
        load = Load.around(before)
    ns = {kernel: {row: seconds[(kernel, row)] / n * 1e9 for (k, row) in seconds if k == kernel}
          for kernel in kernel_names}
    print(f"# The paper authors' kernels beside torchrot\n\nMachine: {machine_info()}\n")
    builds = ", ".join(f"{kernel} beside -march={KERNEL_MARCH[kernel]}" for kernel in kernel_names)
    print(f"N = {n:,} float32 matrices ({args.data}), 1 thread, medians of {args.rounds} rounds, every row of "
          f"every instruction set interleaved in one process (torchrot's kernel {builds}"
          f"); {load.line()}. The unit of the last column and of the targets is the authors' one-step in the "
          "faster of its two floating-point modes:\n")
    print("| call | kernel | ns/matrix | x copy_ | x authors' one-step |\n|---|---|---|---|---|")
    for kernel, times in ns.items():
        unit = authors_unit(times)
        for name, value in times.items():
            print(f"| {name} | {kernel} | {value:.2f} | {value / times[COPY]:.2f} | {value / unit:.2f} |")
    print("\nAgainst the float64 SVD, from the same warm starts:\n")
    print("| computation | kernel | max abs(R - R*)_F | median | failures | max abs(R^T R - I)_F |")
    print("|---|---|---|---|---|---|")
    for kernel, rows in accuracy_rows.items():
        for name, row in rows.items():
            print(f"| {name} | {kernel} | {row['max_error']:.1e} | {row['median_error']:.1e} | {row['failures']} "
                  f"| {row['orthonormality']:.1e} |")
    _print_targets(ns, accuracy_rows)
    authors_guarantees.print_rows(guarantee_rows, authors_guarantees.size(n), f"-march={KERNEL_MARCH[kernel_names[0]]}",
                                  kernel_names[0])


if __name__ == "__main__":
    main()
