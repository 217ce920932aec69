"""Derivatives of fit_rotation through the optimality condition (R^T M symmetric).

Checked against finite differences (gradcheck, float64), autograd through
float64 SVD where that is finite, RoMa's special_procrustes, the pure-PyTorch
reference, and across kernels (bit-identical to the scalar build). Then the
degenerate inputs where SVD gradients fail (repeated singular values,
rank-deficient M, half-turns), torch.func, torch.compile, autocast, and errors.
"""
from __future__ import annotations

import sys

import pytest
import torch
from torch.autograd import forward_ad
from torch.func import grad, jacfwd, jacrev, jvp, vmap

import torchrot
from torchrot._constants import CPU_KERNELS, GRADIENT_EPS
from torchrot._torch_private import below_autograd
from torchrot.reference import fit_rotation_backward_reference
from torchrot.testing import (
    DEGENERATE_FAMILIES,
    cpu_kernel,
    dtype_id,
    make_degenerate_matrices,
    make_matrices,
    make_warm_start,
    random_rotations,
    rounding_reference,
    soa_view,
    tiled_view,
)

op = torch.ops.torchrot
DTYPES = (torch.float32, torch.float64)
ISAS = CPU_KERNELS
SMOOTH = ("warm", "rot60", "uniform", "gaussian", "det_negative", "symmetric")


