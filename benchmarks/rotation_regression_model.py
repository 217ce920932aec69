"""The training benchmark's model, data and training loop
(``benchmarks/train_rotation_regression.py`` runs it).

A small PointNet-style network regresses the rotation R* of a fixed point
cloud P (an asymmetric tripod) from its rotated copy (column vectors:
p_i' = R* p_i); its raw 9-D output M becomes a rotation by ``torchrot.nn.RotationFit``
or by SVD special orthogonalisation (``torchrot.rotation_svd``). Loss: the mean
squared Frobenius (chordal) distance ||R - R*||_F^2; both methods are trained
from the same initial weights on the same batches, stepped alternately.
"""
from __future__ import annotations

import copy
import statistics
import time
from dataclasses import dataclass

import torch
from torch import nn

import torchrot
from torchrot.testing import random_rotations

__all__ = ["COLORS", "Config", "LABELS", "METHODS", "PointNetRegressor", "SHORT_LABELS", "SVDOrthogonalization",
           "chordal_loss", "geodesic_degrees", "make_point_cloud", "network_outputs", "rotation_layer",
           "sample_batch", "summarize", "train_pair"]

METHODS = ("torchrot", "svd")
LABELS = {
    "torchrot": "torchrot.nn.RotationFit",
    "svd": "SVD special orthogonalisation (torch.linalg.svd autograd)",
}
SHORT_LABELS = {"torchrot": "torchrot RotationFit", "svd": "SVD (torch.linalg.svd autograd)"}
COLORS = {"torchrot": "tab:blue", "svd": "tab:orange"}  # of the plots, per method


@dataclass
class Config:
    steps: int = 2000
    batch: int = 64
    points: int = 64
    lr: float = 1e-3
    noise: float = 0.0
    test_size: int = 1000
    eval_every: int = 100
    seeds: int = 3
    threads: int = 1
    layer_batch: int = 100_000
    layer_repeats: int = 5
    min_run_time: float = 0.2


class SVDOrthogonalization(nn.Module):
    """(..., 9) row-major -> (..., 3, 3): U diag(1, 1, det UV^T) V^T by torch.linalg.svd."""

    def forward(self, M: torch.Tensor) -> torch.Tensor:
        return torchrot.rotation_svd(M.unflatten(-1, (3, 3)))


def rotation_layer(method: str) -> nn.Module:
    return torchrot.nn.RotationFit() if method == "torchrot" else SVDOrthogonalization()


class PointNetRegressor(nn.Module):
    """Points (B, N, 3) -> rotations (B, 3, 3): shared per-point MLP, max-pool
    over points, MLP head to 9 numbers, then the rotation layer."""

    def __init__(self, layer: nn.Module, width: int = 128) -> None:
        super().__init__()
        self.point_mlp = nn.Sequential(nn.Linear(3, 64), nn.ReLU(), nn.Linear(64, width), nn.ReLU())
        self.head = nn.Sequential(nn.Linear(width, width), nn.ReLU(), nn.Linear(width, 9))
        self.rotation = layer

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        features = self.point_mlp(points).amax(-2)
        return self.rotation(self.head(features))


def make_point_cloud(n: int, seed: int) -> torch.Tensor:
    """(n, 3) float32 fixed cloud without symmetries: a tripod of three
    orthogonal arms of lengths 1.5, 1.0 and 0.6 (points spread uniformly along
    each, plus a little noise), centred. (A Gaussian blob would be nearly
    symmetric under half-turns about its axes, which traps training at large
    errors on some seeds.)"""
    gen = torch.Generator().manual_seed(seed)
    lengths = torch.tensor([1.5, 1.0, 0.6], dtype=torch.float64)
    arm = torch.arange(n) % 3
    cloud = torch.zeros(n, 3, dtype=torch.float64)
    cloud[torch.arange(n), arm] = torch.rand(n, generator=gen, dtype=torch.float64) * lengths[arm]
    cloud += 0.03 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    return (cloud - cloud.mean(0)).float()


def sample_batch(cloud: torch.Tensor, batch: int, gen: torch.Generator, noise: float):
    """Rotated copies of ``cloud`` (B, N, 3) and their rotations R* (B, 3, 3):
    points_i = R* cloud_i (+ Gaussian noise)."""
    R = random_rotations(batch, gen).float()
    points = cloud @ R.mT
    if noise > 0:
        points = points + noise * torch.randn(points.shape, generator=gen)
    return points, R


