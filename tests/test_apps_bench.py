"""The benchmark machinery of torchrot.bench that drives torchrot.apps
(sessions, recording, cached data sets, the microbenchmark on recorded data,
the rotation-layer and registration stages, report tables, statistics, the
layering of the packages). Small meshes only (a few seconds)."""
from __future__ import annotations

import os

import pytest
import torch

pytest.importorskip("scipy")
igl = pytest.importorskip("igl")

import torchrot  # noqa: E402
from torchrot.apps.arap import ArapSolver  # noqa: E402
from torchrot.apps.elasticity import ElasticitySolver  # noqa: E402
from torchrot.apps.local_step import LocalStep  # noqa: E402
from torchrot.apps.meshes import capsule, octopus  # noqa: E402
from torchrot.bench import cases, experiments, registry, report, tables, workloads  # noqa: E402
from torchrot.bench import data as datasets  # noqa: E402
from torchrot.bench.recording import Recorder, load_recording  # noqa: E402
from torchrot.bench.rows import Row  # noqa: E402
from torchrot.bench.sessions import HandleScript, run_arap_session  # noqa: E402
from torchrot.bench.statistics import one_step_errors, recording_statistics, rotation_angle  # noqa: E402
from torchrot.bench.timing import PhaseTimer  # noqa: E402
from torchrot.testing import random_rotations  # noqa: E402

TINY_ARAP = datasets.ArapDataConfig(resolution=6, frames=4, iterations=2, max_per_step=50)
TINY_ELASTICITY = datasets.ElasticityDataConfig(resolution=8, frames=6, iterations=2, max_per_step=40)


# -- recording, data sets, benchmark ----------------------------------------------------
def test_recording_round_trip(tmp_path):
    mesh = capsule(4)
    script = HandleScript(frames=3)
    handles, _ = script.handles(mesh.V)
    solver = ArapSolver(mesh.V, mesh.F, handles, LocalStep("converged"))
    recorder = Recorder(str(tmp_path / "rec"), "arap", mesh.name, max_per_step=30)
    run_arap_session(solver, script, 2, recorder)
    manifest = recorder.finish({"test": True})
    assert manifest["steps"] == 6 and manifest["matrices"] == 180
    rec = load_recording(str(tmp_path / "rec"))
    assert len(rec) == 180
    assert torch.equal(rec.frame, torch.arange(3).repeat_interleave(60))
    assert torch.equal(rec.iteration, torch.tensor([0, 1]).repeat_interleave(30).repeat(3))
    assert torch.allclose(rec.M_local, rec.R_prev.mT @ rec.M)
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(rec.R_prev.mT @ rec.R_prev, eye.expand_as(rec.R_prev), atol=1e-12)
    assert torch.equal(rec.R_prev[:30], eye.expand(30, 3, 3))  # the first step has no previous rotation
    # a step's warm start is the previous step's fit of the same vertices
    torch.testing.assert_close(rec.R_prev[30:60], torchrot.rotation_svd(rec.M[:30]), atol=1e-10, rtol=0)
    with pytest.raises(FileExistsError):
        Recorder(str(tmp_path / "rec"), "arap", mesh.name)


def test_recorder_rejects_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="max_per_step"):
        Recorder(str(tmp_path), "arap", "m", max_per_step=0)
    with pytest.raises(FileNotFoundError, match="no finished recording"):
        load_recording(str(tmp_path))


def test_dataset_cache_second_request_loads(tmp_path, monkeypatch):
    cache = str(tmp_path / "cache")
    folder = datasets.ensure_dataset("arap", TINY_ARAP, cache, progress=False)
    assert folder.startswith(cache) and os.path.isfile(os.path.join(folder, "manifest.json"))

    def fail(*args, **kwargs):
        raise AssertionError("regenerated a cached data set")

    monkeypatch.setattr(datasets, "_generate_arap", fail)
    assert datasets.ensure_dataset("arap", TINY_ARAP, cache, progress=False) == folder
    rec = datasets.load_dataset("arap", TINY_ARAP, cache)
    assert len(rec) == 4 * 2 * 50
    # another configuration is another folder
    assert datasets.dataset_folder("arap", TINY_ARAP, cache) != datasets.dataset_folder("arap", None, cache)
    with pytest.raises(ValueError, match="unknown recorded data set"):
        datasets.dataset_folder("cloth", None, cache)


