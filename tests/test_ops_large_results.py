"""Fresh results large enough for the operators to advise transparent huge
pages (csrc/cpu/huge_pages.h): bit for bit the results written into out=, in
their layout (structure of arrays kept), as are fit_rotation_info's R, the
derivative and float16 results computed in a float32 buffer."""
from __future__ import annotations

import pytest
import torch

import torchrot
from torchrot._constants import GRADIENT_EPS
from torchrot.testing import make_matrices, rotations, soa_view

# More than 4 MiB of float32 (n, 3, 3): the operators advise transparent huge
# pages for such fresh results (csrc/cpu/huge_pages.h).
LARGE_BATCH = 150_000


@pytest.mark.parametrize("layout", ["contiguous", "soa"])
def test_large_fresh_results_are_the_out_results(layout, dtype):
    """A fresh result large enough for huge pages is, bit for bit, the result
    written into out=, in its layout (structure of arrays kept); so are
    fit_rotation_info's R and the derivative, computed in halves below the
    threshold."""
    M = make_matrices("warm", LARGE_BATCH, 41, torch.float64).to(dtype)
    init = rotations(LARGE_BATCH, 42, dtype)
    if layout == "soa":
        M, init = soa_view(M), soa_view(init)
    for kwargs in ({}, {"max_iter": 1}):
        start = init if kwargs else None
        fresh = torchrot.fit_rotation(M, start, **kwargs)
        out = torch.empty_like(M)
        torchrot.fit_rotation(M, start, out=out, **kwargs)
        assert torch.equal(fresh, out) and fresh.stride() == M.stride()
        assert torch.equal(torchrot.fit_rotation_info(M, start, **kwargs).R, out)
    G = make_matrices("gaussian", LARGE_BATCH, 43, dtype)
    grad = torch.ops.torchrot.fit_rotation_backward(G, fresh, M, GRADIENT_EPS)
    half = LARGE_BATCH // 2
    halves = [torch.ops.torchrot.fit_rotation_backward(G[s], fresh[s], M[s], GRADIENT_EPS)
              for s in (slice(None, half), slice(half, None))]
    assert torch.equal(grad, torch.cat(halves))


def test_large_fresh_reduced_precision_result():
    """float16 computes into a float32 buffer of more than 4 MiB, then casts."""
    M = make_matrices("warm", LARGE_BATCH, 44, torch.float64).half()
    half = LARGE_BATCH // 2
    expected = torch.cat([torchrot.fit_rotation(M[:half]), torchrot.fit_rotation(M[half:])])
    assert torch.equal(torchrot.fit_rotation(M), expected)
