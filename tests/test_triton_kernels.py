"""torchrot's Triton kernels (torchrot.triton: what CUDA and XPU tensors run)
on CPU tensors under Triton's interpreter (torchrot.testing.triton_kernel),
against the scalar C++ kernel, which rounds as they do (a * b + c once,
correctly rounded division and square roots): every result, iteration
count and status code bit for bit, but for the Horn fallback's lanes, which
the Triton path solves with the pure-PyTorch fallback (torch.linalg.eigh
instead of the kernel's Jacobi sweeps): there the criteria. Batches are small:
the interpreter runs each block with NumPy."""
from __future__ import annotations

import pytest
import torch
from kernel_paths import TRITON_MARKS

import torchrot
from torchrot._constants import FitStatus
from torchrot.testing import (
    DEGENERATE_FAMILIES,
    DISTRIBUTIONS,
    cpu_kernel,
    edge_case_matrices,
    make_degenerate_matrices,
    make_matrices,
    make_warm_start,
    random_rotations,
    soa_view,
    tiled_view,
    triton_kernel,
)

pytestmark = list(TRITON_MARKS)
N = 96  # matrices per case: a full block and a masked tail (BLOCK = 128 lanes: one block here, partly masked)


def _both(*args, **kwargs):
    """fit_rotation_info on the Triton path and on the scalar C++ kernel."""
    with triton_kernel():
        triton = torchrot.fit_rotation_info(*args, **kwargs)
    with cpu_kernel("scalar"):
        scalar = torchrot.fit_rotation_info(*args, **kwargs)
    return triton, scalar


def _assert_same_fits(triton, scalar, M, assert_meets_criteria, what):
    """Iterations and statuses equal; R bit for bit (NaN where NaN) but on
    fallback lanes, which meet the criteria."""
    (R, iterations, status), (R_s, iterations_s, status_s) = triton, scalar
    assert torch.equal(status, status_s), f"{what}: status codes"
    assert torch.equal(iterations, iterations_s), f"{what}: iterations"
    same = (R == R_s) | (R.isnan() & R_s.isnan())
    fallback = status == int(FitStatus.FALLBACK)
    assert same.flatten(-2).all(-1)[~fallback].all(), f"{what}: results differ"
    if fallback.any():
        assert_meets_criteria(R[fallback], M[fallback], torch.float64 if M.dtype == torch.float64 else torch.float32,
                              f"{what}: fallback lanes")


@pytest.mark.parametrize("name", sorted(DISTRIBUTIONS))
def test_distributions_cold(name, dtype, assert_meets_criteria):
    M = make_matrices(name, N, 1, dtype)
    _assert_same_fits(*_both(M), M, assert_meets_criteria, f"{name} converged")
    _assert_same_fits(*_both(M, max_iter=1), M, assert_meets_criteria, f"{name} one step")


@pytest.mark.parametrize("max_iter", [None, 1, 3])
@pytest.mark.parametrize("name", ["warm", "rot60"])
def test_warm_starts_each_variant(name, max_iter, variant, dtype, assert_meets_criteria):
    M, init = make_warm_start(name, N, 2, dtype)[:2]
    _assert_same_fits(*_both(M, init, max_iter=max_iter, variant=variant), M, assert_meets_criteria,
                      f"{name} warm, max_iter={max_iter}")


@pytest.mark.parametrize("name", sorted(DEGENERATE_FAMILIES))
def test_degenerate_families(name, dtype, assert_meets_criteria):
    M = make_degenerate_matrices(name, 64, 3, dtype)
    _assert_same_fits(*_both(M), M, assert_meets_criteria, name)


@pytest.mark.parametrize("max_iter", [None, 1])
def test_edge_cases_and_non_finite_lanes(max_iter, dtype, assert_meets_criteria):
    """Zero, NaN, Inf, subnormal, huge and exactly degenerate matrices: NaN
    only in the lanes of non-finite matrices (status NON_FINITE)."""
    M = edge_case_matrices(dtype)
    triton, scalar = _both(M, max_iter=max_iter)
    finite = torch.isfinite(M).flatten(-2).all(-1)
    assert torch.isnan(triton[0][~finite]).all() and not torch.isnan(triton[0][finite]).any()
    assert (triton[2][~finite] == int(FitStatus.NON_FINITE)).all()
    _assert_same_fits(triton, scalar, M, assert_meets_criteria, "edge cases")


