"""The kernels of an aarch64 build against the pure-PyTorch reference.

``.ci/aarch64`` runs it under qemu-aarch64 on the cross-compiled extension
(it also runs natively, on any architecture). Small inputs, every case:
  * forward, float32 and float64: every variant (newton, conservative,
    gershgorin) and max_iter mode (None, 1, 3), cold and warm, against
    torchrot.fit_rotation_reference (R within the test suite's tolerances,
    float32's doubled, see tolerance();
    iterations and status equal); then on every batch size 0..20 (SIMD tails)
    and in transposed, strided and structure-of-arrays layouts, bit for bit
    the contiguous full-batch result; NaN/Inf and zero matrices included;
  * backward: torch.ops.torchrot.fit_rotation_backward against
    fit_rotation_backward_reference, undamped and damped (relative error
    bounded as in tests/test_autograd_operator.py), plus tails and gradient layouts,
    and autograd through torchrot.fit_rotation (recorded in C++) equal to it;
  * every kernel object this build has (the hardware's and each below it)
    gives bit-identical results; the hardware kernel is "default" off x86-64,
    and requests for avx2/avx512 are capped to it there.
Prints one line per group and a closing "N passed, N failed" line; exits 1
on any failure.

Usage: python .ci/aarch64_check.py [--save FILE | --compare FILE]
  --save FILE     also store every result (to compare another build's)
  --compare FILE  also report whether every result is bit-identical to a
                  saved run (e.g. x86-64's): informational, never a failure
Convention: R (det +1) maximises tr(R^T M); column vectors.
"""
from __future__ import annotations

import argparse
import math
import platform
import sys
import time

import torch

import torchrot
from torchrot.reference import GRADIENT_EPS, fit_rotation_backward_reference, rotation_svd
from torchrot.testing import (
    CPU_KERNELS,
    WELL_CONDITIONED,
    bits,
    cpu_kernel,
    make_matrices,
    random_rotations,
    rotations,
    rounding_reference,
)

X86_64 = platform.machine().lower() in ("x86_64", "amd64")
DTYPES = (torch.float32, torch.float64)
VARIANTS = ("newton", "conservative", "gershgorin")
MODES = (None, 1, 3)
REFERENCE_TOL = {torch.float32: 1e-5, torch.float64: 1e-10}  # tests/test_ops_reference.py
BACKWARD_TOL = {torch.float32: 3e-5, torch.float64: 1e-13}  # tests/test_autograd_operator.py, times the condition
NAMES = WELL_CONDITIONED  # where R itself is compared (tests/test_ops_reference.py)
PER_NAME = 7  # 35 matrices: no multiple of any block width, blocks straddle distributions
TAILS = 21  # batch sizes 0..20

passed: list[str] = []
failed: list[str] = []
results: dict[str, torch.Tensor] = {}


def check(name: str, ok: bool, detail: str = "") -> None:
    (passed if ok else failed).append(name)
    if not ok:
        print(f"FAIL {name}: {detail}", flush=True)


def same_bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and torch.equal(bits(a), bits(b))


def inputs(dtype: torch.dtype):
    """(M, init, G, special): matrices of several distributions with NaN, Inf
    and zero matrices at the end (rows ``special``), warm starts, gradients."""
    M = torch.cat([make_matrices(name, PER_NAME, 40 + j, torch.float64) for j, name in enumerate(NAMES)])
    gen = torch.Generator().manual_seed(7)
    specials = torch.randn(5, 3, 3, generator=gen, dtype=torch.float64)
    specials[0, 1, 2] = math.nan
    specials[1, 0, 0] = math.inf
    specials[2, 2, 1] = -math.inf
    specials[3] = 0
    specials[4, :, 0] = math.nan
    # warm starts within 30 degrees of the optimum, as tests/test_ops_reference.py's
    # (from far away Newton's path is chaotic: float rounding picks the branch)
    init = rotation_svd(M) @ rotations(M.shape[0], 8, torch.float64, math.radians(30))
    M = torch.cat([M, specials])
    init = torch.cat([init, random_rotations(5, gen)])
    G = torch.randn(M.shape, generator=gen, dtype=torch.float64)
    special = torch.zeros(M.shape[0], dtype=torch.bool)
    special[-5:] = True
    return M.to(dtype), init.to(dtype), G.to(dtype), special


