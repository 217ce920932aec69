"""API contract of torchrot.fit_rotation and torchrot.fit_orthogonal (the
``fit`` fixture: tests/fits.py): shapes, broadcasting, strides, out=,
reduced precision and argument errors."""
from __future__ import annotations

import math

import pytest
import torch

import torchrot
from torchrot._constants import INIT_TOLERANCE
from torchrot.testing import CRITERIA, make_matrices, rotation_svd, rotations, tiled_view

op = torch.ops.torchrot


def _gaussian(shape, seed=0, dtype=torch.float64) -> torch.Tensor:
    n = math.prod(shape)
    return make_matrices("gaussian", n, seed, dtype).reshape(*shape, 3, 3)


# ---------------------------------------------------------------------------
# Batch shapes
# ---------------------------------------------------------------------------

BATCH_SHAPES = [(), (1,), (7,), (2, 3, 4), (0,), (2, 0), (0, 5, 1)]


@pytest.mark.parametrize("batch", BATCH_SHAPES, ids=str)
@pytest.mark.parametrize("max_iter", [None, 2])
def test_batch_shapes(batch, dtype, max_iter, fit):
    M = _gaussian(batch, 1, dtype)
    R = fit.fn(M, max_iter=max_iter)
    assert R.shape == M.shape and R.dtype == dtype and R.is_contiguous()
    flat = fit.fn(M.reshape(-1, 3, 3), max_iter=max_iter)
    assert torch.equal(R.reshape(-1, 3, 3), flat)
    if not fit.orthogonal:
        info = torchrot.fit_rotation_info(M, max_iter=max_iter)
        assert isinstance(info, torchrot.FitInfo)
        assert torch.equal(info.R, R)
        assert info.iterations.shape == batch and info.iterations.dtype == torch.int32
        assert info.status.shape == batch and info.status.dtype == torch.uint8
    # with a warm start of the same batch shape
    init = rotations(batch, 2, dtype)
    Ri = fit.fn(M, init, max_iter=max_iter)
    assert Ri.shape == M.shape
    flat_init = fit.fn(M.reshape(-1, 3, 3), init.reshape(-1, 3, 3), max_iter=max_iter)
    assert torch.equal(Ri.reshape(-1, 3, 3), flat_init)


def test_single_matrix_matches_batched(dtype, fit):
    M = _gaussian((9,), 3, dtype)
    R = fit.fn(M)
    for i in range(9):
        assert torch.equal(fit.fn(M[i]), R[i])


@pytest.mark.parametrize(
    "m_batch, init_batch",
    [((5,), ()), ((2, 4), (1, 4)), ((2, 4), (4,)), ((2, 4), (2, 1)), ((3, 1, 2), (2,)), ((0,), ()), ((0, 3), (3,))],
    ids=str,
)
@pytest.mark.parametrize("max_iter", [None, 1])
def test_init_broadcasting(m_batch, init_batch, dtype, max_iter, fit):
    M = _gaussian(m_batch, 4, dtype)
    init = rotations(init_batch, 5, dtype)
    R = fit.fn(M, init, max_iter=max_iter)
    expected = fit.fn(M, init.expand(M.shape).contiguous(), max_iter=max_iter)
    assert R.shape == M.shape
    assert torch.equal(R, expected)


# ---------------------------------------------------------------------------
# Strides
# ---------------------------------------------------------------------------


def _non_contiguous_inputs(dtype):
    base = make_matrices("rot60", 120, 6, dtype)
    padded = torch.zeros(60, 5, 5, dtype=dtype)
    padded[:, ::2, ::2] = base[:60]
    return {
        "transposed_strides": base[:60].mT.contiguous().mT,  # same values, column-major
        "transposed": base[:60].mT,
        "batch_step": base[::2],
        "expanded_batch": base[:1].expand(40, 3, 3),
        "expanded_rows": base[:30, :1, :].expand(30, 3, 3),
        "permuted_batch": base.reshape(6, 20, 3, 3).transpose(0, 1),
        "inner_step": padded[:, ::2, ::2],
        "column_major_batch": base.permute(1, 2, 0).contiguous().permute(2, 0, 1),
        "tiled_batch": tiled_view(base[:96], 8),  # tiles of 8 matrices in structure of arrays
        # overlapping matrices: matrix i + 1 starts at row 1 of matrix i
        "overlapping_batch": torch.as_strided(base, (100, 3, 3), (3, 3, 1)),
    }