def test_saddle_escapes_and_fallbacks(assert_meets_criteria):
    """Warm starts at half-turns from the optimum (saddles: escaped), rank-1
    and uniform matrices, edge cases: the kernel's escapes, counts and statuses."""
    M = torch.cat([edge_case_matrices(torch.float64), make_matrices("rank1", 30, 40),
                   make_matrices("uniform", 60, 41), make_matrices("rot60", 40, 42)])
    init = random_rotations(len(M), torch.Generator().manual_seed(43))
    half_turn = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    init[-40:] = torchrot.fit_rotation(M[-40:]) @ half_turn
    triton, scalar = _both(M, init)
    assert (triton[1][-40:] > 4).any()  # some lanes escaped and took more steps
    _assert_same_fits(triton, scalar, M, assert_meets_criteria, "escapes")


@pytest.mark.parametrize("shape", [(0, 3, 3), (2, 0, 3, 3)])
def test_empty_batches(shape, dtype):
    M = torch.empty(shape, dtype=dtype)
    with triton_kernel():
        assert torchrot.fit_rotation(M).shape == shape
        R, iterations, status = torchrot.fit_rotation_info(M, M, max_iter=1)
        assert R.shape == shape and iterations.shape == status.shape == shape[:-2]
        out = torch.empty(shape, dtype=dtype)
        torchrot.fit_rotation(M, out=out)
        assert torch.ops.torchrot.fit_rotation_backward(M, M, M, 0.0).shape == shape


def _layouts(dtype):
    M = make_matrices("rot60", 64, 5, dtype)
    init = torchrot.fit_rotation(M + 0.1 * make_matrices("gaussian", 64, 6, dtype))
    return {
        "transposed": (M.mT, init.mT),
        "strided": (M[::2], init[::2]),
        "batch_nd": (M.reshape(4, 4, 4, 3, 3), init.reshape(4, 4, 4, 3, 3)),
        "batch_permuted": (M.reshape(8, 8, 3, 3).transpose(0, 1), init.reshape(8, 8, 3, 3).transpose(0, 1)),
        "soa": (soa_view(M), soa_view(init)),
        "tiled": (tiled_view(M, 16), tiled_view(init, 16)),
        "init_broadcast": (M.reshape(8, 8, 3, 3), init[:8].reshape(8, 1, 3, 3)),
        "init_single": (M, init[0]),
    }


@pytest.mark.parametrize("layout", sorted(_layouts(torch.float64)))
@pytest.mark.parametrize("max_iter", [None, 1])
def test_layouts_and_strides(layout, max_iter, dtype):
    M, init = _layouts(dtype)[layout]
    with triton_kernel():
        R = torchrot.fit_rotation(M, init, max_iter=max_iter)
        out = torch.empty_like(M)
        torchrot.fit_rotation(M, init, max_iter=max_iter, out=out)
    with cpu_kernel("scalar"):
        expected = torchrot.fit_rotation(M, init, max_iter=max_iter)
    assert R.shape == expected.shape and R.stride() == expected.stride()
    assert torch.equal(R, expected) and torch.equal(out, expected)


@pytest.mark.parametrize("low", [torch.float16, torch.bfloat16], ids=str)
def test_reduced_precision_and_mixed_dtypes(low):
    """float16/bfloat16 are computed in float32; a warm start of another
    dtype is cast to M's compute dtype."""
    M = make_matrices("warm", 64, 7, torch.float32)
    init = torchrot.fit_rotation(M.double())
    for args in ((M.to(low),), (M.to(low), init.to(low), 1), (M, init, None), (M.double(), init.float(), 1)):
        triton, scalar = _both(*args[:2], max_iter=args[2] if len(args) > 2 else None)
        assert triton[0].dtype == scalar[0].dtype
        for a, b in zip(triton, scalar):
            assert torch.equal(a, b)
