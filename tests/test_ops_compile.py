"""The operators under torch.compile (eager, aot_eager and inductor backends,
fullgraph=True): warm and cold fits, out=, in-place updates and
fit_rotation_info as in eager; the layout of fresh results with dynamic
shapes; dynamic batch sizes."""
from __future__ import annotations

import math

import pytest
import torch

import torchrot
from torchrot.testing import make_matrices, make_warm_start, rotation_svd, rotations, soa_view, tiled_view

# ---------------------------------------------------------------------------
# torch.compile
# ---------------------------------------------------------------------------


def _warm_update(M, init):
    R = torchrot.fit_rotation(M, init, max_iter=1, variant="newton")
    return R @ R.mT + 1


def _cold_fit(M):
    return torchrot.fit_rotation(M * 2, variant="gershgorin").sum(0)


def _fit_into(M, out):
    torchrot.fit_rotation(M, out=out)
    return out * 2


def _fit_in_place(M, R):
    torchrot.fit_rotation(M, init=R, max_iter=1, out=R)
    return R.sum()


def _fit_info(M):
    info = torchrot.fit_rotation_info(M, max_iter=3)
    return info.R, info.iterations + 1, info.status


@pytest.fixture
def compile_data():
    M = make_matrices("rot60", 64, 7, torch.float64)
    init = rotation_svd(M) @ rotations(64, 8, torch.float64, math.radians(10))
    return M, init


@pytest.mark.parametrize("backend", ["eager", "aot_eager", "inductor"])
def test_compile_matches_eager(backend, compile_data):
    torch._dynamo.reset()
    M, init = compile_data
    cf = torch.compile(_warm_update, backend=backend, fullgraph=True)
    assert torch.equal(cf(M, init), _warm_update(M, init))
    cg = torch.compile(_cold_fit, backend=backend, fullgraph=True)
    # inductor may reorder the batch sum: equal up to its rounding
    torch.testing.assert_close(cg(M), _cold_fit(M), rtol=0, atol=1e-12)


@pytest.mark.parametrize("backend", ["eager", "aot_eager", "inductor"])
def test_compile_out_matches_eager(backend, compile_data):
    torch._dynamo.reset()
    M, init = compile_data
    cf = torch.compile(_fit_into, backend=backend, fullgraph=True)
    out_c, out_e = torch.full_like(M, 5.0), torch.full_like(M, 5.0)
    r_c, r_e = cf(M, out_c), _fit_into(M, out_e)
    assert torch.equal(out_c, out_e)
    assert torch.equal(r_c, r_e)


@pytest.mark.parametrize("backend", ["eager", "aot_eager"])
def test_compile_in_place_and_info(backend, compile_data):
    torch._dynamo.reset()
    M, init = compile_data
    R_c, R_e = init.clone(), init.clone()
    s_c = torch.compile(_fit_in_place, backend=backend, fullgraph=True)(M, R_c)
    s_e = _fit_in_place(M, R_e)
    assert torch.equal(R_c, R_e) and torch.equal(s_c, s_e)
    got = torch.compile(_fit_info, backend=backend, fullgraph=True)(M)
    expected = _fit_info(M)
    assert all(torch.equal(a, b) for a, b in zip(got, expected))


@pytest.mark.parametrize("backend", ["aot_eager", "inductor"])
def test_compile_orthogonal_fit(backend, compile_data):
    """fit_orthogonal compiled (fullgraph) on matrices of either determinant:
    the eager result, also written into out= and from a warm start."""
    torch._dynamo.reset()
    M, init = compile_data
    M = M.clone()
    M[1::2] = -M[1::2]

    def fit(m, r, out):
        torchrot.fit_orthogonal(m, out=out)
        return torchrot.fit_orthogonal(m, r, max_iter=1), out

    out_c, out_e = torch.empty_like(M), torch.empty_like(M)
    got, expected = torch.compile(fit, backend=backend, fullgraph=True)(M, init, out_c), fit(M, init, out_e)
    assert torch.equal(got[0], expected[0]) and torch.equal(out_c, out_e)


@pytest.mark.parametrize("layout", ["soa", "tiles 16x8", "tiles 8x8"])
def test_compile_keeps_result_layout(layout):
    """Inductor with dynamic shapes: values and strides of the eager result,
    for structure-of-arrays and tiled inputs (fresh results keep their layout;
    8 tiles of 8 make the two batch sizes one symbol). The FX graph cache is
    off: it keys on the graph, not on the fake kernels' layouts."""
    n = 64 if layout == "tiles 8x8" else 128
    M, init = make_warm_start("warm", n, seed=2, dtype=torch.float32)
    view = soa_view if layout == "soa" else (lambda t: tiled_view(t, 8))
    M, init = view(M), view(init)
    torch._dynamo.reset()
    with torch._inductor.config.patch(fx_graph_cache=False):
        def fit_with(max_iter):  # a closure over this iteration's max_iter
            return lambda m, r: torchrot.fit_rotation(m, r, max_iter=max_iter)

        for max_iter in (1, None):
            fit = torch.compile(fit_with(max_iter), backend="inductor", fullgraph=True, dynamic=True)
            got, expected = fit(M, init), torchrot.fit_rotation(M, init, max_iter=max_iter)
            assert torch.equal(got, expected) and got.stride() == expected.stride() == M.stride()


def test_compile_dynamic_batch():
    torch._dynamo.reset()
    cf = torch.compile(_cold_fit, backend="aot_eager", fullgraph=True, dynamic=True)
    for n in (5, 9, 17):
        M = make_matrices("uniform", n, n, torch.float32)
        assert torch.equal(cf(M), _cold_fit(M))
