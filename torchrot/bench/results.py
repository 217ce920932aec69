"""The microbenchmark's result files: ``bench.json`` (every number),
``bench.md`` (every table, all columns, each with the machine's load) and
``bench_scaling.png``."""
from __future__ import annotations

import json
import os
from dataclasses import asdict

from torchrot.bench.figures import plot_scaling
from torchrot.bench.machine import Load, machine_info
from torchrot.bench.rows import Row
from torchrot.bench.tables import format_layer_table, format_registration_table, format_tables

__all__ = ["FILES", "write_results"]

#: The files :func:`write_results` writes, in order.
FILES = ("bench.json", "bench.md", "bench_scaling.png")


def _load_json(load: Load | None) -> dict | None:
    return None if load is None else {"before": list(load.before), "after": list(load.after), "cpus": load.cpus}


def write_results(rows: list[Row], overhead: dict[str, float], folder: str, layer: list[dict] | None = None,
                  registration: list[dict] | None = None, loads: dict[str, Load] | None = None) -> list[str]:
    """:data:`FILES` in ``folder``; returns the paths written. ``loads``: the
    machine's load while each workload table was timed, by its JSON key
    ("single_matrix_us", "rotation_layer", "registration"); the method rows
    carry their own."""
    loads = loads or {}
    machine = machine_info()
    os.makedirs(folder, exist_ok=True)
    paths = [os.path.join(folder, name) for name in FILES]
    with open(paths[0], "w") as f:
        json.dump({"machine": machine, "single_matrix_us": overhead, "rotation_layer": layer or [],
                   "registration": registration or [],
                   "workload_loads": {key: _load_json(load) for key, load in loads.items()},
                   "rows": [asdict(r) for r in rows]}, f, indent=1)

    def load_line(key: str) -> str:
        return f"{loads[key].line()}\n\n" if key in loads else ""

    with open(paths[1], "w") as f:
        f.write(f"# torchrot benchmark\n\nMachine: {machine}\n\n")
        if overhead:
            f.write("## Single-matrix call (microseconds)\n\n" + load_line("single_matrix_us"))
            for name, us in overhead.items():
                f.write(f"- {name}: {us:.2f}\n")
        if layer:
            f.write("\n## Rotation layer: forward + backward, float32, 1 thread\n\n" + load_line("rotation_layer")
                    + format_layer_table(layer) + "\n")
        if registration:
            f.write("\n## Point-set registration: rigid_registration(x, y, scale=True), us per call, 1 thread\n\n"
                    + load_line("registration") + format_registration_table(registration) + "\n")
        for part in ("scaling", "methods"):
            part_rows = [r for r in rows if r.part == part]
            if part_rows:
                f.write(f"\n## {part}\n\n{format_tables(part_rows)}\n")
    if not any(r.part == "scaling" for r in rows):
        return paths[:2]
    try:
        plot_scaling(rows, paths[2], machine)
    except ImportError:
        print("matplotlib is not installed (pip install 'torchrot[bench]'): no plot written")
        paths.pop()
    return paths
