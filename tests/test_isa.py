"""Run-time choice of the CPU kernel (instruction set) and its design claim:
every ISA build ("default", "avx2", "avx512") gives results bit-identical to
the "scalar" build (R, iterations and status), for both dtypes, every mode,
variant and warm start, every batch size (SIMD tails), every layout
(contiguous fast path with in-register transposes vs strided path), in place,
and independently of the thread count. The one exception is x86-64's
"default" build, for CPUs without FMA: it rounds a * b + c twice where the
others round once (csrc/kernel/mul_add.h), so it is held to the accuracy
criteria instead, and to its own results across batch sizes, layouts, in
place and thread counts (torchrot.testing.rounding_reference).

The kernel is forced per thread with ``torchrot.testing.cpu_kernel(name)``
(scalar | default | avx2 | avx512), capped at the hardware level; the process
default is TORCHROT_CPU_CAPABILITY, read once at import (tested in
subprocesses). Every test that compares kernels also checks with
``torch.ops.torchrot.cpu_kernel()`` that the requested kernel is the one that
ran, so an ignored request cannot make a test pass vacuously.

Results are compared bit for bit (integer views of the floats): NaN payloads
and signed zeros count, as "bit-identical" promises.
"""
from __future__ import annotations

import functools
import json
import math
import os
import subprocess
import sys

import pytest
import torch

import torchrot
from torchrot._constants import CPU_KERNELS, VARIANTS
from torchrot.testing import (
    CRITERIA,
    DISTRIBUTIONS,
    bits,
    dtype_id,
    edge_case_matrices,
    make_matrices,
    make_warm_start,
    random_rotations,
    rotation_errors,
    rounding_reference,
    rounds_like_scalar,
    soa_view,
    tiled_view,
)
from torchrot.testing import cpu_kernel as forced_kernel

DTYPES = (torch.float32, torch.float64)

ENV = "TORCHROT_CPU_CAPABILITY"
ISAS = CPU_KERNELS  # lowest to highest
ISA_LEVEL = {name: level for level, name in enumerate(ISAS)}
SIMD_ISAS = ISAS[1:]


def _hardware_isa() -> str:
    """The level the dispatch caps requests at (ATen's, as dispatch.cpp maps it)."""
    cap = torch.backends.cpu.get_cpu_capability()
    return {"AVX512": "avx512", "AVX2": "avx2"}.get(cap, "default")


HARDWARE_ISA = _hardware_isa()


def _supported(isa: str) -> bool:
    return ISA_LEVEL[isa] <= ISA_LEVEL[HARDWARE_ISA]


# Only the kernels this CPU runs are parametrized: a request above the hardware
# is capped to a lower kernel (tested on its own below), so its cases would
# always skip here.
ALL_ISA_PARAMS = [pytest.param(i, id=i) for i in ISAS if _supported(i)]
SIMD_ISA_PARAMS = [pytest.param(i, id=i) for i in SIMD_ISAS if _supported(i)]
# The kernels of this CPU that round a * b + c twice (x86-64's default):
# checked against the accuracy criteria, not the scalar kernel's bits; the others
# are checked bit for bit.
TWO_ROUNDING_ISAS = [i for i in SIMD_ISAS if _supported(i) and not rounds_like_scalar(i)]
SCALAR_ROUNDING_ISA_PARAMS = [p for p in SIMD_ISA_PARAMS if rounds_like_scalar(p.values[0])]

# mode id -> max_iter
MODES = {"converged": None, "iter1": 1, "iter3": 3}


def _cpu_kernel() -> str:
    return torch.ops.torchrot.cpu_kernel()


@pytest.fixture
def use_isa():
    """``with use_isa(name): ...`` runs its body on kernel ``name`` (None or
    "": the process default), in this thread only (torchrot.testing.cpu_kernel)."""
    return forced_kernel


# ---------------------------------------------------------------------------
# Helpers: bitwise comparison with a precise failure message
# ---------------------------------------------------------------------------

def _bad_matrices(got, ref) -> torch.Tensor:
    """Bool (n,) mask of the matrices whose R, iterations or status differ."""
    R, R_ref = got[0], ref[0]
    n = R_ref.reshape(-1, 9).shape[0]
    bad = (bits(R).reshape(n, 9) != bits(R_ref).reshape(n, 9)).any(1)
    if len(got) > 1:
        bad |= got[1].reshape(n) != ref[1].reshape(n)
        bad |= got[2].reshape(n) != ref[2].reshape(n)
    return bad


