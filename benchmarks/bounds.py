"""What bounds torchrot's CPU speed, measured: instructions, bytes and steps per matrix.

    python benchmarks/bounds.py [--output benchmarks/bounds.md]   (about 4-5 minutes)

Issue 3 asks, for every speed target that does not hold, what bounds it,
measured. This script measures on the machine it runs on (float32 and float64,
one thread):

1. Instructions per matrix, exactly, as the difference of the counts of one
   call on two batch sizes divided by the difference of the sizes (per-call
   costs cancel), counting inside the kernel entry point only (fit_batch,
   tangent_batch, at::native::copy_):
   - scalar, default and AVX2 kernels under valgrind's callgrind
     (--toggle-collect on the entry points; client requests of
     bounds_tools/probes.c delimit one dump per call);
   - the AVX-512 kernel by single-stepping the entry point with ptrace
     (bounds_tools/tracer.c), since valgrind cannot execute AVX-512 and perf
     has no hardware counters in this virtual machine. Run on AVX2 as well, it
     matches callgrind exactly up to callgrind's convention for rep-prefixed
     instructions (printed in the report);
   - where the AVX-512 instructions go: by kernel stage (the inline chain of
     every executed address, from the extension's debug info via addr2line)
     and by instruction class (objdump).
2. Time per matrix (N = 1e6): several interleaved torch.utils.benchmark
   medians (wall time) and thread-CPU-time medians (which leave out other
   processes' time slices on a shared machine), beside copy_, a 3-stream add
   (the memory traffic of a warm-start call) and torch.linalg.svd in the same
   run; the core clock (a chain of dependent multiplies), hence cycles and
   instructions per cycle; bytes per matrix against the rate copy_ achieves;
   the cost of first-touching a new output.
3. Cayley steps per matrix (fit_rotation_info): mean, distribution, fallback
   rate, and the steps SIMD blocks execute for them (a block steps until its
   slowest lane converges); the time per step (max_iter = 1 -> 3, cold start).

Then, per missed target of issue 3, the bound these numbers give. Data come
from torchrot.testing.make_warm_start, as in torchrot.benchmark: "warm" is the
warm-start solver data (M, init), "uniform" is M = init @ U[0,1] matrices.
Needs a C compiler; valgrind (with valgrind/callgrind.h), ptrace, objdump and
addr2line for the instruction counts (parts that cannot run are skipped and
say so). Only reads the built extension; never rebuilds it.
"""
from __future__ import annotations

import argparse
import collections
import ctypes
import hashlib
import json
import os
import platform
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from typing import Callable

import torch
import torch.utils.benchmark as tbench

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # the repository's torchrot, installed or not

import torchrot  # noqa: E402
from torchrot.benchmark import forced_isa, supported_isas  # noqa: E402
from torchrot.reference import rotation_svd  # noqa: E402
from torchrot.testing import make_warm_start  # noqa: E402

TOOLS = os.path.join(HERE, "bounds_tools")
DTYPES = {"float32": torch.float32, "float64": torch.float64}

# Timing: N matrices per call, REPEATS blocked_autorange medians per case,
# interleaved across cases so that load from other users spreads over all.
TIME_N = 1_000_000
SVD_N = 100_000  # SVD costs the same per matrix at any N; 1e6 would take seconds per call
# Cache-resident timings: inputs and output of N = 1e4 float32 matrices (1.1 MB)
# stay in the 2 MB L2 across calls, so these time the computation alone.
CACHED_N = 10_000
CACHED_CASES = ("copy", "add3", "onestep", "conv_warm", "cold_uniform")
REPEATS = 5
MIN_RUN_TIME = 0.2
# Instruction counts: (N1, N2) per dtype; instructions per matrix are
# (count(N2) - count(N1)) / (N2 - N1). Single-stepping runs ~1e4 instructions/s
# here, so the traced batches are small (whole SIMD blocks, first sub-chunk).
CALLGRIND_N = (5_000, 25_000)
TRACE_N = {"float32": (256, 768), "float64": (128, 384)}
CROSSCHECK_N = (256, 768)
WORKER_N = max(CALLGRIND_N[1], *(n[1] for n in TRACE_N.values()))
STEP_SLOPE = (1, 3)  # max_iter of the two cold-start calls whose difference is the cost of steps
# The batched driver's pass structure (csrc/cpu/fit_rotation_kernel.h): matrices
# are fitted in sub-chunks; a block takes up to STEPS_PER_PASS steps per pass
# (as many as its slowest lane needs), unfinished lanes are regrouped.
SUB_CHUNK = 1024
STEPS_PER_PASS = 5


# ---------------------------------------------------------------------------
# The measured calls
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    """One call measured per matrix: `make(data, n, out)` returns it as a thunk.

    reads/writes: (3, 3) matrices read and written per matrix (x 36 B in
    float32); entry: the function the tracer steps through ("fit" = fit_batch,
    "tangent" = tangent_batch, "copy" = at::native::copy_, None = not traced);
    kernel: runs a torchrot kernel (so it is timed and counted per ISA)."""

    key: str
    title: str
    make: Callable
    reads: int
    writes: int
    entry: str | None
    kernel: bool = True
    dtypes: tuple = ("float32", "float64")
    time_n: int | None = None  # N for timing, if not TIME_N


def _fit(M_key, init=False, max_iter=None):
    def make(d, n, out):
        M = d[M_key][:n]
        start = d["init"][:n] if init else None
        return lambda: torchrot.fit_rotation(M, start, max_iter=max_iter, out=out[:n])
    return make


CASES = [
    Case("copy", "copy_ (memory floor)", lambda d, n, out: (lambda: out[:n].copy_(d["M"][:n])), 1, 1, "copy",
         kernel=False),
    Case("add3", "add(M, init, out=) (3-stream floor)",
         lambda d, n, out: (lambda: torch.add(d["M"][:n], d["init"][:n], out=out[:n])), 2, 1, None, kernel=False),
    Case("onestep", "1-step warm (max_iter=1, init, out=)", _fit("M", init=True, max_iter=1), 2, 1, "fit"),
    Case("onestep_new", "1-step warm, new output (first touch)",
         lambda d, n, out: (lambda: torchrot.fit_rotation(d["M"][:n], d["init"][:n], max_iter=1)), 2, 1, None,
         dtypes=("float32",)),
    Case("cold_step1", "cold uniform, max_iter=1", _fit("U", max_iter=STEP_SLOPE[0]), 1, 1, "fit"),
    Case("cold_step3", "cold uniform, max_iter=3", _fit("U", max_iter=STEP_SLOPE[1]), 1, 1, "fit"),
    Case("conv_warm", "converged warm (init)", _fit("M", init=True), 2, 1, "fit"),
    Case("cold_uniform", "converged cold, uniform", _fit("U"), 1, 1, "fit"),
    Case("cold_warm", "converged cold, warm data", _fit("M"), 1, 1, "fit"),
    Case("backward", "fit_rotation_backward(G, R, M, 1e-6)",
         lambda d, n, out: (lambda: torch.ops.torchrot.fit_rotation_backward(d["G"][:n], d["R"][:n], d["M"][:n],
                                                                             1e-6)), 3, 1, "tangent"),
    Case("svd", "torch.linalg.svd special Procrustes", lambda d, n, out: (lambda: rotation_svd(d["M"][:n])), 1, 1,
         None, kernel=False, dtypes=("float32",), time_n=SVD_N),
]
CASE = {c.key: c for c in CASES}
TRACED = {"float32": [c.key for c in CASES if c.entry],
          "float64": ["copy", "onestep", "conv_warm", "cold_uniform", "backward"]}


