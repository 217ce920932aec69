"""The design claim of the CPU kernels (instruction sets) on mixed data: every
ISA build ("default", "avx2", "avx512") gives results bit-identical to the
"scalar" build (R, iterations and status), for both dtypes, every mode,
variant and warm start. The one exception is x86-64's "default" build, for
CPUs without FMA: it rounds a * b + c twice where the others round once
(csrc/kernel/mul_add.h), so it is held to the accuracy criteria instead
(torchrot.testing.rounding_reference).

The mixed data (tests/isa_helpers.py: every distribution, the edge cases and
NaN/Inf entries) is checked first for what it promises. Every test that
compares kernels also checks that the requested kernel is the one that ran.
"""
from __future__ import annotations

import pytest
import torch
from isa_helpers import (
    DTYPES,
    N_NON_FINITE,
    SCALAR_ROUNDING_ISA_PARAMS,
    TWO_ROUNDING_ISAS,
    _describe,
    _run_info,
    _same,
    mixed_batch,
)

from torchrot._constants import VARIANTS
from torchrot.testing import CRITERIA, bits, dtype_id, random_rotations, rotation_errors

# mode id -> max_iter
MODES = {"converged": None, "iter1": 1, "iter3": 3}


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


# NaN bit patterns (float32, float64): quiet, negative quiet (x86's default NaN),
# signalling with a payload, all bits set.
_NAN_BITS = {
    torch.float32: (0x7FC00000, -0x00400000, 0x7F800001, -1),
    torch.float64: (0x7FF8000000000000, -0x0008000000000000, 0x7FF0000000000001, -1),
}


@pytest.mark.parametrize("start", ["cold", "warm"])
@pytest.mark.parametrize("mode", list(MODES))
@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", SCALAR_ROUNDING_ISA_PARAMS)
def test_any_nan_at_any_entry(isa, dtype, mode, start, use_isa):
    """Every NaN bit pattern (either sign, quiet or signalling, any payload) at
    each of the nine entries of M, beside infinities, signed zeros and
    subnormal entries: the scalar kernel's results bit for bit. (max_abs_entry
    takes integer maxima of the entries' bits on some kernels, lanes.h.)"""
    nans = torch.tensor(_NAN_BITS[dtype], dtype=bits(torch.zeros((), dtype=dtype)).dtype).view(dtype)
    tiny = torch.finfo(dtype).tiny
    gen = torch.Generator().manual_seed(11)
    M = torch.randn(9 * len(nans) + 5, 3, 3, dtype=dtype, generator=gen)
    for i, nan in enumerate(nans):
        for k in range(9):
            M[9 * i + k].view(9)[k] = nan
    M[-5].view(9)[4] = float("inf")
    M[-4].view(9)[0] = -float("inf")
    M[-3] = -0.0
    M[-2] = M[-2] * tiny / 4  # every entry subnormal
    M[-1].view(9)[8] = -0.0
    init = random_rotations(M.shape[0], gen).to(dtype) if start == "warm" else None
    max_iter = MODES[mode]
    got = _run_info(use_isa, isa, M, init, max_iter, "conservative")
    ref = _run_info(use_isa, "scalar", M, init, max_iter, "conservative")
    assert _same(got, ref), f"{isa} vs scalar, {dtype_id(dtype)} {mode} {start}:\n" + _describe(got, ref, M, init)
    assert (ref[2][: 9 * len(nans) + 2] == 3).all()