def _svd_gradient(M: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    M = M.detach().clone().requires_grad_()
    torchrot.rotation_svd(M).backward(G)
    return M.grad


def _gradient(M: torch.Tensor, G: torch.Tensor, **kwargs) -> torch.Tensor:
    M = M.detach().clone().requires_grad_()
    torchrot.fit_rotation(M, **kwargs).backward(G)
    return M.grad


def _smallest_pair_sum(M: torch.Tensor) -> torch.Tensor:
    """min sigma_i + sigma_j (signed smallest singular value), relative to |M|_F."""
    sigma = torch.linalg.svdvals(M.double())
    sign = torch.sign(torch.linalg.det(M.double()))
    return (sigma[..., 1] + sign * sigma[..., 2]) / M.double().norm(dim=(-2, -1))


# ---------------------------------------------------------------------------
# Exactness where the gradient exists
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", SMOOTH)
def test_gradcheck_random(name):
    M = make_matrices(name, 6, seed=3).requires_grad_()
    assert torch.autograd.gradcheck(torchrot.fit_rotation, (M,), eps=1e-6, atol=1e-8, rtol=1e-6)


@pytest.mark.parametrize(
    "M",
    [
        torch.eye(3),
        torch.diag(torch.tensor([2.0, 2.0, 1.0])),  # repeated singular values: SVD backward is NaN here
        torch.diag(torch.tensor([3.0, 3.0, 3.0])) @ random_rotations(1, torch.Generator().manual_seed(0))[0].float(),
        torch.diag(torch.tensor([3.0, 2.0, -1.0])),  # det < 0
        torch.diag(torch.tensor([-2.0, -2.0, 5.0])),  # det > 0, R a half-turn from I
    ],
    ids=["identity", "diag221", "scaled_rotation", "det_negative", "half_turn_pair"],
)
def test_gradcheck_structured(M):
    M = M.double().requires_grad_()
    assert torch.autograd.gradcheck(torchrot.fit_rotation, (M,), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_matches_svd_autograd_where_finite():
    """Agrees with autograd through float64 SVD to 1e-8 relative (undamped
    and with the default damping) where singular values are distinct and
    sigma_i + sigma_j is well away from 0 (> 3e-2 |M|_F)."""
    M = torch.cat([make_matrices(name, 300, seed=5) for name in SMOOTH])
    keep = _smallest_pair_sum(M) > 3e-2  # damping's relative effect (1e-6 / 3e-2)^2 ~ 1e-9
    M = M[keep]
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    expected = _svd_gradient(M, G)
    finite = torch.isfinite(expected).all(-1).all(-1)
    assert finite.float().mean() > 0.99
    scale = expected.norm(dim=(-2, -1), keepdim=True)
    for eps in (0.0, GRADIENT_EPS):
        got = _gradient(M, G, gradient_eps=eps)
        err = ((got - expected).norm(dim=(-2, -1), keepdim=True) / scale)[finite]
        assert err.max() < 1e-8, f"gradient_eps={eps}: max relative error {err.max():.3g}"


@pytest.mark.parametrize("name", ("warm", "uniform", "gaussian"))
def test_float32_gradient_as_accurate_as_float32_svd(name):
    """float32 rounding is amplified by the system's condition only once (no
    A^2 is formed): on condition-1e3 data the 99th percentile of the relative
    error against float64 SVD autograd stays at float32 SVD's level."""
    M = make_matrices(name, 5000, seed=1)
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    reference = _svd_gradient(M, G)
    relative = lambda g: ((g.double() - reference).norm(dim=(-2, -1)) / reference.norm(dim=(-2, -1)))
    ours = relative(_gradient(M.float(), G.float()))
    svd32 = relative(_svd_gradient(M.float(), G.float()))
    svd32 = svd32[torch.isfinite(svd32)]
    assert ours.quantile(0.99) <= 2 * svd32.quantile(0.99) and ours.max() <= 2 * svd32.max()


def test_matches_roma_special_procrustes():
    roma = pytest.importorskip("roma")
    M = make_matrices("uniform", 500, seed=2)
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    Mr = M.clone().requires_grad_()
    roma.special_procrustes(Mr).backward(G)
    got = _gradient(M, G)
    err = (got - Mr.grad).norm(dim=(-2, -1)) / Mr.grad.norm(dim=(-2, -1))
    # RoMa damps its SVD backward (gradient_eps=1e-5 on sigma differences).
    assert err.median() < 1e-9 and err.max() < 1e-4


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
def test_jacobian_is_rotational_tangent(dtype):
    """dR = R [w]x: R^T dR is skew for every direction dM."""
    M = make_matrices("gaussian", 20, seed=4, dtype=dtype)
    R = torchrot.fit_rotation(M)
    dM = torch.randn(M.shape, generator=torch.Generator().manual_seed(4), dtype=dtype)
    dR = op.fit_rotation_backward(dM, R, M, GRADIENT_EPS)
    W = R.mT @ dR
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert (W + W.mT).abs().max() <= tol * W.abs().max()


def test_init_receives_no_gradient():
    M, init = make_warm_start("warm", 10, seed=1)
    M.requires_grad_()
    init.requires_grad_()
    torchrot.fit_rotation(M, init).sum().backward()
    assert M.grad is not None and init.grad is None


def test_broadcast_init_gradient_shape():
    M = make_matrices("rot60", 4, seed=1).reshape(2, 2, 3, 3).requires_grad_()
    init = torch.eye(3, dtype=torch.float64)
    torchrot.fit_rotation(M, init, max_iter=3).sum().backward()
    assert M.grad.shape == M.shape and torch.isfinite(M.grad).all()


# ---------------------------------------------------------------------------
# The derivative operator: kernels, reference, layouts, dtypes
# ---------------------------------------------------------------------------


def _backward_case(n, dtype, seed=0):
    M = make_matrices("gaussian", n, seed=seed, dtype=dtype)
    R = torchrot.fit_rotation(M)
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(seed + 1), dtype=torch.float64).to(dtype)
    return G, R, M


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


# ---------------------------------------------------------------------------
# Degenerate inputs: finite, bounded, NaN only from NaN
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
def test_degenerate_fuzz_finite_and_bounded(dtype):
    """>= 1e5 matrices over every degenerate family: no NaN/Inf gradient, and
    |dL/dM|_F <= |G|_F / (gradient_eps |M|_F) (the damping's bound:
    |u| <= |g| / (2 lambda), |g| <= sqrt(2) |G|_F, |R [u]x|_F = sqrt(2) |u|)."""
    per_family = 100_000 // len(DEGENERATE_FAMILIES) + 1
    M = torch.cat([make_degenerate_matrices(name, per_family, seed=11, dtype=dtype)
                   for name in DEGENERATE_FAMILIES])
    assert M.shape[0] >= 100_000
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(12), dtype=dtype)
    got = _gradient(M, G)
    assert torch.isfinite(got).all(), f"{int((~torch.isfinite(got)).sum())} non-finite entries"
    norm_M = M.double().norm(dim=(-2, -1))
    bound = 1.001 * G.double().norm(dim=(-2, -1)) / (GRADIENT_EPS * norm_M)
    nonzero = norm_M > 0
    assert (got.double().norm(dim=(-2, -1))[nonzero] <= bound[nonzero]).all()
    assert (got[~nonzero] == 0).all()  # M = 0: every rotation is optimal, nothing moves it