def test_dataset_from_a_user_surface(tmp_path):
    mesh = capsule(4)
    path = str(tmp_path / "bar.off")
    igl.writeOFF(path, mesh.V, mesh.F)
    config = datasets.ArapDataConfig(mesh_path=path, frames=2, iterations=2, max_per_step=None)
    rec = datasets.load_dataset("arap", config, str(tmp_path / "cache"), progress=False)
    assert rec.manifest["mesh"] == "bar" and rec.manifest["config"]["vertices"] == len(mesh.V)
    assert len(rec) == 2 * 2 * len(mesh.V)


def test_warm_start_pairs_draw_and_repeat(tmp_path):
    cache = str(tmp_path / "cache")
    M, init = datasets.warm_start_pairs("elasticity", 500, dtype=torch.float32, config=TINY_ELASTICITY, cache=cache)
    assert M.shape == init.shape == (500, 3, 3) and M.dtype == torch.float32
    total = len(datasets.load_dataset("elasticity", TINY_ELASTICITY, cache))
    assert total == 6 * 2 * 40
    M, _ = datasets.warm_start_pairs("elasticity", total + 10, config=TINY_ELASTICITY, cache=cache)
    assert M.shape[0] == total + 10


def test_benchmark_times_methods_on_recorded_data(tmp_path):
    cache = str(tmp_path / "cache")
    methods = [m for m in registry.all_methods(None, ("conservative",), first_touch=False, comparison=True)
               if m.sample_n is None]
    M, init = datasets.pairs("arap", 400, torch.float32, configs={"arap": TINY_ARAP}, cache=cache, progress=False)
    assert len(datasets.load_dataset("arap", TINY_ARAP, cache)) == 400  # the given configuration, in that cache
    rows = cases.run_case("apps", "arap", M, init, 1, methods, 1, 0.001, log=lambda s: None, warm=True)
    by_key = {(r.key, r.mode): r for r in rows}
    assert ("svd", None) in by_key and ("copy", None) in by_key
    assert ("torchrot", "one_step") in by_key  # recorded data count as warm data
    # the rows keep the methods' order; the copy is timed one call after each other method (interleaved)
    assert [r.method for r in rows] == [m.name for m in methods if any(r.method == m.name for r in rows)]
    assert len(by_key["copy", None].runs_ns) == len(rows) - 1
    for r in rows:
        if r.mode in ("converged_cold", "converged_warm") or r.key == "svd":
            assert r.max_error < 1e-4, r.method
        # every row is timed against the SVD and the copy of the same run
        assert r.speedup_vs_svd == pytest.approx(by_key["svd", None].ns_per_matrix / r.ns_per_matrix)
        assert r.time_vs_copy == pytest.approx(r.ns_per_matrix / by_key["copy", None].ns_per_matrix)
        assert r.n == 400 and r.data == "arap" and r.dtype == "float32"
    # the structure-of-arrays rows fit the same values as their contiguous counterparts
    soa = {r.mode: r for r in rows if r.layout == "soa"}
    assert set(soa) == {"one_step", "converged_warm"}
    for r in rows:
        if r.layout == "aos" and r.mode in soa and r.variant == "conservative" and r.isa is None:
            assert soa[r.mode].max_error == pytest.approx(r.max_error, rel=1e-12), r.method
    # the same data without warm=True: the warm-start-only methods are left out
    cold = cases.run_case("apps", "arap", M[:50], init[:50], 1, methods, 1, 0.001, log=lambda s: None)
    assert not any(r.mode == "one_step" for r in cold)