def make_data(n: int, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """The tensors every case reads: warm (M, init), uniform U, and for the
    backward R = fit(M) and a gradient G. All (n, 3, 3), contiguous."""
    M, init = make_warm_start("warm", n, seed=0, dtype=dtype)
    U, _ = make_warm_start("uniform", n, seed=0, dtype=dtype)
    G = torch.randn(n, 3, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64).to(dtype)
    return {"M": M, "init": init, "U": U, "R": torchrot.fit_rotation(M), "G": G}


# ---------------------------------------------------------------------------
# Tools: the C helpers, built into a temporary folder
# ---------------------------------------------------------------------------

def build_tools(folder: str) -> dict[str, str | None]:
    """Compiles bounds_tools/*.c; a tool that does not build is None."""
    compiler = shutil.which("cc") or shutil.which("gcc")
    built = {}
    for name, args in (("tracer", ["-O2", "-o"]), ("probes", ["-O2", "-shared", "-fPIC", "-o"])):
        target = os.path.join(folder, name + (".so" if name == "probes" else ""))
        result = subprocess.run([compiler, *args, target, os.path.join(TOOLS, name + ".c")],
                                capture_output=True, text=True) if compiler else None
        built[name] = target if result is not None and result.returncode == 0 else None
        if built[name] is None:
            print(f"could not build {name}: {result.stderr if result else 'no C compiler'}", file=sys.stderr)
    return built


def mapped_extension() -> dict:
    """The extension as this process mapped it: path, inode, load base and the
    executable segment [lo, hi). The file at the path may have been replaced
    since (people rebuild and swap it atomically): the inode identifies the build."""
    path = os.path.realpath(torchrot._C.__file__)
    found = {"path": path, "base": None, "lo": None, "hi": None, "inode": None, "range": None}
    with open("/proc/self/maps") as f:
        for line in f:
            parts = line.split(maxsplit=5)
            if len(parts) < 6 or parts[5].strip().removesuffix(" (deleted)") != path:
                continue
            start, end = (int(x, 16) for x in parts[0].split("-"))
            if int(parts[2], 16) == 0 and found["base"] is None:
                found.update(base=start, inode=int(parts[4]), range=parts[0])
            if "x" in parts[1]:
                found.update(lo=start, hi=end)
    return found


def snapshot_extension(mapped: dict, target: str) -> bool:
    """Copies the build this process mapped to `target` (for nm, objdump and
    addr2line); False if it is no longer readable."""
    try:
        shutil.copyfile(f"/proc/self/map_files/{mapped['range']}", target)  # the mapped file itself
        return True
    except OSError:
        pass
    if os.stat(mapped["path"]).st_ino != mapped["inode"]:
        return False
    shutil.copyfile(mapped["path"], target)
    return os.stat(mapped["path"]).st_ino == mapped["inode"]


COPY_SYMBOL = "_ZN2at6native5copy_ERNS_6TensorERKS1_b"  # at::native::copy_(Tensor&, const Tensor&, bool)


def kernel_symbols(so_path: str) -> dict[str, tuple[int, str]]:
    """"isa:entry:dtype" -> (offset in the extension, mangled name) of the
    batched kernels fit_batch ("fit") and tangent_batch ("tangent")."""
    text = subprocess.run(["nm", so_path], capture_output=True, text=True, check=True).stdout
    found = {}
    pattern = re.compile(r"^_ZN8torchrot3cpu\d+([A-Z0-9]+)12_GLOBAL__N_1\d+(fit_batch|tangent_batch)I.*"
                         r"(?:Scalar|Vector)LanesI([fd])E")
    for line in text.splitlines():
        parts = line.split()
        if len(parts) != 3 or "." in parts[2]:
            continue
        m = pattern.match(parts[2])
        if m:
            entry = "fit" if m.group(2) == "fit_batch" else "tangent"
            dtype = "float32" if m.group(3) == "f" else "float64"
            found[f"{m.group(1).lower()}:{entry}:{dtype}"] = (int(parts[0], 16), parts[2])
    return found


# ---------------------------------------------------------------------------
# Workers: re-run this script under callgrind or under the tracer
# ---------------------------------------------------------------------------

def _worker_data(spec: dict) -> dict:
    data = torch.load(spec["data"])
    outs = {dt: torch.empty_like(data[dt]["M"]) for dt in data}
    return data, outs


def callgrind_worker(spec: dict) -> None:
    """Under callgrind (counting only inside the kernel entry points): each
    measurement zeroes the counters, runs its call and dumps a file labelled
    with it. The first call of each case is an unmeasured warm-up, so that
    lazy symbol binding is not counted."""
    torch.set_num_threads(1)
    probes = ctypes.CDLL(spec["probes"])
    data, outs = _worker_data(spec)
    if mapped_extension()["inode"] != spec["inode"]:
        sys.exit("the extension was replaced before this worker loaded it: rerun")
    probes.bounds_cg_instrument()
    skipped, warm = [], set()
    for isa, dtype, key, n in spec["measurements"]:
        with forced_isa(isa):
            if CASE[key].kernel and torch.ops.torchrot.cpu_kernel() != isa:
                skipped.append(f"{isa} (callgrind runs {torch.ops.torchrot.cpu_kernel()})")
                continue
            call = CASE[key].make(data[dtype], n, outs[dtype])
            if (isa, dtype, key) not in warm:
                CASE[key].make(data[dtype], 64, outs[dtype])()
                warm.add((isa, dtype, key))
            probes.bounds_cg_zero()
            call()
            probes.bounds_cg_dump(f"{isa}:{dtype}:{key}:{n}".encode())
    with open(spec["result"], "w") as f:
        json.dump({"skipped": sorted(set(skipped))}, f)


def trace_worker(spec: dict) -> None:
    """Under the tracer: before each measured call, asks the tracer (SIGUSR1)
    to step through the next call of the kernel entry point."""
    torch.set_num_threads(1)
    data, outs = _worker_data(spec)
    mapped = mapped_extension()
    if mapped["inode"] != spec["inode"]:  # the symbol offsets would point into another build
        sys.exit(f"the extension was replaced before this worker loaded it (inode {mapped['inode']}, "
                 f"expected {spec['inode']}): rerun")
    base, lo, hi = mapped["base"], mapped["lo"], mapped["hi"]
    libtorch = ctypes.CDLL(os.path.join(os.path.dirname(torch.__file__), "lib", "libtorch_cpu.so"))
    copy_entry = ctypes.cast(libtorch[COPY_SYMBOL], ctypes.c_void_p).value
    for isa, dtype, key, n in spec["measurements"]:
        with forced_isa(isa):
            case = CASE[key]
            if case.entry == "copy":
                entry = copy_entry
            else:
                entry = base + spec["symbols"][f"{torch.ops.torchrot.cpu_kernel()}:{case.entry}:{dtype}"][0]
            call = case.make(data[dtype], n, outs[dtype])
            call()
            path = os.path.join(spec["folder"], f"{isa}_{dtype}_{key}_{n}.txt")
            with open(spec["command"], "w") as f:
                f.write(f"{entry:x} {lo:x} {hi:x} {base:x} {path}\n")
            os.kill(os.getpid(), signal.SIGUSR1)  # the tracer takes it (and suppresses it)
            call()


def _write_spec(folder: str, name: str, spec: dict) -> str:
    path = os.path.join(folder, f"{name}_spec.json")
    with open(path, "w") as f:
        json.dump(spec, f)
    return path


def start_callgrind(tools: dict, folder: str, data_path: str, symbols: dict, inode: int,
                    env: dict) -> subprocess.Popen | None:
    """The callgrind worker: scalar / default / AVX2, both dtypes, two N each,
    plus the AVX2 cross-check at the tracer's N. None if it cannot run."""
    if not tools["probes"] or not shutil.which("valgrind"):
        return None
    measurements = [(isa, dtype, key, n) for isa in ("scalar", "default", "avx2") if isa in supported_isas()
                    for dtype in DTYPES for key in TRACED["float32"] for n in CALLGRIND_N]
    measurements += [("avx2", "float32", "onestep", n) for n in CROSSCHECK_N]
    out = os.path.join(folder, "callgrind")
    os.makedirs(out)
    spec = _write_spec(folder, "callgrind", {"probes": tools["probes"], "data": data_path, "inode": inode,
                                             "measurements": measurements, "result": os.path.join(out, "result.json")})
    # Count inside the kernel entry points only, as the tracer does: the Python
    # side of a call varies by a few thousand instructions (GC, allocator).
    toggles = [f"--toggle-collect={name}" for _, name in symbols.values()] + [f"--toggle-collect={COPY_SYMBOL}"]
    cmd = ["valgrind", "--tool=callgrind", "--instr-atstart=no", "--collect-atstart=no", "--demangle=no",
           "--dump-line=no", *toggles, f"--callgrind-out-file={os.path.join(out, 'cg.out')}", sys.executable,
           os.path.abspath(__file__), "--worker", "callgrind", "--spec", spec]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def start_tracer(tools: dict, folder: str, data_path: str, symbols: dict, inode: int,
                 env: dict) -> subprocess.Popen | None:
    """The tracer worker: the best ISA (the traced cases per dtype, two N
    each) and the AVX2 cross-check. None if the tracer did not build."""
    if not tools["tracer"]:
        return None
    top = supported_isas()[-1]
    measurements = [(top, dtype, key, n) for dtype, keys in TRACED.items() for key in keys for n in TRACE_N[dtype]]
    if "avx2" in supported_isas():
        measurements += [("avx2", "float32", "onestep", n) for n in CROSSCHECK_N]
    out = os.path.join(folder, "trace")
    os.makedirs(out)
    command = os.path.join(out, "command")
    spec = _write_spec(folder, "trace", {"data": data_path, "measurements": measurements, "folder": out,
                                         "inode": inode, "symbols": symbols, "command": command})
    return subprocess.Popen([tools["tracer"], sys.executable, os.path.abspath(__file__), "--worker", "trace", "--spec",
                             spec], env=dict(env, TRACER_COMMAND=command), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def run_workers(tools: dict, folder: str, data_path: str, snapshot: str, inode: int, log) -> dict:
    """Runs the callgrind and the tracer workers side by side on the build
    `inode` (copied to `snapshot`); returns {"callgrind": {label: instructions},
    "trace": {label: (total, histogram)}, "notes": [...]}."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.dirname(HERE), os.environ.get("PYTHONPATH", "")]))
    symbols = kernel_symbols(snapshot)
    procs = {"callgrind": start_callgrind(tools, folder, data_path, symbols, inode, env),
             "trace": start_tracer(tools, folder, data_path, symbols, inode, env)}
    result = {"callgrind": {}, "trace": {}, "notes": []}
    for name, proc in procs.items():
        if proc is None:
            result["notes"].append(f"{name} counts skipped: " + ("valgrind, its callgrind.h or a C compiler is missing"
                                                                if name == "callgrind" else "the tracer did not build"))
            continue
        started = time.time()
        output, _ = proc.communicate()
        log(f"  {name} worker finished (rc {proc.returncode}) after waiting {time.time() - started:.0f} s")
        if proc.returncode != 0:
            own = "\n".join(line for line in output.splitlines() if not line.startswith("=="))  # not valgrind's
            result["notes"].append(f"{name} worker failed (rc {proc.returncode}): {own[-2000:].strip()}")
    if procs["callgrind"] is not None:
        result["callgrind"] = parse_callgrind(os.path.join(folder, "callgrind"))
        result_file = os.path.join(folder, "callgrind", "result.json")
        if os.path.exists(result_file):
            with open(result_file) as f:
                skipped = json.load(f)["skipped"]
            if skipped:
                result["notes"].append("callgrind could not run: " + ", ".join(skipped))
    if procs["trace"] is not None:
        result["trace"] = parse_traces(os.path.join(folder, "trace"))
    return result


CALLGRIND_LABEL = "desc: Trigger: Client Request: "


def parse_callgrind(folder: str) -> dict[str, int]:
    """label -> instructions, from callgrind's dump files."""
    counts = {}
    for name in os.listdir(folder):
        if not name.startswith("cg.out"):
            continue
        label = total = None
        with open(os.path.join(folder, name)) as f:
            for line in f:
                if line.startswith(CALLGRIND_LABEL):
                    label = line[len(CALLGRIND_LABEL):].strip()
                elif line.startswith("summary:") or line.startswith("totals:"):
                    total = int(line.split()[1])
        if label is not None and total is not None:
            counts[label] = total
    return counts


def parse_traces(folder: str) -> dict[str, tuple[int, dict[int, int]]]:
    """label -> (instructions, {extension offset: executions})."""
    traces = {}
    for name in os.listdir(folder):
        if not name.endswith(".txt"):
            continue
        hist, total = {}, 0
        with open(os.path.join(folder, name)) as f:
            for line in f:
                key, value = line.split()
                if key == "total":
                    total = int(value)
                elif key != "outside":
                    hist[int(key, 16)] = int(value)
        isa, dtype, rest = name[:-4].split("_", 2)
        key, n = rest.rsplit("_", 1)
        traces[f"{isa}:{dtype}:{key}:{n}"] = (total, hist)
    return traces


def per_matrix(counts: dict, isa: str, dtype: str, key: str, ns: tuple[int, int]) -> float | None:
    """Instructions per matrix from the counts of two batch sizes."""
    a, b = (counts.get(f"{isa}:{dtype}:{key}:{n}") for n in ns)
    if a is None or b is None:
        return None
    a, b = (x[0] if isinstance(x, tuple) else x for x in (a, b))
    return (b - a) / (ns[1] - ns[0])


# ---------------------------------------------------------------------------
# Where the instructions go: stages (inline chains) and classes (objdump)
# ---------------------------------------------------------------------------

# Stage of an executed address: the first entry of this list whose function
# appears anywhere in the address's inline chain (so gram() inside the
# Newton-Schulz step counts as the clean-up, gram() in begin_fit as the
# warm-start validation, and times() in advance as the step's R Q).
STAGES = [
    ("load_soa", "AoS<->SoA transpose"), ("store_soa", "AoS<->SoA transpose"),
    ("load_block", "block load/store (non-transposed part)"), ("store_block", "block load/store (non-transposed part)"),
    ("rotation_tangent", "backward: solve and R [u]x"),
    ("reorthonormalize", "Newton-Schulz clean-up"),
    ("is_rotation", "warm-start validation (R^T R, det)"),
    ("best_start_rotation", "cold start (best of 12 rotations)"),
    ("saddle_escape_rotation", "saddle escape"),
    ("horn_rotation", "fallback (Horn)"),
    ("is_maximum", "maximum check (converged mode)"),
    ("objective_estimate", "Cayley step: estimate c (Eqs. 26-27)"),
    ("cayley_step", "Cayley step: solve for z (Alg. 2)"),
    ("cayley_rotation", "Cayley step: Q(z) (Eq. 10)"),
    ("transpose_times", "Cayley step: S = R^T A"),
    ("times", "Cayley step: R <- R Q"),
    ("advance", "Cayley step: masks, counters, convergence tests"),
    ("gram", "warm-start validation (R^T R, det)"),
    ("begin_fit", "normalisation and lane set-up"),
    ("save_running_lanes", "regrouping unfinished lanes"), ("restore_block", "regrouping unfinished lanes"),
    ("store_diagnostics", "regrouping unfinished lanes"), ("extract_lane", "regrouping unfinished lanes"),
    ("finish", "finish: fallback/NaN lanes"),
    ("fit_range", "driver loop"), ("tangent_range", "driver loop"),
]
STAGE_PRIORITY = {name: i for i, (name, _) in enumerate(STAGES)}
STAGE_ORDER = list(dict.fromkeys(s for _, s in STAGES)) + ["other (in the extension)", "outside the extension"]
STEP_STAGES = [s for s in STAGE_ORDER if s.startswith("Cayley step")]


def _base_name(function: str) -> str:
    """'ns::Mat3<...> ns::finish<...>(...)' -> 'finish'."""
    text = function.replace("(anonymous namespace)", "anon")
    previous = None
    while previous != text:
        previous = text
        text = re.sub(r"<[^<>]*>", "", text)
        text = re.sub(r"\([^()]*\)", "", text)
    return text.split()[-1].split("::")[-1] if text.split() else text


def stage_of_addresses(so_path: str, addresses: list[int]) -> dict[int, str]:
    """Offset -> stage, from the inline chain addr2line reads in the debug info."""
    if not addresses:
        return {}
    output = subprocess.run(["addr2line", "-e", so_path, "-i", "-f", "-C", "-a", *map(hex, addresses)],
                            capture_output=True, text=True, check=True).stdout.splitlines()
    stages, current, chain, i = {}, None, [], 0

    def close():
        if current is not None:
            ranks = [STAGE_PRIORITY[n] for n in map(_base_name, chain) if n in STAGE_PRIORITY]
            stages[current] = STAGES[min(ranks)][1] if ranks else "other (in the extension)"

    while i < len(output):
        line = output[i]
        if line.startswith("0x"):
            close()
            current, chain = int(line, 16), []
            i += 1
        else:
            chain.append(line)
            i += 2  # function, then file:line
    close()
    return stages


def disassembly(so_path: str) -> dict[int, tuple[str, str]]:
    """Offset -> (mnemonic, operands) of every instruction in the extension."""
    text = subprocess.run(["objdump", "-d", "--no-show-raw-insn", so_path], capture_output=True, text=True,
                          check=True).stdout
    instructions = {}
    for line in text.splitlines():
        m = re.match(r"^\s+([0-9a-f]+):\s+(\S+)\s*(.*)$", line)
        if m:
            instructions[int(m.group(1), 16)] = (m.group(2), m.group(3))
    return instructions


ARITHMETIC = ("vadd", "vsub", "vmul", "vdiv", "vsqrt", "vfmadd", "vfmsub", "vfnmadd", "vmax", "vmin", "vand", "vor",
              "vxor", "vrcp", "vrsqrt", "vpternlog", "vpand", "vpor", "vpxor")
SHUFFLES = ("vperm", "vblend", "vpblend", "vshuf", "vunpck", "vinsert", "vextract", "vpshuf", "valign", "vmovsh",
            "vmovhlps", "vmovlhps", "vmovshdup", "vmovsldup", "vmovddup")
COMPARES = ("vcmp", "vpcmp", "vptest", "vpmovm2", "vpmov", "vmovmsk", "vfpclass", "vtest", "vucomi", "vcomi")
CLASS_ORDER = ["FP arithmetic / logic", "shuffle / blend / permute", "compare / mask", "vector register move",
               "vector spill / reload (stack)", "vector load / store (data, tables)", "mask-register ops",
               "scalar and control (integer, branches, calls)"]


def instruction_class(mnemonic: str, operands: str) -> str:
    stack = "(%rsp" in operands or "(%rbp" in operands
    if mnemonic.startswith("k"):
        return "mask-register ops"
    if not mnemonic.startswith("v"):
        return "scalar and control (integer, branches, calls)"
    if mnemonic.startswith(SHUFFLES):
        return "shuffle / blend / permute"
    if mnemonic.startswith(("vmov", "vbroadcast", "vpbroadcast")):
        if stack:
            return "vector spill / reload (stack)"
        return "vector load / store (data, tables)" if "(" in operands else "vector register move"
    if mnemonic.startswith(COMPARES):
        return "compare / mask"
    if mnemonic.startswith(ARITHMETIC):
        return "FP arithmetic / logic"
    return "scalar and control (integer, branches, calls)"


def breakdown(trace_a, trace_b, n_diff: int, stages: dict, instructions: dict) -> dict:
    """Per-matrix instructions of the difference of two traces, by stage and by class,
    and how many of them read or write the stack."""
    (total_a, hist_a), (total_b, hist_b) = trace_a, trace_b
    by_stage, by_class = collections.Counter(), collections.Counter()
    stack = 0.0
    inside = 0
    for offset in set(hist_a) | set(hist_b):
        count = hist_b.get(offset, 0) - hist_a.get(offset, 0)
        inside += count
        by_stage[stages.get(offset, "other (in the extension)")] += count
        mnemonic, operands = instructions.get(offset, ("?", ""))
        by_class[instruction_class(mnemonic, operands)] += count
        stack += count * ("(%rsp" in operands or "(%rbp" in operands)
    outside = (total_b - total_a) - inside
    by_stage["outside the extension"] += outside
    by_class["scalar and control (integer, branches, calls)"] += outside  # libc / runtime: not classified
    scale = 1.0 / n_diff
    return {"stage": {k: v * scale for k, v in by_stage.items()}, "class": {k: v * scale for k, v in by_class.items()},
            "stack": stack * scale}


def rep_starts(traces: dict, label: str, ns: tuple[int, int], instructions: dict) -> float | None:
    """rep-prefixed instructions started per matrix in the difference of two
    traces, counted by executions of the instruction just before each."""
    a, b = (traces.get(f"{label}:{n}") for n in ns)
    if a is None or b is None:
        return None
    order = sorted(instructions)
    position = {offset: i for i, offset in enumerate(order)}
    starts = 0
    for offset in set(a[1]) | set(b[1]):
        if instructions.get(offset, ("", ""))[0].startswith("rep") and position.get(offset, 0) > 0:
            before = order[position[offset] - 1]
            starts += b[1].get(before, 0) - a[1].get(before, 0)
    return starts / (ns[1] - ns[0])


# ---------------------------------------------------------------------------
# Time, clock, iterations
# ---------------------------------------------------------------------------

def clock_ghz(probes_path: str | None, samples: int = 5) -> list[float]:
    """GHz from the dependent-multiply chain (3 cycles per imul), timed in
    thread CPU time so that other processes' time slices do not count."""
    if probes_path is None:
        return []
    chain = ctypes.CDLL(probes_path).bounds_multiply_chain
    chain.argtypes, chain.restype = [ctypes.c_long], ctypes.c_long
    iterations = 5_000_000
    chain(iterations // 10)
    result = []
    for _ in range(samples):
        start = time.thread_time_ns()
        chain(iterations)
        result.append(3 * 8 * iterations / (time.thread_time_ns() - start))
    return result


def cpu_seconds(call: Callable, calls: int = 3, inner: int = 1) -> float:
    """Median thread CPU time per call of `calls` samples of `inner` calls:
    unlike wall time, it excludes the time slices other processes take on
    this shared 2-core machine."""
    samples = []
    for _ in range(calls):
        start = time.thread_time_ns()
        for _ in range(inner):
            call()
        samples.append((time.thread_time_ns() - start) / inner)
    return statistics.median(samples) * 1e-9


def time_cases(data: dict, log) -> dict[str, dict[str, list[float]]]:
    """"isa:dtype:case" -> {"wall": [...], "cpu": [...]} in ns per matrix:
    REPEATS blocked_autorange medians (wall) and thread-CPU-time medians,
    interleaved: repeat r of every case runs before repeat r + 1 of any.
    Labels ending in "@cached" are the CACHED_N timings."""
    isas = [i for i in ("avx512", "avx2") if i in supported_isas()]
    outs = {dt: torch.empty_like(data[dt]["M"]) for dt in data}
    plan = {}
    for dtype in DTYPES:
        for case in CASES:
            if dtype not in case.dtypes:
                continue
            for isa in isas if case.kernel and dtype == "float32" else isas[:1]:
                n = case.time_n or TIME_N
                plan[f"{isa}:{dtype}:{case.key}"] = (isa, n, case.make(data[dtype], n, outs[dtype]))
    for key in CACHED_CASES:
        plan[f"{isas[0]}:float32:{key}@cached"] = (isas[0], CACHED_N,
                                                    CASE[key].make(data["float32"], CACHED_N, outs["float32"]))
    times = {label: {"wall": [], "cpu": []} for label in plan}
    for r in range(REPEATS):
        for label, (isa, n, call) in plan.items():
            timer = tbench.Timer(stmt="call()", globals={"call": call}, num_threads=1)
            with forced_isa(isa):
                times[label]["wall"].append(timer.blocked_autorange(min_run_time=MIN_RUN_TIME).median / n * 1e9)
                inner = TIME_N // n if label.endswith("@cached") else 1  # samples of ~1e6 matrices
                times[label]["cpu"].append(cpu_seconds(call, inner=inner) / n * 1e9)
        log(f"  timing repeat {r + 1}/{REPEATS} done")
    return times


def lane_width(dtype: torch.dtype) -> int:
    """Matrices per SIMD block of the best kernel this CPU runs (ATen's
    Vectorized is 512 bits wide for AVX-512, 256 bits for AVX2 and default)."""
    bits = 512 if supported_isas()[-1] == "avx512" else 256
    return bits // torch.finfo(dtype).bits


def block_steps(steps: torch.Tensor, width: int) -> float:
    """Cayley steps per matrix the batched kernel executes, as lane slots:
    each block of `width` lanes steps as long as its slowest lane (up to
    STEPS_PER_PASS per pass; lanes left over are regrouped into full blocks
    for the next pass, per sub-chunk). Equals the mean steps per matrix only
    if every block's lanes need the same number of steps."""
    total = 0
    for chunk in steps.long().split(SUB_CHUNK):
        pending = chunk
        while pending.numel():
            padded = torch.nn.functional.pad(pending, (0, -pending.numel() % width))
            total += int(padded.view(-1, width).amax(1).clamp(max=STEPS_PER_PASS).sum())
            pending = pending[pending > STEPS_PER_PASS] - STEPS_PER_PASS
    return total * width / steps.numel()


def iteration_stats(dtype: torch.dtype, n: int) -> list[dict]:
    """Cayley steps per matrix for warm / uniform / rot60, cold and warm start,
    and the steps the SIMD blocks execute for them."""
    rows = []
    width = lane_width(dtype)
    for data in ("warm", "uniform", "rot60"):
        M, init = make_warm_start(data, n, seed=0, dtype=dtype)
        for start in ("cold", "warm"):
            info = torchrot.fit_rotation_info(M, init if start == "warm" else None)
            steps = info.iterations.long()
            hist = torch.bincount(steps, minlength=8).double() / n
            rows.append({"data": data, "start": start, "mean": steps.double().mean().item(),
                         "p50": steps.median().item(), "p99": steps.double().quantile(0.99).item(),
                         "max": steps.max().item(), "hist": hist.tolist(), "width": width,
                         "block_steps": block_steps(steps, width),
                         "fallback": (info.status == 1).double().mean().item()})
    return rows


# ---------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------

@dataclass
class Report:
    """Everything measured: format_report turns it into bounds.md."""

    machine: dict
    ghz: list[float]
    times: dict  # "isa:dtype:case" -> {"wall": [ns], "cpu": [ns]}
    counts: dict  # {"callgrind": {label: count}, "trace": {label: (count, histogram)}}
    breakdowns: dict  # "dtype:case" -> breakdown()
    iterations: dict  # dtype -> iteration_stats()
    slices: dict  # "dtype:case" -> mean steps of the traced slice
    rep_invocations: float | None = None  # rep-prefixed instructions started per matrix, AVX2 cross-check
    notes: list = field(default_factory=list)


def _median(values):
    return statistics.median(values) if values else None


def _f(x, spec=".1f"):
    return "-" if x is None else format(x, spec)


def format_report(rep: Report) -> str:
    ghz = statistics.median(rep.ghz) if rep.ghz else None
    top = supported_isas()[-1]
    lines = ["# What bounds torchrot's CPU speed (measured)", "",
             "Written by `python benchmarks/bounds.py` (the method is in its docstring). One thread throughout.",
             "", "## Machine and run", ""]
    lines += [f"- {k}: {v}" for k, v in rep.machine.items()]
    if rep.ghz:
        lines.append(f"- core clock (dependent imul chain, thread CPU time): "
                     f"{', '.join(f'{g:.2f}' for g in rep.ghz)} GHz; the median, {ghz:.2f} GHz, converts time "
                     "to cycles")
    lines += [f"- note: {n}" for n in rep.notes]
    lines += _instruction_section(rep, top)
    lines += _time_section(rep, top, ghz)
    lines += _iteration_section(rep)
    lines += conclusions(rep, top, ghz)
    return "\n".join(lines) + "\n"


def _instruction_section(rep: Report, top: str) -> list[str]:
    lines = ["", "## 1. Instructions per matrix (exact counts, differenced over two batch sizes)", "",
             f"{top.upper()}: ptrace single-stepping of the kernel function, N = {TRACE_N['float32']} (float32), "
             f"{TRACE_N['float64']} (float64). scalar / default / AVX2: callgrind, N = {CALLGRIND_N}; its copy_ "
             "row is ATen's AVX2 copy (valgrind hides AVX-512 from ATen too). `AVX2/2` is the estimate first "
             "proposed for AVX-512 (the same code on twice the lanes); the measured column replaces it. Converged "
             "counts depend on the steps the measured matrices took: the last two columns give the mean steps of "
             "the matrices differenced (section 3 has the means over 1e6 matrices).", "",
             f"| case | dtype | scalar | default | AVX2 | AVX2/2 | {top.upper()} (measured) | steps, callgrind slice | "
             f"steps, {top.upper()} slice |", "|---|---|---|---|---|---|---|---|---|"]
    for dtype in DTYPES:
        for key in TRACED["float32"]:
            cg = {isa: per_matrix(rep.counts["callgrind"], isa, dtype, key, CALLGRIND_N)
                  for isa in ("scalar", "default", "avx2")}
            traced = per_matrix(rep.counts["trace"], top, dtype, key, TRACE_N[dtype])
            half = cg["avx2"] / 2 if cg["avx2"] is not None else None
            lines.append(f"| {CASE[key].title} | {dtype} | {_f(cg['scalar'])} | {_f(cg['default'])} | "
                         f"{_f(cg['avx2'])} | {_f(half)} | {_f(traced)} | "
                         f"{_f(rep.slices.get(f'callgrind:{dtype}:{key}'), '.2f')} | "
                         f"{_f(rep.slices.get(f'trace:{dtype}:{key}') if key in TRACED[dtype] else None, '.2f')} |")
    a = per_matrix(rep.counts["callgrind"], "avx2", "float32", "onestep", CROSSCHECK_N)
    b = per_matrix(rep.counts["trace"], "avx2", "float32", "onestep", CROSSCHECK_N)
    if a is not None and b is not None:
        lines += ["", f"Cross-check of the two counting methods, AVX2 float32 1-step warm on the same matrices "
                  f"(N = {CROSSCHECK_N}), both counting inside the kernel function: callgrind {a:.4f}, tracer "
                  f"{b:.4f} instructions/matrix. The difference, {a - b:.4f}/matrix, equals the rep-prefixed string "
                  f"instructions started per matrix, {_f(rep.rep_invocations, '.4f')} (counted by the instruction "
                  "before each): callgrind counts a rep instruction's final rcx = 0 test as one more execution, the "
                  "CPU's single-step trap counts iterations only. Otherwise the counts are identical."]
    for key, bd in rep.breakdowns.items():
        dtype, case = key.split(":")
        width = (16 if dtype == "float32" else 8) // (1 if top == "avx512" else 2)
        total = sum(bd["stage"].values())
        lines += ["", f"### Where the {top.upper()} instructions go: {CASE[case].title}, {dtype}", "",
                  f"{total:.1f} per matrix, {total * width:.0f} per {width}-matrix block; by stage (the "
                  "inline chain of each executed address) and by instruction class.", "",
                  "| stage | instr/matrix | share |", "|---|---|---|"]
        step = sum(bd["stage"].get(k, 0.0) for k in STEP_STAGES)
        for stage in STAGE_ORDER:
            v = bd["stage"].get(stage, 0.0)
            if abs(v) >= 0.05:
                lines.append(f"| {stage} | {v:.1f} | {v / total:.0%} |")
        if step:
            lines.append(f"| (Cayley step stages together) | {step:.1f} | {step / total:.0%} |")
        lines += ["", "| instruction class | instr/matrix | share |", "|---|---|---|"]
        for cls in CLASS_ORDER:
            v = bd["class"].get(cls, 0.0)
            if abs(v) >= 0.05:
                lines.append(f"| {cls} | {v:.1f} | {v / total:.0%} |")
        lines.append(f"| (any class: instructions with a stack operand) | {bd['stack']:.1f} | "
                     f"{bd['stack'] / total:.0%} |")
    return lines


def _time_section(rep: Report, top: str, ghz: float | None) -> list[str]:
    lines = ["", f"## 2. Time, bytes and instructions per cycle (N = {TIME_N:.0e}; SVD N = {SVD_N:.0e})", "",
             f"Per case {REPEATS} interleaved repeats of a torch.utils.benchmark blocked_autorange median (wall "
             "time, what the benchmark suite reports) and of a median of 3 calls in thread CPU time, which leaves "
             "out the time slices other processes take on this shared machine (user + system time, so page "
             "faults count). Cycles and IPC use the CPU time. Bytes: matrices read + written x 36 B (float32) / "
             "72 B (float64), without write-allocate reads; `ns at copy_'s rate` is those bytes at the rate copy_ "
             "achieves (CPU time).", ""]
    for dtype in DTYPES:
        copy_cpu = _median(rep.times.get(f"{top}:{dtype}:copy", {}).get("cpu"))
        if copy_cpu is None:
            continue
        size = 36 if dtype == "float32" else 72
        rate = 2 * size / copy_cpu
        svd = _median(rep.times.get(f"{top}:{dtype}:svd", {}).get("cpu"))
        lines += [f"### {dtype}: copy_ moves {2 * size} B/matrix at {rate:.1f} GB/s (CPU time)", "",
                  "| case | ISA | wall ns/matrix: median (min - max) | CPU ns/matrix: median (min - max) | x copy_ "
                  "| x SVD | bytes/matrix | ns at copy_'s rate | instr/matrix | cycles/matrix | IPC |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for label, samples in rep.times.items():
            isa, dt, key = label.split(":")
            if dt != dtype or key.endswith("@cached"):
                continue
            case = CASE[key]
            wall, cpu = _median(samples["wall"]), _median(samples["cpu"])
            moved = (case.reads + case.writes) * size
            instr = instructions_per_matrix(rep, isa if case.kernel else top, dtype, key)
            cycles = cpu * ghz if ghz else None
            ipc = instr / cycles if instr is not None and cycles else None
            lines.append(f"| {case.title} | {isa if case.kernel else '-'} | {wall:.2f} ({min(samples['wall']):.2f} - "
                         f"{max(samples['wall']):.2f}) | {cpu:.2f} ({min(samples['cpu']):.2f} - "
                         f"{max(samples['cpu']):.2f}) | {cpu / copy_cpu:.2f} | {_f(svd / cpu if svd else None)} | "
                         f"{moved} | {moved / rate:.2f} | {_f(instr)} | {_f(cycles)} | {_f(ipc, '.2f')} |")
        lines += _cached_table(rep, top, dtype, ghz)
        fresh, reused = (_median(rep.times.get(f"{top}:{dtype}:{k}", {}).get("cpu"))
                         for k in ("onestep_new", "onestep"))
        if fresh is not None and reused is not None:
            per_page = (fresh - reused) * 4096 / size
            lines += ["", f"First touch of a new output (1-step warm without `out=`): {fresh - reused:.2f} ns/matrix "
                      f"more, {per_page / 1000:.2f} us per 4 KiB page of output (page faults and zeroing, in "
                      "system time). The backward allocates its output the same way, which is why its IPC is low: "
                      "kernel-side instructions are not in the count."]
        lines.append("")
    return lines


def _cached_table(rep: Report, top: str, dtype: str, ghz: float | None) -> list[str]:
    """The CACHED_N timings: the same calls with data resident in L2."""
    labels = [k for k in rep.times if k.endswith("@cached") and k.split(":")[1] == dtype]
    copy = _median(rep.times.get(f"{top}:{dtype}:copy@cached", {}).get("cpu"))
    if not labels or copy is None:
        return []
    lines = ["", f"Cache-resident: the same calls on N = {CACHED_N:.0e} (inputs and output, "
             f"{CACHED_N * 36 * 3 / 2**20:.1f} MiB, stay in L2 across calls), CPU time:", "",
             "| case | CPU ns/matrix: median (min - max) | x copy_ (cached) | same at N = 1e6 | instr/matrix | "
             "cycles/matrix | IPC |", "|---|---|---|---|---|---|---|"]
    for label in labels:
        key = label.split(":")[2].removesuffix("@cached")
        cpu = _median(rep.times[label]["cpu"])
        big = _median(rep.times.get(f"{top}:{dtype}:{key}", {}).get("cpu"))
        instr = instructions_per_matrix(rep, top, dtype, key)
        cycles = cpu * ghz if ghz else None
        lines.append(f"| {CASE[key].title} | {cpu:.2f} ({min(rep.times[label]['cpu']):.2f} - "
                     f"{max(rep.times[label]['cpu']):.2f}) | {cpu / copy:.2f} | {_f(big, '.2f')} | {_f(instr)} | "
                     f"{_f(cycles)} | {_f(instr / cycles if instr is not None and cycles else None, '.2f')} |")
    return lines


def instructions_per_matrix(rep: Report, isa: str, dtype: str, key: str) -> float | None:
    """The measured count for this ISA: traced for the top ISA, callgrind below."""
    if isa == supported_isas()[-1]:
        return per_matrix(rep.counts["trace"], isa, dtype, key, TRACE_N[dtype])
    return per_matrix(rep.counts["callgrind"], isa, dtype, key, CALLGRIND_N)


def _iteration_section(rep: Report) -> list[str]:
    lines = ["## 3. Cayley steps per matrix (fit_rotation_info, converged mode, conservative variant)", "",
             "`steps executed` replays the driver's pass structure on these per-matrix counts: a block of lanes "
             f"steps while any lane runs (up to {STEPS_PER_PASS} steps per pass), then unfinished lanes are "
             f"regrouped into full blocks (per sub-chunk of {SUB_CHUNK}); `useful` = mean / executed.", ""]
    for dtype, rows in rep.iterations.items():
        lines += [f"{dtype}, N = {TIME_N:.0e}:", "",
                  f"| data | start | mean | median | p99 | max | share with 1 / 2 / 3 / 4 / 5 / 6+ steps | fallback | "
                  f"steps executed per matrix in {rows[0]['width']}-lane blocks | useful |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            h = r["hist"]
            shares = " / ".join(f"{x:.1%}" for x in h[1:6]) + f" / {sum(h[6:]):.1%}"
            lines.append(f"| {r['data']} | {r['start']} | {r['mean']:.2f} | {r['p50']} | {r['p99']:.0f} | "
                         f"{r['max']} | {shares} | {r['fallback']:.4%} | {r['block_steps']:.2f} | "
                         f"{r['mean'] / r['block_steps']:.0%} |")
        lines.append("")
    return lines


def conclusions(rep: Report, top: str, ghz: float | None) -> list[str]:
    """Per missed target of issue 3, its bound, from the numbers above (float32, CPU time)."""
    dtype = "float32"

    def cpu(key):
        return _median(rep.times.get(f"{top}:{dtype}:{key}", {}).get("cpu"))

    def wall(key):
        return _median(rep.times.get(f"{top}:{dtype}:{key}", {}).get("wall"))

    def instr(key):
        return per_matrix(rep.counts["trace"], top, dtype, key, TRACE_N[dtype])

    keys = ("copy", "add3", "onestep", "cold_step1", "cold_step3", "conv_warm", "cold_uniform", "svd")
    stats = {(r["data"], r["start"]): r for r in rep.iterations.get(dtype, [])}
    if ghz is None or any(cpu(k) is None for k in keys) or any(instr(k) is None for k in keys[2:7]) or \
            f"{dtype}:onestep" not in rep.breakdowns or not stats:
        return ["## 4. Bounds", "", "Not enough measurements to conclude (see the notes above)."]
    copy, add3, one, c1, c3, cw, cu, svd = (cpu(k) for k in keys)
    span = STEP_SLOPE[1] - STEP_SLOPE[0]
    step_ns = (c3 - c1) / span
    step_instr = (instr("cold_step3") - instr("cold_step1")) / span
    i_one, i_cw, i_cu = instr("onestep"), instr("conv_warm"), instr("cold_uniform")
    stage, cls = rep.breakdowns[f"{dtype}:onestep"]["stage"], rep.breakdowns[f"{dtype}:onestep"]["class"]
    step_stages = sum(stage.get(k, 0.0) for k in STEP_STAGES)
    exactness = sum(stage.get(k, 0.0) for k in ("warm-start validation (R^T R, det)", "normalisation and lane set-up",
                                                 "Newton-Schulz clean-up"))
    ports = sum(cls.get(k, 0.0) for k in ("FP arithmetic / logic", "shuffle / blend / permute", "compare / mask"))
    overhead = sum(cls.get(k, 0.0) for k in ("vector spill / reload (stack)", "vector register move",
                                             "scalar and control (integer, branches, calls)", "mask-register ops"))
    ipc_one = i_one / (one * ghz)
    cached = {k: cpu(f"{k}@cached") for k in ("onestep", "conv_warm", "cold_uniform")}
    one_c = cached["onestep"] if cached["onestep"] is not None else one
    ipc_c = i_one / (one_c * ghz)
    budget = 1.5 * copy * ghz * ipc_c
    warm, uniform = stats[("warm", "warm")], stats[("uniform", "cold")]
    if one_c > 1.5 * copy:
        verdict = "bound by instructions: the computation alone, without any memory traffic, exceeds the target"
    else:
        verdict = ("bound by instructions and by memory time they do not hide: the computation alone is just "
                   "under the target in this run")
    if 1.5 * copy < add3:
        floor_text = "the target is below the call's own memory floor"
    else:
        floor_text = (f"the target is {1.5 * copy / add3:.2f}x the call's own memory floor, so the computation would "
                      f"have to hide {'almost entirely ' if 1.5 * copy < 1.3 * add3 else ''}under its memory traffic")
    if ports / 2 / ghz > 1.5 * copy:
        port_text = "these alone exceed the target, before any load, store, spill or branch"
    else:
        port_text = (f"meeting it would need near-peak use of both ports and almost none of the other "
                     f"{i_one - ports:.1f} instructions, or dropping work the exactness requires")
    lines = ["## 4. Bounds of the missed targets (float32, 1 thread, N = 1e6, CPU time)", "",
             f"Times are this run's CPU-time medians (wall-clock medians: copy_ {wall('copy'):.2f}, 1-step warm "
             f"{wall('onestep'):.2f}, converged warm {wall('conv_warm'):.2f}, converged cold uniform "
             f"{wall('cold_uniform'):.2f}, SVD {wall('svd'):.0f} ns/matrix). copy_ and add are memory-bound and "
             f"slow down with other users' memory traffic (load average in the machine section), so the "
             f"time ratios to copy_ move between runs; instruction and step counts do not.", ""]
    lines += [
        f"**One-step warm start <= 1.5x copy_** (target {1.5 * copy:.2f} ns, measured {one:.2f} ns = "
        f"{one / copy:.2f}x copy_): {verdict}. The call moves 108 B/matrix, 1.5x copy_'s "
        f"72 B, and the same traffic without computation (`add(M, init, out=)`) takes {add3:.2f} ns = "
        f"{add3 / copy:.2f}x copy_: {floor_text}. The computation alone, with "
        f"the data resident in L2, takes {one_c:.2f} ns = {one_c / (1.5 * copy):.2f}x the target: "
        f"{i_one:.1f} instructions/matrix in {one_c * ghz:.0f} cycles (IPC {ipc_c:.2f} at {ghz:.2f} GHz). At "
        f"N = 1e6 memory stalls add {one - one_c:.2f} ns (IPC {ipc_one:.2f}): computation and memory traffic overlap "
        f"only partly (fully overlapped, the call would take max({one_c:.2f}, {add3:.2f}) ns). At the in-cache IPC "
        f"the target allows {budget:.0f} instructions/matrix. Of the {i_one:.1f}: AoS<->SoA transposes "
        f"{stage.get('AoS<->SoA transpose', 0.0):.1f}, the Cayley step {step_stages:.1f}, warm-start validation + "
        f"normalisation + Newton-Schulz clean-up (what makes the result exact and safe for any input) "
        f"{exactness:.1f}, the rest driver and finish; by class, FP arithmetic "
        f"{cls.get('FP arithmetic / logic', 0.0):.1f}, spills/reloads, register moves, mask and scalar "
        f"instructions {overhead:.1f}. The vector FP, shuffle and compare instructions ({ports:.1f}/matrix) can "
        f"only issue on the two 512-bit vector ports of this Intel core (0 and 5), so they alone need >= "
        f"{ports / 2:.1f} cycles = {ports / 2 / ghz:.2f} ns (a port-model estimate, not measured) against a target "
        f"of {1.5 * copy:.2f} ns: {port_text}.", ""]
    fixed = one - step_ns
    lines += [
        f"**Converged fit on warm data <= 10 ns** (measured {cw:.2f} ns, {_f(cached['conv_warm'], '.2f')} ns with "
        f"the data in L2; {i_cw:.1f} instructions/matrix, IPC {i_cw / (cw * ghz):.2f}): "
        f"bound by the fixed per-call work plus the steps SIMD blocks execute. A matrix "
        f"needs {warm['mean']:.2f} steps on average, but a {warm['width']}-lane block steps until its slowest lane "
        f"has converged: {warm['block_steps']:.2f} steps per matrix are executed "
        f"({warm['mean'] / warm['block_steps']:.0%} of the lane steps are useful; section 3). A step costs "
        f"{step_ns:.2f} ns and {step_instr:.1f} "
        f"instructions per matrix (max_iter {STEP_SLOPE[0]} -> {STEP_SLOPE[1]}); the rest of a one-step call "
        f"(two loads and transposes, validation, normalisation, clean-up, store) is {fixed:.2f} ns. Fixed + "
        f"executed steps = {fixed:.2f} + {warm['block_steps']:.2f} x {step_ns:.2f} = "
        f"{fixed + warm['block_steps'] * step_ns:.2f} ns; the other {cw - fixed - warm['block_steps'] * step_ns:.2f} "
        f"ns is converged mode's checks (maximum check, convergence and switch tests, regrouping). Even with every "
        f"lane of a block needing the same number of steps it would be {fixed + warm['mean'] * step_ns:.2f} ns: "
        f"10 ns needs the fixed part and the step both cheaper, not only fewer steps.", ""]
    cold_fixed = c1 - step_ns
    lines += [
        f"**Converged cold start on uniform >= 100x SVD** (torch.linalg.svd {svd:.0f} ns, target <= "
        f"{svd / 100:.2f} ns; measured {cu:.2f} ns = {svd / cu:.0f}x, {_f(cached['cold_uniform'], '.2f')} ns with "
        f"the data in L2; {i_cu:.1f} instructions/matrix, IPC {i_cu / (cu * ghz):.2f}): "
        f"bound by the number of steps. A cold start needs {uniform['mean']:.2f} steps, "
        f"blocks execute {uniform['block_steps']:.2f} per matrix ({uniform['mean'] / uniform['block_steps']:.0%} "
        f"useful); max_iter=1 costs {c1:.2f} ns, i.e. {cold_fixed:.2f} ns besides its step (load, normalisation, "
        f"cold start, clean-up, store). Fixed + executed steps = {cold_fixed + uniform['block_steps'] * step_ns:.2f} "
        f"ns, converged mode's checks and saddle escapes the other "
        f"{cu - cold_fixed - uniform['block_steps'] * step_ns:.2f} ns. Even with no SIMD divergence and no checks, "
        f"fixed + {uniform['mean']:.2f} steps = {cold_fixed + uniform['mean'] * step_ns:.2f} ns, "
        f"{'above' if cold_fixed + uniform['mean'] * step_ns > svd / 100 else 'below'} the target. This is compute "
        f"work that a second core divides (the suite's 2-thread rows), unlike the memory-bound copy_.", ""]
    return lines


# ---------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------

def _read(path: str) -> str:
    try:
        with open(path) as f:
            return f.read().strip()
    except OSError:
        return "?"


def machine() -> dict:
    """What the numbers were measured on."""
    cpuinfo = _read("/proc/cpuinfo").splitlines()
    model = next((line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("model name")), "?")
    caches = []
    for index in range(4):
        folder = f"/sys/devices/system/cpu/cpu0/cache/index{index}"
        if os.path.isdir(folder):
            caches.append(f"L{_read(folder + '/level')} {_read(folder + '/type').lower()} {_read(folder + '/size')}")
    return {"cpu": model, "caches (per core / shared)": ", ".join(caches), "cores": os.cpu_count(),
            "torch": torch.__version__,
            "ATen capability": torch.backends.cpu.get_cpu_capability(),
            "torchrot kernel": torch.ops.torchrot.cpu_kernel(), "python": platform.python_version(),
            "load average at start": " ".join(f"{x:.2f}" for x in os.getloadavg())}


def slice_steps(data: dict) -> dict[str, float]:
    """"method:dtype:case" -> mean Cayley steps of the matrices whose counts
    are differenced (method: "trace" or "callgrind")."""
    result = {}
    for method, pairs in (("trace", TRACE_N), ("callgrind", {dt: CALLGRIND_N for dt in DTYPES})):
        for dtype, (n1, n2) in pairs.items():
            d = data[dtype]
            calls = {"onestep": (d["M"], d["init"], 1), "cold_step1": (d["U"], None, STEP_SLOPE[0]),
                     "cold_step3": (d["U"], None, STEP_SLOPE[1]), "conv_warm": (d["M"], d["init"], None),
                     "cold_uniform": (d["U"], None, None), "cold_warm": (d["M"], None, None)}
            for key, (M, init, max_iter) in calls.items():
                info = torchrot.fit_rotation_info(M[n1:n2], None if init is None else init[n1:n2],
                                                  max_iter=max_iter)
                result[f"{method}:{dtype}:{key}"] = info.iterations.double().mean().item()
    return result


def attribute(traces: dict, so_path: str) -> tuple[dict, float | None]:
    """Breakdowns of the main traced cases by stage and class, and the rep
    instructions started per matrix in the AVX2 cross-check."""
    top = supported_isas()[-1]
    instructions = disassembly(so_path)
    wanted = [(dt, key) for dt in DTYPES for key in ("onestep", "conv_warm", "cold_uniform", "backward")
              if key in TRACED[dt]]
    offsets = set()
    for dt, key in wanted:
        for n in TRACE_N[dt]:
            offsets |= set(traces.get(f"{top}:{dt}:{key}:{n}", (0, {}))[1])
    stages = stage_of_addresses(so_path, sorted(offsets))
    breakdowns = {}
    for dt, key in wanted:
        a, b = (traces.get(f"{top}:{dt}:{key}:{n}") for n in TRACE_N[dt])
        if a and b:
            breakdowns[f"{dt}:{key}"] = breakdown(a, b, TRACE_N[dt][1] - TRACE_N[dt][0], stages, instructions)
    return breakdowns, rep_starts(traces, "avx2:float32:onestep", CROSSCHECK_N, instructions)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default=os.path.join(HERE, "bounds.md"))
    parser.add_argument("--worker", choices=("callgrind", "trace"), help=argparse.SUPPRESS)
    parser.add_argument("--spec", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        with open(args.spec) as f:
            spec = json.load(f)
        (callgrind_worker if args.worker == "callgrind" else trace_worker)(spec)
        return

    started = time.time()

    def log(message):
        print(f"[{time.time() - started:6.1f} s] {message}", flush=True)

    torch.set_num_threads(1)
    info = machine()
    mapped = mapped_extension()
    notes, counts = [], {"callgrind": {}, "trace": {}}
    breakdowns, rep_invocations = {}, None
    with tempfile.TemporaryDirectory(prefix="torchrot_bounds_") as folder:
        snapshot = os.path.join(folder, "extension.so")
        have_snapshot = snapshot_extension(mapped, snapshot)
        if have_snapshot:
            with open(snapshot, "rb") as f:
                info["extension build (sha256)"] = hashlib.sha256(f.read()).hexdigest()[:16]
        tools = build_tools(folder)
        log("making data")
        data = {dt: make_data(TIME_N, DTYPES[dt]) for dt in DTYPES}
        worker_data = {dt: {k: v[:WORKER_N].clone() for k, v in d.items()} for dt, d in data.items()}
        data_path = os.path.join(folder, "data.pt")
        torch.save(worker_data, data_path)
        log("clock and timings")
        ghz = clock_ghz(tools["probes"])
        times = time_cases(data, log)
        ghz += clock_ghz(tools["probes"])
        del data
        log("iteration statistics")
        iterations = {dt: iteration_stats(DTYPES[dt], TIME_N) for dt in DTYPES}
        slices = slice_steps(worker_data)
        if have_snapshot:
            log("instruction counts (callgrind and tracer workers, side by side)")
            counts = run_workers(tools, folder, data_path, snapshot, mapped["inode"], log)
            notes += counts.pop("notes")
            if counts["trace"]:
                log("attributing instructions")
                breakdowns, rep_invocations = attribute(counts["trace"], snapshot)
        else:
            notes.append("the extension was replaced before it could be copied: no instruction counts; rerun")
    info["load average at end"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    info["run time"] = f"{time.time() - started:.0f} s"
    report = Report(info, ghz, times, counts, breakdowns, iterations, slices, rep_invocations, notes)
    text = format_report(report)
    with open(args.output, "w") as f:
        f.write(text)
    print(text)
    log(f"wrote {args.output}")


if __name__ == "__main__":
    main()
