"""The device benchmark, ``python -m torchrot bench --device DEVICE``:
torchrot's operators on one device's tensors (an accelerator's: what CUDA
and XPU tensors run is torchrot's Triton kernels; the CPU's: a quick check of
the job itself), each beside ``torch.linalg.svd`` on the same device, RoMa's
``special_procrustes`` where it is installed, and a ``copy_`` of the input
into a preallocated tensor, timed interleaved in one process with the device
synchronised (:func:`torchrot.bench.timing.device_median_seconds`); and the
latency of a first call in a fresh process with an empty Triton cache.
Writes ``device.json`` and ``device.md``."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time

import torch

from torchrot.bench.machine import machine_info
from torchrot.bench.options import dtype_name
from torchrot.bench.tables import fmt
from torchrot.bench.timing import device_median_seconds
from torchrot.fitting import fit_rotation
from torchrot.nn import RotationFit
from torchrot.reference import rigid_registration_svd, rotation_svd
from torchrot.registration import rigid_registration
from torchrot.testing.data import make_matrices, make_warm_start, registration_problem

__all__ = ["DEVICE_N", "SVD_MAX_N", "REGISTRATION_PROBLEMS", "FILES", "synchronizer", "method_rows",
           "registration_rows", "first_call_seconds", "format_device_report", "target_lines", "device_bench"]

#: Matrices per row (``--device-n``).
DEVICE_N = (1_000, 10_000, 100_000, 1_000_000, 10_000_000)
#: torch.linalg.svd, RoMa and the rotation layer are timed up to this many
#: matrices (``--svd-max-n``): batched 3x3 SVDs of 1e7 matrices take minutes on some GPUs.
SVD_MAX_N = 1_000_000
#: Point-set registration: problems of REGISTRATION_POINTS points each.
REGISTRATION_PROBLEMS = (1_000, 10_000, 100_000)
REGISTRATION_POINTS = 64
#: The files :func:`device_bench` writes.
FILES = ("device.json", "device.md")


def synchronizer(device: torch.device):
    """A function that waits for ``device``'s queued work (nothing on the CPU)."""
    if device.type == "cpu":
        return lambda: None
    module = getattr(torch, device.type)
    return lambda: module.synchronize(device)


def _roma():
    try:
        import roma
    except ImportError:
        return None
    return roma.special_procrustes


def method_rows(device: torch.device, ns, dtype: torch.dtype, rounds: int, min_run_time: float,
                svd_max_n: int = SVD_MAX_N) -> list[dict]:
    """One row per N: ns per matrix of each method (the median of ``rounds``
    interleaved rounds), on warm-start data (testing.make_warm_start("warm"),
    generated once at the largest N and sliced)."""
    synchronize = synchronizer(device)
    M_all, init_all = (t.to(device) for t in make_warm_start("warm", max(ns), 0, dtype))
    roma = _roma()
    layer = RotationFit()
    rows = []
    for n in ns:
        M, init = M_all[:n], init_all[:n]
        buffer, R = torch.empty_like(M), init.clone()
        G = make_matrices("gaussian", n, 1, dtype).to(device) if n <= svd_max_n else None
        V = M.detach().clone().requires_grad_()

        def layer_step(fit, V=V, G=G):
            V.grad = None
            (fit(V) * G).sum().backward()

        calls = {
            "copy_": lambda M=M, buffer=buffer: buffer.copy_(M),
            "converged cold": lambda M=M: fit_rotation(M),
            "converged warm": lambda M=M, init=init: fit_rotation(M, init),
            "one step in place": lambda M=M, R=R: fit_rotation(M, R, max_iter=1, out=R),
        }
        if n <= svd_max_n:
            calls["torch.linalg.svd"] = lambda M=M: rotation_svd(M)
            if roma is not None:
                calls["roma"] = lambda M=M: roma(M)
            calls["layer torchrot"] = lambda: layer_step(layer)
            calls["layer svd"] = lambda: layer_step(rotation_svd)
        seconds = device_median_seconds(calls, synchronize, rounds, min_run_time)
        rows.append({"n": n, "dtype": dtype_name(dtype), **{name: s / n * 1e9 for name, s in seconds.items()}})
    return rows