def test_rotation_layer_rows():
    """The rotation-layer stage: one row per batch, every time from the same run."""
    rows = workloads.rotation_layer((8, 40), min_run_time=0.001, repeats=1)
    assert [r["batch"] for r in rows] == [8, 40]
    for r in rows:
        assert r["torchrot_vs_svd"] == pytest.approx(r["torchrot_us"] / r["svd_autograd_us"])
        assert r["autograd_floor_us"] > 0
    assert "| 40 |" in tables.format_layer_table(rows)


def test_registration_rows():
    """The registration stage: one row per dtype and shape, times and accuracy from the same run."""
    rows = workloads.registration_rows(((1, 20), (3, 10)), (torch.float32, torch.float64), rounds=1, min_run_time=0.001)
    assert [(r["dtype"], r["problems"], r["points"]) for r in rows] == \
        [("float32", 1, 20), ("float32", 3, 10), ("float64", 1, 20), ("float64", 3, 10)]
    for r in rows:
        assert r["speedup_vs_svd"] == pytest.approx(r["svd_us"] / r["torchrot_us"])
        assert r["copy_us"] > 0
        assert r["max_r_error"] < (1e-5 if r["dtype"] == "float32" else 1e-12)
    assert "| 3 x 10 | float64 |" in tables.format_registration_table(rows)


def test_report_tables_select_rows_by_field():
    def row(method, key, group, isa=None, ns=10.0, data="arap"):
        return Row("apps", data, method, "float32", 100, 1, ns, isa=isa, group=group, key=key,
                         max_error=0.0, share_above_1e3=0.0, speedup_vs_svd=1000.0 / ns)

    rows = [row("copy", "copy", "floor"), row("svd (renamed)", "svd", "baseline", ns=1000.0),
            row("mcadams (renamed)", "igl_single", "baseline", ns=500.0),
            row("t scalar", "torchrot", "torchrot", "scalar", ns=100.0),
            row("t vec", "torchrot", "torchrot", "avx2", ns=20.0), row("horn", "horn", "paper method")]
    t1, t2 = report.table1(rows, data_sets=("arap",)), report.table2(rows, data_sets=("arap",))
    assert "t scalar" in t1 and "horn" in t1 and "svd (renamed)" in t1
    assert "t vec" not in t1 and "| copy |" not in t1
    assert "t vec" in t2 and "mcadams (renamed)" in t2 and "t scalar" not in t2 and "horn" not in t2
    assert "| t vec | 20.0 | 50.0x | 25.0x |" in t2  # over SVD and over McAdams, found by key


def test_recording_statistics(tmp_path):
    cache = str(tmp_path / "cache")
    rec = datasets.load_dataset("arap", TINY_ARAP, cache, progress=False)
    stats = recording_statistics(rec, scatter=20)
    assert stats["matrices"] == 400
    assert sum(stats["angle_degrees"]["histogram"]["counts"]) == 400
    assert len(stats["scatter"]["newton"]) == 20
    # TINY_ARAP is a 4-frame session: the handles jump far between frames, so about half of the
    # warm starts are within 1 degree of the answer (measured: 46.75%, 62% within 10 degrees)
    angle = stats["angle_degrees"]
    assert 0.3 < angle["share_below_1"] <= angle["share_below_10"] < 0.8, angle
    assert angle["p10"] <= angle["median"] <= angle["p90"] <= angle["p99"] <= angle["max"] < 180
    # the shares match the errors of one step computed directly (all 400 matrices are sampled)
    R_star = torchrot.rotation_svd(rec.M)
    for variant in ("newton", "conservative"):
        err = one_step_errors(rec.M, rec.R_prev, R_star, variant)
        one = stats["one_step"][variant]
        assert one["share_below_1e-5"] == pytest.approx((err < 1e-5).double().mean().item(), abs=1e-12)
        assert one["max"] == pytest.approx(err.max().item(), rel=1e-12)
    # where the warm start already is the answer (over 10% of the matrices: the frames' last
    # iterations on a converged fit), one step stays there to rounding
    assert angle["p10"] < 1e-10 and stats["one_step"]["newton"]["p10"] < 1e-12
    # cotangent covariances of the small capsule: well conditioned (measured median 55, p90 115)
    cond = stats["condition_number"]
    assert 10 < cond["median"] < 200 and cond["p90"] < 1e3, cond