def _same(got, ref) -> bool:
    """``got`` and ``ref`` (R, or (R, iterations, status)) are bit-identical."""
    got = got if isinstance(got, tuple) else (got,)
    ref = ref if isinstance(ref, tuple) else (ref,)
    if len(got) != len(ref):
        return False
    for a, b in zip(got, ref):
        if a.shape != b.shape or a.dtype != b.dtype or not torch.equal(bits(a), bits(b)):
            return False
    return True


def _describe(got, ref, M, init=None, limit=3) -> str:
    got = got if isinstance(got, tuple) else (got,)
    ref = ref if isinstance(ref, tuple) else (ref,)
    if any(a.shape != b.shape or a.dtype != b.dtype for a, b in zip(got, ref)):
        return f"shape/dtype differ: {[(a.shape, a.dtype) for a in got]} vs {[(b.shape, b.dtype) for b in ref]}"
    bad = _bad_matrices(got, ref).nonzero().flatten().tolist()
    lines = [f"{len(bad)} of {ref[0].reshape(-1, 9).shape[0]} matrices differ, first at {bad[:10]}"]
    M9 = M.reshape(-1, 9)
    for i in bad[:limit]:
        line = f"  [{i}] M={M9[i].tolist()}"
        if init is not None:
            line += f" init={init.reshape(-1, 9)[i].tolist()}"
        line += f"\n       R={got[0].reshape(-1, 9)[i].tolist()}\n   R_ref={ref[0].reshape(-1, 9)[i].tolist()}"
        gb, rb = bits(got[0]).reshape(-1, 9)[i], bits(ref[0]).reshape(-1, 9)[i]
        width = 2 * got[0].element_size()
        diffs = [f"{k}: {int(g) & (1 << 4 * width) - 1:0{width}x} vs {int(r) & (1 << 4 * width) - 1:0{width}x}"
                 for k, (g, r) in enumerate(zip(gb.tolist(), rb.tolist())) if g != r]
        if diffs:
            line += "\n       bits differ at entries " + ", ".join(diffs)
        if len(got) > 1:
            line += (
                f"\n       iterations={int(got[1].reshape(-1)[i])} (ref {int(ref[1].reshape(-1)[i])}),"
                f" status={int(got[2].reshape(-1)[i])} (ref {int(ref[2].reshape(-1)[i])})"
            )
        lines.append(line)
    return "\n".join(lines)


def _info(M, init, max_iter, variant):
    return tuple(torchrot.fit_rotation_info(M, init, max_iter=max_iter, variant=variant))


def _run_info(use_isa, isa, M, init, max_iter, variant):
    """fit_rotation_info under kernel ``isa``, checking that it is the one used."""
    with use_isa(isa):
        assert _cpu_kernel() == isa, f"cpu_kernel({isa!r}) selected kernel {_cpu_kernel()!r}"
        return _info(M, init, max_iter, variant)


# ---------------------------------------------------------------------------
# Test data: every distribution, the edge cases and NaN/Inf entries, both in
# homogeneous SIMD blocks (ordered) and mixed into the same blocks (shuffled)
# ---------------------------------------------------------------------------

REQUIRED_DISTRIBUTIONS = (
    "warm", "gaussian", "uniform", "rank1", "ill_conditioned", "symmetric", "det_negative", "rot180_exact",
)
assert set(REQUIRED_DISTRIBUTIONS) <= set(DISTRIBUTIONS)
PER_DISTRIBUTION = 19  # not a multiple of any width: blocks straddle distributions
N_NON_FINITE = 48


