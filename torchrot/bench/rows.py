"""One measured row of a benchmark table (:class:`Row`) and how rows group
into tables (:func:`table_key`)."""
from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["Row", "row_value", "table_key"]


@dataclass
class Row:
    """One method timed on one data set of ``n`` matrices at one dtype and
    thread count. Times are ns per matrix; ``runs_ns`` are the timed runs
    whose median is ``ns_per_matrix`` (``blocked_autorange`` medians, or the
    interleaved samples of the ``copy_`` row); errors are against float64 SVD."""

    part: str
    data: str
    method: str  # the display name; select rows on group, key, mode, variant and isa
    dtype: str
    n: int
    threads: int
    ns_per_matrix: float
    runs_ns: list = field(default_factory=list)
    isa: str | None = None
    group: str = ""
    key: str = ""
    mode: str | None = None
    variant: str | None = None
    layout: str = "aos"
    max_error: float | None = None  # max |R - R*|_F against float64 SVD
    median_error: float | None = None
    share_above_1e3: float | None = None  # share of matrices with |R - R*|_F > 1e-3 (or non-finite)
    failures: int | None = None  # number of matrices with |R - R*|_F > 1e-3 or a non-finite result
    max_shortfall: float | None = None  # max (tr(R*^T M) - tr(R^T M)) / |M|_F
    mean_iterations: float | None = None
    fallback_rate: float | None = None
    speedup_vs_svd: float | None = None
    time_vs_copy: float | None = None
    # The machine while the row's table was timed (torchrot.bench.machine.Load): load
    # averages (1, 5, 15 min) before and after, and the CPU count.
    load_before: list | None = None
    load_after: list | None = None
    cpus: int | None = None
    # What still makes the row doubtful after its re-timings (torchrot.bench.trust.REASONS
    # keys; empty: trusted), and ns_per_matrix of each timing it had, the reported one included.
    suspicion: list = field(default_factory=list)
    attempts_ns: list = field(default_factory=list)


def row_value(row, name: str):
    """Field ``name`` of ``row``, a Row or its dict (saved JSON); None if absent."""
    return row.get(name) if isinstance(row, dict) else getattr(row, name, None)


def table_key(row) -> tuple[str, str, str, int]:
    """The printed table a row belongs to: part, data set, dtype and thread
    count (a table of the scaling part spans N; one of the methods part holds
    the sampled comparison methods' smaller N too). ``row``: a Row or its dict."""
    return tuple(row_value(row, name) for name in ("part", "data", "dtype", "threads"))
