"""The PNG figures of ``python -m torchrot bench`` (matplotlib, Agg): the
microbenchmark's scaling sweep (:func:`plot_scaling`, from its rows) and the
paper's Figs. 5, 6 and 7 (from the plain-data results of
:mod:`torchrot.bench.statistics` / :mod:`torchrot.bench.experiments`).
Every number drawn comes from the run's results.
"""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

__all__ = ["SCALING_COLORS", "method_colors", "plot_fig5", "plot_fig6", "plot_fig7", "plot_scaling",
           "scaling_figure"]

FIT_LABELS = {"svd": "torch.linalg.svd", "one_step": "torchrot 1-step warm start",
              "converged": "torchrot converged (warm start)"}
FIT_COLORS = {"svd": "#7f7f7f", "one_step": "#d62728", "converged": "#1f77b4"}
DATA_COLORS = {"arap": "#6baed6", "elasticity": "#fd8d3c"}
DATA_LABELS = {"arap": "ARAP session", "elasticity": "elasticity drop"}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _step_hist(ax, histogram: dict, color: str, label: str) -> None:
    edges = np.asarray(histogram["edges"])
    counts = np.asarray(histogram["counts"], dtype=float)
    share = counts / max(counts.sum(), 1.0)
    ax.stairs(share, edges, fill=True, alpha=0.35, color=color)
    ax.stairs(share, edges, color=color, linewidth=1.5, label=label)