def _scatter_non_finite(A: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Copy of A (k, 3, 3) with NaN / +Inf / -Inf at one random entry of each
    matrix; every 8th matrix gets two entries, every 12th is all NaN."""
    A = A.clone()
    k = A.shape[0]
    flat = A.view(k, 9)
    vals = torch.tensor([math.nan, math.inf, -math.inf], dtype=A.dtype)
    rows = torch.arange(k)
    flat[rows, torch.randint(0, 9, (k,), generator=gen)] = vals[rows % 3]
    two = rows[rows % 8 == 5]
    flat[two, torch.randint(0, 9, (len(two),), generator=gen)] = vals[(two + 1) % 3]
    flat[rows[rows % 12 == 7]] = math.nan
    return A


@functools.cache
def mixed_batch(dtype: torch.dtype, warm: bool, seed: int = 0):
    """``(M, init)`` (init None when cold): all DISTRIBUTIONS, the edge cases
    and matrices with NaN/Inf entries (in M, and for warm also in init), once
    in order and once shuffled; contiguous, 662 (cold) or 686 (warm) matrices."""
    Ms, inits = [], []
    for j, name in enumerate(DISTRIBUTIONS):
        if warm:
            M, init = make_warm_start(name, PER_DISTRIBUTION, seed + 31 * j, dtype)
            inits.append(init)
        else:
            M = make_matrices(name, PER_DISTRIBUTION, seed + 31 * j, dtype)
        Ms.append(M)
    edge = edge_case_matrices(dtype)
    Ms.append(edge)
    if warm:
        # the edge cases as given (M = 0 returns init, ...) with random warm starts
        inits.append(random_rotations(len(edge), torch.Generator().manual_seed(seed + 5)).to(dtype))
    gen = torch.Generator().manual_seed(seed + 11)
    finite = make_matrices("gaussian", N_NON_FINITE, seed + 13, dtype)
    Ms.append(_scatter_non_finite(finite, gen))
    if warm:
        inits.append(random_rotations(N_NON_FINITE, torch.Generator().manual_seed(seed + 17)).to(dtype))
        # and finite M with a non-finite warm start
        M_bad_init, bad_init = make_warm_start("warm", N_NON_FINITE // 4, seed + 23, dtype)
        Ms.append(M_bad_init)
        inits.append(_scatter_non_finite(bad_init, gen))
    M = torch.cat(Ms)
    init = torch.cat(inits) if warm else None
    perm = torch.randperm(M.shape[0], generator=torch.Generator().manual_seed(seed + 19))
    M = torch.cat([M, M[perm]]).contiguous()
    if warm:
        init = torch.cat([init, init[perm]]).contiguous()
    return M, init


def test_mixed_batch_has_what_it_promises():
    """Guard against the data silently losing its hard cases."""
    for dtype in DTYPES:
        for warm in (False, True):
            M, init = mixed_batch(dtype, warm)
            assert 200 <= M.shape[0] <= 800
            finite = torch.isfinite(M).reshape(-1, 9).all(1)
            assert (~finite).sum() >= 2 * N_NON_FINITE * 0.9
            assert torch.isnan(M).any() and torch.isinf(M).any()
            if warm:
                assert init.shape == M.shape
                bad_init = ~torch.isfinite(init).reshape(-1, 9).all(1)
                assert (bad_init & finite).sum() >= N_NON_FINITE // 2


# ---------------------------------------------------------------------------
# 1. the kernel follows the request (per thread) and TORCHROT_CPU_CAPABILITY
#    (at import), capped at the hardware
# ---------------------------------------------------------------------------


def test_unset_selects_hardware_level(use_isa):
    with use_isa(None):
        assert _cpu_kernel() == HARDWARE_ISA
    with use_isa(""):  # empty counts as unset
        assert _cpu_kernel() == HARDWARE_ISA


@pytest.mark.parametrize("isa", ALL_ISA_PARAMS)
def test_cpu_kernel_follows_request(isa, use_isa):
    for spelling in (isa, isa.upper(), isa.capitalize()):  # case-insensitive
        with use_isa(spelling) as used:
            assert _cpu_kernel() == used == isa, f"cpu_kernel({spelling!r})"
    # switching back and forth takes effect at once, and requests nest
    for other in ISAS:
        if not _supported(other):
            continue
        with use_isa(other):
            assert _cpu_kernel() == other
            with use_isa(isa):
                assert _cpu_kernel() == isa
            assert _cpu_kernel() == other
    assert _cpu_kernel() == HARDWARE_ISA


def test_request_above_hardware_is_capped(use_isa):
    above = [isa for isa in ISAS if not _supported(isa)]
    if not above:
        pytest.skip(f"this CPU supports every kernel ({HARDWARE_ISA}); see the ATEN_CPU_CAPABILITY test")
    M = make_matrices("gaussian", 37, 0)
    for isa in above:
        with use_isa(isa):
            assert _cpu_kernel() == HARDWARE_ISA, f"cpu_kernel({isa!r})"
            # and it computes (no illegal instruction)
            assert torch.isfinite(torchrot.fit_rotation(M)).all()


def test_request_is_per_thread(use_isa):
    """A kernel forced in one thread does not change another thread's."""
    import threading

    seen = {}
    entered, release = threading.Event(), threading.Event()

    def other():
        with use_isa("scalar"):
            seen["inside"] = _cpu_kernel()
            entered.set()
            release.wait(30)

    thread = threading.Thread(target=other)
    thread.start()
    assert entered.wait(30)
    seen["main"] = _cpu_kernel()
    release.set()
    thread.join()
    assert seen == {"inside": "scalar", "main": HARDWARE_ISA}


_ENV_SCRIPT = r"""
import json, os, torch, torchrot
first = torch.ops.torchrot.cpu_kernel()
os.environ["TORCHROT_CPU_CAPABILITY"] = "sse2"  # read once, at import: no effect now
print(json.dumps([first, torch.ops.torchrot.cpu_kernel()]))
"""


def _run_with_env(script: str, **env_vars) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != ENV}
    env.update(env_vars)
    return subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)


