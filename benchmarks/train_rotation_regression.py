"""Training benchmark: rotation regression with torchrot's layer vs SVD.

The same small PointNet-style network is trained twice, with the same initial
weights, the same batches and the same number of steps; only its last layer
differs: the raw 9-D output M becomes a rotation either by
``torchrot.nn.RotationFit`` (R = argmax tr(R^T M), backward through the
optimality condition) or by SVD special orthogonalisation
``U diag(1, 1, det UV^T) V^T`` (``torchrot.rotation_svd``, autograd through
``torch.linalg.svd``). Both compute the same function, so the two runs should
reach the same accuracy; they differ in speed.

Task: a fixed point cloud P (N points, an asymmetric tripod) is rotated
by a random rotation R* (``torchrot.testing.random_rotations``); the network
sees the rotated points (column vectors: p_i' = R* p_i) and predicts R*. Loss:
the mean squared Frobenius (chordal) distance ||R - R*||_F^2. Reported: the
mean geodesic error on a fixed test set after training, the time per training
step (the two models are stepped alternately, so machine load hits both
alike), and the rotation layer's forward+backward alone in ns/matrix at batch
1e5, float32, 1 thread, beside SVD autograd and a plain copy in the same run
(medians of several ``torch.utils.benchmark`` runs).

Run: ``python benchmarks/train_rotation_regression.py`` (2000 steps, 3 seeds:
a few minutes); e.g. ``--steps 20000 --seeds 10`` for a longer run. Writes
``train_rotation_regression.{json,md,png}`` into ``benchmarks/results/``.
"""
from __future__ import annotations

import argparse
import copy
import json
import math
import os
import statistics
import time
from dataclasses import asdict, dataclass

import torch
from torch import nn

import torchrot
from torchrot import baselines
from torchrot.bench.micro import machine_info, median_seconds
from torchrot.testing import make_matrices, random_rotations

METHODS = ("torchrot", "svd")
LABELS = {
    "torchrot": "torchrot.nn.RotationFit",
    "svd": "SVD special orthogonalisation (torch.linalg.svd autograd)",
}
SHORT_LABELS = {"torchrot": "torchrot RotationFit", "svd": "SVD (torch.linalg.svd autograd)"}
COLORS = {"torchrot": "tab:blue", "svd": "tab:orange"}


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


# ---------------------------------------------------------------------------
# Model and data
# ---------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------
# Rotation layer alone
# ---------------------------------------------------------------------------


def _layer_calls(M: torch.Tensor):
    """name -> (forward, forward+backward) callables on the float32 ``(B, 3, 3)``
    matrices M, plus the copy floor (forward only)."""
    M = M.detach().clone().requires_grad_()
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(1))
    out = torch.empty_like(M)
    layers = {"torchrot.nn.RotationFit": torchrot.nn.RotationFit(),
              "SVD (torch.linalg.svd autograd)": torchrot.rotation_svd}
    if baselines.available("roma"):
        layers["roma.special_procrustes"] = baselines.roma_special_procrustes

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


def network_outputs(model: PointNetRegressor, points: torch.Tensor) -> torch.Tensor:
    """The raw 9-D outputs M (before the rotation layer) as ``(B, 3, 3)``."""
    with torch.no_grad():
        return model.head(model.point_mlp(points).amax(-2)).unflatten(-1, (3, 3))


# ---------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------


def summarize(runs: list[dict]) -> dict:
    """Per method: mean over seeds of each final figure (and the spread)."""
    summary = {}
    for method in METHODS:
        finals = [run["final"][method] for run in runs]
        summary[method] = {key: statistics.fmean(f[key] for f in finals) for key in finals[0]}
        summary[method]["test_mean_deg_per_seed"] = [f["test_mean_deg"] for f in finals]
    return summary


