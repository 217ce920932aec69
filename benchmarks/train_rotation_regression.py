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
The model, data and training: ``rotation_regression_model.py``; the layers
alone: ``rotation_regression_layers.py``; this file runs them and writes
the results.
"""
from __future__ import annotations

import argparse
import json
import os
from dataclasses import asdict

import torch
from rotation_regression_layers import (
    format_accuracy_table,
    format_layer_table,
    gradient_accuracy,
    time_rotation_layers,
)
from rotation_regression_model import (
    COLORS,
    LABELS,
    METHODS,
    SHORT_LABELS,
    Config,
    network_outputs,
    summarize,
    train_pair,
)

import torchrot
from torchrot.bench.machine import machine_info
from torchrot.bench.options import positive_int
from torchrot.testing import make_matrices

__all__ = ["main", "parse_args"]


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


def parse_args(argv=None) -> tuple[Config, str]:
    defaults = Config()
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    for name, kind in (("steps", positive_int), ("batch", positive_int), ("points", positive_int),
                       ("lr", float), ("noise", float), ("test-size", positive_int),
                       ("eval-every", positive_int), ("seeds", positive_int), ("threads", positive_int),
                       ("layer-batch", positive_int), ("layer-repeats", positive_int), ("min-run-time", float)):
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