@pytest.mark.slow
@pytest.mark.parametrize("isa", ["scalar", "default", "AVX2", "avx512", ""])
def test_environment_variable_is_read_once_at_import(isa):
    proc = _run_with_env(_ENV_SCRIPT, **{ENV: isa})
    assert proc.returncode == 0, proc.stderr[-3000:]
    expected = ISAS[min(ISA_LEVEL[isa.lower()], ISA_LEVEL[HARDWARE_ISA])] if isa else HARDWARE_ISA
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == [expected, expected]


_CAP_SCRIPT = r"""
import json, torch, torchrot
from torchrot.testing import cpu_kernel, rounding_reference
out = {"aten": torch.backends.cpu.get_cpu_capability(), "kernels": {}, "same_as_reference": {}}
M = torch.randn(53, 3, 3, generator=torch.Generator().manual_seed(3))
for req in ("scalar", "default", "avx2", "avx512", "AVX512"):
    with cpu_kernel(req) as used:
        out["kernels"][req] = used
        got = torchrot.fit_rotation_info(M)
    with cpu_kernel(rounding_reference(req)):
        ref = torchrot.fit_rotation_info(M)
    out["same_as_reference"][req] = all(torch.equal(a, b) for a, b in zip(got, ref))
out["kernels"]["<unset>"] = torch.ops.torchrot.cpu_kernel()
print(json.dumps(out))
"""


@pytest.mark.slow
@pytest.mark.parametrize("aten_level", ["default", "avx2"])
def test_request_above_lowered_hardware_level_is_capped(aten_level):
    """With ATen's level lowered by ATEN_CPU_CAPABILITY (read once at start-up,
    hence a subprocess), every request above it is capped to it."""
    if not _supported(aten_level):
        pytest.skip(f"CPU supports up to {HARDWARE_ISA}")
    proc = _run_with_env(_CAP_SCRIPT, ATEN_CPU_CAPABILITY=aten_level)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["aten"] == aten_level.upper()
    expected = {
        req: ISAS[min(ISA_LEVEL[req.lower()], ISA_LEVEL[aten_level])]
        for req in ("scalar", "default", "avx2", "avx512", "AVX512")
    }
    expected["<unset>"] = aten_level
    assert result["kernels"] == expected
    assert all(result["same_as_reference"].values()), result["same_as_reference"]


@pytest.mark.parametrize("value", ["sse4", "avx-512", "avx512 ", " avx2", "AVX2x", "none", "1", "neon"])
def test_invalid_request_raises(value, use_isa):
    """A bad name raises ValueError naming it, and changes nothing."""
    with pytest.raises(ValueError, match=r"scalar, default, avx2, avx512; got") as excinfo:
        with use_isa(value):
            pass
    assert f"'{value}'" in str(excinfo.value)
    assert _cpu_kernel() == HARDWARE_ISA


@pytest.mark.slow
@pytest.mark.parametrize("value", ["sse4", "avx-512", "neon"])
def test_invalid_environment_variable_fails_the_import(value):
    proc = _run_with_env("import torchrot", **{ENV: value})
    assert proc.returncode != 0
    assert f"ValueError: {ENV} must be one of scalar, default, avx2, avx512; got '{value}'" in proc.stderr


# ---------------------------------------------------------------------------
# 2. Bit-identity with the scalar kernel on mixed data
# ---------------------------------------------------------------------------

_SCALAR_REFERENCE: dict = {}


