"""The training benchmark's rotation layers alone: their forward and
forward + backward timed on fixed matrices beside SVD autograd and a copy
(``torchrot.bench.timing``), and their gradients' accuracy against float64
SVD autograd; each with its Markdown table."""
from __future__ import annotations

import math
import statistics

import torch
from rotation_regression_model import Config

import torchrot
from torchrot.baselines import available, roma_special_procrustes
from torchrot.bench.timing import median_seconds

__all__ = ["format_accuracy_table", "format_layer_table", "gradient_accuracy", "time_rotation_layers"]


def _layer_calls(M: torch.Tensor):
    """name -> (forward, forward+backward) callables on the float32 ``(B, 3, 3)``
    matrices M, plus the copy floor (forward only)."""
    M = M.detach().clone().requires_grad_()
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(1))
    out = torch.empty_like(M)
    layers = {"torchrot.nn.RotationFit": torchrot.nn.RotationFit(),
              "SVD (torch.linalg.svd autograd)": torchrot.rotation_svd}
    if available("roma"):
        layers["roma.special_procrustes"] = roma_special_procrustes

    def forward(layer):
        def run():
            with torch.no_grad():
                return layer(M)
        return run

    def forward_backward(layer):
        return lambda: torch.autograd.grad(layer(M), M, G)

    calls = {name: (forward(layer), forward_backward(layer)) for name, layer in layers.items()}
    calls["copy_ (memory floor)"] = (lambda: out.copy_(M.detach()), None)
    return calls


def _median_seconds(fn, repeats: int, min_run_time: float) -> float:
    return statistics.median(median_seconds(fn, repeats, min_run_time))


def _tiled(M: torch.Tensor, n: int) -> torch.Tensor:
    """The first n matrices of M repeated: ``(n, 3, 3)``."""
    return M.repeat(math.ceil(n / M.shape[0]), 1, 1)[:n].contiguous()


def time_rotation_layers(config: Config, data: dict[str, torch.Tensor], log=print) -> list[dict]:
    """For each data set (name -> float32 ``(K, 3, 3)`` matrices, tiled to the
    batch): ns/matrix of forward and forward+backward at ``config.layer_batch``
    (1 thread) and microseconds per forward+backward call at the training batch."""
    rows = []
    for data_name, M in data.items():
        big, small = _layer_calls(_tiled(M, config.layer_batch)), _layer_calls(_tiled(M, config.batch))
        data_rows = []
        for name, (fwd, fwd_bwd) in big.items():
            row = {"data": data_name, "method": name, "batch": config.layer_batch,
                   "forward_ns": _median_seconds(fwd, config.layer_repeats, config.min_run_time)
                   / config.layer_batch * 1e9}
            if fwd_bwd is not None:
                row["forward_backward_ns"] = (_median_seconds(fwd_bwd, config.layer_repeats, config.min_run_time)
                                              / config.layer_batch * 1e9)
                row["forward_backward_us_at_train_batch"] = _median_seconds(
                    small[name][1], config.layer_repeats, config.min_run_time) * 1e6
            data_rows.append(row)
            log(f"  {data_name:24s} {name:34s} forward {row['forward_ns']:9.1f} ns/matrix"
                + (f"  forward+backward {row['forward_backward_ns']:9.1f} ns/matrix" if fwd_bwd else ""))
        svd = next(r for r in data_rows if r["method"].startswith("SVD"))
        copy_row = next(r for r in data_rows if r["method"].startswith("copy_"))
        for row in data_rows:
            if "forward_backward_ns" in row:
                row["forward_backward_speedup_vs_svd"] = svd["forward_backward_ns"] / row["forward_backward_ns"]
            row["forward_speedup_vs_svd"] = svd["forward_ns"] / row["forward_ns"]
            row["forward_vs_copy"] = row["forward_ns"] / copy_row["forward_ns"]
        rows += data_rows
    return rows