NON_CONTIGUOUS_KINDS = [
    "transposed_strides", "transposed", "batch_step", "expanded_batch", "expanded_rows",
    "permuted_batch", "inner_step", "column_major_batch", "tiled_batch", "overlapping_batch",
]


@pytest.mark.parametrize("kind", NON_CONTIGUOUS_KINDS)
@pytest.mark.parametrize("max_iter", [None, 1])
def test_non_contiguous_M(kind, dtype, max_iter, fit):
    M = _non_contiguous_inputs(dtype)[kind]
    assert not M.is_contiguous()
    init = None
    if max_iter is not None:
        init = fit.svd(M.double()).to(dtype) @ rotations(M.shape[:-2], 8, dtype, math.radians(10))
    R = fit.fn(M, init, max_iter=max_iter)
    expected = fit.fn(M.contiguous(), init, max_iter=max_iter)
    if kind in ("column_major_batch", "tiled_batch"):  # structure of arrays: the result keeps M's layout
        assert R.stride() == M.stride()
    else:
        assert R.is_contiguous()
    assert torch.equal(R, expected)


def test_non_contiguous_init(dtype, fit):
    M = make_matrices("rot60", 50, 9, dtype)
    R0 = fit.svd(M.double()).to(dtype)
    for init in (R0.mT.contiguous().mT, R0.repeat(2, 1, 1)[::2], R0.permute(1, 2, 0).contiguous().permute(2, 0, 1)):
        assert not init.is_contiguous()
        for max_iter in (None, 1):
            assert torch.equal(
                fit.fn(M, init, max_iter=max_iter),
                fit.fn(M, init.contiguous(), max_iter=max_iter),
            )


# ---------------------------------------------------------------------------
# out=
# ---------------------------------------------------------------------------


def _outs(shape, dtype):
    n = shape[0]
    return {
        "contiguous": torch.empty(shape, dtype=dtype),
        "permuted": torch.empty(3, 3, n, dtype=dtype).permute(2, 0, 1),
        "transposed": torch.empty(shape, dtype=dtype).mT,
        "batch_step": torch.empty(2 * n, 3, 3, dtype=dtype)[::2],
        "inner_step": torch.empty(n, 6, 6, dtype=dtype)[:, ::2, ::2],
    }


