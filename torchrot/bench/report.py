"""The paper's Tables 1 and 2 on the recorded data, Fig. 5-6 numbers, Markdown.

Table 1 (paper: non-vectorized methods, speed-up over Eigen's SVD): every
method timed on the recorded "arap" and "elasticity" data, with torchrot's
scalar kernel, as speed-up over ``torch.linalg.svd`` in the same run, plus
accuracy. Table 2 (paper: AVX code, speed-up over Eigen and over McAdams et
al.'s AVX SVD): torchrot's vectorized kernel over ``torch.linalg.svd`` and
over libigl's single-precision ``fit_rotations`` (McAdams et al.'s 3x3 SVD,
the scalar build the Python binding exposes).

Rows are selected on their fields (``group``, ``key``, ``isa``; see
:class:`torchrot.bench.rows.Row`), never on their display names. A row
still suspicious after its re-timings (``Row.suspicion``) has its time
marked with :data:`torchrot.bench.trust.MARKER`.
"""
from __future__ import annotations

from torchrot.bench.rows import row_value
from torchrot.bench.trust import MARKER

__all__ = ["MCADAMS", "SVD", "phase_table", "statistics_table", "table1", "table2"]

MCADAMS = "igl_single"  # Row.key of libigl's single-precision fit_rotations (McAdams et al.'s SVD)
SVD = "svd"  # Row.key of torch.linalg.svd


def _fmt(x, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _by_method(rows, dtype: str, threads: int, keep) -> dict:
    """method -> data -> row, for the rows of one dtype/thread count that ``keep(row)``."""
    table: dict[str, dict] = {}
    for r in rows:
        if row_value(r, "dtype") == dtype and row_value(r, "threads") == threads and keep(r):
            table.setdefault(row_value(r, "method"), {})[row_value(r, "data")] = r
    return table


def _table1_row(r) -> bool:
    """Table 1: every method but the floor; torchrot only with its scalar kernel."""
    group = row_value(r, "group")
    return group != "floor" and (group != "torchrot" or row_value(r, "isa") == "scalar")


def _table2_row(r) -> bool:
    """Table 2: torchrot with a vectorized (or the default) kernel, and the two SVD references."""
    vectorized = row_value(r, "group") == "torchrot" and row_value(r, "isa") != "scalar"
    return vectorized or row_value(r, "key") in (SVD, MCADAMS)


def _ns(row) -> str:
    """The row's ns/matrix, marked if the row is suspicious."""
    return _fmt(row_value(row, "ns_per_matrix"), ".1f") + (f" {MARKER}" if row_value(row, "suspicion") else "")


def _row_cells(by_data: dict, data_sets, reference: dict | None = None) -> list[str]:
    cells = []
    for data in data_sets:
        r = by_data.get(data)
        if r is None:
            cells += ["-", "-", "-", "-"]
            continue
        speed = row_value(r, "speedup_vs_svd")
        if reference is not None:
            ref = reference.get(data)
            speed = None if ref is None else row_value(ref, "ns_per_matrix") / row_value(r, "ns_per_matrix")
        cells += [_ns(r), _fmt(speed, ".1f") + ("x" if speed else ""),
                  _fmt(row_value(r, "max_error"), ".1e"), _fmt(row_value(r, "share_above_1e3"), ".2%")]
    return cells


def _columns(data_sets, names: list[str], keep: int) -> tuple[str, int]:
    """The header of a table with ``names`` per data set, of which the first
    ``keep`` are shown, and the number of cells per data set."""
    return "| method | " + " | ".join(f"{d} {n}" for d in data_sets for n in names[:keep]) + " |", len(names)


def _shown(cells: list[str], per_data: int, keep: int) -> list[str]:
    return [c for i, c in enumerate(cells) if i % per_data < keep]


def table1(rows, data_sets=("arap", "elasticity"), dtype: str = "float32", threads: int = 1,
           narrow: bool = False) -> str:
    """Markdown: every method except torchrot's vectorized kernels, speed-up over
    SVD (``narrow``: ns/matrix and speed-up only, for the terminal)."""
    table = _by_method(rows, dtype, threads, _table1_row)
    keep = 2 if narrow else 4
    header, per_data = _columns(data_sets, ["ns/matrix", "x SVD", "max err", "err>1e-3"], keep)
    lines = [header, "|" + "---|" * (1 + keep * len(data_sets))]
    for method, by_data in table.items():
        lines.append(f"| {method} | " + " | ".join(_shown(_row_cells(by_data, data_sets), per_data, keep)) + " |")
    return "\n".join(lines)


def table2(rows, data_sets=("arap", "elasticity"), dtype: str = "float32", threads: int = 1,
           narrow: bool = False) -> str:
    """Markdown: torchrot's vectorized kernels and the two SVD references,
    speed-up over torch.linalg.svd and over libigl's McAdams SVD (``narrow``:
    without the errors, for the terminal)."""
    table = _by_method(rows, dtype, threads, _table2_row)
    mcadams = next((by_data for by_data in table.values()
                    if row_value(next(iter(by_data.values())), "key") == MCADAMS), None)
    keep = 3 if narrow else 4
    header, per_data = _columns(data_sets, ["ns" if narrow else "ns/matrix", "x SVD", "x McAdams", "max err"], keep)
    lines = [header, "|" + "---|" * (1 + keep * len(data_sets))]
    for method, by_data in table.items():
        cells = []
        for data in data_sets:
            r = by_data.get(data)
            if r is None:
                cells += ["-"] * 4
                continue
            over_mcadams = None
            if mcadams and data in mcadams:
                over_mcadams = row_value(mcadams[data], "ns_per_matrix") / row_value(r, "ns_per_matrix")
            speed = row_value(r, "speedup_vs_svd")
            cells += [_ns(r), _fmt(speed, ".1f") + ("x" if speed else ""),
                      _fmt(over_mcadams, ".1f") + ("x" if over_mcadams else ""), _fmt(row_value(r, "max_error"), ".1e")]
        lines.append(f"| {method} | " + " | ".join(_shown(cells, per_data, keep)) + " |")
    return "\n".join(lines)


def phase_table(timings: dict) -> str:
    """Markdown: median ms per iteration of every phase, per app and fit (Fig. 6's numbers)."""
    lines = ["| app | fit | assembly | rotation fit | local step | rhs | back-subst. | global step | "
             "fit / global | local / global |", "|" + "---|" * 10]
    for app, result in timings.items():
        for fit, t in result["fits"].items():
            lines.append(f"| {app} ({result['mesh']}) | {fit} | {t['assembly']:.3g} | {t['fit']:.3g} | "
                         f"{t['local']:.3g} | {t['rhs']:.3g} | {t['solve']:.3g} | {t['global']:.3g} | "
                         f"{t['fit'] / t['global']:.3f} | {t['local'] / t['global']:.2f} |")
    return "\n".join(lines)


def statistics_table(stats: dict) -> str:
    """Markdown: the recorded data's Fig. 5 numbers."""
    lines = ["| data set | matrices | median angle | < 1 deg | median cond | p90 cond | "
             "Newton step < 1e-5 | conserv. step < 1e-5 |", "|" + "---|" * 8]
    for name, s in stats.items():
        a, c, o = s["angle_degrees"], s["condition_number"], s["one_step"]
        lines.append(f"| {name} | {s['matrices']:,} | {a['median']:.3g} deg | {a['share_below_1']:.1%} | "
                     f"{c['median']:.3g} | {c['p90']:.3g} | {o['newton']['share_below_1e-5']:.1%} | "
                     f"{o['conservative']['share_below_1e-5']:.1%} |")
    return "\n".join(lines)
