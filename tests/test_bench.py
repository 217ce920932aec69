"""The report machinery of ``python -m torchrot bench`` on synthetic numbers:
the trust checks and re-timing, the tables and the terminal's width, the
headline, progress without carriage returns off a terminal, ``--help``, the
scaling figure's colours, and the layout of the benchmark code. Nothing here
times anything (speed lives in benchmarks/); each test runs in well under a
second."""
from __future__ import annotations

import ast
import io
import pathlib

import pytest

from torchrot.bench import cli, options, plans, progress, summary, tables, trust
from torchrot.bench.rows import Row

ROOT = pathlib.Path(__file__).resolve().parents[1]


def row(method: str, ns: float, runs=None, key: str = "", threads: int = 1, group: str = "", mode=None,
        data: str = "warm", part: str = "methods", **fields) -> Row:
    return Row(part, data, method, "float32", 1000, threads, ns, runs_ns=list(runs or [ns, ns, ns]), key=key,
               group=group, mode=mode, **fields)


def table(threads: int = 1, copy_runs=(1.0, 1.0, 1.1, 1.0, 0.9), fit_runs=(10.0, 10.1, 9.9)) -> list[Row]:
    return [row("copy_ (memory floor)", 1.0, copy_runs, key="copy", threads=threads, group="floor"),
            row("torch.linalg.svd", 2000.0, key="svd", threads=threads, group="baseline"),
            row("torchrot converged warm", 10.0, fit_runs, key="torchrot", threads=threads, group="torchrot",
                mode="converged_warm", variant="conservative")]


# -- trust ------------------------------------------------------------------------
def test_spread_is_the_interquartile_range_over_the_median():
    assert trust.spread([10.0]) is None
    assert trust.spread([9.0, 10.0, 11.0]) == pytest.approx(0.1)  # (q3 - q1) / median, inclusive quartiles
    # one stalled sample among many does not count; a quarter of them does
    assert trust.spread([1.0] * 11 + [100.0]) == pytest.approx(0.0)
    assert trust.spread([1.0] * 6 + [3.0] * 4) > trust.SPREAD_LIMIT


def test_suspicions_name_each_reason():
    assert trust.suspicions(table()) == [[], [], []]
    noisy = table(fit_runs=(10.0, 20.0, 30.0))
    assert trust.suspicions(noisy) == [[], [], ["spread"]]
    # a 2-thread row far slower than the same method's 1-thread row: a thread waited for a busy core
    one_thread = trust.one_thread_times(table())
    slow = table(threads=2)
    slow[2].ns_per_matrix = slow[2].runs_ns[0] = 10.0 * trust.THREAD_SLOWDOWN_LIMIT + 1
    slow[2].runs_ns = [slow[2].ns_per_matrix] * 3
    assert trust.suspicions(slow, one_thread) == [[], [], ["threads"]]
    # the floor off (its own 2-thread copy_ at 1,556 ns against 1 ns with 1 thread): every row is doubtful
    stalled = table(threads=2)
    stalled[0].ns_per_matrix, stalled[0].runs_ns = 1556.0, [1500.0, 1556.0, 1600.0]
    assert trust.suspicions(stalled, one_thread) == [["threads"], ["floor"], ["floor"]]
    # the copy_'s interleaved samples differ with what the method before each left in the caches
    # (1.2 against 6-8 ns at N = 1e4); a stalled quarter of them is what counts
    cached = table(copy_runs=(7.4, 7.8, 6.8, 6.3, 1.2, 1.2, 1.3, 8.0, 8.0))
    assert trust.suspicions(cached) == [[], [], []]
    stalled_quarter = table(copy_runs=(1.0, 1.0, 1000.0, 1.0, 1.0, 1000.0, 1.0, 1000.0, 1.0))
    assert trust.quartile_ratio(stalled_quarter[0].runs_ns) > trust.FLOOR_QUARTILE_RATIO
    assert trust.suspicions(stalled_quarter) == [["spread"], ["floor"], ["floor"]]


def test_retime_replaces_fixed_rows_marks_the_rest_and_stops():
    rows = table()
    rows[1].runs_ns = [1000.0, 2000.0, 3000.0]  # the SVD's runs disagree: it is fixed by the re-timing
    rows[2].runs_ns = [5.0, 10.0, 20.0]  # torchrot's stay in disagreement
    calls = []

    def retime(names):
        calls.append(names)
        fresh = {r.method: r for r in table(fit_runs=(5.0, 10.0, 20.0))}
        fresh["torch.linalg.svd"].ns_per_matrix = 1500.0
        return [fresh[name] for name in names]

    logged = []
    out = trust.retime_suspicious(rows, retime, max_retimes=2, log=logged.append)
    assert len(calls) == 2  # bounded
    assert "copy_ (memory floor)" in calls[0]  # the floor is timed again beside the re-timed rows
    assert calls[1] == ["torchrot converged warm", "copy_ (memory floor)"]
    svd, fit = out[1], out[2]
    assert svd.ns_per_matrix == 1500.0 and svd.suspicion == [] and svd.attempts_ns == [2000.0, 1500.0]
    assert fit.suspicion == ["spread"] and len(fit.attempts_ns) == 3
    assert fit.speedup_vs_svd == pytest.approx(1500.0 / fit.ns_per_matrix)  # related to the final SVD row
    assert out[0].suspicion == [] and len(logged) == 2
    assert len(trust.retime_suspicious(table(fit_runs=(5.0, 10.0, 20.0)), retime, log=logged.append)[2].attempts_ns) \
        == 1 + trust.MAX_RETIMES


