"""Which rows of a timed table not to trust, and their re-timing.

A shared machine can stall a timing: another process holding a core makes a
2-thread call wait for its second thread (measured: a 2-thread ``copy_`` of
4,000 matrices at 1,556 ns per matrix against 1.1 with 1 thread, and
torchrot's converged warm fit slower than SVD, in a run that flagged
nothing). A row is suspicious for one of :data:`REASONS`:

- ``spread``: its runs disagree, :func:`spread` above :data:`SPREAD_LIMIT`
  (the ``copy_`` row: :func:`quartile_ratio` above :data:`FLOOR_QUARTILE_RATIO`);
- ``threads``: with more threads it took over :data:`THREAD_SLOWDOWN_LIMIT`
  times its 1-thread time (same data, dtype, N and method);
- ``floor``: its table's ``copy_`` row, the memory floor timed interleaved
  with the table's methods, is suspicious for either reason, so the whole
  table was timed on a disturbed machine.

:func:`retime_suspicious` re-times a table's suspicious rows up to
:data:`MAX_RETIMES` times and records what still makes each doubtful in
``Row.suspicion``; tables mark those rows with :data:`MARKER` and print
:func:`legend`. Every check is on the rows' own numbers: nothing here times.
"""
from __future__ import annotations

import statistics
from collections.abc import Callable, Iterable

from torchrot.bench.rows import Row

__all__ = ["FLOOR_QUARTILE_RATIO", "MARKER", "MAX_RETIMES", "REASONS", "SPREAD_LIMIT", "THREAD_SLOWDOWN_LIMIT",
           "legend", "one_thread_times", "quartile_ratio", "relate_to_baselines", "retime_suspicious", "spread",
           "suspicions"]

#: A row's runs disagree when their interquartile range exceeds this share of
#: their median (with 3 runs: max - min above twice this share). Quartiles,
#: not the extremes, so that one stalled sample of the copy_ row's many
#: interleaved ones does not count, while a quarter of them does.
SPREAD_LIMIT = 0.25
#: The copy_ row's samples follow different methods, each leaving other data in
#: the caches, so they legitimately differ up to ~5x (measured at N = 1e5 float32:
#: 0.85-4.4 ns per matrix; at 1e4, 1.2 after the SoA fits against 6-8 after the
#: others): they disagree only when their upper quartile exceeds this multiple of
#: their lower one, as a stalled quarter of them (a busy core: 100-1000x) does.
FLOOR_QUARTILE_RATIO = 10.0
#: Given more threads, no method should take this many times its 1-thread time:
#: where one does, a thread waited for a core that another process held.
THREAD_SLOWDOWN_LIMIT = 3.0
#: Re-timings of a table's suspicious rows before those still suspicious are marked.
#: One: where another process holds a core for the whole table, a suspicious floor
#: re-times the whole table, and each further round would add that table's time again
#: (measured: the four 2-thread tables of the default run, 13 s alone, took 63 s with 2).
MAX_RETIMES = 1
#: Marks a suspicious row in the printed and saved tables.
MARKER = "!"
REASONS = {
    "spread": f"its runs disagree (interquartile range above {SPREAD_LIMIT:.0%} of their median; copy_: upper "
              f"quartile over {FLOOR_QUARTILE_RATIO:g}x the lower)",
    "threads": f"over {THREAD_SLOWDOWN_LIMIT:g}x its 1-thread time with more threads",
    "floor": "its table's copy_ row (the memory floor) is suspicious",
}


def legend() -> str:
    """The lines that explain :data:`MARKER` under the tables (a Markdown list)."""
    timings = "one re-timing" if MAX_RETIMES == 1 else f"up to {MAX_RETIMES} re-timings"
    return "\n".join([f"{MARKER} = still suspicious after {timings}, because"]
                     + [f"- {name}: {why}" for name, why in REASONS.items()])


def spread(runs: Iterable[float]) -> float | None:
    """Interquartile range of ``runs`` over their median ("inclusive"
    quartiles; None for fewer than 2 runs or a zero median)."""
    runs = list(runs)
    if len(runs) < 2:
        return None
    q1, median, q3 = statistics.quantiles(runs, n=4, method="inclusive")
    return (q3 - q1) / median if median > 0 else None


def quartile_ratio(runs: Iterable[float]) -> float | None:
    """Upper quartile of ``runs`` over their lower quartile ("inclusive"; None
    for fewer than 2 runs or a zero lower quartile)."""
    runs = list(runs)
    if len(runs) < 2:
        return None
    q1, _, q3 = statistics.quantiles(runs, n=4, method="inclusive")
    return q3 / q1 if q1 > 0 else None


def _runs_disagree(row: Row) -> bool:
    if row.key == "copy":
        ratio = quartile_ratio(row.runs_ns)
        return ratio is not None and ratio > FLOOR_QUARTILE_RATIO
    row_spread = spread(row.runs_ns)
    return row_spread is not None and row_spread > SPREAD_LIMIT


