"""The workloads beside the method tables, each timed against its SVD
counterpart in the same run, in interleaved rounds (1 thread unless the
caller set more): a single-matrix call (:func:`single_matrix_overhead`), a
training step's rotation layer (:func:`rotation_layer`) and point-set
registration (:func:`registration_rows`). Their tables:
:mod:`torchrot.bench.tables`."""
from __future__ import annotations

import statistics

import torch

from torchrot.bench.timing import interleaved_median_seconds, median_seconds
from torchrot.fitting import fit_rotation
from torchrot.nn import RotationFit
from torchrot.reference import rigid_registration_svd, rotation_svd
from torchrot.registration import rigid_registration
from torchrot.testing.data import make_matrices, registration_problem

__all__ = ["registration_row", "registration_rows", "rotation_layer", "single_matrix_overhead"]


def single_matrix_overhead(min_run_time: float = 0.5) -> dict[str, float]:
    """Microseconds per call on one (3, 3) matrix, beside empty custom ops
    (the benchmark-only operators ``torch.ops.torchrot_bench.*``)."""
    M = torch.randn(3, 3)
    R = fit_rotation(M)
    out = torch.empty(3, 3)
    calls = {
        "empty custom op (1 argument)": lambda: torch.ops.torchrot_bench.empty_op(M),
        "empty custom op (fit_rotation's signature and output)":
            lambda: torch.ops.torchrot_bench.empty_fit_rotation(M, None, None, "conservative"),
        "torchrot.fit_rotation(M)": lambda: fit_rotation(M),
        "torch.ops.torchrot.fit_rotation(M)": lambda: torch.ops.torchrot.fit_rotation(M),
        "torchrot.fit_rotation(M, out=out)": lambda: fit_rotation(M, out=out),
        "torchrot.fit_rotation(M, R, max_iter=1, out=R)": lambda: fit_rotation(M, R, max_iter=1, out=R),
        "torch.linalg.svd special Procrustes": lambda: rotation_svd(M),
    }
    return {name: statistics.median(median_seconds(fn, 3, min_run_time)) * 1e6 for name, fn in calls.items()}


def rotation_layer(batches: tuple[int, ...], min_run_time: float = 0.05, repeats: int = 3) -> list[dict]:
    """A training step's rotation layer: microseconds per forward + backward of
    ``torchrot.nn.RotationFit`` on a float32 ``(B, 3, 3)`` batch (gaussian
    network outputs), beside the same through SVD autograd (rotation_svd), the
    same step with a ``clone`` in the layer's place (what PyTorch's autograd
    engine and the loss's own ops cost: the floor of any layer) and a ``copy_``
    of the batch, timed in the same run, in interleaved rounds; 1 thread."""
    layer = RotationFit()
    results = []
    for batch in batches:
        M = make_matrices("gaussian", batch, 0, torch.float32).requires_grad_()
        G = make_matrices("gaussian", batch, 1, torch.float32)
        buffer = torch.empty_like(M)

        def step(fit, M=M, G=G):
            M.grad = None
            (fit(M) * G).sum().backward()

        calls = {"copy_": lambda M=M, buffer=buffer: buffer.copy_(M.detach()), "svd": lambda: step(rotation_svd),
                 "floor": lambda: step(torch.clone), "torchrot": lambda: step(layer)}
        us = {name: seconds * 1e6 for name, seconds in interleaved_median_seconds(calls, repeats, min_run_time).items()}
        results.append({"batch": batch, "copy_us": us["copy_"], "svd_autograd_us": us["svd"],
                        "autograd_floor_us": us["floor"], "torchrot_us": us["torchrot"],
                        "torchrot_vs_svd": us["torchrot"] / us["svd"]})
    return results


# Point-set registration: torchrot.rigid_registration beside the same closed
# form by SVD (torchrot.reference.rigid_registration_svd: Umeyama by
# torch.linalg.svd, as one writes it in PyTorch today), scale=True, on the
# tests' problems (torchrot.testing.registration_problem, noise 0.1), with a
# copy_ of x and y into preallocated tensors (the floor of reading the points
# once), timed in interleaved rounds at the caller's thread count; each row
# also gives torchrot's largest |R - R*| against the float64 SVD answer.
def registration_row(problems: int, points: int, dtype: torch.dtype, rounds: int,
                     min_run_time: float = 0.05) -> dict:
    """One row: us per call of each method (median of ``rounds`` interleaved
    rounds) and torchrot's largest rotation error against float64 SVD."""
    x, y, _ = registration_problem((problems,), n=points, seed=0, noise=0.1, dtype=dtype)
    x_copy, y_copy = torch.empty_like(x), torch.empty_like(y)
    calls = {
        "copy_": lambda: (x_copy.copy_(x), y_copy.copy_(y)),
        "svd": lambda: rigid_registration_svd(x, y, scale=True),
        "torchrot": lambda: rigid_registration(x, y, scale=True),
    }
    for call in calls.values():  # warm-up
        call()
    us = {name: s * 1e6 for name, s in interleaved_median_seconds(calls, rounds, min_run_time).items()}
    reference, _, _ = rigid_registration_svd(x.double(), y.double(), scale=True)
    error = (rigid_registration(x, y, scale=True).R.double() - reference).abs().max().item()
    return {"problems": problems, "points": points, "dtype": str(dtype).removeprefix("torch."),
            "copy_us": us["copy_"], "svd_us": us["svd"], "torchrot_us": us["torchrot"],
            "speedup_vs_svd": us["svd"] / us["torchrot"], "max_r_error": error}


def registration_rows(shapes, dtypes=(torch.float32,), rounds: int = 5, min_run_time: float = 0.05) -> list[dict]:
    """:func:`registration_row` for every dtype and (problems, points) shape
    (the main job's: ``Plan.registration_shapes``)."""
    return [registration_row(problems, points, dtype, rounds, min_run_time)
            for dtype in dtypes for problems, points in shapes]