def chordal_loss(R: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (R - target).square().sum((-2, -1)).mean()


def geodesic_degrees(R: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Angle of R^T R* per matrix, in degrees."""
    cos = ((R.double() * target.double()).sum((-2, -1)) - 1) / 2
    return torch.rad2deg(torch.arccos(cos.clamp(-1, 1)))


def _train_step(model, optimizer, points, target) -> tuple[float, float, bool]:
    """One step; returns (loss, seconds, all gradients finite)."""
    start = time.perf_counter()
    optimizer.zero_grad(set_to_none=True)
    loss = chordal_loss(model(points), target)
    loss.backward()
    finite = all(bool(torch.isfinite(p.grad).all()) for p in model.parameters())
    optimizer.step()
    return loss.item(), time.perf_counter() - start, finite


@torch.no_grad()
def _evaluate(model, test_points, test_R) -> torch.Tensor:
    return geodesic_degrees(model(test_points), test_R)


def train_pair(config: Config, seed: int, log=print) -> tuple[dict, dict[str, nn.Module], torch.Tensor]:
    """Trains one model per method from the same initial weights on the same
    batches, stepping them alternately (order swapped every step). Returns the
    run's figures and histories, the trained models and the test inputs."""
    torch.manual_seed(seed)
    base = PointNetRegressor(nn.Identity())
    models = {}
    for method in METHODS:
        model = copy.deepcopy(base)
        model.rotation = rotation_layer(method)
        models[method] = model
    optimizers = {m: torch.optim.Adam(models[m].parameters(), lr=config.lr) for m in METHODS}
    schedulers = {m: torch.optim.lr_scheduler.CosineAnnealingLR(optimizers[m], config.steps) for m in METHODS}
    cloud = make_point_cloud(config.points, seed)
    train_gen = torch.Generator().manual_seed(seed + 1)
    test_points, test_R = sample_batch(cloud, config.test_size, torch.Generator().manual_seed(seed + 2), config.noise)
    history = {m: {"loss": [], "seconds": [], "eval_step": [], "eval_mean_deg": [], "nonfinite_steps": 0}
               for m in METHODS}
    for step in range(1, config.steps + 1):
        points, target = sample_batch(cloud, config.batch, train_gen, config.noise)
        order = METHODS if step % 2 else METHODS[::-1]
        for method in order:
            loss, seconds, finite = _train_step(models[method], optimizers[method], points, target)
            schedulers[method].step()
            h = history[method]
            h["loss"].append(loss)
            h["seconds"].append(seconds)
            h["nonfinite_steps"] += not finite
        if step % config.eval_every == 0 or step == config.steps:
            line = [f"seed {seed} step {step:6d}"]
            for method in METHODS:
                errors = _evaluate(models[method], test_points, test_R)
                history[method]["eval_step"].append(step)
                history[method]["eval_mean_deg"].append(errors.mean().item())
                line.append(f"{method}: loss {statistics.fmean(history[method]['loss'][-config.eval_every:]):.4f} "
                            f"test {errors.mean().item():6.2f} deg")
            log("  ".join(line))
    final = {}
    for method in METHODS:
        errors = _evaluate(models[method], test_points, test_R)
        h = history[method]
        final[method] = {
            "test_mean_deg": errors.mean().item(),
            "test_median_deg": errors.median().item(),
            "final_train_loss": statistics.fmean(h["loss"][-min(100, len(h["loss"])):]),
            "step_ms_median": statistics.median(h["seconds"]) * 1e3,
            "step_ms_mean": statistics.fmean(h["seconds"]) * 1e3,
            "train_seconds": sum(h["seconds"]),
            "nonfinite_steps": h["nonfinite_steps"],
        }
    return {"seed": seed, "final": final, "history": history}, models, test_points


def network_outputs(model: PointNetRegressor, points: torch.Tensor) -> torch.Tensor:
    """The raw 9-D outputs M (before the rotation layer) as ``(B, 3, 3)``."""
    with torch.no_grad():
        return model.head(model.point_mlp(points).amax(-2)).unflatten(-1, (3, 3))


def summarize(runs: list[dict]) -> dict:
    """Per method: mean over seeds of each final figure (and the spread)."""
    summary = {}
    for method in METHODS:
        finals = [run["final"][method] for run in runs]
        summary[method] = {key: statistics.fmean(f[key] for f in finals) for key in finals[0]}
        summary[method]["test_mean_deg_per_seed"] = [f["test_mean_deg"] for f in finals]
    return summary