def test_retime_leaves_a_trusted_table_alone():
    def retime(names):
        raise AssertionError("nothing to re-time")

    out = trust.retime_suspicious(table(), retime)
    assert all(r.suspicion == [] and len(r.attempts_ns) == 1 for r in out)


# -- tables -----------------------------------------------------------------------
def test_tables_mark_suspicious_rows_and_fit_the_terminal():
    rows = table(threads=2)
    for r in rows:
        r.load_before, r.load_after, r.cpus = [1.5, 1.0, 0.5], [2.5, 1.2, 0.6], 2
    rows[2].suspicion = ["threads"]
    narrow = tables.format_tables_narrow(rows)
    assert f"| {trust.MARKER} threads |" in narrow and trust.legend() in narrow
    assert "1.50 -> 2.50 on 2 CPUs (at or above the CPU count)" in narrow
    assert max(len(line) for line in narrow.splitlines()) <= tables.TERMINAL_WIDTH
    wide = tables.format_tables(rows)
    assert max(len(line) for line in wide.splitlines()) > tables.TERMINAL_WIDTH
    assert tables.for_terminal(wide, "bench.md") == (f"(a table wider than {tables.TERMINAL_WIDTH} columns: "
                                                      "see bench.md)")
    assert tables.for_terminal(narrow, "bench.md") == narrow
    assert trust.legend() not in tables.format_tables(table())


# -- summary ----------------------------------------------------------------------
def test_headline_has_at_most_ten_lines_from_the_rows():
    rows = []
    for data in ("warm", "uniform", "rot60"):
        rows += [row("copy_", 1.0, key="copy", group="floor", data=data),
                 row("torch.linalg.svd", 2000.0, key="svd", group="baseline", data=data, max_error=1e-4),
                 row("roma", 3000.0, key="roma", group="baseline", data=data),
                 row("igl (single)", 500.0, key="igl_single", group="baseline", data=data)]
        rows += [row(f"torchrot {mode}", ns, key="torchrot", group="torchrot", mode=mode, variant="conservative",
                     data=data, max_error=5e-5) for mode, ns in
                 (("one_step", 10.0), ("converged_cold", 20.0), ("converged_warm", 25.0))]
    rows[-1].suspicion = ["spread"]
    apps_rows = [row("torchrot converged_cold", 20.0, key="torchrot", group="torchrot", mode="converged_cold",
                     variant="conservative", part="apps", data="arap", speedup_vs_svd=150.0)]
    layer = [{"batch": 64, "torchrot_vs_svd": 0.5}, {"batch": 10_000, "torchrot_vs_svd": 0.02}]
    registration = [{"speedup_vs_svd": 2.0}, {"speedup_vs_svd": 5.0}]
    lines = summary.headline(rows, layer, registration, apps_rows, "/tmp/results")
    assert len(lines) <= summary.MAX_LINES == 10
    text = "\n".join(lines)
    assert "torchrot converged cold: 20.0 ns/matrix; 100x SVD, 150x RoMa, 25x igl single" in text
    assert "converged warm: 25.0 ns/matrix" in text  # the suspicious row left out
    assert "50.0x SVD autograd (batch 10,000)" in text and "2.0-5.0x" in text
    assert "x SVD: converged cold 150x" in text and "suspicious rows: 1 of 22" in text
    assert max(len(line) for line in lines) <= tables.TERMINAL_WIDTH
    assert "/tmp/results" in lines[-1]
    assert len(summary.headline([], output=None)) <= summary.MAX_LINES


# -- progress ---------------------------------------------------------------------
class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_redraws_only_on_a_terminal():
    log, errors = io.StringIO(), io.StringIO()
    assert not progress.redraws_in_place(log, errors)
    assert not progress.redraws_in_place(_Terminal(), errors)  # a redirected stderr would keep the redraws
    assert progress.redraws_in_place(_Terminal(), _Terminal())
    bar = progress.progress_bar(16, "recording", stdout=log, stderr=errors)
    for _ in range(16):
        bar.update(1)
    bar.close()
    text = log.getvalue() + errors.getvalue()
    assert "\r" not in text
    assert text.count("\n") == progress.LinesProgress.LINES and "recording: 16/16" in text
    assert progress.progress_bar(16, "recording", enabled=False) is None