def gradient_accuracy(data: dict[str, torch.Tensor], max_matrices: int = 10_000) -> list[dict]:
    """float32 dL/dM of each layer against float64 SVD autograd (L = sum G * R,
    G Gaussian), per data set: per-matrix relative Frobenius error
    ||g - g64|| / ||g64|| (matrices where the float64 gradient is finite), and
    how close M's singular values are (min_i<j |sigma_i - sigma_j| / sigma_1):
    SVD's backward divides by sigma_i^2 - sigma_j^2."""
    rows = []
    layers = {"torchrot.nn.RotationFit": torchrot.nn.RotationFit(),
              "SVD (torch.linalg.svd autograd)": torchrot.rotation_svd}
    for data_name, M in data.items():
        M = M[:max_matrices].detach()
        G = torch.randn(M.shape, generator=torch.Generator().manual_seed(2))
        reference = _gradient(torchrot.rotation_svd, M.double(), G.double())
        usable = torch.isfinite(reference).all(-1).all(-1)
        sigma = torch.linalg.svdvals(M.double())
        gaps = torch.stack([sigma[:, 0] - sigma[:, 1], sigma[:, 1] - sigma[:, 2]], -1).amin(-1) / sigma[:, 0]
        for name, layer in layers.items():
            g = _gradient(layer, M, G).double()
            error = ((g - reference).norm(dim=(-2, -1)) / reference.norm(dim=(-2, -1)))[usable]
            rows.append({"data": data_name, "layer": name, "matrices": int(usable.sum()),
                         "median_relative_error": error.median().item(),
                         "p99_relative_error": error.quantile(0.99).item(),
                         "max_relative_error": error.max().item(),
                         "nonfinite_share": 1 - torch.isfinite(g).all(-1).all(-1).double().mean().item(),
                         "median_relative_sigma_gap": gaps.median().item()})
    return rows


def _gradient(layer, M: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    M = M.clone().requires_grad_()
    return torch.autograd.grad((layer(M) * G).sum(), M)[0]


def format_layer_table(config: Config, layer_rows: list[dict]) -> str:
    lines = [
        f"Rotation layer alone: float32, batch {config.layer_batch:.0e}, 1 thread, median of "
        f"{config.layer_repeats} runs, every row of a data set in the same run; last column: one call at the "
        f"training batch ({config.batch}). Data: 'gaussian' = torchrot.testing's Gaussian matrices (like an "
        "untrained network's outputs); 'trained network outputs' = the raw 9-D outputs of the trained torchrot "
        "model on the test set (tiled).",
        "",
        "| data | layer | forward+backward ns/matrix | speed-up vs SVD | forward ns/matrix | forward vs copy "
        f"| forward+backward us per call (batch {config.batch}) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in layer_rows:
        fb = r.get("forward_backward_ns")
        if fb is None:
            backward_cells = ("-", "-")
            call = "-"
        else:
            backward_cells = (f"{fb:.1f}", f"{r['forward_backward_speedup_vs_svd']:.1f}x")
            call = f"{r['forward_backward_us_at_train_batch']:.1f}"
        lines.append(f"| {r['data']} | {r['method']} | {backward_cells[0]} | {backward_cells[1]} | "
                     f"{r['forward_ns']:.1f} | {r['forward_vs_copy']:.1f} | {call} |")
    return "\n".join(lines)


def format_accuracy_table(rows: list[dict]) -> str:
    lines = [
        "Gradient accuracy in float32: dL/dM (L = sum G * R, G Gaussian) against autograd through float64 SVD, "
        "per matrix ||g - g64||_F / ||g64||_F; sigma gap = median of min |sigma_i - sigma_j| / sigma_1 "
        "(SVD's backward divides by sigma_i^2 - sigma_j^2).",
        "",
        "| data | layer | matrices | median rel. error | 99th percentile | max | non-finite | sigma gap |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['data']} | {r['layer']} | {r['matrices']} | {r['median_relative_error']:.1e} | "
                     f"{r['p99_relative_error']:.1e} | {r['max_relative_error']:.1e} | {r['nonfinite_share']:.2%} | "
                     f"{r['median_relative_sigma_gap']:.3f} |")
    return "\n".join(lines)
