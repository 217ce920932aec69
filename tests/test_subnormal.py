"""Subnormal numbers and the ends of the floating-point range.

Subnormal inputs are read as they are, a matrix whose largest entry is beyond
1 / tiny (whose reciprocal is subnormal) is scaled exactly
(csrc/kernel/unit_scale.h), a lane's result does not depend on its neighbours
in a SIMD block, the fitting kernels flush subnormal results themselves
(csrc/cpu/flush_to_zero.h: x86) without losing accuracy, so a result does not
depend on the caller's floating-point mode (torch.set_flush_denormal), and a
call leaves that mode as it was.

Convention: R (det +1) maximises tr(R^T M); column vectors.
"""
from __future__ import annotations

import contextlib

import pytest
import torch

import torchrot
from torchrot.testing import available_cpu_kernels, conditioning, cpu_kernel, dtype_id, rotation_svd

DTYPES = (torch.float32, torch.float64)


def _subnormal_product(dtype: torch.dtype) -> torch.Tensor:
    """tiny * 0.5: a subnormal number, or 0 where results are flushed."""
    return torch.tensor(torch.finfo(dtype).tiny, dtype=dtype) * 0.5


@contextlib.contextmanager
def _callers_mode(flush: bool):
    """The caller's floating-point mode set to flush subnormal numbers (results
    and inputs) or not, restored to torch's default after; skips where the CPU
    has no such mode and flushing is asked for."""
    supported = torch.set_flush_denormal(flush)  # whether the CPU has the mode, not the previous mode
    try:
        if flush and not supported:
            pytest.skip("this CPU has no flush-to-zero mode")
        yield
    finally:
        torch.set_flush_denormal(False)  # torch's default


@pytest.mark.parametrize("flush", [False, True])
def test_callers_floating_point_mode_is_restored(flush):
    M = torch.randn(100, 3, 3)
    with _callers_mode(flush):
        for max_iter in (None, 1):
            torchrot.fit_rotation(M, max_iter=max_iter)
            torchrot.fit_rotation(M, torchrot.fit_rotation(M), max_iter=max_iter, out=torch.empty_like(M))
            flushed = bool(_subnormal_product(torch.float32) == 0)
            assert flushed == flush, f"after a fit (max_iter={max_iter}) flush-to-zero is {flushed}, was {flush}"


def _rank1(value: float, dtype: torch.dtype) -> torch.Tensor:
    """value * e2 e1^T: its maximiser maps e1 to e2."""
    M = torch.zeros(3, 3, dtype=dtype)
    M[1, 0] = value
    return M


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("kernel", available_cpu_kernels())
def test_largest_entry_beyond_reciprocal_of_tiny(kernel, dtype):
    """A largest entry above 1 / tiny (its reciprocal subnormal) is scaled by an exact power of two."""
    finfo = torch.finfo(dtype)
    values = [1.5 / finfo.tiny, finfo.max, 1 / finfo.tiny, 1.0]
    M = torch.stack([_rank1(v, dtype) for v in values])
    with cpu_kernel(kernel):
        R = torchrot.fit_rotation(M)
    maps_e1_to_e2 = R[:, :, 0]
    expected = torch.tensor([0.0, 1.0, 0.0], dtype=dtype).expand(len(values), 3)
    assert torch.equal(maps_e1_to_e2, expected), maps_e1_to_e2