# -- command line -----------------------------------------------------------------
def test_help_lists_the_valid_choices(capsys):
    with pytest.raises(SystemExit):
        cli.main(["bench", "--help"])
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    for name in options.data_sets():
        assert name in text
    for dtype in options.DTYPES:
        assert dtype in text
    assert f"each 1 to {options.max_threads()}" in text
    for argv in (["bench", "--data", "nonexistent"], ["bench", "--dtype", "float16"],
                 ["bench", "--threads", str(options.max_threads() + 1)]):
        with pytest.raises(SystemExit):
            cli.parser().parse_args(argv)


def test_scaling_sweep_spans_five_decades_and_the_default_a_subset():
    assert plans.FULL.scaling_n[0] == 100 and plans.FULL.scaling_n[-1] == 10_000_000
    assert set(plans.QUICK.scaling_n) < set(plans.FULL.scaling_n) and len(plans.QUICK.scaling_n) >= 3


# -- figures ----------------------------------------------------------------------
def test_scaling_figure_one_colour_per_method_and_legend_outside():
    pytest.importorskip("matplotlib")
    from torchrot.bench import figures

    methods = ["copy_", "torch.linalg.svd", "roma", "igl (double)", "torchrot converged"]
    rows = [row(m, 10.0 * (i + 1), key="copy" if m == "copy_" else "", part="scaling", data=data)
            for data in ("warm", "uniform") for i, m in enumerate(methods if data == "warm" else methods[::-1])]
    for r, n in zip(rows, [100, 1000] * len(rows)):
        r.n = n
    colors = figures.method_colors(r.method for r in rows)
    assert list(colors) == methods and len(set(colors.values())) == len(methods)
    fig = figures.scaling_figure(rows)
    try:
        drawn = {}
        for ax in fig.axes:
            assert ax.get_legend() is None  # no legend over the data
            for line in ax.get_lines():
                drawn.setdefault(line.get_label(), set()).add(line.get_color())
        assert {label: color for label, (color,) in ((k, tuple(v)) for k, v in drawn.items())} == colors
        assert len(fig.legends) == 1
    finally:
        import matplotlib.pyplot as plt

        plt.close(fig)
    with pytest.raises(ValueError, match="distinct colours"):
        figures.method_colors(str(i) for i in range(len(figures.SCALING_COLORS) + 1))


# -- layout of the benchmark code -------------------------------------------------
BENCH_MODULES = sorted((ROOT / "torchrot" / "bench").glob("*.py")) + sorted((ROOT / "benchmarks").glob("*.py"))


@pytest.mark.parametrize("path", BENCH_MODULES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_benchmark_modules_are_short_declare_all_and_skip_the_package_root(path):
    source = path.read_text()
    assert source.count("\n") <= 400, "one file, one job: split it"
    tree = ast.parse(source)
    assert any(isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "__all__" for t in node.targets)
               or isinstance(node, ast.AnnAssign) and getattr(node.target, "id", "") == "__all__"
               for node in tree.body), "no __all__"
    if path.parent.name == "bench":
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                assert all(a.name != "torchrot" for a in node.names), "imports the package root"
            elif isinstance(node, ast.ImportFrom) and node.module == "torchrot":
                assert all(a.name in {"bench"} for a in node.names), "imports from the package root"


def test_instruction_profile_charges_each_instruction_to_one_part_of_the_fit(monkeypatch):
    """benchmarks/instruction_profile.py's table by part: an instruction goes to
    the first part of PARTS that one of the functions it was inlined from makes
    up (a load inside the step is moving, a mask inside begin_fit a check), an
    out-of-line lambda by its function's name, the rest to the loop."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import instruction_profile as ip

    parts = {name: name for name, _ in ip.PARTS}
    step = next(p for p in parts if p.startswith("the Cayley step"))
    moving = next(p for p in parts if p.startswith("moving"))
    checks = next(p for p in parts if p.startswith("scaling"))
    warm_check = next(p for p in parts if p.startswith("the warm-start check"))
    lambda_ = ip.LAMBDA
    cases = {
        ("fit_range", "advance", "take_step", "rotate_by", "mat3.h:10"): step,
        ("fit_range", "one_step_warm_from_memory", "transpose_times_by_rows", lambda_, "load",
         "avxintrin.h:1"): moving,
        ("fit_range", "begin_fit", "check_warm_start", "mask_and", "lanes.h:1"): checks,
        ("count_bad_warm_starts::{lambda}", "check_warm_start", "gram", "mat3.h:1"): warm_check,
        ("fit_range", lambda_, "any", "lanes.h:1"): ip.LOOP_PART,
        ("fit_rotation_small_avx", "_mm256_add_ps", "avxintrin.h:1"): next(p for p in parts if "authors" in p),
        (): ip.LOOP_PART,
    }
    for chain, part in cases.items():
        assert ip._part(list(chain)) == part, chain
    assert len(set(parts)) == len(ip.PARTS) and ip.LOOP_PART not in parts
