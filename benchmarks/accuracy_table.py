"""Accuracy, iteration counts and fallback rates per test distribution.

    python benchmarks/accuracy_table.py [--n 100000]

For every distribution of torchrot.testing (cold start, converged mode): the
max and median |R - R*|_F and objective shortfall of torchrot in float32 and
float64 beside float32 torch.linalg.svd, R* being float64 SVD; then the mean
Cayley steps and the share of matrices that needed the fallback, per variant
and dtype. Deterministic (seeded data); writes Markdown to stdout.
"""
from __future__ import annotations

import argparse

import torchrot
from torchrot.bench.machine import machine_info
from torchrot.bench.options import positive_int
from torchrot.bench.registry import VARIANTS
from torchrot.testing import DISTRIBUTIONS, make_matrices, rotation_errors

__all__ = ["main"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=positive_int, default=100_000)
    n = parser.parse_args().n
    print(f"Machine: {machine_info()}\n")
    print(f"Accuracy against float64 SVD, {n} matrices per distribution, cold start, converged mode\n")
    print("| distribution | torchrot f32 max / median err | f32 SVD max / median err | torchrot f64 max err | "
          "max shortfall f32 / f64 |")
    print("|---|---|---|---|---|")
    counts = []
    for name in DISTRIBUTIONS:
        M64 = make_matrices(name, n, seed=0)
        M32 = M64.float()
        e32 = rotation_errors(torchrot.fit_rotation(M32), M64)
        e64 = rotation_errors(torchrot.fit_rotation(M64), M64)
        svd = rotation_errors(torchrot.rotation_svd(M32), M64)
        print(f"| {name} | {e32['distance'].max():.1e} / {e32['distance'].median():.1e} | "
              f"{svd['distance'].max():.1e} / {svd['distance'].median():.1e} | {e64['distance'].max():.1e} | "
              f"{e32['shortfall'].max():.1e} / {e64['shortfall'].max():.1e} |")
        row = [name]
        for M in (M32, M64):
            for variant in VARIANTS:
                info = torchrot.fit_rotation_info(M, variant=variant)
                row.append(f"{info.iterations.double().mean():.2f} / {(info.status == 1).double().mean():.3%}")
        counts.append(row)
    print(f"\nMean Cayley steps / fallback rate per variant ({', '.join(VARIANTS)})\n")
    columns = [f"{dtype} {variant}" for dtype in ("f32", "f64") for variant in VARIANTS]
    print("| distribution | " + " | ".join(columns) + " |")
    print("|---|" + "---|" * len(columns))
    for row in counts:
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
