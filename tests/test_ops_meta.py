"""The operators and the pure-PyTorch reference on meta and fake tensors:
the shapes and dtypes of the results, and argument checks without data."""
from __future__ import annotations

import pytest
import torch

import torchrot

op = torch.ops.torchrot


# ---------------------------------------------------------------------------
# meta / fake tensors
# ---------------------------------------------------------------------------


META_BATCHES = [(), (4,), (2, 5), (0,)]
META_DTYPES = [torch.float32, torch.float64, torch.float16, torch.bfloat16]


def _check_meta_result(R, iterations, status, M, batch, dt):
    assert R.device.type == "meta" and R.shape == M.shape and R.dtype == dt
    if iterations is not None:
        assert iterations.shape == batch and iterations.dtype == torch.int32 and iterations.device.type == "meta"
        assert status.shape == batch and status.dtype == torch.uint8 and status.device.type == "meta"


@pytest.mark.parametrize("batch", META_BATCHES, ids=str)
@pytest.mark.parametrize("dt", META_DTYPES, ids=str)
def test_meta_op(batch, dt):
    """The operator on meta tensors (its fake kernel): shapes and dtypes."""
    M = torch.empty(*batch, 3, 3, dtype=dt, device="meta")
    init = torch.empty(3, 3, dtype=dt, device="meta")
    for R in (
        op.fit_rotation(M, None, None, "conservative"),
        op.fit_rotation(M, init, 1, "newton"),
        torchrot.fit_rotation(M, init, max_iter=2, variant="gershgorin"),
        torchrot.fit_orthogonal(M, init, max_iter=2, variant="gershgorin"),
        torchrot.fit_orthogonal(M, out=torch.empty_like(M)),
    ):
        _check_meta_result(R, None, None, M, batch, dt)
    _check_meta_result(*op.fit_rotation_info(M, init, None, "conservative"), M, batch, dt)
    _check_meta_result(*torchrot.fit_rotation_info(M), M, batch, dt)
    out = torch.empty(*batch, 3, 3, dtype=dt, device="meta")
    assert torchrot.fit_rotation(M, out=out) is out


@pytest.mark.parametrize(
    "batch, dt", [(b, torch.float32) for b in META_BATCHES] + [((4,), torch.float16), ((), torch.float64)], ids=str
)
@pytest.mark.parametrize("with_init", [False, True], ids=["cold", "warm"])
def test_meta_reference(batch, dt, with_init):
    """fit_rotation_reference runs on meta tensors (no data-dependent control
    flow) and returns the right shapes and dtypes."""
    M = torch.empty(*batch, 3, 3, dtype=dt, device="meta")
    init = torch.empty(3, 3, dtype=dt, device="meta") if with_init else None
    _check_meta_result(torchrot.fit_rotation_reference(M, init), None, None, M, batch, dt)
    _check_meta_result(torchrot.fit_rotation_reference(M, init, max_iter=1), None, None, M, batch, dt)
    _check_meta_result(*torchrot.fit_rotation_reference(M, init, return_info=True), M, batch, dt)


def test_meta_checks_arguments():
    M = torch.empty(4, 3, 3, device="meta")
    with pytest.raises(ValueError, match="M must have shape"):
        op.fit_rotation(torch.empty(4, 3, 2, device="meta"), None, None, "conservative")
    with pytest.raises(ValueError, match="variant"):
        op.fit_rotation(M, None, None, "bad")
    with pytest.raises(ValueError, match="max_iter"):
        torchrot.fit_rotation_reference(M, max_iter=0)
    with pytest.raises(ValueError, match="init"):
        torchrot.fit_rotation_reference(M, torch.empty(2, 3, 3, device="meta"))
    with pytest.raises(ValueError, match="out"):
        torchrot.fit_rotation(M, out=torch.empty(3, 3, 3, device="meta"))


def test_fake_tensor_mode():
    from torch._subclasses.fake_tensor import FakeTensorMode

    with FakeTensorMode():
        M = torch.empty(7, 3, 3, dtype=torch.float64)
        R = op.fit_rotation(M, None, 2, "newton")
        R2, it, st = op.fit_rotation_info(M, None, None, "conservative")
    assert R.shape == (7, 3, 3) and R.dtype == torch.float64
    assert it.shape == (7,) and it.dtype == torch.int32 and st.dtype == torch.uint8