def _scalar_reference(use_isa, dtype, warm, max_iter, variant):
    key = (dtype, warm, max_iter, variant)
    if key not in _SCALAR_REFERENCE:
        M, init = mixed_batch(dtype, warm)
        _SCALAR_REFERENCE[key] = _run_info(use_isa, "scalar", M, init, max_iter, variant)
    return _SCALAR_REFERENCE[key]


@pytest.mark.parametrize("start", ["cold", "warm"])
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("mode", list(MODES))
@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", SCALAR_ROUNDING_ISA_PARAMS)
def test_bit_identical_to_scalar(isa, dtype, mode, variant, start, use_isa):
    warm = start == "warm"
    max_iter = MODES[mode]
    M, init = mixed_batch(dtype, warm)
    ref = _scalar_reference(use_isa, dtype, warm, max_iter, variant)
    got = _run_info(use_isa, isa, M, init, max_iter, variant)
    assert _same(got, ref), f"{isa} vs scalar, {dtype_id(dtype)} {mode} {variant} {start}:\n" + _describe(
        got, ref, M, init
    )
    # the data exercises what it should: non-finite status, and in converged
    # mode several iteration counts (blocks whose lanes finish at different steps)
    status = ref[2]
    assert (status == 3).any()
    if max_iter is None:
        assert ref[1].unique().numel() >= 3
    else:
        assert int(ref[1].max()) <= max_iter


@pytest.mark.parametrize("start", ["cold", "warm"])
@pytest.mark.parametrize("mode", list(MODES))
@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", TWO_ROUNDING_ISAS)
def test_two_rounding_kernel_meets_criteria(isa, dtype, mode, start, use_isa, assert_meets_criteria):
    """A kernel that rounds a * b + c twice (x86-64's default, for CPUs
    without FMA) is not bit-identical to the scalar kernel, but on the mixed
    batch it flags the same matrices (NaN/Inf, bad warm starts), its results
    are rotations at the dtype's precision, and converged fits reach the
    maximum (CRITERIA)."""
    warm = start == "warm"
    max_iter = MODES[mode]
    M, init = mixed_batch(dtype, warm)
    ref = _scalar_reference(use_isa, dtype, warm, max_iter, "conservative")
    R, _, status = _run_info(use_isa, isa, M, init, max_iter, "conservative")
    flagged = ref[2] >= 2
    assert torch.equal(status >= 2, flagged)
    assert torch.equal(status[flagged], ref[2][flagged])
    fitted = ~flagged
    if max_iter is None:
        assert_meets_criteria(R[fitted], M[fitted], dtype, f"{isa} converged {start}")
    else:
        errors = rotation_errors(R[fitted], M[fitted])
        for metric in ("orthonormality", "det"):
            assert errors[metric].max() <= CRITERIA[dtype][metric], f"{isa} {mode} {start}: {metric}"


# ---------------------------------------------------------------------------
# 3. Every tail length, contiguous and strided layouts
# ---------------------------------------------------------------------------

TAIL_SIZES = range(0, 71)  # every remainder mod 16 (and mod 8, 4), several full blocks


@functools.cache
def _tail_pool(dtype):
    """70 (M, init) pairs mixing distributions, edge cases and NaN/Inf, from
    the shuffled half of the warm mixed batch."""
    M, init = mixed_batch(dtype, True)
    half = M.shape[0] // 2
    pool_M, pool_init = M[half:half + 70].clone(), init[half:half + 70].clone()
    assert (~torch.isfinite(pool_M)).any() and pool_M.shape[0] == 70
    return pool_M, pool_init


def _strided_copy(A: torch.Tensor) -> torch.Tensor:
    """A copy of A as ``big[::2]`` with NaN in the gaps (reading a wrong
    element shows)."""
    big = torch.full((2 * A.shape[0], 3, 3), math.nan, dtype=A.dtype)
    big[::2] = A
    return big[::2]


def _offset_copy(A: torch.Tensor) -> torch.Tensor:
    """A contiguous copy of A starting one element into its storage
    (misaligned for vector loads)."""
    flat = torch.full((A.numel() + 1,), math.nan, dtype=A.dtype)
    view = flat[1:].view(A.shape)
    view.copy_(A)
    assert view.is_contiguous() and view.storage_offset() == 1
    return view


def _one_rotation(dtype) -> torch.Tensor:
    return random_rotations(1, torch.Generator().manual_seed(4242)).to(dtype)


