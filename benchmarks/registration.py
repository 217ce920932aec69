"""Times torchrot.rigid_registration beside the same closed form by SVD.

Interleaved in one process (torchrot.bench.micro.interleaved_median_seconds),
median of several rounds, us per call, 1 thread, scale=True, on the tests'
problems (torchrot.testing.registration_problem): a copy_ of x and y into
preallocated tensors (the floor of reading the points once),
torchrot.reference.rigid_registration_svd (Umeyama by torch.linalg.svd, as
one writes it in PyTorch today) and torchrot.rigid_registration (fit_rotation
on the same covariance). The last column is the largest |R - R*| of
torchrot's rotations against the float64 SVD answer.

    python benchmarks/registration.py [--shapes 1x100 64x64 16x1000 1024x64 1x100000] [--dtype float32 float64]
"""
from __future__ import annotations

import argparse
import os

import torch

import torchrot
from torchrot.bench.micro import interleaved_median_seconds
from torchrot.reference import rigid_registration_svd
from torchrot.testing import registration_problem


def run(problems: int, points: int, dtype: torch.dtype, rounds: int) -> None:
    x, y, _ = registration_problem((problems,), n=points, seed=0, noise=0.1, dtype=dtype)
    x_copy, y_copy = torch.empty_like(x), torch.empty_like(y)
    calls = {
        "copy_": lambda: (x_copy.copy_(x), y_copy.copy_(y)),
        "svd": lambda: rigid_registration_svd(x, y, scale=True),
        "torchrot": lambda: torchrot.rigid_registration(x, y, scale=True),
    }
    for call in calls.values():  # warm-up
        call()
    seconds = interleaved_median_seconds(calls, rounds, min_run_time=0.05)
    reference, _, _ = rigid_registration_svd(x.double(), y.double(), scale=True)
    error = (torchrot.rigid_registration(x, y, scale=True).R.double() - reference).abs().max().item()
    us = {name: s * 1e6 for name, s in seconds.items()}
    print(f"| {problems:,} x {points:,} | {str(dtype).removeprefix('torch.')} | {us['copy_']:.1f} | {us['svd']:.1f} "
          f"| {us['torchrot']:.1f} | {us['svd'] / us['torchrot']:.1f}x | {error:.1e} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", nargs="+", default=["1x100", "64x64", "16x1000", "1024x64", "1x100000"],
                        help="problems x points per problem")
    parser.add_argument("--dtype", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    parser.add_argument("--rounds", type=int, default=9)
    args = parser.parse_args()
    torch.set_num_threads(1)
    load = os.getloadavg()
    print(f"rigid_registration(x, y, scale=True), 1 thread, median of {args.rounds} interleaved rounds (us per call); "
          f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print("| problems x points | dtype | copy_ of x, y | SVD closed form | torchrot | faster than SVD | max R error |")
    print("|---|---|---|---|---|---|---|")
    for dtype in args.dtype:
        for shape in args.shapes:
            problems, points = (int(v) for v in shape.split("x"))
            run(problems, points, getattr(torch, dtype), args.rounds)


if __name__ == "__main__":
    main()