def tolerance(M: torch.Tensor) -> float:
    """tests/test_ops_reference.py's bound on |R - R_ref|: in float32 no better than the
    float32 problem is determined, and twice its 1e-5: the float32 reference
    is itself rounded, differently on each platform (aarch64's torch lands
    1.02e-5 from the kernel after one conservative step from a warm start
    where x86-64's lands within 1e-5, with the kernel's results bit-identical
    on both, see --compare). How well float32 determines R: a float32 SVD's
    distance from float64's, and eps sigma_1 / (sigma_2 + sign(det M) sigma_3),
    R's sensitivity to a rounding of M (the smallest of the sums sigma_i +
    sigma_j that the derivative divides by, torchrot/_autograd.py). The second
    bounds the results that a fixed number of steps leaves unconfirmed: one
    exact first step from the cold start (c = the maximal objective, rounded)
    on a "warm" matrix with singular values (1000, 1.07, 1.0) lands 2.45e-5
    from the reference on x86-64, whose sensitivity is 5.8e-5, while the
    float32 SVDs of that batch are all within 2e-5."""
    if M.dtype != torch.float32 or M.shape[0] == 0:
        return REFERENCE_TOL[M.dtype]
    M64 = M.double()
    svd32 = (rotation_svd(M) - rotation_svd(M64)).norm(dim=(-2, -1)).max().item()
    s = torch.linalg.svdvals(M64)
    smallest_sum = s[:, 1] + torch.sign(torch.linalg.det(M64)) * s[:, 2]
    tiny = torch.finfo(torch.float64).tiny
    sensitivity = (torch.finfo(torch.float32).eps * s[:, 0] / smallest_sum.clamp_min(tiny)).max().item()
    return max(2 * REFERENCE_TOL[M.dtype], svd32, sensitivity)


def layouts(X: torch.Tensor) -> dict[str, torch.Tensor]:
    return {
        "transposed": X.mT.contiguous().mT,
        "strided": torch.stack([X, X], 1)[:, 0],
        "soa": X.permute(1, 2, 0).contiguous().permute(2, 0, 1),  # matrix stride 1
    }


def forward(kernel: str, tag: str, M, init, special) -> None:
    dtype = M.dtype
    for variant in VARIANTS:
        for max_iter in MODES:
            for warm in (False, True):
                key = f"{tag}/{kernel}/{variant}/{max_iter}/{'warm' if warm else 'cold'}"
                start = init if warm else None
                R, it, st = torch.ops.torchrot.fit_rotation_info(M, start, max_iter, variant)
                results[f"{key}/R"], results[f"{key}/it"], results[f"{key}/st"] = R, it, st
                R_ref, it_ref, st_ref = torchrot.fit_rotation_reference(
                    M, start, max_iter=max_iter, variant=variant, return_info=True)
                ok = ~special
                err = (R - R_ref)[ok].abs().amax().item() if ok.any() else 0.0
                check(f"{key} R vs reference", err <= tolerance(M[ok]), f"max |R - R_ref| = {err:.3g}")
                close = torch.isclose(R[special], R_ref[special], rtol=0, atol=REFERENCE_TOL[dtype], equal_nan=True)
                check(f"{key} NaN/Inf/zero rows vs reference", bool(close.all()),
                      f"R={R[special].tolist()} R_ref={R_ref[special].tolist()}")
                check(f"{key} iterations and status vs reference",
                      torch.equal(it, it_ref) and torch.equal(st, st_ref),
                      f"it {it.tolist()} vs {it_ref.tolist()}, status {st.tolist()} vs {st_ref.tolist()}")
                R_plain = torch.ops.torchrot.fit_rotation(M, start, max_iter, variant, GRADIENT_EPS)
                check(f"{key} fit_rotation == fit_rotation_info", same_bits(R_plain, R))
                bad = [n for n in range(TAILS) if not same_bits(
                    torch.ops.torchrot.fit_rotation_info(
                        M[:n].clone(), None if start is None else start[:n].clone(), max_iter, variant)[0], R[:n])]
                check(f"{key} tails 0..{TAILS - 1}", not bad, f"batch sizes {bad} differ from the full batch")
                starts = layouts(start) if warm else {k: None for k in layouts(M)}
                for name, A in layouts(M).items():
                    got = torch.ops.torchrot.fit_rotation_info(A, starts[name], max_iter, variant)
                    check(f"{key} {name} layout", all(same_bits(g, r) for g, r in zip(got, (R, it, st))))