# layout -> (M, init) -> (M_layout, init_layout); values equal the inputs'
# except for "transposed", which fits the transposed matrices (M.mT)
LAYOUTS = {
    "contiguous": lambda M, init: (M.clone(), init.clone()),
    "offset": lambda M, init: (_offset_copy(M), _offset_copy(init)),
    "transposed": lambda M, init: (M.clone().mT, init.clone().mT),
    "strided": lambda M, init: (_strided_copy(M), _strided_copy(init)),
    # contiguous M, broadcast (stride-0) init: the strided path for all inputs
    "expanded_init": lambda M, init: (M.clone(), _one_rotation(M.dtype).expand(M.shape)),
    # contiguous M and init, strided out=
    "strided_out": lambda M, init: (M.clone(), init.clone()),
    # structure of arrays (plain vector loads and stores), fresh results in it too
    "soa": lambda M, init: (soa_view(M), soa_view(init)),
    # structure of arrays for M, init and out=
    "soa_out": lambda M, init: (soa_view(M), soa_view(init)),
}
OUT_LAYOUTS = {"strided_out": _strided_copy, "soa_out": soa_view}


@pytest.mark.parametrize("layout", list(LAYOUTS))
@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", ALL_ISA_PARAMS)
def test_tails_and_layouts(isa, dtype, layout, use_isa):
    """Every batch size 0..70, in each layout: identical to the scalar kernel
    on a contiguous copy (so both the SIMD tails and the strided path are
    checked against the plain one-matrix-at-a-time result). A kernel that
    rounds differently from the scalar kernel (rounding_reference) is checked
    against its own result for the whole pool, contiguous: a matrix's result
    does not depend on its block."""
    pool_M, pool_init = _tail_pool(dtype)
    reference = rounding_reference(isa)
    pool_refs = {}

    def reference_info(Mc, initc, n, mode, use_init, max_iter, variant):
        if reference == "scalar":
            return _run_info(use_isa, "scalar", Mc, initc if use_init else None, max_iter, variant)
        key = (mode, variant)
        if key not in pool_refs:
            M_all, init_all = LAYOUTS[layout](pool_M, pool_init)
            M_all, init_all = M_all.contiguous(), init_all.contiguous()
            pool_refs[key] = _run_info(use_isa, reference, M_all, init_all if use_init else None, max_iter, variant)
        return tuple(t[:n] for t in pool_refs[key])

    failures = []
    for n in TAIL_SIZES:
        variant = VARIANTS[n % 3]
        M, init = LAYOUTS[layout](pool_M[:n], pool_init[:n])
        if layout in ("transposed", "strided", "expanded_init", "soa", "soa_out") and n > 1:  # the strided path
            assert not (M.is_contiguous() and init.is_contiguous())
        Mc, initc = M.contiguous(), init.contiguous()
        for mode, use_init, max_iter in (("cold", False, None), ("warm-iter1", True, 1), ("warm", True, None)):
            ref = reference_info(Mc, initc, n, mode, use_init, max_iter, variant)
            with use_isa(isa):
                assert _cpu_kernel() == isa
                if layout in OUT_LAYOUTS:
                    out = OUT_LAYOUTS[layout](torch.zeros_like(Mc))
                    gaps = None  # the NaN between the matrices of a strided out=
                    if layout == "strided_out" and n:
                        gaps = out.as_strided((n, 3, 3), out.stride(), out.storage_offset() + 9)
                    returned = torchrot.fit_rotation(
                        M, init if use_init else None, max_iter=max_iter, variant=variant, out=out
                    )
                    assert returned is out
                    if not _same(out, ref[0]):
                        failures.append(f"n={n} {mode} {variant}:\n" + _describe(out, ref[0], Mc, initc))
                    if gaps is not None and not torch.isnan(gaps).all():
                        failures.append(f"n={n} {mode} {variant}: out= wrote into the gaps of the strided view")
                    continue
                got = _info(M, init if use_init else None, max_iter, variant)
            if layout == "soa" and n > 1 and got[0].stride() != M.stride():
                failures.append(f"n={n} {mode}: result strides {got[0].stride()}, not M's {M.stride()}")
            if not _same(got, ref):
                failures.append(f"n={n} {mode} {variant}:\n" + _describe(got, ref, Mc, initc))
    assert not failures, f"{isa} {dtype_id(dtype)} layout={layout}: {len(failures)} failing cases\n" + "\n".join(
        failures[:5]
    )