def format_tables(config: Config, summary: dict, layer_rows: list[dict]) -> str:
    seeds = f"mean of {config.seeds} seeds" if config.seeds > 1 else "1 seed"
    lines = [
        f"Training: {config.steps} steps, batch {config.batch}, {config.points} points, Adam lr {config.lr} "
        f"(cosine), float32, {config.threads} thread(s), {seeds}; test set {config.test_size} rotations.",
        "",
        "| rotation layer | test mean geodesic error (deg) | per seed | test median (deg) | train loss (last 100) "
        "| ms per training step (median) | training time (s) | non-finite gradient steps |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for method in METHODS:
        s = summary[method]
        per_seed = ", ".join(f"{v:.3f}" for v in s["test_mean_deg_per_seed"])
        lines.append(f"| {LABELS[method]} | {s['test_mean_deg']:.3f} | {per_seed} | {s['test_median_deg']:.3f} | "
                     f"{s['final_train_loss']:.5f} | {s['step_ms_median']:.2f} | {s['train_seconds']:.1f} | "
                     f"{s['nonfinite_steps']:.0f} |")
    return "\n".join(lines) + "\n\n" + format_layer_table(config, layer_rows)


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


def _smooth(values: list[float], window: int) -> list[float]:
    """Trailing running mean (window clipped at the start)."""
    out, total = [], 0.0
    for i, v in enumerate(values):
        total += v
        if i >= window:
            total -= values[i - window]
        out.append(total / min(i + 1, window))
    return out


def _cumulative(values: list[float]) -> list[float]:
    out, total = [], 0.0
    for v in values:
        total += v
        out.append(total)
    return out


def plot(runs: list[dict], summary: dict, config: Config, path: str) -> None:
    """Three panels, both methods: training loss vs step and vs wall-clock
    (first seed raw and faint, running means of every seed), test error vs step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator

    window = max(1, min(100, config.steps // 30))
    fig, axes = plt.subplots(1, 3, figsize=(18, 5.2))
    for index, run in enumerate(runs):
        first = index == 0
        for method in METHODS:
            h = run["history"][method]
            color = COLORS[method]
            steps = range(1, len(h["loss"]) + 1)
            clock = _cumulative(h["seconds"])
            label = SHORT_LABELS[method] if first else None
            for ax, x in ((axes[0], steps), (axes[1], clock)):
                if first:
                    ax.plot(x, h["loss"], color=color, alpha=0.12, linewidth=0.5)
                ax.plot(x, _smooth(h["loss"], window), color=color, linewidth=1.8 if first else 0.9,
                        alpha=1.0 if first else 0.6, linestyle="-" if first else "--", label=label)
            if first:
                label = f"{SHORT_LABELS[method]}: final {summary[method]['test_mean_deg']:.2f} deg"
                if len(runs) > 1:
                    label += f" (mean of {len(runs)} seeds)"
            axes[2].plot(h["eval_step"], h["eval_mean_deg"], color=color, marker="o" if first else None,
                         markersize=3, linewidth=1.6 if first else 0.9, alpha=1.0 if first else 0.6,
                         linestyle="-" if first else "--", label=label)
    axes[0].set_xlabel("training step")
    axes[1].set_xlabel("training time (s; each model's own steps)")
    for ax in axes[:2]:
        ax.set_ylabel(f"training loss ||R - R*||²_F (running mean of {window} steps)")
    axes[2].set_xlabel("training step")
    axes[2].set_ylabel(f"mean geodesic error on {config.test_size} test rotations (deg)")
    titles = ("training loss vs step", "training loss vs wall-clock", "test error vs step")
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    for ax, title in zip(axes, titles):
        ax.set_yscale("log")
        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(plain)
        ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))
        ax.set_title(title)
        ax.grid(True, which="major", alpha=0.35)
        ax.legend(fontsize=9)
    speed = {m: summary[m]["step_ms_median"] for m in METHODS}
    others = "seed 1" if len(runs) == 2 else f"seeds 1-{len(runs) - 1}"
    seeds = f"seed 0 solid, {others} dashed" if len(runs) > 1 else "seed 0"
    fig.suptitle(f"Rotation regression: PointNet on {config.points} points, batch {config.batch}, {config.steps} "
                 f"steps, same init and batches for both layers ({seeds}). Median step: torchrot "
                 f"{speed['torchrot']:.1f} ms, SVD {speed['svd']:.1f} ms")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_results(config: Config, runs: list[dict], summary: dict, layer_rows: list[dict],
                  accuracy_rows: list[dict], tables: str, folder: str) -> list[str]:
    os.makedirs(folder, exist_ok=True)
    stem = os.path.join(folder, "train_rotation_regression")
    paths = [stem + ".json", stem + ".md", stem + ".png"]
    with open(paths[0], "w") as f:
        json.dump({"machine": machine_info(), "config": asdict(config), "summary": summary,
                   "layer_timings": layer_rows, "gradient_accuracy": accuracy_rows, "runs": runs}, f)
    with open(paths[1], "w") as f:
        f.write(f"# Training benchmark: rotation regression\n\nMachine: {machine_info()}\n\n{tables}\n")
    try:
        plot(runs, summary, config, paths[2])
    except ImportError:
        print("matplotlib is not installed (pip install 'torchrot[bench]'): no plot written")
        paths.pop()
    return paths


# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------


def _positive_int(text: str) -> int:
    value = int(float(text))  # accepts 1e5
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


def parse_args(argv=None) -> tuple[Config, str]:
    defaults = Config()
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    for name, kind in (("steps", _positive_int), ("batch", _positive_int), ("points", _positive_int),
                       ("lr", float), ("noise", float), ("test-size", _positive_int),
                       ("eval-every", _positive_int), ("seeds", _positive_int), ("threads", _positive_int),
                       ("layer-batch", _positive_int), ("layer-repeats", _positive_int), ("min-run-time", float)):
        attr = name.replace("-", "_")
        parser.add_argument(f"--{name}", type=kind, default=getattr(defaults, attr),
                            help=f"(default {getattr(defaults, attr)})")
    parser.add_argument("--skip-training", action="store_true", help="only time the rotation layers")
    parser.add_argument("--output", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results"),
                        help="folder for the JSON, Markdown and PNG (default benchmarks/results)")
    args = parser.parse_args(argv)
    config = Config(**{k: v for k, v in vars(args).items() if k in Config.__dataclass_fields__})
    return config, args.output, args.skip_training


def main(argv=None) -> int:
    config, output, skip_training = parse_args(argv)
    grad_fn = torchrot.fit_rotation(torch.eye(3).requires_grad_()).grad_fn
    if not skip_training and (grad_fn is None or "NotImplemented" in grad_fn.name()):
        raise SystemExit("torchrot.fit_rotation has no autograd in this build: cannot train through "
                         "RotationFit (use --skip-training to time the rotation layers only)")
    print(f"training benchmark: {machine_info()}\n{config}")
    torch.set_num_threads(config.threads)
    runs, timing_data = [], {}
    if not skip_training:
        for seed in range(config.seeds):
            run, models, test_points = train_pair(config, seed)
            runs.append(run)
            if seed == 0:
                timing_data["trained network outputs"] = network_outputs(models["torchrot"], test_points)
    # Generic 3x3 matrices, like an untrained network's outputs.
    timing_data = {"gaussian": make_matrices("gaussian", config.layer_batch, seed=0, dtype=torch.float32),
                   **timing_data}
    print("rotation layer alone:")
    layer_rows = time_rotation_layers(config, timing_data)
    accuracy_rows = gradient_accuracy(timing_data)
    if skip_training:
        print(format_layer_table(config, layer_rows) + "\n\n" + format_accuracy_table(accuracy_rows))
        return 0
    summary = summarize(runs)
    tables = format_tables(config, summary, layer_rows) + "\n\n" + format_accuracy_table(accuracy_rows)
    print("\n" + tables)
    for path in write_results(config, runs, summary, layer_rows, accuracy_rows, tables, output):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
