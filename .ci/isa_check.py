"""Every kernel the CPU offers, on fixed data, saved or compared bit for bit.

``.ci/qemu`` runs ``save`` natively with the scalar kernel (and with each
kernel that rounds differently from it: x86-64's default, see
``torchrot.testing.rounding_reference``), then ``compare`` inside qemu-x86_64
emulating older CPUs: each kernel the emulated CPU supports (and each request
above it, which must be capped, not executed) must reproduce the native
results of its rounding reference exactly: forward in every mode and
variant, cold and warm, every batch size 0-70, transposed and strided
layouts, NaN/Inf inputs, and the backward kernel.

Usage: python .ci/isa_check.py save FILE
       python .ci/isa_check.py compare FILE [--expect-aten DEFAULT|AVX2|AVX512]
Convention: R (det +1) maximises tr(R^T M); column vectors.
"""
from __future__ import annotations

import argparse
import json
import math
import sys

import torch

import torchrot
from torchrot.testing import (
    DISTRIBUTIONS,
    cpu_kernel,
    edge_case_matrices,
    make_matrices,
    random_rotations,
    rounding_reference,
)

ISAS = ("scalar", "default", "avx2", "avx512")
INT_VIEW = {torch.float32: torch.int32, torch.float64: torch.int64, torch.int32: torch.int32,
            torch.uint8: torch.uint8}
FORWARD_CASES = (  # (warm, max_iter, variant)
    (False, None, "conservative"), (False, None, "gershgorin"), (False, 3, "newton"),
    (True, 1, "newton"), (True, None, "conservative"), (True, 2, "gershgorin"),
)


def inputs(dtype: torch.dtype):
    """(M, init, G): every distribution, the edge cases, NaN/Inf entries; 627 matrices."""
    M = torch.cat([make_matrices(name, 37, 11 + j, dtype) for j, name in enumerate(DISTRIBUTIONS)]
                  + [edge_case_matrices(dtype)])
    gen = torch.Generator().manual_seed(5)
    flat = M.view(-1, 9)
    rows = torch.randperm(flat.shape[0], generator=gen)[:40]
    values = torch.tensor([math.nan, math.inf, -math.inf], dtype=dtype)
    flat[rows, torch.randint(0, 9, (40,), generator=gen)] = values[torch.arange(40) % 3]
    perm = torch.randperm(M.shape[0], generator=gen)
    M = M[perm].contiguous()
    init = random_rotations(M.shape[0], gen).to(dtype)
    G = torch.randn(M.shape, generator=gen, dtype=torch.float64).to(dtype)
    return M, init, G


def results(data: dict) -> dict[str, torch.Tensor]:
    """name -> tensor for the kernel TORCHROT_CPU_CAPABILITY selects now, on
    ``data`` (dtype name -> (M, init, G)), generated natively and loaded by
    the emulated run (torch's own random and math functions are ISA-specific
    in their last bits, so the inputs are not regenerated under emulation)."""
    out = {}
    for tag, (M, init, G) in data.items():
        for warm, max_iter, variant in FORWARD_CASES:
            key = f"{tag}/{'warm' if warm else 'cold'}/{max_iter}/{variant}"
            for layout, (A, B) in {
                "contiguous": (M, init),
                "transposed": (M.mT.contiguous().mT, init.mT.contiguous().mT),
                "strided": (torch.stack([M, M], 1)[:, 0], torch.stack([init, init], 1)[:, 0]),
            }.items():
                R, it, st = torchrot.fit_rotation_info(A, B if warm else None, max_iter=max_iter, variant=variant)
                out[f"{key}/{layout}/R"], out[f"{key}/{layout}/iterations"], out[f"{key}/{layout}/status"] = R, it, st
        for n in range(71):  # every SIMD tail, exactly-sized tensors
            out[f"{tag}/tail{n}"] = torchrot.fit_rotation(M[:n].clone())
        R = torchrot.fit_rotation(M)
        for eps in (0.0, 1e-6):
            out[f"{tag}/backward/{eps}"] = torch.ops.torchrot.fit_rotation_backward(G, R, M, eps)
            out[f"{tag}/backward/{eps}/strided"] = torch.ops.torchrot.fit_rotation_backward(
                G.mT.contiguous().mT, R, M[:1], eps)
    return out


def bits(t: torch.Tensor) -> torch.Tensor:
    return t.contiguous().view(INT_VIEW[t.dtype])


def same(a: torch.Tensor, b: torch.Tensor, any_nan: bool) -> bool:
    """Bit for bit; with ``any_nan``, NaN matches NaN of any sign/payload (the
    backward kernel's NaN for NaN input differs in sign between the scalar and
    SIMD min/max; the forward's NaN is bit-identical and compared as such)."""
    equal = bits(a) == bits(b)
    if any_nan:
        equal |= torch.isnan(a) & torch.isnan(b)
    return bool(equal.all())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("action", choices=["save", "compare"])
    parser.add_argument("file")
    parser.add_argument("--expect-aten", help="ATen capability the CPU must report (e.g. DEFAULT, AVX2)")
    args = parser.parse_args()
    aten = torch.backends.cpu.get_cpu_capability()
    if args.action == "save":
        data = {str(dtype).removeprefix("torch."): inputs(dtype) for dtype in (torch.float32, torch.float64)}
        saved = {}
        for name in sorted({rounding_reference(isa) for isa in ISAS}):
            with cpu_kernel(name) as used:
                assert used == name
                saved[name] = results(data)
        torch.save({"inputs": data, "results": saved}, args.file)
        print(json.dumps({"saved": args.file, "aten": aten, "references": sorted(saved)}))
        return 0
    if args.expect_aten and aten != args.expect_aten:
        print(f"FAIL: ATen reports {aten}, expected {args.expect_aten}")
        return 1
    saved = torch.load(args.file)
    hardware = {"AVX512": "avx512", "AVX2": "avx2"}.get(aten, "default")
    report = {"aten": aten, "kernels": {}, "tensors_compared": 0, "mismatches": []}
    for request in ISAS:
        with cpu_kernel(request) as kernel:  # capped at the hardware: never an instruction the CPU lacks
            expected_kernel = ISAS[min(ISAS.index(request), ISAS.index(hardware))]
            if kernel != expected_kernel:
                report["mismatches"].append(f"request {request} ran kernel {kernel}, expected {expected_kernel}")
                continue
            got = results(saved["inputs"])
            reference_name = rounding_reference(kernel)
        report["kernels"][request] = f"{kernel} (as {reference_name})"
        for name, ref in saved["results"][reference_name].items():
            report["tensors_compared"] += 1
            if ref.shape != got[name].shape or not same(ref, got[name], any_nan="/backward/" in name):
                report["mismatches"].append(f"{request}: {name}")
    print(json.dumps(report))
    return 1 if report["mismatches"] else 0


if __name__ == "__main__":
    sys.exit(main())