TILES = (2, 3, 4, 8, 16, 32)


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", ALL_ISA_PARAMS)
def test_tiled_layouts(isa, dtype, use_isa):
    """Tiled inputs (torchrot.testing.tiled_view: tiles of 2 to 32 matrices in
    structure of arrays, narrower and wider than every block, up to 70
    matrices): fresh results (in M's layout), out= a tiled tensor and
    out=init in place are the scalar kernel's on contiguous copies
    (rounding_reference)."""
    pool_M, pool_init = _tail_pool(dtype)
    reference = rounding_reference(isa)
    failures = []
    for tile in TILES:
        for n in range(tile, 71, tile):
            variant = VARIANTS[n % 3]
            Mc, initc = pool_M[:n].contiguous(), pool_init[:n].contiguous()
            M, init = tiled_view(Mc, tile), tiled_view(initc, tile)
            for mode, use_init, max_iter in (("cold", False, None), ("warm-iter1", True, 1), ("warm", True, None)):
                ref = _run_info(use_isa, reference, Mc, initc if use_init else None, max_iter, variant)
                with use_isa(isa):
                    fresh = _info(M, init if use_init else None, max_iter, variant)
                    if fresh[0].stride() != M.stride():
                        failures.append(f"tile={tile} n={n}: result strides {fresh[0].stride()}, not M's {M.stride()}")
                    got = tuple(t.reshape(ref_t.shape) for t, ref_t in zip(fresh, ref))
                    out = tiled_view(torch.zeros_like(Mc), tile)
                    torchrot.fit_rotation(M, init if use_init else None, max_iter=max_iter, variant=variant, out=out)
                    in_place = init.clone()
                    if use_init:
                        torchrot.fit_rotation(M, in_place, max_iter=max_iter, variant=variant, out=in_place)
                for what, result in (("result", got), ("out=", out.reshape(n, 3, 3)),
                                     ("out=init", in_place.reshape(n, 3, 3) if use_init else ref[0])):
                    if not _same(result, ref if what == "result" else ref[0]):
                        failures.append(f"tile={tile} n={n} {mode} {variant} {what}:\n" +
                                        _describe(result, ref if what == "result" else ref[0], Mc, initc))
    assert not failures, f"{isa} {dtype_id(dtype)}: {len(failures)} failing cases\n" + "\n".join(failures[:5])


@pytest.mark.parametrize("tile", [8, 12])
def test_tiled_layout_two_threads(tile, use_isa):
    """A tiled batch larger than a parallel chunk, in 2 threads: the threads
    split it at block boundaries, and each matrix's result is the one-thread
    contiguous result (best kernel)."""
    n = 6000 - 6000 % tile
    M, init = make_warm_start("warm", n, seed=5, dtype=torch.float32)
    expected = [torchrot.fit_rotation(M, init, max_iter=k) for k in (1, None)]
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        got = [torchrot.fit_rotation(tiled_view(M, tile), tiled_view(init, tile), max_iter=k) for k in (1, None)]
    finally:
        torch.set_num_threads(previous)
    for g, e in zip(got, expected):
        assert torch.equal(g.reshape(n, 3, 3), e)


# ---------------------------------------------------------------------------
# 4. out= aliasing init or M (in-place updates)
# ---------------------------------------------------------------------------

ALIAS_SIZES = range(1, 41)


@pytest.mark.parametrize("layout", ["contiguous", "transposed"])
@pytest.mark.parametrize("target", ["init", "M"])
@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", ALL_ISA_PARAMS)
def test_out_aliasing_inputs(isa, dtype, target, layout, use_isa):
    """``out=init`` (warm-start update in place) and ``out=M`` give the
    out-of-place scalar result (rounding_reference); the aliased buffer is the
    only thing written."""
    pool_M, pool_init = _tail_pool(dtype)
    failures = []
    for n in ALIAS_SIZES:
        variant = VARIANTS[n % 3]
        M, init = pool_M[:n].contiguous(), pool_init[:n].contiguous()
        cases = [("warm-iter1", True, 1), ("warm", True, None)]
        if target == "M":
            cases.append(("cold", False, None))
        for mode, use_init, max_iter in cases:
            reference = rounding_reference(isa)  # out-of-place, without aliasing
            with use_isa(reference):
                assert _cpu_kernel() == reference
                ref = torchrot.fit_rotation(M, init if use_init else None, max_iter=max_iter, variant=variant)
            # the aliased buffer, with the input's values, in the layout tested
            source = init if target == "init" else M
            buf = source.mT.contiguous().mT if layout == "transposed" else source.clone()
            assert torch.equal(bits(buf), bits(source))
            M_arg = buf if target == "M" else M.clone()
            init_arg = buf if target == "init" else init.clone()
            other_before = (init_arg if target == "M" else M_arg).clone()
            with use_isa(isa):
                assert _cpu_kernel() == isa
                torchrot.fit_rotation(
                    M_arg, init_arg if use_init else None, max_iter=max_iter, variant=variant, out=buf
                )
            if not _same(buf, ref):
                failures.append(f"n={n} {mode} {variant} out={target}:\n" + _describe(buf.clone(), ref, M, init))
            other = init_arg if target == "M" else M_arg
            if not _same(other, other_before):
                failures.append(f"n={n} {mode} {variant}: the non-aliased input was modified")
    assert not failures, f"{isa} {dtype_id(dtype)} out={target} {layout}: {len(failures)} failing cases\n" + (
        "\n".join(failures[:5])
    )