def _same_case(row: Row) -> tuple:
    return row.data, row.dtype, row.n, row.method


def one_thread_times(rows: Iterable[Row]) -> dict[tuple, float]:
    """ns/matrix of the 1-thread rows, by (data, dtype, N, method): the
    references of :func:`suspicions`' thread check."""
    return {_same_case(r): r.ns_per_matrix for r in rows if r.threads == 1}


def _own_reasons(row: Row, one_thread: dict[tuple, float]) -> list[str]:
    reasons = ["spread"] if _runs_disagree(row) else []
    reference = one_thread.get(_same_case(row)) if row.threads > 1 else None
    if reference is not None and row.ns_per_matrix > THREAD_SLOWDOWN_LIMIT * reference:
        reasons.append("threads")
    return reasons


def suspicions(rows: list[Row], one_thread: dict[tuple, float] | None = None) -> list[list[str]]:
    """The reasons (keys of :data:`REASONS`) to doubt each row of one timed
    table (the rows of one ``run_case`` call), in order; ``one_thread``: the
    1-thread references (:func:`one_thread_times`), if any."""
    one_thread = one_thread or {}
    reasons = [_own_reasons(r, one_thread) for r in rows]
    floor_off = any(why for r, why in zip(rows, reasons) if r.key == "copy")
    if floor_off:
        for r, why in zip(rows, reasons):
            if r.key != "copy":
                why.append("floor")
    return reasons


def relate_to_baselines(rows: list[Row]) -> None:
    """Sets each row's speed-up over the table's SVD row and time over its
    copy_ row (None where the table has none)."""
    by_key = {r.key: r for r in rows if r.key in ("svd", "copy")}
    svd, copy = by_key.get("svd"), by_key.get("copy")
    for row in rows:
        row.speedup_vs_svd = svd.ns_per_matrix / row.ns_per_matrix if svd else None
        row.time_vs_copy = row.ns_per_matrix / copy.ns_per_matrix if copy else None


def _preferred(old: Row, new: Row, one_thread: dict[tuple, float]) -> Row:
    """The timing to keep of a re-timed row: the one with fewer reasons of its
    own to doubt it; between equally doubtful ones the faster (a disturbed
    machine only adds time), then the newer."""
    def doubt(row: Row) -> tuple[int, float]:
        return len(_own_reasons(row, one_thread)), row.ns_per_matrix

    return old if doubt(old) < doubt(new) else new


def retime_suspicious(rows: list[Row], retime: Callable[[list[str]], list[Row]],
                      one_thread: dict[tuple, float] | None = None, max_retimes: int = MAX_RETIMES,
                      log: Callable[[str], None] = print) -> list[Row]:
    """The rows of one timed table after re-timing its suspicious ones.

    ``retime(names)`` times the methods of those display names again, on the
    same data, and returns their rows; the ``copy_`` row is always among
    them, so that its samples interleave with the re-timed methods as in
    the first timing (with a suspicious floor, every row is re-timed). A
    re-timed row keeps the timing :func:`_preferred` picks; ``attempts_ns``
    lists every timing's ns/matrix. Afterwards, the speed-ups are related
    to the table's final SVD and copy_ rows, ``suspicion`` holds what still
    makes each row doubtful, and every row's load is the table's: before
    its first timing, after its last."""
    one_thread = one_thread or {}
    rows = list(rows)
    for row in rows:
        row.attempts_ns = [row.ns_per_matrix]
    copy_name = next((r.method for r in rows if r.key == "copy"), None)
    load_before, load_after = (rows[0].load_before, rows[0].load_after) if rows else (None, None)
    for attempt in range(1, max_retimes + 1):
        doubtful = [r.method for r, why in zip(rows, suspicions(rows, one_thread)) if why]
        if not doubtful:
            break
        log(f"  re-timing {len(doubtful)} suspicious row{'s' * (len(doubtful) > 1)} "
            f"({attempt}/{max_retimes}): {'; '.join(doubtful)}")
        names = doubtful + ([copy_name] if copy_name and copy_name not in doubtful else [])
        fresh = {r.method: r for r in retime(names)}
        load_after = next((r.load_after for r in fresh.values()), load_after)
        for index, row in enumerate(rows):
            new = fresh.get(row.method)
            if new is None or row.method not in doubtful:
                continue  # the companion copy_ of trusted rows keeps its first timing
            new.attempts_ns = row.attempts_ns + [new.ns_per_matrix]
            rows[index] = _preferred(row, new, one_thread)
            rows[index].attempts_ns = new.attempts_ns
    relate_to_baselines(rows)
    for row, why in zip(rows, suspicions(rows, one_thread)):
        row.suspicion = why
        # the table's load: from before its first timing to after its last re-timing
        row.load_before, row.load_after = load_before, load_after
    return rows