def backward(kernel: str, tag: str, M_all, G_all, special) -> None:
    dtype = M_all.dtype
    ok = ~special
    M, G = M_all[ok].contiguous(), G_all[ok].contiguous()
    R = torchrot.fit_rotation(M)
    sigma = torch.linalg.svdvals(M.double())
    pair = torch.minimum(sigma[:, 0] + sigma[:, 1], torch.minimum(sigma[:, 0] + sigma[:, 2], sigma[:, 1] + sigma[:, 2]))
    # rounding is amplified by the system's condition |M| / min(sigma_i + sigma_j)
    # (tests/test_autograd_operator.py's 1 / min(sigma_i + sigma_j) for its |M| ~ 1)
    cond = sigma[:, 0] / pair.clamp_min(1e-3 * sigma[:, 0])
    for eps in (0.0, GRADIENT_EPS):
        key = f"{tag}/{kernel}/backward/{eps:g}"
        got = torch.ops.torchrot.fit_rotation_backward(G, R, M, eps)
        results[key] = got
        ref = fit_rotation_backward_reference(G.double(), R.double(), M.double(), eps)
        err = (got.double() - ref).norm(dim=(-2, -1)) / ref.norm(dim=(-2, -1)).clamp_min(1e-300)
        tol = BACKWARD_TOL[dtype] * cond
        check(f"{key} vs reference", bool((err <= tol).all()), f"max relative error {err.max():.3g}")
        bad = [n for n in range(TAILS) if not same_bits(
            torch.ops.torchrot.fit_rotation_backward(G[:n].clone(), R[:n].clone(), M[:n].clone(), eps), got[:n])]
        check(f"{key} tails 0..{TAILS - 1}", not bad, f"batch sizes {bad} differ")
        for name, Gl in layouts(G).items():
            check(f"{key} {name} gradient", same_bits(torch.ops.torchrot.fit_rotation_backward(Gl, R, M, eps), got))
    # autograd through torchrot.fit_rotation (the training call, recorded in C++) is that operator
    Mg = M.clone().requires_grad_()
    (g_train,) = torch.autograd.grad(torchrot.fit_rotation(Mg), Mg, G)
    check(f"{tag}/{kernel}/backward: autograd of fit_rotation is the operator",
          same_bits(g_train, results[f"{tag}/{kernel}/backward/{GRADIENT_EPS:g}"]))
    # NaN/Inf inputs: same non-finite pattern as the reference
    Ms, Gs = M_all[special], G_all[special]
    Rs = torchrot.fit_rotation(Ms)
    got = torch.ops.torchrot.fit_rotation_backward(Gs, Rs, Ms, GRADIENT_EPS)
    ref = fit_rotation_backward_reference(Gs.double(), Rs.double(), Ms.double(), GRADIENT_EPS)
    check(f"{tag}/{kernel}/backward NaN/Inf/zero rows: finite where the reference is",
          torch.equal(torch.isfinite(got), torch.isfinite(ref)),
          f"got {got.tolist()} ref {ref.tolist()}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--save")
    parser.add_argument("--compare")
    args = parser.parse_args()
    torch.set_num_threads(1)
    hardware = torch.ops.torchrot.cpu_kernel()
    print(f"machine {platform.machine()}, ATen capability {torch.backends.cpu.get_cpu_capability()}, "
          f"torchrot kernel {hardware}", flush=True)
    if not X86_64:
        check("hardware kernel is 'default' off x86-64", hardware == "default", f"got {hardware!r}")
    kernels = CPU_KERNELS[: CPU_KERNELS.index(hardware) + 1]
    for name in CPU_KERNELS:  # requests above the hardware are capped, never executed
        with cpu_kernel(name) as used:
            expected = CPU_KERNELS[min(CPU_KERNELS.index(name), CPU_KERNELS.index(hardware))]
            check(f"request {name} runs {expected}", used == expected, f"got {used!r}")
    # --compare: the saved run's inputs (torch's random and math functions
    # differ between instruction sets in their last bits, so inputs made here
    # would not be the same matrices)
    saved = torch.load(args.compare) if args.compare else {}
    for dtype in DTYPES:
        tag = str(dtype).replace("torch.", "")
        M, init, G, special = saved.get(f"inputs/{tag}") or inputs(dtype)
        results[f"inputs/{tag}"] = (M, init, G, special)
        for kernel in kernels:
            start = time.time()
            count = len(passed) + len(failed)
            with cpu_kernel(kernel):
                forward(kernel, tag, M, init, special)
                backward(kernel, tag, M, G, special)
            print(f"{tag} {kernel}: {len(passed) + len(failed) - count} checks, {time.time() - start:.0f} s",
                  flush=True)
        first = kernels[0]
        for kernel in kernels[1:]:
            if rounding_reference(kernel) != first:  # x86-64's default kernel: tests/test_isa_*.py check it
                print(f"info: {tag}: {kernel} rounds a * b + c twice (csrc/kernel/mul_add.h): not compared "
                      f"with {first}")
                continue
            keys = [k for k in results if k.startswith(f"{tag}/{first}/") and not k.startswith("inputs/")]
            bad = [k for k in keys if not same_bits(results[k], results[k.replace(f"/{first}/", f"/{kernel}/", 1)])]
            check(f"{tag}: {kernel} bit-identical to {first}", not bad, f"{len(bad)} results differ, e.g. {bad[:3]}")
    if args.save:
        torch.save({k: v for k, v in results.items() if "/scalar/" in k or k.startswith("inputs/")}, args.save)
    if args.compare:
        keys = [k for k in saved if not k.startswith("inputs/")]
        differ = [k for k in keys if k in results and not same_bits(saved[k], results[k])]
        print(f"info: {len(keys) - len(differ)} of {len(keys)} scalar-kernel results (same inputs) bit-identical "
              f"to the saved run's" + (f"; differ: {differ[:5]}" if differ else ""))
    print(f"{len(passed)} passed, {len(failed)} failed")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
