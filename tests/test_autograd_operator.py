"""The derivative operator (torch.ops.torchrot.fit_rotation_backward):
against the pure-PyTorch reference, across kernels (bit-identical to the
scalar build, or for x86-64's default kernel to its own results; every tail
length, strided, structure-of-arrays and tiled layouts), expanded and
broadcast inputs, threads, reduced precision and the empty batch.
"""
from __future__ import annotations

import pytest
import torch
from autograd_helpers import DTYPES, _backward_case, _smallest_pair_sum, op

import torchrot
from torchrot._constants import CPU_KERNELS, GRADIENT_EPS
from torchrot.reference import fit_rotation_backward_reference
from torchrot.testing import cpu_kernel, dtype_id, rounding_reference, soa_view, tiled_view

ISAS = CPU_KERNELS


# ---------------------------------------------------------------------------
# The derivative operator: kernels, reference, layouts, dtypes
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
def test_kernel_matches_reference(dtype):
    G, R, M = _backward_case(2000, dtype)
    got = op.fit_rotation_backward(G, R, M, GRADIENT_EPS)
    ref = fit_rotation_backward_reference(G.double(), R.double(), M.double(), GRADIENT_EPS)
    # float32 rounding is amplified by the system's condition 1 / min(sigma_i + sigma_j).
    cond = 1 / _smallest_pair_sum(M).clamp_min(1e-3)
    tol = (3e-5 if dtype == torch.float32 else 1e-13) * cond
    err = (got.double() - ref).norm(dim=(-2, -1)) / ref.norm(dim=(-2, -1))
    assert (err <= tol).all(), f"max error {err.max():.3g}"


def _supported_isas():
    hardware = {"AVX512": "avx512", "AVX2": "avx2"}.get(torch.backends.cpu.get_cpu_capability(), "default")
    return ISAS[: ISAS.index(hardware) + 1]


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
def test_every_kernel_bit_identical_to_scalar(dtype):
    """All tail lengths 0..70, contiguous and strided layouts. A kernel that
    rounds differently (x86-64's default, rounding_reference) is compared with
    its own result for all 70, contiguous: a matrix's result does not depend
    on its block."""
    G, R, M = _backward_case(70, dtype, seed=7)
    G_strided = G.mT.contiguous().mT  # column-major entries
    G_soa = soa_view(G)  # structure of arrays (vector loads)
    for isa in _supported_isas()[1:]:
        reference = rounding_reference(isa)
        with cpu_kernel(reference):
            whole = op.fit_rotation_backward(G, R, M, GRADIENT_EPS)
        for n in range(0, 71):
            for g in (G[:n], G_strided[:n], G_soa[:n]):
                if reference == "scalar":
                    with cpu_kernel("scalar"):
                        expected = op.fit_rotation_backward(g, R[:n], M[:n], GRADIENT_EPS)
                else:
                    expected = whole[:n]
                with cpu_kernel(isa) as used:
                    assert used == isa
                    got = op.fit_rotation_backward(g, R[:n], M[:n], GRADIENT_EPS)
                assert torch.equal(got, expected), f"{isa}, n={n}"
            if n % 8 == 0 and n:  # tiled (tiles of 8 in SoA): all three inputs and the result
                with cpu_kernel(isa):
                    got = op.fit_rotation_backward(*(tiled_view(t[:n], 8) for t in (G, R, M)), GRADIENT_EPS)
                assert torch.equal(got.reshape(n, 3, 3), expected), f"{isa}, n={n}, tiled"


def test_expanded_gradient_and_broadcast_M():
    """A loss like R.sum() gives a stride-0 gradient; M may broadcast to R."""
    G, R, M = _backward_case(33, torch.float64)
    ones = torch.ones(1, 1, 1, dtype=torch.float64).expand(R.shape)
    assert torch.equal(op.fit_rotation_backward(ones, R, M, 1e-6),
                       op.fit_rotation_backward(ones.contiguous(), R, M, 1e-6))
    single = M[:1]
    assert torch.equal(op.fit_rotation_backward(G, R, single, 1e-6),
                       op.fit_rotation_backward(G, R, single.expand(R.shape).contiguous(), 1e-6))


def test_out_aliasing_and_threads():
    G, R, M = _backward_case(5000, torch.float32, seed=9)
    expected = op.fit_rotation_backward(G, R, M, 1e-6)
    previous = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            assert torch.equal(op.fit_rotation_backward(G, R, M, 1e-6), expected)
    finally:
        torch.set_num_threads(previous)


@pytest.mark.parametrize("dtype", (torch.float16, torch.bfloat16), ids=dtype_id)
def test_reduced_precision_backward(dtype):
    G, R, M = _backward_case(50, torch.float32)
    got = op.fit_rotation_backward(G.to(dtype), R.to(dtype), M.to(dtype), 1e-6)
    expected = op.fit_rotation_backward(G.to(dtype).float(), R.to(dtype).float(), M.to(dtype).float(), 1e-6)
    assert got.dtype == dtype and torch.equal(got, expected.to(dtype))


def test_empty_batch():
    M = torch.empty(0, 3, 3, requires_grad=True)
    torchrot.fit_rotation(M).sum().backward()
    assert M.grad.shape == (0, 3, 3)
