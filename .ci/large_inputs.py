"""Large inputs: memory and 64-bit indexing of the CPU kernels.

Each check runs in a fresh subprocess, so its peak resident set (VmHWM,
reset with /proc/self/clear_refs before the call) is the call's own:

* ``contiguous``: N = 5e7 float32 matrices (1.8 GB in, 1.8 GB out):
  fit_rotation's peak must stay within input + output + a small margin (no
  hidden full-size temporaries); likewise fit_rotation_info (+ 5 bytes per
  matrix of diagnostics), out= in place (no output at all), a transposed
  (strided) input, and the backward kernel; results sampled against fits of
  small slices (bit-identical: matrices are independent).
* ``float64``: N = 5e7 float64 (3.6 GB each way): byte offsets above 2^32.
* ``strided64``: matrices 2^31 + 7 elements apart in a sparse file mapping
  (element offsets up to 1.7e10, beyond 32 bits; only the touched pages are
  resident): M, init, out and the backward's inputs, each against the same
  matrices fitted contiguously.
* ``huge`` (opt-in, 8.6 GB): N = 2.4e8 float32 in place (out=M), so element
  indices pass 2^31 in the contiguous path.

Usage: python .ci/large_inputs.py [check ...] [--n N]
Default checks: contiguous float64 strided64. Prints one line per check;
exits non-zero on any failure. Convention: R (det +1) maximises tr(R^T M).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

MB = 2**20
MARGIN = 64 * MB  # allocator slack, thread stacks, small temporaries


CHILD = r"""
import json, os, sys, time, torch, torchrot

def rss():
    with open("/proc/self/status") as f:
        fields = dict(line.split(":", 1) for line in f)
    return {k: int(fields[k].split()[0]) * 1024 for k in ("VmRSS", "VmHWM")}

def reset_peak():
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # resets VmHWM to the current RSS

def measure(fn):
    reset_peak()
    before = rss()["VmRSS"]
    t = time.perf_counter()
    result = fn()
    seconds = time.perf_counter() - t
    return result, rss()["VmHWM"] - before, seconds

