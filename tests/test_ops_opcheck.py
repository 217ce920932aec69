"""Operator registration: torch.library.opcheck of fit_rotation,
fit_rotation_info and fit_rotation_out over shapes, dtypes, warm starts, step
limits, variants and strides (also with inputs that require grad), and the
operators' schemas."""
from __future__ import annotations

import pytest
import torch

from torchrot.testing import make_matrices, rotation_svd, rotations

op = torch.ops.torchrot


# ---------------------------------------------------------------------------
# opcheck
# ---------------------------------------------------------------------------


def _samples():
    """(id, (M, init, max_iter, variant)) covering shapes, dtypes, warm starts,
    step limits, variants and strides. No input requires grad: the op has no
    autograd formula yet, so opcheck's test_autograd_registration only checks
    that nothing is wrongly registered."""
    M32 = make_matrices("rot60", 6, 1, torch.float32)
    M64 = make_matrices("gaussian", 6, 2, torch.float64)
    init32 = rotation_svd(M32.double()).float()
    init64 = rotations(6, 3, torch.float64)
    return [
        ("unbatched", (M64[0], None, None, "conservative")),
        ("batch_f32", (M32, None, None, "conservative")),
        ("batch_f64_newton", (M64, None, None, "newton")),
        ("nd_gershgorin", (make_matrices("uniform", 24, 4).reshape(2, 3, 4, 3, 3), None, None, "gershgorin")),
        ("empty", (torch.empty(0, 3, 3), None, None, "conservative")),
        ("empty_nd", (torch.empty(2, 0, 3, 3, dtype=torch.float64), None, 1, "newton")),
        ("init_max_iter_1", (M32, init32, 1, "newton")),
        ("init_max_iter_3", (M64, init64, 3, "gershgorin")),
        ("init_converged", (M64, init64, None, "conservative")),
        ("init_broadcast", (M64.reshape(2, 3, 3, 3), init64[0], 1, "conservative")),
        ("max_iter_1_cold", (M32, None, 1, "conservative")),
        ("transposed", (M64.mT, None, None, "conservative")),
        ("sliced_init_transposed", (M32[::2], init32[::2].mT.contiguous().mT, 3, "newton")),
        ("expanded", (M32[:1].expand(4, 3, 3), init32[:1].expand(4, 3, 3), 1, "conservative")),
        ("float16", (M32.half(), None, None, "conservative")),
        ("bfloat16", (M32.bfloat16(), None, 1, "gershgorin")),
        ("zeros", (torch.zeros(3, 3, 3), None, None, "conservative")),
    ]


SAMPLES = _samples()


@pytest.mark.parametrize("args", [a for _, a in SAMPLES], ids=[i for i, _ in SAMPLES])
def test_opcheck_fit_rotation(args):
    torch.library.opcheck(op.fit_rotation.default, args)


@pytest.mark.parametrize("args", [a for _, a in SAMPLES], ids=[i for i, _ in SAMPLES])
def test_opcheck_fit_rotation_info(args):
    torch.library.opcheck(op.fit_rotation_info.default, args)


@pytest.mark.parametrize("args", [a for _, a in SAMPLES], ids=[i for i, _ in SAMPLES])
def test_opcheck_fit_rotation_out(args):
    M = args[0]
    torch.library.opcheck(op.fit_rotation_out.default, args + (torch.empty_like(M),))


#: Samples whose tensors are made to require grad (opcheck then also checks
#: that an Autograd kernel is registered and that the derivatives trace).
GRAD_SAMPLES = [(i, a) for i, a in SAMPLES if i in (
    "unbatched", "batch_f32", "init_max_iter_1", "init_converged", "init_broadcast", "transposed", "float16")]


def _requiring_grad(t):
    return None if t is None else t.detach().clone().requires_grad_()


@pytest.mark.parametrize("args", [a for _, a in GRAD_SAMPLES], ids=[i for i, _ in GRAD_SAMPLES])
def test_opcheck_with_requires_grad(args):
    """M requires grad: fit_rotation records its derivative, fit_rotation_info
    records none (its outputs never require grad); fit_rotation_out, which
    refuses an M or out that requires grad in grad mode (as torch's out=
    operators), takes an init that does (no gradient flows to init)."""
    M, init, max_iter, variant = args
    torch.library.opcheck(op.fit_rotation.default, (_requiring_grad(M), init, max_iter, variant))
    torch.library.opcheck(op.fit_rotation_info.default, (_requiring_grad(M), init, max_iter, variant))
    if init is not None:
        out = torch.empty(M.shape, dtype=M.dtype)
        torch.library.opcheck(op.fit_rotation_out.default, (M, _requiring_grad(init), max_iter, variant, out))


def test_opcheck_fit_rotation_out_non_contiguous():
    M = make_matrices("rot60", 6, 5, torch.float32)
    out = torch.empty(3, 3, 6).permute(2, 0, 1)
    torch.library.opcheck(op.fit_rotation_out.default, (M, None, None, "conservative", out))
    out = torch.empty(12, 3, 3)[::2]
    torch.library.opcheck(op.fit_rotation_out.default, (M, rotation_svd(M.double()).float(), 1, "newton", out))


def test_opcheck_default_arguments():
    M = make_matrices("rot60", 4, 6, torch.float64)
    torch.library.opcheck(op.fit_rotation.default, (M,))
    torch.library.opcheck(op.fit_rotation_info.default, (M,), {"max_iter": 2, "variant": "newton"})


def test_schema():
    schema = op.fit_rotation.default._schema
    assert [a.name for a in schema.arguments] == ["M", "init", "max_iter", "variant", "gradient_eps"]
    assert schema.arguments[4].default_value == pytest.approx(1e-6)
    backward = op.fit_rotation_backward.default._schema
    assert [a.name for a in backward.arguments] == ["grad", "R", "M", "gradient_eps"]
    out_schema = op.fit_rotation_out.default._schema
    assert out_schema.arguments[-1].name == "out" and out_schema.arguments[-1].alias_info.is_write
    assert len(out_schema.returns) == 0
    info = op.fit_rotation_info.default._schema
    assert [r.name for r in info.returns] == ["R", "iterations", "status"]