def _mixed_block(dtype: torch.dtype, n: int = 64) -> torch.Tensor:
    """Random matrices at the edges of the range, mixed in every SIMD block: a
    largest entry just above tiny with subnormal others, subnormal maxima,
    largest entries beyond 1 / tiny, and ordinary ones."""
    gen = torch.Generator().manual_seed(7)
    tiny = torch.finfo(dtype).tiny
    scales = torch.tensor([1.6 * tiny, 0.3 * tiny, 4.0 / tiny, 1.0], dtype=torch.float64)
    M = torch.randn(n, 3, 3, generator=gen, dtype=torch.float64)
    M = M / M.abs().amax((-2, -1), keepdim=True)  # largest entry 1
    M = M * scales[torch.arange(n) % len(scales)].view(n, 1, 1).clamp_max(torch.finfo(dtype).max)
    return M.to(dtype)


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("kernel", available_cpu_kernels())
@pytest.mark.parametrize("max_iter", [None, 1])
def test_edges_of_the_range_in_mixed_blocks(kernel, dtype, max_iter):
    """Each matrix gets the result it gets alone, whatever its neighbours (a
    neighbour beyond 1 / tiny or below it sends a block through the exact
    scaling), and a converged fit is the SVD's rotation."""
    M = _mixed_block(dtype)
    assert bool(((M.abs() < torch.finfo(dtype).tiny) & (M != 0)).any()), "the data holds subnormal entries"
    with cpu_kernel(kernel):
        R = torchrot.fit_rotation(M, max_iter=max_iter)
        alone = torch.stack([torchrot.fit_rotation(m, max_iter=max_iter) for m in M])
    assert torch.equal(R, alone)
    if max_iter is None:
        # Scaled exactly by powers of two, the float64 SVD's rotation is the reference.
        unit = M.double() / M.double().abs().amax((-2, -1), keepdim=True)
        distance = (R.double() - rotation_svd(unit)).norm(dim=(-2, -1))
        worst = (distance / (torch.finfo(dtype).eps * conditioning(unit))).max().item()
        assert worst <= 64, f"|R - R*| = {worst:.3g} eps kappa"  # as tests/test_warm_start_precision.py


@pytest.mark.parametrize("kernel", available_cpu_kernels())
def test_scaled_signed_permutation_meets_criteria(kernel, assert_meets_criteria):
    """A fuzz case with a step |(d, w)| ~ 1e-18: where the Cayley map formed
    products of two components before the division by d^2 + w.w, the kernels'
    flush-to-zero lost orthonormality (6e-6 on the default kernel)."""
    M = torch.tensor([[-1652449792.0, 0.0, 1.401298464324817e-45], [1.0000001192092896, 0.0, 1652449792.0],
                      [0.0, -1652449792.0, 0.0]]).expand(16, 3, 3).contiguous()
    for variant in ("newton", "conservative", "gershgorin"):
        with cpu_kernel(kernel):
            R = torchrot.fit_rotation(M, variant=variant)
        assert_meets_criteria(R, M, torch.float32, f"{kernel} {variant}")


def _near_identity_steps(dtype: torch.dtype, n: int = 1024):
    """Pairs (M, init) like the ARAP recording's matrices of vertices that have
    not moved: init = I, M symmetric in its (0, 1) block and with entries of
    1e-15 to 1e-20 (float64: 1e-150 to 1e-160) elsewhere, so the step is tiny
    about two axes and 0 about the third, and products inside it are
    subnormal."""
    gen = torch.Generator().manual_seed(11)
    lo, hi = (15, 20) if dtype == torch.float32 else (150, 160)
    f64 = dict(generator=gen, dtype=torch.float64)
    M = torch.diag_embed(torch.rand(n, 3, **f64) * 2 - 0.5)
    b = (torch.rand(n, **f64) - 0.5) * 0.4
    M[:, 0, 1], M[:, 1, 0] = b, b
    tiny = torch.randn(n, 4, **f64) * 10.0 ** -torch.randint(lo, hi, (n, 4), generator=gen).double()
    M[:, 0, 2], M[:, 2, 0], M[:, 1, 2], M[:, 2, 1] = tiny.unbind(-1)
    return M.to(dtype), torch.eye(3, dtype=dtype).expand(n, 3, 3)


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("kernel", available_cpu_kernels())
@pytest.mark.parametrize("max_iter", [None, 1])
def test_result_does_not_depend_on_callers_mode(kernel, dtype, max_iter):
    """Inputs without subnormal entries whose steps make subnormal products get
    the same result bit for bit whether or not the caller flushes (results and
    inputs: torch.set_flush_denormal sets both): the kernels flush themselves.
    (Kernels that ran in the caller's mode gave 474 of these 1,024 float32
    one-step results and 764 float64 ones that differed in their last bits.)"""
    M, init = _near_identity_steps(dtype)
    assert not bool(((M.abs() < torch.finfo(dtype).tiny) & (M != 0)).any())
    results = []
    for flush in (False, True):
        with _callers_mode(flush), cpu_kernel(kernel):
            results.append(torchrot.fit_rotation(M, init, max_iter=max_iter))
    assert torch.equal(results[0], results[1])
