"""Every committed result (benchmarks/results/, benchmarks/accuracy.md) was
written by this version of torchrot: each names the version, machine, date
and command that wrote it (torchrot.bench.machine.machine_info), and a result
of another minor version fails here, so that no figure is older than the
code it describes. Regenerate with the command the file names."""
from __future__ import annotations

import ast
import json
import pathlib
import re
import tomllib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULTS = sorted((ROOT / "benchmarks" / "results").glob("*.json")) + sorted(
    (ROOT / "benchmarks" / "results").glob("*.md")) + [ROOT / "benchmarks" / "accuracy.md"]
VERSION = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]


def _minor(version: str) -> tuple[int, int]:
    major, minor = version.split(".")[:2]
    return int(major), int(minor)


def _machine(path: pathlib.Path) -> dict:
    if path.suffix == ".json":
        return json.loads(path.read_text())["machine"]
    line = re.search(r"^Machine: (\{.*\})", path.read_text(), re.M)
    assert line, f"{path.name} has no 'Machine: {{...}}' line"
    return ast.literal_eval(line.group(1).split("}, ")[0] + ("}" if "}, " in line.group(1) else ""))


@pytest.mark.parametrize("path", RESULTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_written_by_this_version(path):
    machine = _machine(path)
    assert {"torchrot", "torch", "processor", "cores", "date", "command"} <= set(machine), path.name
    assert _minor(machine["torchrot"]) == _minor(VERSION), (
        f"{path.relative_to(ROOT)} was written by torchrot {machine['torchrot']}, this is {VERSION}: "
        f"rerun `{machine['command']}`")


def test_every_picture_has_its_run():
    """Each PNG of benchmarks/results/ comes with the results file of its run."""
    folder = ROOT / "benchmarks" / "results"
    runs = {"bench_scaling": "bench.json", "fig5_data": "apps.json", "fig6_local_global": "apps.json",
            "fig7_energy_time": "apps.json", "train_rotation_regression": "train_rotation_regression.json"}
    for picture in folder.glob("*.png"):
        assert picture.stem in runs and (folder / runs[picture.stem]).exists(), picture.name


def _text_block(markdown: str) -> str:
    block = re.search(r"```text\n(.*?)```", markdown, re.S)
    assert block, "no ```text block"
    return block.group(1)


def test_readme_quotes_the_committed_summary():
    """The README's headline is the committed run's summary
    (benchmarks/results/summary.md, written by the main job), verbatim, with
    its scaling plot."""
    summary = _text_block((ROOT / "benchmarks" / "results" / "summary.md").read_text())
    readme = (ROOT / "README.md").read_text()
    assert summary in readme, "README.md does not quote benchmarks/results/summary.md's summary as it stands"
    assert "](benchmarks/results/bench_scaling.png)" in readme
