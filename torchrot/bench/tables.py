"""Markdown tables of the microbenchmark: the method tables, each under its
data set, dtype, thread count and the machine's load, in a wide form for
the files (:func:`format_tables`) and a narrow one for the terminal
(:func:`format_tables_narrow`); the rotation-layer and registration tables;
and the rule that keeps tables wider than :data:`TERMINAL_WIDTH` off the
terminal (:func:`for_terminal`)."""
from __future__ import annotations

from collections.abc import Callable, Iterable

from torchrot.bench.machine import Load
from torchrot.bench.rows import Row, row_value, table_key
from torchrot.bench.trust import MARKER, legend

__all__ = ["TERMINAL_WIDTH", "fmt", "for_terminal", "format_layer_table", "format_registration_table",
           "format_table", "format_tables", "format_tables_narrow", "group_tables", "table_load"]

#: Widest line printed to the terminal; wider tables are written to the files only.
TERMINAL_WIDTH = 120


def fmt(x: float | None, spec: str) -> str:
    """``x`` formatted by ``spec``, or "-" where there is no value."""
    return "-" if x is None else format(x, spec)


def for_terminal(text: str, where: str) -> str:
    """``text`` if none of its lines is wider than TERMINAL_WIDTH, else a
    pointer to ``where`` (the file that holds it)."""
    if max((len(line) for line in text.splitlines()), default=0) <= TERMINAL_WIDTH:
        return text
    return f"(a table wider than {TERMINAL_WIDTH} columns: see {where})"


def _flag(row: Row) -> str:
    return f"{MARKER} {', '.join(row.suspicion)}" if row.suspicion else ""


def group_tables(rows: Iterable) -> dict[tuple, list]:
    """The rows (Rows or their dicts) by table (:func:`torchrot.bench.rows.table_key`), in order."""
    tables: dict[tuple, list[Row]] = {}
    for row in rows:
        tables.setdefault(table_key(row), []).append(row)
    return tables


def table_load(rows: list) -> Load | None:
    """The load of a table's rows (Rows or their dicts), in the order they
    were timed: before the first row's timing, after the last's (None for
    rows without it)."""
    if not rows or row_value(rows[0], "load_before") is None or row_value(rows[-1], "load_after") is None:
        return None
    return Load(tuple(row_value(rows[0], "load_before")), tuple(row_value(rows[-1], "load_after")),
                row_value(rows[0], "cpus") or 1)


def _heading(rows: list[Row]) -> str:
    part, data, dtype, threads = table_key(rows[0])
    sizes = sorted({r.n for r in rows})
    n = f"N = {', '.join(f'{x:,}' for x in sizes)}" if part == "scaling" else f"N = {max(sizes):,}"
    load = table_load(rows)
    return (f"### {data}, {dtype}, {n}, {threads} thread{'s' * (threads > 1)}\n\n"
            + (f"{load.line()}\n\n" if load else ""))


def format_table(rows: list[Row]) -> str:
    """Markdown table: ns/matrix beside SVD and copy of the same run, accuracy, flag."""
    header = ("| data | dtype | N | threads | method | ns/matrix | speedup vs SVD | time vs copy | max err | "
              "median err | share >1e-3 | failures | max shortfall | mean iters | fallback | flag |")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in rows:
        lines.append(
            f"| {r.data} | {r.dtype} | {r.n:.0e} | {r.threads} | {r.method} | {r.ns_per_matrix:.2f} | "
            f"{fmt(r.speedup_vs_svd, '.1f')} | {fmt(r.time_vs_copy, '.2f')} | {fmt(r.max_error, '.1e')} | "
            f"{fmt(r.median_error, '.1e')} | {fmt(r.share_above_1e3, '.2%')} | {fmt(r.failures, 'd')} | "
            f"{fmt(r.max_shortfall, '.1e')} | "
            f"{fmt(r.mean_iterations, '.2f')} | {fmt(r.fallback_rate, '.3%')} | {_flag(r)} |"
        )
    return "\n".join(lines)


def _narrow_table(rows: list[Row]) -> str:
    lines = ["| N | method | ns/matrix | x SVD | x copy | max err | iters | flag |", "|" + "---|" * 8]
    for r in rows:
        lines.append(f"| {r.n:.0e} | {r.method} | {r.ns_per_matrix:.2f} | {fmt(r.speedup_vs_svd, '.1f')} | "
                     f"{fmt(r.time_vs_copy, '.2f')} | {fmt(r.max_error, '.1e')} | "
                     f"{fmt(r.mean_iterations, '.2f')} | {_flag(r)} |")
    return "\n".join(lines)


def _tables(rows: Iterable[Row], table: Callable[[list[Row]], str]) -> str:
    rows = list(rows)
    parts = [_heading(group) + table(group) for group in group_tables(rows).values()]
    if any(r.suspicion for r in rows):
        parts.append(legend())
    return "\n\n".join(parts)


def format_tables(rows: Iterable[Row]) -> str:
    """Every table of ``rows`` (:func:`format_table`, all columns), each under
    its heading and load line; the marker's legend if a row is suspicious."""
    return _tables(rows, format_table)


def format_tables_narrow(rows: Iterable[Row]) -> str:
    """:func:`format_tables` in the columns that fit a terminal: N, method,
    ns/matrix, speed-up over SVD, time over copy_, max error, steps, flag."""
    return _tables(rows, _narrow_table)


def format_layer_table(results: list[dict]) -> str:
    """Markdown: :func:`torchrot.bench.workloads.rotation_layer`'s rows."""
    lines = ["| batch | RotationFit fwd+bwd (us) | SVD autograd fwd+bwd (us) | torchrot / SVD | "
             "clone in its place (us) | copy_ (us) |",
             "|---|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['batch']:,} | {r['torchrot_us']:.1f} | {r['svd_autograd_us']:.1f} | "
                     f"{r['torchrot_vs_svd']:.3f}x ({1 / r['torchrot_vs_svd']:.1f}x faster) | "
                     f"{r['autograd_floor_us']:.1f} | {r['copy_us']:.2f} |")
    return "\n".join(lines)


def format_registration_table(rows: list[dict]) -> str:
    """Markdown: :func:`torchrot.bench.workloads.registration_rows`' rows."""
    lines = ["| problems x points | dtype | copy_ of x, y | SVD closed form | torchrot | faster than SVD | "
             "max R error |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['problems']:,} x {r['points']:,} | {r['dtype']} | {r['copy_us']:.1f} | {r['svd_us']:.1f} "
                     f"| {r['torchrot_us']:.1f} | {r['speedup_vs_svd']:.1f}x | {r['max_r_error']:.1e} |")
    return "\n".join(lines)
