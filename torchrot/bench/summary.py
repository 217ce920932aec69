"""The headline that ends ``python -m torchrot bench``: at most
:data:`MAX_LINES` lines, every number taken from the run's rows."""
from __future__ import annotations

import os
from collections.abc import Iterable

from torchrot._constants import DEFAULT_VARIANT
from torchrot.bench.machine import machine_info
from torchrot.bench.rows import Row, table_key
from torchrot.bench.trust import MARKER

__all__ = ["MAX_LINES", "PEERS", "SUMMARY_FILE", "headline", "write_summary"]

MAX_LINES = 10
#: The file the headline is written to in the output folder: the README and the performance page quote it.
SUMMARY_FILE = "summary.md"
#: The peers the headline compares with, by Row.key, if they ran.
PEERS = {"svd": "SVD", "roma": "RoMa", "igl_double": "igl double", "igl_single": "igl single"}
_MODES = {"converged_cold": "converged cold", "converged_warm": "converged warm", "one_step": "1-step warm"}


def _span(values: list[float], spec: str, unit: str = "") -> str:
    low, high = min(values), max(values)
    same = format(low, spec) == format(high, spec)
    return f"{low:{spec}}{unit}" if same else f"{low:{spec}}-{high:{spec}}{unit}"


def _torchrot_rows(rows: list[Row], kernel: str | None) -> list[Row]:
    """torchrot's headline rows: each mode, the default variant, on (N, 3, 3)
    tensors, with the process's kernel."""
    return [r for r in rows if r.group == "torchrot" and r.mode in _MODES and r.layout == "aos"
            and r.variant == DEFAULT_VARIANT and r.isa in (None, kernel)]


def _ratios(rows: list[Row], mode: str, peer: str, kernel: str | None) -> list[float]:
    """The peer's time over torchrot's in ``mode``, per table of ``rows``
    holding both, neither suspicious."""
    tables: dict[tuple, list[Row]] = {}
    for r in rows:
        tables.setdefault(table_key(r), []).append(r)
    ratios = []
    for table in tables.values():
        mine = next((r for r in _torchrot_rows(table, kernel) if r.mode == mode), None)
        theirs = next((r for r in table if r.key == peer), None)
        if mine and theirs and not (mine.suspicion or theirs.suspicion):
            ratios.append(theirs.ns_per_matrix / mine.ns_per_matrix)
    return ratios


def headline(rows: Iterable[Row], layer: list[dict] | None = None, registration: list[dict] | None = None,
             apps_rows: Iterable[Row] | None = None, output: str | None = None,
             kernel: str | None = None) -> list[str]:
    """At most MAX_LINES lines: torchrot's speed-ups over SVD and the peers
    in the 1-thread method tables (ranges over their data sets, suspicious
    rows left out), its accuracy, the rotation layer and registration
    against SVD, the recorded solver data, the suspicious rows, and where
    the files are. ``kernel``: the torchrot CPU kernel the process runs (the
    rows forced to other kernels are left out)."""
    rows, apps_rows = list(rows), list(apps_rows or [])
    lines = []
    methods = [r for r in rows if r.part == "methods"]
    dtype = methods[0].dtype if methods else None
    table = [r for r in methods if r.threads == 1 and r.dtype == dtype]
    if table:
        data_sets = list(dict.fromkeys(r.data for r in table))
        lines.append(f"Summary ({dtype}, 1 thread, N = {max(r.n for r in table):,}; ranges over "
                     f"{', '.join(data_sets)}; x = times faster, same table):")
        for mode, label in _MODES.items():
            mine = [r for r in _torchrot_rows(table, kernel) if r.mode == mode and not r.suspicion]
            if not mine:
                continue
            peers = [f"{_span(ratios, '.0f', 'x')} {name}" for key, name in PEERS.items()
                     if (ratios := _ratios(table, mode, key, kernel))]
            lines.append(f"  torchrot {label}: {_span([r.ns_per_matrix for r in mine], '.1f')} ns/matrix; "
                         + (", ".join(peers) if peers else "no peer timed beside it"))
        converged = [r.max_error for r in _torchrot_rows(table, kernel)
                     if r.mode.startswith("converged") and r.max_error is not None]
        svd = [r.max_error for r in table if r.key == "svd" and r.max_error is not None]
        if converged:
            lines.append(f"  max |R - R*|_F against float64 SVD: torchrot converged {max(converged):.1e}"
                         + (f", torch.linalg.svd in {dtype} {max(svd):.1e}" if svd else ""))
    if layer or registration:
        parts = [f"nn.RotationFit fwd+bwd {1 / r['torchrot_vs_svd']:.1f}x SVD autograd (batch {r['batch']:,})"
                 for r in (layer or [])[-1:]]
        if registration:
            parts.append(f"rigid_registration {_span([r['speedup_vs_svd'] for r in registration], '.1f', 'x')} "
                         "SVD's closed form")
        lines.append("  " + "; ".join(parts))
    recorded = [r for r in _torchrot_rows(apps_rows, kernel) if r.speedup_vs_svd and not r.suspicion]
    if recorded:
        speedups = {label: [r.speedup_vs_svd for r in recorded if r.mode == mode] for mode, label in _MODES.items()}
        lines.append("  recorded data (" + ", ".join(dict.fromkeys(r.data for r in recorded)) + "), x SVD: "
                     + ", ".join(f"{label} {_span(v, '.0f', 'x')}" for label, v in speedups.items() if v))
    doubtful = [r for r in rows + apps_rows if r.suspicion]
    total = len(rows) + len(apps_rows)
    lines.append(f"  suspicious rows: {len(doubtful)} of {total}, marked {MARKER} in the tables and left out above"
                 if doubtful else f"  suspicious rows: none of {total}")
    if output:
        lines.append(f"  results: {output}{os.sep} (bench.md, apps.md: every table; .json: every number)")
    return lines[:MAX_LINES]


def write_summary(lines: list[str], folder: str) -> str:
    """The headline ``lines`` as ``folder``/SUMMARY_FILE, under the machine and
    run that wrote them; returns its path."""
    path = os.path.join(folder, SUMMARY_FILE)
    with open(path, "w") as f:
        f.write(f"Machine: {machine_info()}\n\n```text\n" + "\n".join(lines) + "\n```\n")
    return path