@pytest.mark.parametrize("kind", ["contiguous", "permuted", "transposed", "batch_step", "inner_step"])
@pytest.mark.parametrize("out_dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16], ids=str)
def test_out(kind, out_dtype, fit):
    M = make_matrices("gaussian", 50, 10, torch.float64).to(out_dtype)
    expected = fit.fn(M)
    out = _outs(M.shape, out_dtype)[kind]
    out.fill_(123.0)
    returned = fit.fn(M, out=out)
    assert returned is out
    assert torch.equal(out, expected)
    if fit.orthogonal:
        return
    # and through the operator directly
    out2 = _outs(M.shape, out_dtype)[kind]
    assert op.fit_rotation_out(M, None, None, "conservative", out2) is None
    assert torch.equal(out2, expected)


def test_out_leaves_neighbouring_memory_alone(dtype, fit):
    M = make_matrices("gaussian", 20, 11, dtype)
    storage = torch.full((2 * 20, 3, 3), 7.0, dtype=dtype)
    fit.fn(M, out=storage[1::2])
    assert (storage[::2] == 7.0).all()
    assert torch.equal(storage[1::2], fit.fn(M))


@pytest.mark.parametrize("max_iter", [1, 3, None])
def test_out_aliases_init(dtype, variant, max_iter, fit):
    """In-place warm-start update: fit_rotation(M, init=R, out=R)."""
    M = make_matrices("warm", 500, 12, dtype)
    init = (fit.svd(M.double()) @ rotations((500,), 13, torch.float64, math.radians(20))).to(dtype)
    expected = fit.fn(M, init, max_iter=max_iter, variant=variant)
    R = init.clone()
    returned = fit.fn(M, init=R, max_iter=max_iter, variant=variant, out=R)
    assert returned is R
    assert torch.equal(R, expected)
    # non-contiguous R updated in place
    Rt = init.mT.contiguous().mT
    fit.fn(M, init=Rt, max_iter=max_iter, variant=variant, out=Rt)
    assert torch.equal(Rt, expected)


def test_out_aliases_M(dtype, fit):
    M = make_matrices("gaussian", 300, 14, dtype)
    expected = fit.fn(M)
    Mc = M.clone()
    assert fit.fn(Mc, out=Mc) is Mc
    assert torch.equal(Mc, expected)
    # with a warm start as well
    init = rotations((300,), 15, dtype)
    expected = fit.fn(M, init, max_iter=2)
    Mc = M.clone()
    fit.fn(Mc, init, max_iter=2, out=Mc)
    assert torch.equal(Mc, expected)


def test_out_aliases_M_reduced_precision(fit):
    M = make_matrices("gaussian", 100, 16, torch.float64).half()
    expected = fit.fn(M)
    Mc = M.clone()
    fit.fn(Mc, out=Mc)
    assert torch.equal(Mc, expected)


# ---------------------------------------------------------------------------
# Reduced precision
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("low", [torch.float16, torch.bfloat16], ids=str)
@pytest.mark.parametrize("max_iter", [None, 1])
def test_reduced_precision(low, variant, max_iter, fit):
    M64 = make_matrices("rot60", 2000, 20, torch.float64)
    M = M64.to(low)
    R = fit.fn(M, max_iter=max_iter, variant=variant)
    assert R.dtype == low and R.shape == M.shape
    # computed in float32 and rounded once
    assert torch.equal(R, fit.fn(M.float(), max_iter=max_iter, variant=variant).to(low))
    if max_iter is None:
        # close to the float32 fit of the unrounded data: the input rounding
        # (eps of the dtype, amplified <= ~10x on rot60 data) dominates
        R32 = fit.fn(M64.float(), variant=variant)
        assert (R.float() - R32).abs().max().item() <= 10 * torch.finfo(low).eps
        if fit.orthogonal:
            return
        info = torchrot.fit_rotation_info(M, variant=variant)
        assert info.R.dtype == low and torch.equal(info.R, R)


# ---------------------------------------------------------------------------
# Determinism across thread counts
# ---------------------------------------------------------------------------


# ---------------------------------------------------------------------------
# Argument errors
# ---------------------------------------------------------------------------

M5 = torch.randn(5, 3, 3, generator=torch.Generator().manual_seed(0))
ROT5 = rotation_svd(M5.double()).float()
REFLECT_ONE = ROT5.clone()
REFLECT_ONE[3] = torch.diag(torch.tensor([1.0, 1.0, -1.0]))

# id -> (M, init, max_iter, variant, exception type, regex the message must match)
ERROR_CASES = {
    "M_shape_3x4": (torch.randn(5, 3, 4), None, None, "conservative", ValueError, r"\bM\b.*shape"),
    "M_shape_4x3": (torch.randn(4, 3), None, None, "conservative", ValueError, r"\bM\b.*shape"),
    "M_shape_1d": (torch.randn(9), None, None, "conservative", ValueError, r"\bM\b.*shape"),
    "M_shape_0d": (torch.tensor(1.0), None, None, "conservative", ValueError, r"\bM\b.*shape"),
    "M_int": (torch.ones(5, 3, 3, dtype=torch.int32), None, None, "conservative", TypeError, r"\bM\b.*float"),
    "M_long": (torch.ones(5, 3, 3, dtype=torch.int64), None, None, "conservative", TypeError, r"\bM\b.*float"),
    "M_bool": (torch.ones(5, 3, 3, dtype=torch.bool), None, None, "conservative", TypeError, r"\bM\b.*float"),
    "M_complex": (torch.ones(5, 3, 3, dtype=torch.complex64), None, None, "conservative", TypeError, r"\bM\b.*float"),
    "init_int": (M5, ROT5.int(), None, "conservative", TypeError, r"\binit\b.*float32.*got torch\.int32"),
    "init_shape": (M5, torch.eye(2), None, "conservative", ValueError, r"\binit\b.*shape"),
    "init_not_broadcastable": (M5, ROT5[:4], None, "conservative", ValueError, r"\binit\b"),
    "init_not_broadcastable_inner": (M5.expand(2, 5, 3, 3), ROT5[:2], None, "conservative", ValueError, r"\binit\b"),
    "init_more_dims": (M5, ROT5[None, None], None, "conservative", ValueError, r"\binit\b.*broadcast"),
    "init_device": (M5, torch.empty(5, 3, 3, device="meta"), None, "conservative", ValueError, r"\binit\b.*device"),
    "M_device": (M5.to("meta"), ROT5, None, "conservative", ValueError, r"\binit\b.*device"),
    "init_zeros": (M5, torch.zeros(5, 3, 3), None, "conservative", ValueError, r"\binit\b.*rotation"),
    "init_zeros_max_iter": (M5, torch.zeros(3, 3), 1, "newton", ValueError, r"\binit\b.*rotation"),
    "init_one_reflection": (M5, REFLECT_ONE, 1, "conservative", ValueError, r"\binit\b.*rotation.*1 of 5"),
    "init_scaled": (M5, 2 * ROT5, None, "conservative", ValueError, r"\binit\b.*rotation"),
    "variant": (M5, None, None, "cayley", ValueError, r"variant.*'newton', 'conservative', 'gershgorin'"),
    "variant_case": (M5, None, None, "Newton", ValueError, r"variant"),
    "max_iter_0": (M5, None, 0, "conservative", ValueError, r"max_iter.*>= 1"),
    "max_iter_negative": (M5, None, -1, "conservative", ValueError, r"max_iter.*>= 1"),
    "max_iter_float": (M5, None, 1.5, "conservative", TypeError, r"max_iter"),
}

CALLERS = {
    "fit_rotation": lambda M, init, k, v: torchrot.fit_rotation(M, init, max_iter=k, variant=v),
    "fit_orthogonal": lambda M, init, k, v: torchrot.fit_orthogonal(M, init, max_iter=k, variant=v),
    "fit_rotation_info": lambda M, init, k, v: torchrot.fit_rotation_info(M, init, max_iter=k, variant=v),
    "op": lambda M, init, k, v: op.fit_rotation(M, init, k, v),
    "op_info": lambda M, init, k, v: op.fit_rotation_info(M, init, k, v),
    "op_out": lambda M, init, k, v: op.fit_rotation_out(M, init, k, v, torch.empty_like(M)),
}


@pytest.mark.parametrize("caller", sorted(CALLERS))
@pytest.mark.parametrize("case", sorted(ERROR_CASES))
def test_argument_errors(case, caller):
    M, init, max_iter, variant, exception, match = ERROR_CASES[case]
    if caller.startswith("op") and isinstance(max_iter, float):
        # torch.ops parses its arguments against the schema first: torch's own
        # RuntimeError, naming the argument (docs/errors.md)
        exception, match = RuntimeError, r"argument 'max_iter'"
    if caller == "fit_orthogonal":
        if case == "init_one_reflection":  # a reflection is an orthogonal warm start
            assert CALLERS[caller](M, init, max_iter, variant).shape == M.shape
            return
        match = "^torchrot.fit_orthogonal: .*" + match.replace("rotation", "orthogonal")
    with pytest.raises(exception, match=match) as excinfo:
        CALLERS[caller](M, init, max_iter, variant)
    assert type(excinfo.value) is exception


@pytest.mark.parametrize("case", sorted(ERROR_CASES))
def test_argument_errors_reference(case):
    """The pure-PyTorch implementation rejects the same arguments, with the
    same exception types."""
    M, init, max_iter, variant, exception, match = ERROR_CASES[case]
    with pytest.raises(exception, match=match) as excinfo:
        torchrot.fit_rotation_reference(M, init, max_iter=max_iter, variant=variant)
    assert type(excinfo.value) is exception


OUT_CASES = {
    "shape": (lambda: torch.empty(4, 3, 3), ValueError, r"\bout\b.*shape"),
    "shape_unbatched": (lambda: torch.empty(3, 3), ValueError, r"\bout\b.*shape"),
    "dtype": (lambda: torch.empty(5, 3, 3, dtype=torch.float64), TypeError, r"\bout\b.*dtype"),
    "dtype_half": (lambda: torch.empty(5, 3, 3, dtype=torch.float16), TypeError, r"\bout\b.*dtype"),
    "expanded": (lambda: torch.empty(1, 3, 3).expand(5, 3, 3), ValueError, r"\bout\b.*overlap"),
    "expanded_rows": (lambda: torch.empty(5, 1, 3).expand(5, 3, 3), ValueError, r"\bout\b.*overlap"),
    # matrices 0 and 1 share entries: overlapping without a zero stride
    "overlapping_strides": (lambda: torch.empty(20).as_strided((5, 3, 3), (1, 3, 1)), ValueError,
                            r"\bout\b.*overlap"),
    "device": (lambda: torch.empty(5, 3, 3, device="meta"), ValueError, r"\bout\b.*device"),
}


@pytest.mark.parametrize("via", ["fit_rotation", "fit_orthogonal", "op"])
@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_out_errors(case, via):
    make_out, exception, match = OUT_CASES[case]
    out = make_out()
    with pytest.raises(exception, match=match) as excinfo:
        if via == "op":
            op.fit_rotation_out(M5, None, None, "conservative", out)
        else:
            getattr(torchrot, via)(M5, out=out)
    assert type(excinfo.value) is exception
    assert str(excinfo.value).startswith(f"torchrot.{'fit_rotation' if via == 'op' else via}: ")


def test_errors_leave_out_untouched_for_argument_checks(fit):
    out = torch.full((5, 3, 3), 3.0)
    with pytest.raises(ValueError):
        fit.fn(M5, variant="nope", out=out)
    with pytest.raises(TypeError):
        fit.fn(M5, ROT5.int(), out=out)
    with pytest.raises(ValueError):
        fit.fn(M5, 2 * ROT5, out=out)
    assert (out == 3.0).all()


def test_good_init_within_tolerance_accepted(dtype, fit):
    """init is accepted below |R^T R - I|_F < INIT_TOLERANCE (5e-2, any
    dtype), rejected above, and an accepted but rough init still gives
    rotations at the dtype's precision."""
    gen = torch.Generator().manual_seed(23)
    M = M5.to(dtype)
    R0 = ROT5.double()
    E = torch.rand(5, 3, 3, generator=gen, dtype=torch.float64) * 2 - 1
    eye = torch.eye(3, dtype=torch.float64)
    for drift, accepted in ((1e-3, True), (5e-3, True), (3e-2, False), (1e-1, False)):
        init = R0 + drift * E
        deviation = (init.mT @ init - eye).norm(dim=(-2, -1)).max().item()
        assert (deviation < INIT_TOLERANCE) == accepted, (drift, deviation)  # the case tests what it says
        if accepted:
            R = fit.fn(M, init.to(dtype), max_iter=1)
            errors = fit.errors(R, M)
            assert errors["orthonormality"].max() <= CRITERIA[dtype]["orthonormality"]
            assert errors["det"].max() <= CRITERIA[dtype]["det"]
        else:
            with pytest.raises(ValueError, match=f"init must hold {fit.init_words}"):
                fit.fn(M, init.to(dtype), max_iter=1)


def test_status_codes_are_one_enum():
    """FitStatus (defined in C++, csrc/fit_rotation.h) names the codes that
    fit_rotation_info reports, on the C++ kernel and the generic path."""
    assert {s.name: int(s) for s in torchrot.FitStatus} == {"CAYLEY": 0, "FALLBACK": 1, "BAD_INIT": 2, "NON_FINITE": 3}
    M = make_matrices("rank1", 64, 46, torch.float64)
    M[5, 0, 0] = float("nan")
    kernel = torchrot.fit_rotation_info(M)
    reference = torchrot.FitInfo(*torchrot.fit_rotation_reference(M, return_info=True))
    for info in (kernel, reference):
        assert info.status[5] == torchrot.FitStatus.NON_FINITE
        assert (info.status == torchrot.FitStatus.FALLBACK).any()  # rank 1: no isolated maximum
        assert set(info.status.unique().tolist()) <= {int(s) for s in torchrot.FitStatus}


def test_gradient_eps_default_is_one_sentinel():
    """fit_rotation and nn.RotationFit share one default (None: torchrot's
    DEFAULT_GRADIENT_EPS), told apart by None, not by float identity: a
    float equal to the default is the default, however it was made."""
    import inspect

    assert inspect.signature(torchrot.fit_rotation).parameters["gradient_eps"].default is None
    assert inspect.signature(torchrot.nn.RotationFit).parameters["gradient_eps"].default is None
    M = make_matrices("gaussian", 8, 47, torch.float64).requires_grad_()
    grads = []
    for eps in (None, torchrot.DEFAULT_GRADIENT_EPS, float("1e-6"), 1e-3):
        (g,) = torch.autograd.grad(torchrot.fit_rotation(M, gradient_eps=eps).sum(), M)
        grads.append(g)
        (g_layer,) = torch.autograd.grad(torchrot.nn.RotationFit(gradient_eps=eps)(M).sum(), M)
        assert torch.equal(g, g_layer)
    assert torch.equal(grads[0], grads[1]) and torch.equal(grads[0], grads[2])
    assert not torch.equal(grads[0], grads[3])  # a value of one's own is used