def test_solvers_take_their_instrumentation_as_arguments():
    mesh = capsule(4)
    script = HandleScript(frames=2)
    handles, _ = script.handles(mesh.V)
    solver = ArapSolver(mesh.V, mesh.F, handles, LocalStep("converged"))
    timer = PhaseTimer()
    run_arap_session(solver, script, 2, fit=LocalStep("svd"), timer=timer)
    assert {k: len(v) for k, v in timer.seconds.items()} == {"assembly": 4, "fit": 4, "rhs": 4, "solve": 4}
    assert solver.fit == LocalStep("converged") and not hasattr(solver, "timer")  # not switched
    tets = octopus(8)
    elastic = ElasticitySolver(tets.V, tets.F, iterations=2)
    timer = PhaseTimer()
    elastic.step(elastic.initial_state(), fit=LocalStep("one_step"), timer=timer)
    assert len(timer.seconds["fit"]) == 2 and elastic.fit == LocalStep()


def test_start_states_leave_the_solver_unchanged():
    mesh = capsule(4)
    script = HandleScript(frames=6)
    solver = experiments.arap_solver(mesh, script, fit="one_step")
    experiments.arap_start_state(solver, script, 2, 2)
    assert solver.fit == LocalStep("one_step")


def _imports(path, package_root):
    """Modules of the torchrot package imported by the file at ``path`` (absolute and relative)."""
    import ast

    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package_root.rsplit(".", node.level)[0] if node.level > 1 else package_root
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module
            found.add(module)
            found |= {f"{module}.{a.name}" for a in node.names}
    return {m for m in found if m.split(".")[0] == "torchrot"}


def test_package_layering_no_cycles_and_library_never_imports_bench():
    """Every module's imports (lazy ones included), resolved to modules of the
    package: torchrot.bench is imported by no library module, and the import
    graph has no cycle (a package's __init__ counts as the package)."""
    import pathlib

    root = pathlib.Path(torchrot.__file__).parent
    modules = {}
    for path in root.rglob("*.py"):
        parts = path.relative_to(root.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        modules[name] = path
    graph = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        targets = set()
        for m in _imports(path, package):
            while m and m not in modules:  # "from torchrot.bench import data" -> torchrot.bench.data
                m = m.rsplit(".", 1)[0] if "." in m else ""
            if m and m != name:
                targets.add(m)
        graph[name] = targets
    library = [m for m in modules if not m.startswith("torchrot.bench") and m != "torchrot.__main__"]
    for m in library:
        assert not any(t.startswith("torchrot.bench") for t in graph[m]), f"{m} imports the benchmark"
    # no cycle (the top package "torchrot" is every module's parent: imports of it name the library API)
    state: dict = {}

    def visit(m, stack):
        state[m] = "open"
        for t in graph[m]:
            if t == "torchrot" and m != "torchrot":
                continue
            if state.get(t) == "open":
                raise AssertionError("import cycle: " + " -> ".join(stack + [m, t]))
            if t not in state:
                visit(t, stack + [m])
        state[m] = "done"

    for m in graph:
        if m not in state:
            visit(m, [])
    assert "torchrot.bench.plans" in graph["torchrot.bench.cli"]
    assert graph["torchrot.__main__"] == {"torchrot.bench.cli"}


def test_rotation_angle_is_accurate_near_zero():
    gen = torch.Generator().manual_seed(3)
    for angle in (1e-9, 1e-4, 0.5, 3.0):
        R = random_rotations(5, gen, max_angle=angle, concentration=0.0)
        torch.testing.assert_close(rotation_angle(R), torch.full((5,), angle, dtype=torch.float64),
                                   rtol=1e-9, atol=1e-15)