def registration_rows(device: torch.device, dtype: torch.dtype, rounds: int, min_run_time: float,
                      problems=REGISTRATION_PROBLEMS) -> list[dict]:
    """rigid_registration(x, y, scale=True) beside the SVD closed form and a
    copy_ of the points: us per call."""
    synchronize = synchronizer(device)
    rows = []
    for count in problems:
        x, y, _ = registration_problem((count,), n=REGISTRATION_POINTS, seed=0, noise=0.1, dtype=dtype)
        x, y = x.to(device), y.to(device)
        x_copy, y_copy = torch.empty_like(x), torch.empty_like(y)
        calls = {"copy_": lambda x=x, y=y, xc=x_copy, yc=y_copy: (xc.copy_(x), yc.copy_(y)),
                 "svd": lambda x=x, y=y: rigid_registration_svd(x, y, scale=True),
                 "torchrot": lambda x=x, y=y: rigid_registration(x, y, scale=True)}
        seconds = device_median_seconds(calls, synchronize, rounds, min_run_time)
        rows.append({"problems": count, "points": REGISTRATION_POINTS, "dtype": dtype_name(dtype),
                     **{name: s * 1e6 for name, s in seconds.items()}})
    return rows


_FIRST_CALL = r"""
import json, sys, time
import torch
start = time.perf_counter()
import torchrot  # noqa
device, dtype = torch.device(sys.argv[1]), getattr(torch, sys.argv[2])
sync = (lambda: None) if device.type == "cpu" else (lambda: getattr(torch, device.type).synchronize(device))
M = torch.randn(10_000, 3, 3, dtype=dtype, device=device)
sync()
seconds = {"import torchrot": time.perf_counter() - start}
for name, call in (("converged cold", lambda: torchrot.fit_rotation(M)),
                   ("one step warm", lambda: torchrot.fit_rotation(M, R, max_iter=1, out=R)),
                   ("backward", lambda: torch.ops.torchrot.fit_rotation_backward(M, R, M, 0.0))):
    start = time.perf_counter()
    result = call()
    sync()
    seconds[name] = time.perf_counter() - start
    if name == "converged cold":
        R = result
print(json.dumps(seconds))
"""


