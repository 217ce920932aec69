"""The acceptance targets of the applications part, checked on its results.

These thresholds are the project's goals for the ARAP/elasticity experiments
(not part of the installed package): run ``python -m torchrot bench`` (it
writes ``results/apps.json``), then

    python benchmarks/app_targets.py [results/apps.json]

prints each target with the measured value and whether it holds (exit
status 1 if one does not).
"""
from __future__ import annotations

import json
import sys

ENERGY_TOLERANCE = 1e-6  # converged energies must agree to this, relative
MONOTONE_TOLERANCE = 1e-10  # energy increases below this (relative) are rounding of its evaluation

__all__ = ["ENERGY_TOLERANCE", "MONOTONE_TOLERANCE", "main", "targets", "targets_markdown"]


def targets(results: dict) -> list[dict]:
    """The targets, each {"target", "measured", "holds"}, from the results
    of :func:`torchrot.bench.apps.run_apps` (``apps.json``)."""
    out = []
    for label, timings in results["timings"].items():
        arap = timings["arap"]
        fits = arap["fits"]
        where = f"{arap['mesh']}, {arap['vertices']:,} vertices, {label} local step, {arap['threads']} thread"
        for fit in ("one_step", "converged"):
            if fit in fits:
                ratio = fits[fit]["fit"] / fits[fit]["global"]
                out.append({"target": f"ARAP ({where}): torchrot rotation fit ({fit}) <= 0.1x the global step",
                            "measured": f"{fits[fit]['fit']:.3g} ms vs {fits[fit]['global']:.3g} ms = {ratio:.3f}x",
                            "holds": ratio <= 0.1})
                ratio = fits[fit]["local"] / fits[fit]["global"]
                out.append({"target": f"ARAP ({where}): whole local step ({fit}) no slower than the global step",
                            "measured": f"{fits[fit]['local']:.3g} ms vs {fits[fit]['global']:.3g} ms = "
                                        f"{ratio:.2f}x", "holds": ratio <= 1.0})
        if "svd" in fits:
            ratio = fits["svd"]["local"] / fits["svd"]["global"]
            out.append({"target": f"ARAP ({where}): with torch.linalg.svd the local step dominates",
                        "measured": f"{fits['svd']['local']:.3g} ms vs {fits['svd']['global']:.3g} ms = "
                                    f"{ratio:.1f}x", "holds": ratio > 1.0})
    validation = results.get("validation")
    if validation:
        where = (f"{validation['mesh']}, {validation['vertices']:,} vertices, {validation['iterations']} iterations, "
                 f"{validation.get('dtype', 'float64')} local step")
        for fit, v in validation["fits"].items():
            if fit == "svd":
                continue
            d = abs(v["relative_difference_to_svd"])
            out.append({"target": f"ARAP ({where}): converged energy with {fit} = SVD solver's within 1e-6",
                        "measured": f"relative difference {d:.1e}", "holds": d <= ENERGY_TOLERANCE})
        for fit, v in validation["fits"].items():
            d = abs(v["relative_difference_to_libigl"])
            out.append({"target": f"ARAP ({where}): converged energy with {fit} = igl.arap_solve's within 1e-6",
                        "measured": f"relative difference {d:.1e}", "holds": d <= ENERGY_TOLERANCE})
    worst, where = 0.0, []
    for name, trace in results.get("traces", {}).items():
        for fit, t in trace["fits"].items():
            worst = max(worst, t["max_relative_increase"])
            where.append(f"{name}/{fit}")
    if validation:
        for fit, v in validation["fits"].items():
            worst = max(worst, v["max_relative_increase"])
            where.append(f"validation/{fit}")
    if where:
        out.append({"target": "energy never increases across local-global iterations "
                              f"(runs: {', '.join(where)})",
                    "measured": f"largest increase {worst:.1e} relative (tolerance {MONOTONE_TOLERANCE:g}: "
                                "rounding of the energy evaluation)",
                    "holds": worst <= MONOTONE_TOLERANCE})
    return out


def targets_markdown(items: list[dict]) -> str:
    lines = ["| target | measured | holds |", "|---|---|---|"]
    for t in items:
        lines.append(f"| {t['target']} | {t['measured']} | {'yes' if t['holds'] else '**no**'} |")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    path = argv[1] if len(argv) > 1 else "results/apps.json"
    with open(path) as f:
        results = json.load(f)
    items = targets(results)
    print(targets_markdown(items))
    return 0 if all(t["holds"] for t in items) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
