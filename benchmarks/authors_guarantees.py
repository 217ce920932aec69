"""What torchrot's guarantees buy beside the paper authors' one-step, for authors_kernel.py.

The timings of ``authors_kernel.py`` show what torchrot's one-step pays for its guarantees:
the scaling to unit largest entry, the masks, and the check of the warm starts before
anything is written. This module shows what they buy: inputs made from the same recorded
data (``GUARANTEES``), each through the authors' one-step and torchrot's, and what each
returns: failures against the float64 SVD, non-finite results, reflections, the
orthonormality of the results, or torchrot's error (then its ``out`` is checked to hold its
values bit for bit, as "an error changes nothing" asks).

    rows = authors_guarantees.rows(authors_one_step, M, init)
    authors_guarantees.print_rows(rows, "-march=haswell", "avx2")
"""
from __future__ import annotations

import math
from collections.abc import Callable

import torch

import torchrot
from torchrot.bench.accuracy import FAILURE_THRESHOLD, accuracy
from torchrot.testing import bits, rotation_svd

__all__ = ["GUARANTEES", "GUARANTEE_N", "ZERO_EVERY", "print_rows", "result_row", "rows", "size"]

#: How many of the data's matrices (the first) the inputs of GUARANTEES are made from.
GUARANTEE_N = 65_536
#: A vertex whose edges all weigh 0 in every this many matrices (the authors' tile: one per tile).
ZERO_EVERY = 8


def _zeroed(M: torch.Tensor) -> torch.Tensor:
    """M with every ZERO_EVERY-th matrix set to 0 (a copy)."""
    Z = M.clone()
    Z[::ZERO_EVERY] = 0
    return Z


def _reflected(R: torch.Tensor) -> torch.Tensor:
    """R with its last column negated (a copy): det -1 where R is a rotation."""
    F = R.clone()
    F[..., 2] = -F[..., 2]
    return F


#: An input made from the recorded data -> (the guarantee of torchrot's it meets, a function
#: (M, init) -> (M', init')). The answer is the float64 SVD's rotation of M' (the same rotation
#: at any scale of M).
GUARANTEES = {
    "the recorded data as they are": ("(none)", lambda M, init: (M, init)),
    "M x 2^-40 (the same data in smaller units)": (
        "unit scaling (`max_abs_entry`, `unit_scale`)",
        lambda M, init: (M * 2.0**-40, init),
    ),
    "M x 2^64": ("unit scaling", lambda M, init: (M * 2.0**64, init)),
    f"M = 0 in every {ZERO_EVERY}th matrix (a vertex whose edges all weigh 0)": (
        "the masks (`can_take`: no step where H is singular, as for M = 0)",
        lambda M, init: (_zeroed(M), init),
    ),
    "warm starts off orthonormal by 1e-3, R0 (1 + 1e-3)": (
        "the warm-start check's clean-up (`clean_warm_start`)",
        lambda M, init: (M, init * (1 + 1e-3)),
    ),
    "warm starts reflected (det -1: a column negated)": (
        "the warm-start check before writing",
        lambda M, init: (M, _reflected(init)),
    ),
}


def size(total: int) -> int:
    """How many matrices the inputs are made from, of ``total``."""
    return min(GUARANTEE_N, total) // ZERO_EVERY * ZERO_EVERY


def result_row(R: torch.Tensor, M: torch.Tensor) -> dict:
    """What a one-step gave for M ``(K, 3, 3)``: failures against the float64
    SVD (accuracy(), over the matrices with M != 0, whose answer is unique),
    non-finite results, results with det < 0, and the largest orthonormality
    error of the finite ones."""
    R64, M64 = R.double(), M.double()
    finite = torch.isfinite(R64).all(dim=(-2, -1))
    nonzero = M64.ne(0).any(dim=(-2, -1))
    orthonormality = (R64[finite].mT @ R64[finite] - torch.eye(3, dtype=torch.float64)).norm(dim=(-2, -1))
    return {
        "failures": accuracy(R[nonzero], M64[nonzero], rotation_svd(M64[nonzero]))["failures"],
        "non_finite": int((~finite).sum()),
        "reflections": int((torch.linalg.det(R64[finite]) < 0).sum()),
        "orthonormality": orthonormality.max().item() if orthonormality.numel() else math.nan,
    }


def rows(authors_one_step: Callable, M: torch.Tensor, init: torch.Tensor) -> dict[str, dict]:
    """Each input of GUARANTEES, made from the first GUARANTEE_N matrices of
    M and init ``(N, 3, 3)``, through ``authors_one_step(M, init) -> R`` and
    torchrot's one-step (``out=`` a copy of its warm starts, on the calling
    thread's CPU kernel): input -> computation -> result_row, or {"raised":
    what torchrot raised, and whether ``out`` kept its values bit for bit}."""
    n = size(M.shape[0])
    found = {}
    for name, (_, make) in GUARANTEES.items():
        M_case, init_case = make(M[:n], init[:n])
        found[name] = {"authors' one-step": result_row(authors_one_step(M_case, init_case), M_case)}
        out = init_case.clone()
        try:
            R = torchrot.fit_rotation(M_case, init_case, max_iter=1, out=out)
            found[name]["torchrot one-step"] = result_row(R, M_case)
        except ValueError as error:
            kept = torch.equal(bits(out), bits(init_case))
            message = str(error).split(": ", 1)[-1].split(" (")[0]
            found[name]["torchrot one-step"] = {
                "raised": f"raises ValueError ({message}); `out` {'unchanged, bit for bit' if kept else 'CHANGED'}"
            }
    return found


def print_rows(found: dict[str, dict], n: int, authors_build: str, kernel: str) -> None:
    """The table of rows() on ``n`` matrices (size()): the authors' one-step
    built with ``authors_build``, torchrot's on its CPU kernel ``kernel``."""
    print(
        f"\nWhat the guarantees buy: inputs made from the first {n:,} matrices of the data, "
        f"through the authors' one-step (as shipped, {authors_build}) and torchrot's (`out=`, kernel {kernel}). "
        f"Failures: |R - R*|_F > {FAILURE_THRESHOLD:g} against the float64 SVD or not finite, over the matrices "
        "with M != 0 (for M = 0 every rotation is the answer):\n"
    )
    print("| input | guarantee | computation | failures | non-finite | det < 0 | max abs(R^T R - I)_F |")
    print("|---|---|---|---|---|---|---|")
    for name, computations in found.items():
        guarantee = GUARANTEES[name][0]
        for computation, row in computations.items():
            if "raised" in row:
                print(f"| {name} | {guarantee} | {computation} | {row['raised']} | | | |")
            else:
                print(
                    f"| {name} | {guarantee} | {computation} | {row['failures']} | {row['non_finite']} "
                    f"| {row['reflections']} | {row['orthonormality']:.1e} |"
                )