def sample_matches(M, R, fit=lambda m: torchrot.fit_rotation(m)):
    n = M.shape[0]
    for start in (0, 1, n // 2 - 3, n - 17, n - 1):
        start = max(0, min(start, n - 1))
        stop = min(n, start + 17)
        if not torch.equal(fit(M[start:stop].contiguous()), R[start:stop]):
            return False
    return True

args = json.loads(sys.argv[1])
torch.set_num_threads(args["threads"])
report = {}
if args["check"] in ("contiguous", "float64"):
    dtype = torch.float32 if args["check"] == "contiguous" else torch.float64
    n = args["n"]
    M = torch.empty(n, 3, 3, dtype=dtype)
    for i in range(0, n, 1 << 22):  # filled in chunks: no full-size temporary
        M[i:i + (1 << 22)] = torch.randn(min(1 << 22, n - i), 3, 3, dtype=dtype)
    size = M.numel() * M.element_size()
    report["input_bytes"] = size
    R, peak, sec = measure(lambda: torchrot.fit_rotation(M))
    report["fit"] = {"peak_over_input": peak, "seconds": sec,
                     "ok": sample_matches(M, R) and bool(torch.isfinite(R[-1]).all())}
    if args["check"] == "contiguous":
        G = R  # any incoming gradient of R's shape
        D, peak, sec = measure(lambda: torch.ops.torchrot.fit_rotation_backward(G, R, M, 1e-6))
        ref = lambda m: torch.ops.torchrot.fit_rotation_backward(G[:m.shape[0]].contiguous(),
                                                                 R[:m.shape[0]].contiguous(), m, 1e-6)
        report["backward"] = {"peak_over_input": peak, "seconds": sec,
                              "ok": torch.equal(D[:17], ref(M[:17].contiguous())) and bool(torch.isfinite(D).all())}
        del D, G
        (R2, it, st), peak, sec = measure(lambda: torchrot.fit_rotation_info(M))
        report["info"] = {"peak_over_input": peak, "seconds": sec, "ok": torch.equal(R2, R)}
        del R2, it, st
        Mt = M.mT  # strided (transposed) view: no copy expected
        Rt, peak, sec = measure(lambda: torchrot.fit_rotation(Mt))
        report["transposed"] = {"peak_over_input": peak, "seconds": sec,
                                "ok": torch.equal(Rt[:17], torchrot.fit_rotation(Mt[:17].contiguous()))}
        del Rt
        expected_tail = R[-17:].clone()
        del R
        _, peak, sec = measure(lambda: torchrot.fit_rotation(M, out=M))
        report["in_place"] = {"peak_over_input": peak, "seconds": sec, "ok": torch.equal(M[-17:], expected_tail)}
elif args["check"] == "huge":
    n = args["n"]
    M = torch.empty(n, 3, 3)
    for i in range(0, n, 1 << 22):
        M[i:i + (1 << 22)] = torch.randn(min(1 << 22, n - i), 3, 3)
    last = M[-17:].clone()
    report["input_bytes"] = M.numel() * 4
    _, peak, sec = measure(lambda: torchrot.fit_rotation(M, out=M))
    report["in_place"] = {"peak_over_input": peak, "seconds": sec,
                          "ok": torch.equal(M[-17:], torchrot.fit_rotation(last)),
                          "last_element_index": M.numel() - 1}
elif args["check"] == "strided64":
    count, gap = 9, 2**31 + 7  # matrices `gap` elements apart
    span = (count - 1) * gap + 9
    path = args["path"]
    with open(path, "wb") as f:
        f.truncate(4 * span * 4)  # sparse: M, init, out and dR regions
    base = torch.from_file(path, shared=True, size=4 * span, dtype=torch.float32)
    views = [base[k * span:(k + 1) * span].as_strided((count, 3, 3), (gap, 3, 1)) for k in range(4)]
    M, init, out, G = views
    gen = torch.Generator().manual_seed(0)
    Mc = torch.randn(count, 3, 3, generator=gen)
    initc = torchrot.fit_rotation(torch.randn(count, 3, 3, generator=gen))
    Gc = torch.randn(count, 3, 3, generator=gen)
    M.copy_(Mc); init.copy_(initc); G.copy_(Gc)
    offsets = [(k * span + i * gap) for k in range(4) for i in range(count)]
    report["largest_element_offset"] = max(offsets)
    checks = {}
    torchrot.fit_rotation(M, init, max_iter=1, out=out)
    checks["warm_out"] = torch.equal(out, torchrot.fit_rotation(Mc, initc, max_iter=1))
    R = torchrot.fit_rotation(M)
    checks["cold"] = torch.equal(R, torchrot.fit_rotation(Mc))
    Rc = R.clone()
    out.copy_(R)
    D = torch.ops.torchrot.fit_rotation_backward(G, out, M, 1e-6)
    checks["backward"] = torch.equal(D, torch.ops.torchrot.fit_rotation_backward(Gc, Rc, Mc, 1e-6))
    report["checks"] = checks
    report["rss_bytes"] = rss()["VmHWM"]
    del base, views, M, init, out, G
    os.remove(path)
print("RESULT " + json.dumps(report))
"""


def run_child(check: str, n: int, threads: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="torchrot-large-") as tmp:
        args = {"check": check, "n": n, "threads": threads, "path": os.path.join(tmp, "sparse.bin")}
        proc = subprocess.run([sys.executable, "-c", CHILD, json.dumps(args)], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{check}: child failed (rc {proc.returncode}):\n{proc.stderr[-3000:]}")
    line = [l for l in proc.stdout.splitlines() if l.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def expected_extra(name: str, n: int, itemsize: int) -> int:
    """Bytes a call may add beyond its input: its outputs."""
    out = 9 * itemsize * n
    return {"fit": out, "backward": out, "info": out + 5 * n, "transposed": out, "in_place": 0}[name]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checks", nargs="*", metavar="{contiguous,float64,strided64,huge}")
    parser.add_argument("--n", type=float, help="matrices (default 5e7; huge: 2.4e8)")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()
    # (Checked here, not with choices=: argparse checks an empty nargs="*" list against them as one value.)
    args.checks = args.checks or ["contiguous", "float64", "strided64"]
    unknown = set(args.checks) - {"contiguous", "float64", "strided64", "huge"}
    if unknown:
        parser.error(f"unknown checks {sorted(unknown)}; known: contiguous float64 strided64 huge")
    failed = False
    for check in args.checks:
        n = int(args.n or (2.4e8 if check == "huge" else 5e7))
        start = time.perf_counter()
        report = run_child(check, n, args.threads)
        wall = time.perf_counter() - start
        if check == "strided64":
            ok = all(report["checks"].values())
            print(f"{check}: largest element offset {report['largest_element_offset']:,} (> 2^32: "
                  f"{report['largest_element_offset'] > 2**32}), checks {report['checks']}, "
                  f"peak RSS {report['rss_bytes'] / MB:.0f} MB, {wall:.0f} s -> {'ok' if ok else 'FAIL'}")
            failed |= not ok
            continue
        itemsize = 4 if check in ("contiguous", "huge") else 8
        print(f"{check}: N = {n:,} ({report['input_bytes'] / 1e9:.2f} GB input), {wall:.0f} s in all")
        for name, r in report.items():
            if not isinstance(r, dict):
                continue
            allowed = expected_extra(name, n, itemsize) + MARGIN
            ok = r["ok"] and r["peak_over_input"] <= allowed
            print(f"  {name:11s} peak over its inputs {r['peak_over_input'] / MB:8.0f} MB "
                  f"(outputs {expected_extra(name, n, itemsize) / MB:.0f} MB + {MARGIN // MB} MB allowed), "
                  f"{r['seconds']:.2f} s, results {'match' if r['ok'] else 'DIFFER'} -> {'ok' if ok else 'FAIL'}"
                  + (f"; last element index {r['last_element_index']:,} (> 2^31: {r['last_element_index'] > 2**31})"
                     if "last_element_index" in r else ""))
            failed |= not ok
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