def test_damping_bound_and_limit():
    """At an exact half-turn ambiguity (sigma_2 + sigma_3 = 0) the gradient is
    bounded by 1 / gradient_eps; where the system is regular, damping -> 0
    converges to the exact gradient."""
    M = torch.diag(torch.tensor([2.0, 1.0, -1.0], dtype=torch.float64))
    G = torch.randn(3, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    for eps in (1e-2, 1e-4, 1e-6):
        g = _gradient(M, G, gradient_eps=eps)
        assert torch.isfinite(g).all()
        assert g.norm() <= 1.001 * G.norm() / (eps * M.norm())
    M = make_matrices("uniform", 50, seed=8)
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    exact = _gradient(M, G, gradient_eps=0.0)
    errors = [(_gradient(M, G, gradient_eps=eps) - exact).norm() / exact.norm() for eps in (1e-2, 1e-3, 1e-4)]
    # Tikhonov damping: the error falls quadratically, (lambda / (sigma_i + sigma_j))^2.
    assert errors[0] / errors[1] > 50 and errors[1] / errors[2] > 50 and errors[2] < 1e-6


def test_nan_only_where_input_nan():
    M = make_matrices("gaussian", 40, seed=6)
    M[3, 1, 2] = float("nan")
    M[17, 0, 0] = float("inf")
    M.requires_grad_()
    torchrot.fit_rotation(M).sum().backward()
    bad = torch.zeros(40, dtype=torch.bool)
    bad[[3, 17]] = True
    assert torch.isnan(M.grad[bad]).all()
    assert torch.isfinite(M.grad[~bad]).all()


def test_subnormal_input_saturates_instead_of_overflowing():
    M = torch.full((3, 3), 1e-40, dtype=torch.float32) + torch.diag(torch.tensor([3e-40, 0.0, 0.0]))
    g = _gradient(M, torch.ones(3, 3))
    assert not torch.isnan(g).any() and not torch.isinf(g).any()


# ---------------------------------------------------------------------------
# torch.func, torch.compile, autocast, forward mode
# ---------------------------------------------------------------------------


def _weights():
    return torch.arange(1.0, 10.0, dtype=torch.float64).view(3, 3)


def _loss(M):
    return (torchrot.fit_rotation(M) * _weights()).sum()


def test_func_grad_and_vmap():
    M = make_matrices("rot60", 8, seed=2)
    per_matrix = vmap(grad(_loss))(M)
    for i in range(8):
        expected = _svd_gradient(M[i], _weights().expand(3, 3))
        torch.testing.assert_close(per_matrix[i], expected, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("transform", [jacrev, jacfwd], ids=["jacrev", "jacfwd"])
def test_func_jacobians_match_svd(transform):
    M = make_matrices("uniform", 1, seed=3)[0]
    J = transform(torchrot.fit_rotation)(M)
    J_svd = jacrev(torchrot.rotation_svd)(M)
    torch.testing.assert_close(J, J_svd, rtol=1e-9, atol=1e-10)


def test_func_jvp_and_forward_ad():
    M = make_matrices("gaussian", 5, seed=4)
    dM = torch.randn(M.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    R, dR = jvp(torchrot.fit_rotation, (M,), (dM,))
    _, dR_svd = jvp(torchrot.rotation_svd, (M,), (dM,))
    torch.testing.assert_close(R, torchrot.fit_rotation(M))
    torch.testing.assert_close(dR, dR_svd, rtol=1e-8, atol=1e-10)
    import torch.autograd.forward_ad as fwAD

    with fwAD.dual_level():
        out = torchrot.fit_rotation(fwAD.make_dual(M, dM))
        torch.testing.assert_close(fwAD.unpack_dual(out).tangent, dR, rtol=0, atol=0)


def test_vmap_with_batched_init():
    M, init = make_warm_start("warm", 12, seed=5)
    M, init = M.view(3, 4, 3, 3), init.view(3, 4, 3, 3)
    for in_dims, args in (((0, 0), (M, init)), ((None, 0), (M[0], init)), ((0, None), (M, init[0, 0]))):
        got = vmap(lambda m, r: torchrot.fit_rotation(m, r), in_dims=in_dims)(*args)
        m_i, r_i = ([a[i] if d is not None else a for i in range(3)] for a, d in zip(args, in_dims))
        expected = torch.stack([torchrot.fit_rotation(m, r) for m, r in zip(m_i, r_i)])
        assert torch.equal(got, expected)


def test_compile_fullgraph_backward():
    torch._dynamo.reset()
    M = make_matrices("gaussian", 16, seed=1, dtype=torch.float32)

    def loss(m, eps):
        return (torchrot.fit_rotation(m, gradient_eps=eps) * m).sum()

    compiled = torch.compile(loss, fullgraph=True)
    for eps in (1e-6, 0.3):
        Mc = M.clone().requires_grad_()
        compiled(Mc, eps).backward()
        Me = M.clone().requires_grad_()
        loss(Me, eps).backward()
        torch.testing.assert_close(Mc.grad, Me.grad)


def test_autocast_runs_in_float32():
    M = make_matrices("gaussian", 8, seed=2, dtype=torch.float32).requires_grad_()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        x = torch.nn.functional.linear(M.view(8, 9), torch.eye(9)).view(8, 3, 3)  # bf16 under autocast
        assert x.dtype == torch.bfloat16
        R = torchrot.fit_rotation(x)
        R_op = op.fit_rotation(x.detach())
    assert R.dtype == torch.float32 and R_op.dtype == torch.float32
    R.sum().backward()
    assert M.grad.dtype == torch.float32 and torch.isfinite(M.grad).all()


def test_opcheck_backward_and_autograd_registration():
    G, R, M = _backward_case(6, torch.float64)
    torch.library.opcheck(op.fit_rotation_backward.default, (G, R, M, 1e-6))
    torch.library.opcheck(op.fit_rotation.default, (M.clone().requires_grad_(), None, None, "conservative", 1e-6))


def test_training_call_records_in_cpp():
    """A plain reverse-mode fit (torchrot.fit_rotation, torch.ops) records its
    derivative in C++, in the operator's Autograd kernel (csrc/autograd.cpp):
    the same gradients, bit for bit, as the Python Autograd kernel (its twin
    operator's, which the C++ kernel hands torch.func, forward-mode and
    traced calls); init gets none."""
    M, init = make_warm_start("warm", 37, seed=5, dtype=torch.float32)
    G = make_matrices("gaussian", 37, seed=6, dtype=torch.float32)
    for kwargs in ({}, {"max_iter": 1}):
        Mc = M.clone().requires_grad_()
        R = torchrot.fit_rotation(Mc, init, **kwargs)
        assert "FitRotationAutograd" in R.grad_fn.name()  # the C++ node
        (g_cpp,) = torch.autograd.grad(R, Mc, G)
        Mp = M.clone().requires_grad_()
        R_py = op._fit_rotation_python_autograd(Mp, init, kwargs.get("max_iter"), "conservative", 1e-6)
        assert "FitRotationFunction" in R_py.grad_fn.name()
        (g_py,) = torch.autograd.grad(R_py, Mp, G)
        assert torch.equal(g_cpp, g_py)


def test_eager_call_without_derivative_records_nothing():
    """The plain eager call with nothing to record (M not requiring grad, also
    with an init that does; or grad mode off) runs the kernel through the same
    C++ operator and returns a result without autograd history, equal bit for
    bit to the operator's."""
    M, init = make_warm_start("warm", 11, seed=7, dtype=torch.float32)
    expected = op.fit_rotation(M, init, None, "conservative", 1e-6)
    cases = [(M, init.clone().requires_grad_(), True), (M.clone().requires_grad_(), init, False)]
    for M_in, init_in, grad_mode in cases:
        with torch.set_grad_enabled(grad_mode):
            R = torchrot.fit_rotation(M_in, init_in)
        assert R.grad_fn is None and not R.requires_grad
        assert torch.equal(R, expected)


def _torchrot_python_calls(fn):
    """fn() and the names of the functions in torchrot/_autograd.py that ran
    during it (this thread's Python calls, through sys.setprofile)."""
    source = torchrot._autograd.__file__
    names = []

    def profile(frame, event, arg):
        if event == "call" and frame.f_code.co_filename == source:
            names.append(frame.f_code.co_name)

    sys.setprofile(profile)
    try:
        result = fn()
    finally:
        sys.setprofile(None)
    return result, names


def _without_grad_mode(fn, *args):
    with torch.no_grad():
        return fn(*args)


def test_operator_calls_run_no_python_unless_a_transform_or_tangent_needs_it():
    """torch.ops.torchrot.fit_rotation and fit_rotation_backward decide in C++
    (csrc/autograd.cpp) what a call records: with nothing to record (grad
    mode off, nothing requiring grad but init, which receives no gradient; no
    tangent, also inside an open dual level) they run below autograd, and a
    fit whose M requires grad records the C++ node of torchrot.fit_rotation's
    plain call, both without a Python frame; the results and gradients are
    those of the Python Autograd kernel, bit for bit, which still records the
    calls with a tangent."""
    M, init = make_warm_start("warm", 9, seed=9, dtype=torch.float64)
    G = make_matrices("gaussian", 9, seed=10, dtype=torch.float64)
    with below_autograd():
        R = op.fit_rotation(M, init)
        tangent = op.fit_rotation_backward(G, R, M)
    quiet = {
        "plain": lambda: op.fit_rotation(M, init),
        "defaults": lambda: op.fit_rotation.default(M, init),
        "grad mode off": lambda: _without_grad_mode(op.fit_rotation, M.clone().requires_grad_(), init),
        "backward": lambda: op.fit_rotation_backward(G, R, M),
    }
    for name, call in quiet.items():
        result, python = _torchrot_python_calls(call)
        expected = tangent if name == "backward" else R
        assert python == [] and result.grad_fn is None and torch.equal(result, expected), name
    with forward_ad.dual_level():
        result, python = _torchrot_python_calls(lambda: op.fit_rotation(M, init))
        assert python == [] and forward_ad.unpack_dual(result).tangent is None and torch.equal(result, R)
        dual = forward_ad.make_dual(M, G)
        result, python = _torchrot_python_calls(lambda: op.fit_rotation(dual, init))
        assert "kernel" in python and torch.equal(forward_ad.unpack_dual(result).tangent, tangent)

    Mg = M.clone().requires_grad_()
    for init_in in (init, init.clone().requires_grad_()):
        result, python = _torchrot_python_calls(lambda init_in=init_in: op.fit_rotation(Mg, init_in))
        assert python == [] and "FitRotationAutograd" in result.grad_fn.name() and torch.equal(result.detach(), R)
        (g,) = torch.autograd.grad(result, Mg, G)
        assert torch.equal(g, tangent)
    # init receives no gradient: where only init requires grad, nothing is
    # recorded, as through torchrot.fit_rotation and under torch.compile.
    init_g = init.clone().requires_grad_()
    result, python = _torchrot_python_calls(lambda: op.fit_rotation(M, init_g))
    assert python == [] and result.grad_fn is None and torch.equal(result, R)
    for fit in (torchrot.fit_rotation, torch.compile(torchrot.fit_rotation, fullgraph=True)):
        assert not fit(M, init_g).requires_grad

    # A torch.compile'd training step: traced through the Python kernel, its
    # graphs then call both operators with grad mode off.
    compiled = torch.compile(lambda M, init: op.fit_rotation(M, init) * 2, fullgraph=True)
    step = lambda: torch.autograd.grad(compiled(Mg, init), Mg, G)  # noqa: E731
    step()
    (g,), python = _torchrot_python_calls(step)
    assert python == [] and torch.equal(g, 2 * tangent)


def test_eager_entry_leaves_subclasses_and_modes_to_torch_ops():
    """The plain eager call's direct entry (torchrot._C.fit_rotation_eager,
    with out= too) declines, before doing anything, what torch.ops handles: a
    tensor subclass's __torch_function__, an active torch function mode,
    max_iter beyond int64. fit_rotation then calls the operator through
    torch.ops: the mode sees that call and the subclass survives; the results
    are the same, and out= returns out itself."""
    M, init = make_warm_start("warm", 7, seed=8, dtype=torch.float32)
    expected = op.fit_rotation(M, init, None, "conservative", GRADIENT_EPS)
    entry = torchrot._C.fit_rotation_eager
    args = (None, "conservative", GRADIENT_EPS)
    assert torch.equal(entry(M, init, *args, None), expected)
    out = torch.empty_like(M)
    assert entry(M, init, *args, out) is out and torch.equal(out, expected)

    class Sub(torch.Tensor):
        pass

    declined = [(M.as_subclass(Sub), init, *args, None), (M, init.as_subclass(Sub), *args, None),
                (M, init, 2**63, "conservative", GRADIENT_EPS, None), (M, init, *args, out.as_subclass(Sub))]
    for call in declined:
        assert entry(*call) is NotImplemented
    R = torchrot.fit_rotation(M.as_subclass(Sub), init)
    assert type(R) is Sub and torch.equal(R.as_subclass(torch.Tensor), expected)
    out_sub = torch.zeros_like(M).as_subclass(Sub)
    assert torchrot.fit_rotation(M, init, out=out_sub) is out_sub and torch.equal(out_sub.as_subclass(torch.Tensor),
                                                                                  expected)

    class Recorder(torch.overrides.TorchFunctionMode):
        def __init__(self):
            super().__init__()
            self.calls = []

        def __torch_function__(self, func, types, args=(), kwargs=None):
            self.calls.append(func)
            return func(*args, **(kwargs or {}))

    out = torch.zeros_like(M)
    with Recorder() as mode:
        assert entry(M, init, *args, None) is NotImplemented
        assert entry(M, init, *args, out) is NotImplemented
        R = torchrot.fit_rotation(M, init)
        assert torchrot.fit_rotation(M, init, out=out) is out
    assert op.fit_rotation.default in mode.calls and op.fit_rotation_out.default in mode.calls
    assert torch.equal(R, expected) and torch.equal(out, expected)


def test_op_level_autograd_uses_gradient_eps():
    M = torch.diag(torch.tensor([2.0, 1.0, -1.0], dtype=torch.float64)).requires_grad_()
    G = torch.ones(3, 3, dtype=torch.float64)
    for eps in (1e-3, 1e-1):
        (g_op,) = torch.autograd.grad(op.fit_rotation(M, None, None, "conservative", eps), M, G)
        (g_api,) = torch.autograd.grad(torchrot.fit_rotation(M, gradient_eps=eps), M, G)
        torch.testing.assert_close(g_op, g_api, rtol=0, atol=0)


# ---------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------


def test_out_with_requires_grad_raises():
    M = make_matrices("rot60", 2, seed=1).requires_grad_()
    with pytest.raises(ValueError, match="out= does not support automatic differentiation"):
        torchrot.fit_rotation(M, out=torch.empty(2, 3, 3, dtype=torch.float64))


@pytest.mark.parametrize("bad", [-1e-3, float("nan"), float("inf")])
def test_bad_gradient_eps(bad):
    M = make_matrices("rot60", 2, seed=1)
    with pytest.raises(ValueError, match="gradient_eps must be a finite number >= 0"):
        torchrot.fit_rotation(M, gradient_eps=bad)
    with pytest.raises(ValueError, match="gradient_eps must be a finite number >= 0"):
        op.fit_rotation_backward(M, M, M, bad)
    with pytest.raises(TypeError, match="gradient_eps must be a float"):
        torchrot.fit_rotation(M, gradient_eps="small")


def test_backward_op_argument_errors():
    G, R, M = _backward_case(4, torch.float64)
    with pytest.raises(ValueError, match="grad must have R's shape"):
        op.fit_rotation_backward(G[:2], R, M, 1e-6)
    with pytest.raises(ValueError, match="M of shape .* must broadcast to R's shape"):
        op.fit_rotation_backward(G, R, M[:3], 1e-6)
    with pytest.raises(TypeError, match="grad must have R's dtype"):
        op.fit_rotation_backward(G.float(), R, M, 1e-6)
    with pytest.raises(ValueError, match=r"R must have shape \(\.\.\., 3, 3\)"):
        op.fit_rotation_backward(G, R.view(4, 9), M, 1e-6)
    with pytest.raises(TypeError, match="R must be float32, float64"):
        op.fit_rotation_backward(G.long(), R.long(), M.long(), 1e-6)


def test_second_derivatives_raise_instead_of_zeros():
    M = make_matrices("gaussian", 3, seed=1).requires_grad_()
    (g,) = torch.autograd.grad(torchrot.fit_rotation(M).sum(), M, create_graph=True)
    with pytest.raises(RuntimeError, match="second derivatives are not implemented"):
        g.sum().backward()
    (g,) = torch.autograd.grad(op.fit_rotation(M).sum(), M, create_graph=True)
    with pytest.raises(RuntimeError, match="second derivatives are not implemented"):
        g.sum().backward()
    from torch.func import hessian

    with pytest.raises(RuntimeError, match="second derivatives are not implemented"):
        hessian(lambda m: torchrot.fit_rotation(m).sum())(M[0].detach())