# ---------------------------------------------------------------------------
# 5. Thread-count independence
# ---------------------------------------------------------------------------

N_THREADED = 50_001  # odd: 2 or 3 threads split it at boundaries inside SIMD blocks


@functools.cache
def _large_batch(dtype):
    """(M, init): N_THREADED warm-start pairs from several distributions, with
    NaN/Inf matrices, shuffled."""
    names = ("warm", "gaussian", "rank1", "ill_conditioned", "rot180_exact", "det_negative")
    per = N_THREADED // len(names)
    Ms, inits = [], []
    for j, name in enumerate(names):
        M, init = make_warm_start(name, per, 100 + j, dtype)
        Ms.append(M)
        inits.append(init)
    rest = N_THREADED - per * len(names)
    M, init = make_warm_start("gaussian", rest, 200, dtype)
    Ms.append(M)
    inits.append(init)
    M, init = torch.cat(Ms), torch.cat(inits)
    gen = torch.Generator().manual_seed(300)
    idx = torch.randperm(N_THREADED, generator=gen)[:500]
    M[idx] = _scatter_non_finite(M[idx], gen)
    perm = torch.randperm(N_THREADED, generator=gen)
    return M[perm].contiguous(), init[perm].contiguous()


_THREAD_CASES = {  # name -> (warm start?, max_iter, variant)
    "cold-converged-conservative": (False, None, "conservative"),
    "warm-iter1-gershgorin": (True, 1, "gershgorin"),
    "warm-converged-newton": (True, None, "newton"),
}


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", [pytest.param(None, id="unset")] + ALL_ISA_PARAMS)
def test_thread_count_independence(isa, dtype, use_isa, restore_threads):
    """At the default kernel (variable unset: the hardware level) and at each
    kernel by name, 1, 2 and 3 threads give bit-identical R, iterations and
    status, in converged cold, one-step warm and converged warm mode; the
    single-threaded result also equals the scalar kernel's on these 50k
    matrices (for the kernels that round like it, rounds_like_scalar)."""
    M, init = _large_batch(dtype)
    expected_kernel = HARDWARE_ISA if isa is None else isa
    results = {}
    for threads in (1, 2, 3):
        torch.set_num_threads(threads)
        assert torch.get_num_threads() == threads
        for name, (warm, k, v) in _THREAD_CASES.items():
            with use_isa(isa):
                assert _cpu_kernel() == expected_kernel
                results[threads, name] = _info(M, init if warm else None, k, v)
    torch.set_num_threads(1)
    failures = []
    for name, (warm, k, v) in _THREAD_CASES.items():
        for threads in (2, 3):
            if not _same(results[threads, name], results[1, name]):
                failures.append(
                    f"{name}: {threads} threads vs 1:\n"
                    + _describe(results[threads, name], results[1, name], M, init if warm else None)
                )
        if not rounds_like_scalar(expected_kernel):
            continue  # test_two_rounding_kernel_meets_criteria
        ref = _run_info(use_isa, "scalar", M, init if warm else None, k, v)
        if not _same(results[1, name], ref):
            failures.append(f"{name}: 1 thread vs the scalar kernel:\n" + _describe(
                results[1, name], ref, M, init if warm else None))
    assert not failures, f"{expected_kernel} {dtype_id(dtype)}:\n" + "\n".join(failures)
    assert (results[1, "cold-converged-conservative"][2] == 3).any()
