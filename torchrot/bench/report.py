"""The paper's Tables 1 and 2 on the recorded data, Fig. 5-6 numbers, Markdown.

Table 1 (paper: non-vectorized methods, speed-up over Eigen's SVD): every
method timed on the recorded "arap" and "elasticity" data, with torchrot's
scalar kernel, as speed-up over ``torch.linalg.svd`` in the same run, plus
accuracy. Table 2 (paper: AVX code, speed-up over Eigen and over McAdams et
al.'s AVX SVD): torchrot's vectorized kernel over ``torch.linalg.svd`` and
over libigl's single-precision ``fit_rotations`` (McAdams et al.'s 3x3 SVD,
the scalar build the Python binding exposes).

Rows are selected on their fields (``group``, ``key``, ``isa``; see
:class:`torchrot.bench.micro.Row`), never on their display names.
"""
from __future__ import annotations

MCADAMS = "igl_single"  # Row.key of libigl's single-precision fit_rotations (McAdams et al.'s SVD)
SVD = "svd"  # Row.key of torch.linalg.svd


def _get(row, key):
    return row[key] if isinstance(row, dict) else getattr(row, key, None)


def _fmt(x, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _by_method(rows, dtype: str, threads: int, keep) -> dict:
    """method -> data -> row, for the rows of one dtype/thread count that ``keep(row)``."""
    table: dict[str, dict] = {}
    for r in rows:
        if _get(r, "dtype") == dtype and _get(r, "threads") == threads and keep(r):
            table.setdefault(_get(r, "method"), {})[_get(r, "data")] = r
    return table


def _table1_row(r) -> bool:
    """Table 1: every method but the floor; torchrot only with its scalar kernel."""
    group = _get(r, "group")
    return group != "floor" and (group != "torchrot" or _get(r, "isa") == "scalar")


def _table2_row(r) -> bool:
    """Table 2: torchrot with a vectorized (or the default) kernel, and the two SVD references."""
    return (_get(r, "group") == "torchrot" and _get(r, "isa") != "scalar") or _get(r, "key") in (SVD, MCADAMS)


def _row_cells(by_data: dict, data_sets, reference: dict | None = None) -> list[str]:
    cells = []
    for data in data_sets:
        r = by_data.get(data)
        if r is None:
            cells += ["-", "-", "-", "-"]
            continue
        speed = _get(r, "speedup_vs_svd")
        if reference is not None:
            ref = reference.get(data)
            speed = None if ref is None else _get(ref, "ns_per_matrix") / _get(r, "ns_per_matrix")
        cells += [_fmt(_get(r, "ns_per_matrix"), ".1f"), _fmt(speed, ".1f") + ("x" if speed else ""),
                  _fmt(_get(r, "max_error"), ".1e"), _fmt(_get(r, "share_above_1e3"), ".2%")]
    return cells


def table1(rows, data_sets=("arap", "elasticity"), dtype: str = "float32", threads: int = 1) -> str:
    """Markdown: every method except torchrot's vectorized kernels, speed-up over SVD."""
    table = _by_method(rows, dtype, threads, _table1_row)
    header = "| method | " + " | ".join(f"{d} ns/matrix | {d} vs SVD | {d} max err | {d} err>1e-3"
                                        for d in data_sets) + " |"
    lines = [header, "|" + "---|" * (1 + 4 * len(data_sets))]
    for method, by_data in table.items():
        lines.append(f"| {method} | " + " | ".join(_row_cells(by_data, data_sets)) + " |")
    return "\n".join(lines)


def table2(rows, data_sets=("arap", "elasticity"), dtype: str = "float32", threads: int = 1) -> str:
    """Markdown: torchrot's vectorized kernels and the two SVD references,
    speed-up over torch.linalg.svd and over libigl's McAdams SVD."""
    table = _by_method(rows, dtype, threads, _table2_row)
    mcadams = next((by_data for by_data in table.values()
                    if _get(next(iter(by_data.values())), "key") == MCADAMS), None)
    header = "| method | " + " | ".join(f"{d} ns/matrix | {d} vs SVD | {d} vs McAdams SVD | {d} max err"
                                        for d in data_sets) + " |"
    lines = [header, "|" + "---|" * (1 + 4 * len(data_sets))]
    for method, by_data in table.items():
        cells = []
        for data in data_sets:
            r = by_data.get(data)
            if r is None:
                cells += ["-"] * 4
                continue
            over_mcadams = None
            if mcadams and data in mcadams:
                over_mcadams = _get(mcadams[data], "ns_per_matrix") / _get(r, "ns_per_matrix")
            speed = _get(r, "speedup_vs_svd")
            cells += [_fmt(_get(r, "ns_per_matrix"), ".1f"), _fmt(speed, ".1f") + ("x" if speed else ""),
                      _fmt(over_mcadams, ".1f") + ("x" if over_mcadams else ""), _fmt(_get(r, "max_error"), ".1e")]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def phase_table(timings: dict) -> str:
    """Markdown: median ms per iteration of every phase, per app and fit (Fig. 6's numbers)."""
    lines = ["| app | fit | assembly | rotation fit | local step | rhs | back-substitution | global step | "
             "fit / global | local / global |", "|" + "---|" * 10]
    for app, result in timings.items():
        for fit, t in result["fits"].items():
            lines.append(f"| {app} ({result['mesh']}) | {fit} | {t['assembly']:.3g} | {t['fit']:.3g} | "
                         f"{t['local']:.3g} | {t['rhs']:.3g} | {t['solve']:.3g} | {t['global']:.3g} | "
                         f"{t['fit'] / t['global']:.3f} | {t['local'] / t['global']:.2f} |")
    return "\n".join(lines)


def statistics_table(stats: dict) -> str:
    """Markdown: the recorded data's Fig. 5 numbers."""
    lines = ["| data set | matrices | median angle | share < 1 deg | median cond | p90 cond | "
             "1 Newton step < 1e-5 | 1 conservative step < 1e-5 |", "|" + "---|" * 8]
    for name, s in stats.items():
        a, c, o = s["angle_degrees"], s["condition_number"], s["one_step"]
        lines.append(f"| {name} | {s['matrices']:,} | {a['median']:.3g} deg | {a['share_below_1']:.1%} | "
                     f"{c['median']:.3g} | {c['p90']:.3g} | {o['newton']['share_below_1e-5']:.1%} | "
                     f"{o['conservative']['share_below_1e-5']:.1%} |")
    return "\n".join(lines)