def first_call_seconds(device: torch.device, dtype: torch.dtype) -> dict:
    """Seconds of the first call of each kind (converged cold fit, in-place
    one-step update, derivative) in a fresh Python process with an empty
    Triton cache (TRITON_CACHE_DIR): what a first training step waits for
    (kernel compilation included), and the import."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, TRITON_CACHE_DIR=cache)
        done = subprocess.run([sys.executable, "-c", _FIRST_CALL, str(device), dtype_name(dtype)], env=env,
                              capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _ratio(row: dict, a: str, b: str) -> float | None:
    return row[a] / row[b] if a in row and b in row else None


def format_device_report(result: dict) -> str:
    """device.md: the method tables (ns per matrix, and ratios), the
    registration table and the first calls."""
    lines = [f"# torchrot on {result['device_name']}", "", f"Machine: {result['machine']}", "",
             f"Command: `{result['command']}`", ""]
    methods = ["copy_", "torch.linalg.svd", "roma", "converged cold", "converged warm", "one step in place",
               "layer svd", "layer torchrot"]
    for dtype in result["dtypes"]:
        rows = [r for r in result["methods"] if r["dtype"] == dtype]
        shown = [m for m in methods if any(m in r for r in rows)]
        lines += [f"## {dtype}: ns per matrix (median of {result['rounds']} interleaved rounds)", "",
                  "| N | " + " | ".join(shown) + " | cold x SVD | one step x copy_ |",
                  "|---:|" + "---:|" * (len(shown) + 2)]
        for r in rows:
            speedup = _ratio(r, "torch.linalg.svd", "converged cold")
            lines.append(f"| {r['n']:,} | " + " | ".join(fmt(r.get(m), ".2f") for m in shown)
                         + f" | {fmt(speedup, '.0f')} | {fmt(_ratio(r, 'one step in place', 'copy_'), '.2f')} |")
        lines.append("")
    lines += ["## rigid_registration(x, y, scale=True): us per call", "",
              "| problems x points | dtype | copy_ | SVD closed form | torchrot | x SVD |",
              "|---|---|---:|---:|---:|---:|"]
    for r in result["registration"]:
        lines.append(f"| {r['problems']:,} x {r['points']} | {r['dtype']} | {r['copy_']:.1f} | {r['svd']:.1f} | "
                     f"{r['torchrot']:.1f} | {r['svd'] / r['torchrot']:.1f} |")
    lines += ["", "## First call in a fresh process, empty Triton cache (seconds)", ""]
    for dtype, seconds in result["first_call"].items():
        lines.append(f"- {dtype}: " + ", ".join(f"{name} {s:.2f}" for name, s in seconds.items()))
    return "\n".join(lines + ["", *target_lines(result), ""])


def target_lines(result: dict) -> list[str]:
    """The accelerator targets, as measured: at N >= 1e5 converged fits at
    least 100x torch.linalg.svd, the one-step update within 3x of copy_, a
    first call under 10 s."""
    big = [r for r in result["methods"] if r["n"] >= 100_000]
    lines = ["Targets (N >= 1e5):"]
    speedups = [r["torch.linalg.svd"] / r[m] for r in big for m in ("converged cold", "converged warm")
                if "torch.linalg.svd" in r]
    if speedups:
        lines.append(f"- converged fits {min(speedups):.0f}-{max(speedups):.0f}x faster than torch.linalg.svd "
                     f"(target >= 100x): {'met' if min(speedups) >= 100 else 'not met'}")
    copies = [r["one step in place"] / r["copy_"] for r in big]
    if copies:
        lines.append(f"- one-step update {min(copies):.2f}-{max(copies):.2f}x copy_ (target <= 3x): "
                     f"{'met' if max(copies) <= 3 else 'not met'}")
    firsts = [s for seconds in result["first_call"].values() for name, s in seconds.items()
              if name != "import torchrot"]
    if firsts:
        lines.append(f"- first calls {min(firsts):.2f}-{max(firsts):.2f} s (target < 10 s): "
                     f"{'met' if max(firsts) < 10 else 'not met'}")
    return lines


def device_bench(device: str, ns=DEVICE_N, dtypes=(torch.float32, torch.float64), rounds: int = 5,
                 min_run_time: float = 0.05, svd_max_n: int = SVD_MAX_N, output: str | None = None,
                 command: str = "", log=print) -> dict:
    """The whole device job: method rows for every dtype, registration
    rows, first calls; prints device.md and writes the files into ``output``."""
    device = torch.device(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else device.type
    result = {"device": str(device), "device_name": name, "machine": machine_info(), "command": command,
              "rounds": rounds, "dtypes": [dtype_name(d) for d in dtypes], "methods": [], "registration": [],
              "first_call": {}}
    clock = time.perf_counter()
    for dtype in dtypes:
        log(f"[{time.perf_counter() - clock:6.0f} s] {dtype_name(dtype)}: first calls, methods at N = "
            f"{', '.join(f'{n:,}' for n in ns)}, registration")
        result["first_call"][dtype_name(dtype)] = first_call_seconds(device, dtype)
        result["methods"] += method_rows(device, ns, dtype, rounds, min_run_time, svd_max_n)
        result["registration"] += registration_rows(device, dtype, rounds, min_run_time,
                                                    [p for p in REGISTRATION_PROBLEMS if p <= max(ns)])
    report = format_device_report(result)
    log(report)
    if output:
        os.makedirs(output, exist_ok=True)
        with open(os.path.join(output, FILES[0]), "w") as f:
            json.dump(result, f, indent=1)
        with open(os.path.join(output, FILES[1]), "w") as f:
            f.write(report)
        for file in FILES:
            log(f"wrote {os.path.join(output, file)}")
    return result
