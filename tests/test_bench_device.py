"""The device benchmark (python -m torchrot bench --device DEVICE) as a
smoke test on CPU tensors: every table, the first-call subprocess, the
files, the targets' lines; no timing is checked."""
from __future__ import annotations

import json

import torch

from torchrot.bench import device
from torchrot.bench.cli import main


def test_device_job_writes_every_table(tmp_path):
    lines = []
    result = device.device_bench("cpu", ns=(64, 256), dtypes=(torch.float32,), rounds=1, min_run_time=1e-4,
                                 svd_max_n=64, output=str(tmp_path), log=lines.append)
    rows = result["methods"]
    assert [r["n"] for r in rows] == [64, 256]
    assert {"copy_", "converged cold", "converged warm", "one step in place", "torch.linalg.svd",
            "layer torchrot"} <= set(rows[0])
    assert "torch.linalg.svd" not in rows[1]  # above svd_max_n
    assert {r["problems"] for r in result["registration"]} == set()  # no problem count up to 256 matrices
    assert set(result["first_call"]["float32"]) == {"import torchrot", "converged cold", "one step warm", "backward"}
    saved = json.loads((tmp_path / "device.json").read_text())
    assert saved["methods"] == rows
    report = (tmp_path / "device.md").read_text()
    assert "## float32: ns per matrix" in report and "Targets (N >= 1e5):" in report and "first calls" in report


def test_cli_runs_the_device_job(tmp_path, capsys):
    assert main(["bench", "--device", "cpu", "--device-n", "1000", "--svd-max-n", "1000", "--dtype", "float64",
                 "--repeats", "1", "--output", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "## float64: ns per matrix" in out and "1,000 x 64" in out
    assert (tmp_path / "device.md").exists()