def plot_fig5(stats: dict, path: str) -> None:
    """Fig. 5: how far the optimal rotation is from the warm start, the
    condition numbers, and the error of one Newton (Cayley) step from the warm
    start. ``stats``: data set name -> :func:`~torchrot.bench.statistics.recording_statistics`."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(18, 5))
    ax = axes[0]
    for name, s in stats.items():
        a = s["angle_degrees"]
        hist = a["histogram"]
        unmoved = hist["counts"][0] / max(sum(hist["counts"]), 1)  # the first bin holds everything below it
        _step_hist(ax, {"edges": hist["edges"][1:], "counts": hist["counts"][1:]}, DATA_COLORS.get(name, "k"),
                   f"{DATA_LABELS.get(name, name)}: median {a['median']:.2g}°, {a['share_below_1']:.0%} < 1°\n"
                   f"(+{unmoved:.0%} below {hist['edges'][1]:.0e}°, not drawn)")
    ax.set_xscale("log")
    ax.set_xlabel("angle of the optimal rotation from the warm start (degrees)")
    ax.set_ylabel("share of recorded matrices")
    ax.set_title("Optimal rotation vs warm start R_prev")
    ax.legend(fontsize=8, loc="upper left")
    ax = axes[1]
    for name, s in stats.items():
        c = s["condition_number"]
        _step_hist(ax, c["histogram"], DATA_COLORS.get(name, "k"),
                   f"{DATA_LABELS.get(name, name)}: median {c['median']:.3g}, 90% below {c['p90']:.3g}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_ylim(1e-5, 1.5)
    ax.set_xlabel("condition number σ_max / σ_min of M")
    ax.set_ylabel("share of recorded matrices (log scale)")
    ax.set_title("Condition numbers of the recorded M")
    ax.legend(fontsize=8, loc="upper right")
    ax = axes[2]
    floor = 1e-17
    for name, s in reversed(list(stats.items())):  # the first data set drawn on top
        angle = np.asarray(s["scatter"]["angle_degrees"])
        moved = angle > 1e-6  # matrices whose warm start is already exact are left out
        err = np.maximum(np.asarray(s["scatter"]["newton"]), floor)[moved]
        newton, conservative = s["one_step"]["newton"], s["one_step"]["conservative"]
        ax.scatter(angle[moved], err, s=6, alpha=0.4, color=DATA_COLORS.get(name, "k"), edgecolors="none",
                   label=f"{DATA_LABELS.get(name, name)}: {newton['share_below_1e-5']:.1%} below 1e-5 "
                         f"(conservative step: {conservative['share_below_1e-5']:.1%})")
    ax.axhline(1e-5, color="k", linestyle=":", linewidth=1)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_ylim(floor / 2, 10)
    ax.set_xlabel("angle of the optimal rotation from the warm start (degrees)")
    ax.set_ylabel("|R_1 - R*|_F after one Newton step")
    ax.set_title("Error of one Newton step from the warm start (float64)")
    ax.legend(fontsize=8, loc="upper left", markerscale=3)
    fig.suptitle("Fig. 5 analogue: the recorded local steps of the built-in ARAP session and elasticity drop")
    # fixed margins: tight_layout would lay out the log axes' ticks once more (seconds on 2 cores)
    fig.subplots_adjust(left=0.04, right=0.99, bottom=0.11, top=0.87, wspace=0.22)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_fig6(timings: dict, path: str) -> None:
    """Fig. 6: rotation fit, whole local step and global step, median ms per
    iteration, for each fit. ``timings``: local-step dtype -> app name ->
    phase-times result (one row of panels per dtype)."""
    plt = _pyplot()
    labels = list(timings)
    apps = list(next(iter(timings.values())))
    fig, axes = plt.subplots(len(labels), len(apps), figsize=(7.4 * len(apps), 5.0 * len(labels)), squeeze=False)
    bars = (("fit", "rotation fit", "#fdae6b"), ("local", "local step (assembly + fit)", "#e6550d"),
            ("global", "global step (rhs + back-substitution)", "#3182bd"))
    top = max(r["fits"][f][k] for per_app in timings.values() for r in per_app.values() for f in r["fits"]
              for k, _, _ in bars)
    bottom = min(r["fits"][f][k] for per_app in timings.values() for r in per_app.values() for f in r["fits"]
                 for k, _, _ in bars)
    for row, label in enumerate(labels):
        for ax, app in zip(axes[row], apps):
            result = timings[label][app]
            fits = list(result["fits"])
            x = np.arange(len(fits))
            width = 0.26
            for k, (key, name, color) in enumerate(bars):
                values = [result["fits"][f][key] for f in fits]
                rects = ax.bar(x + (k - 1) * width, values, width, label=name, color=color)
                for rect, value in zip(rects, values):
                    ax.annotate(f"{value:.3g}", (rect.get_x() + rect.get_width() / 2, value), ha="center",
                                va="bottom", fontsize=8, xytext=(0, 2), textcoords="offset points")
            ratios = [f"fit {result['fits'][f]['fit'] / result['fits'][f]['global']:.2f}x global,\n"
                      f"local {result['fits'][f]['local'] / result['fits'][f]['global']:.2f}x global" for f in fits]
            ax.set_xticks(x, [f"{FIT_LABELS.get(f, f)}\n{r}" for f, r in zip(fits, ratios)], fontsize=8.5)
            ax.set_yscale("log")
            ax.set_ylim(bottom / 2, top * 6)
            ax.set_ylabel("ms per iteration (median, log scale)")
            size = (f"{result['vertices']:,} vertices" if "tets" not in result
                    else f"{result['tets']:,} tets, {result['vertices']:,} vertices")
            ax.set_title(f"{'ARAP' if app == 'arap' else 'Co-rotational elasticity'}: {result['mesh']} ({size}), "
                         f"{label} local step, {result['threads']} thread", fontsize=10)
            ax.legend(fontsize=8, loc="upper right")
            ax.grid(True, axis="y", which="both", alpha=0.25)
    fig.suptitle("Fig. 6 analogue: local vs global step per local-global iteration")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_fig7(traces: dict, path: str) -> None:
    """Fig. 7: energy against accumulated solver time for each fit, from the
    same start. ``traces``: app name -> energy-trace result."""
    plt = _pyplot()
    apps = list(traces)
    fig, axes = plt.subplots(1, len(apps), figsize=(7.2 * len(apps), 6.4), squeeze=False)
    for ax, app in zip(axes[0], apps):
        result = traces[app]
        for fit, trace in result["fits"].items():
            seconds = np.asarray(trace["seconds"])
            energy = np.asarray(trace["energy"])
            ax.plot(seconds, energy, marker="o", markersize=2.5, linewidth=1.5, color=FIT_COLORS.get(fit),
                    label=f"{FIT_LABELS.get(fit, fit)}: {len(energy)} iterations in {seconds[-1]:.2f} s, "
                          f"E = {energy[-1]:.7g}")
        if "reference_iterations" in result:
            ax.axhline(result["reference_energy"], color="k", linestyle=":", linewidth=1,
                       label=f"converged fit after {result['reference_iterations']} iterations: "
                             f"E = {result['reference_energy']:.7g}")
        ax.set_xscale("log")
        ax.set_xlabel("accumulated solver time (s, log scale; energy evaluation excluded)")
        ax.set_ylabel("energy after each global step")
        if app == "arap":
            title = (f"ARAP {result['mesh']} ({result['vertices']:,} vertices): handles jump "
                     f"{result['jump_frames']} frames")
        else:
            title = f"Elasticity {result['mesh']} ({result['tets']:,} tets): one time step (frame {result['frame']})"
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=1, frameon=False)
        ax.grid(True, which="both", alpha=0.25)
    fig.suptitle("Fig. 7 analogue: energy vs wall-clock time, same start for every rotation fit")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


#: The scaling plot's colours, one per method in the order methods first
#: appear (matplotlib's tab10, then tab20's lighter shades).
SCALING_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
                  "#bcbd22", "#17becf", "#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5", "#c49c94",
                  "#f7b6d2", "#c7c7c7", "#dbdb8d", "#9edae5")


def method_colors(methods: Iterable[str]) -> dict[str, str]:
    """One colour per distinct method, in order of first appearance: the one
    mapping every panel of the scaling figure draws with, so a method keeps
    its colour across panels. Raises ValueError beyond len(SCALING_COLORS) methods."""
    names = list(dict.fromkeys(methods))
    if len(names) > len(SCALING_COLORS):
        raise ValueError(f"{len(names)} methods, but only {len(SCALING_COLORS)} distinct colours")
    return dict(zip(names, SCALING_COLORS))


def scaling_figure(rows, machine: dict | None = None):
    """The scaling sweep's figure: ns/matrix against N (log-log), a panel per
    data set, one line per method in its :func:`method_colors` colour (the
    ``copy_`` floor dashed), suspicious timings crossed out, and one legend
    below the panels. ``rows``: the run's :class:`~torchrot.bench.rows.Row` s
    (those of the "scaling" part are drawn)."""
    plt = _pyplot()
    from matplotlib.lines import Line2D

    scaling = [r for r in rows if r.part == "scaling"]
    data_sets = list(dict.fromkeys(r.data for r in scaling))
    colors = method_colors(r.method for r in scaling)
    fig, axes = plt.subplots(1, len(data_sets), figsize=(6.5 * len(data_sets), 6.2), squeeze=False, sharey=True)
    flagged = False
    for ax, data in zip(axes[0], data_sets):
        for method, color in colors.items():
            points = sorted((r.n, r.ns_per_matrix, bool(r.suspicion)) for r in scaling
                            if r.data == data and r.method == method)
            if not points:
                continue
            n, ns, suspicious = zip(*points)
            floor = any(r.key == "copy" for r in scaling if r.method == method)
            ax.plot(n, ns, "--" if floor else "-", marker="o", color=color, label=method)
            marked = [(x, y) for x, y, s in points if s]
            if marked:
                flagged = True
                ax.plot(*zip(*marked), linestyle="none", marker="x", markersize=11, color="k")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("N (matrices per call)")
        kinds = sorted({(r.dtype, r.threads) for r in scaling if r.data == data})
        ax.set_title(f"{data} data, " + "; ".join(f"{dtype}, {threads} thread{'s' * (threads > 1)}"
                                                  for dtype, threads in kinds))
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("ns per matrix (median)")
    handles = [Line2D([], [], color=c, marker="o", linestyle="--" if any(
        r.key == "copy" for r in scaling if r.method == m) else "-", label=m) for m, c in colors.items()]
    if flagged:
        handles.append(Line2D([], [], color="k", marker="x", linestyle="none", markersize=9,
                              label="suspicious timing (marked ! in bench.md)"))
    columns = 3
    fig.legend(handles=handles, loc="lower center", ncol=columns, fontsize=9, frameon=False)
    legend_rows = -(-len(handles) // columns)
    machine = machine or {}
    fig.suptitle(f"torchrot vs baselines ({machine.get('aten_cpu_capability', '?')}, "
                 f"{machine.get('processor', '?')})")
    # fixed margins (tight_layout: seconds), the bottom one sized to the legend below the panels
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.1 + 0.045 * legend_rows, top=0.9, wspace=0.08)
    return fig


def plot_scaling(rows, path: str, machine: dict | None = None) -> None:
    """PNG of :func:`scaling_figure` at ``path``."""
    plt = _pyplot()
    fig = scaling_figure(rows, machine)
    fig.savefig(path, dpi=110)
    plt.close(fig)
