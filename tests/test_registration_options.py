"""torchrot.rigid_registration's shapes, dtypes and options: broadcasting
batch dimensions, the empty batch, meta tensors, non-contiguous inputs
(left unmodified), half precision and autocast, the warm start (init: passed
on to fit_rotation as it is, and checked in every dtype), extreme finite
weights, torch.compile, and allow_reflection (the orthogonal fit)."""
from __future__ import annotations

import pytest
import torch
from registration_helpers import assert_close, umeyama_reference

import torchrot
from torchrot.testing import registration_problem

# ---------------------------------------------------------------------------
# Shapes, dtypes, options
# ---------------------------------------------------------------------------


def test_batch_dimensions_broadcast():
    gen = torch.Generator().manual_seed(11)
    x = torch.randn(2, 1, 10, 3, generator=gen, dtype=torch.float64)
    y = torch.randn(3, 10, 3, generator=gen, dtype=torch.float64)
    w = torch.rand(10, generator=gen, dtype=torch.float64) + 0.1
    out = torchrot.rigid_registration(x, y, w, scale=True)
    assert out.R.shape == (2, 3, 3, 3) and out.t.shape == (2, 3, 3) and out.s.shape == (2, 3)
    for i in range(2):
        for j in range(3):
            one = torchrot.rigid_registration(x[i, 0], y[j], w, scale=True)
            for a, b, name in zip(out, one, "Rts"):
                assert_close(a[i, j], b, 1e-12, name)
    # weights carrying the batch dimensions
    wb = torch.rand(2, 3, 10, generator=gen, dtype=torch.float64) + 0.1
    out = torchrot.rigid_registration(x[:, 0, None], y, wb)
    R, t, _ = umeyama_reference(x[:, 0, None].expand(2, 3, 10, 3), y.expand(2, 3, 10, 3), wb)
    assert_close(out.R, R, 1e-11, "R")
    assert_close(out.t, t, 1e-10, "t")


def test_empty_batch():
    x = torch.zeros(0, 10, 3, dtype=torch.float64)
    out = torchrot.rigid_registration(x, x, torch.ones(0, 10, dtype=torch.float64), scale=True)
    assert out.R.shape == (0, 3, 3) and out.t.shape == (0, 3) and out.s.shape == (0,)


def test_meta_tensors_give_shapes():
    """On meta (no values, no autocast) the call runs and gives the result's shapes and dtype."""
    x = torch.empty(5, 10, 3, dtype=torch.float32, device="meta")
    out = torchrot.rigid_registration(x, x, torch.empty(5, 10, device="meta"), scale=True)
    assert out.R.shape == (5, 3, 3) and out.t.shape == (5, 3) and out.s.shape == (5,)
    assert out.R.device.type == "meta" and out.R.dtype == torch.float32


def test_non_contiguous_inputs_and_no_input_modification():
    x, y, _ = registration_problem((4,), n=16, seed=12, noise=0.1)
    xt = x.transpose(-1, -2).contiguous().transpose(-1, -2)  # same values, other strides
    w = torch.rand(16, 4, dtype=torch.float64).T + 0.1
    copies = [t.clone() for t in (xt, y, w)]
    out = torchrot.rigid_registration(xt, y[:, :, :], w, scale=True)
    ref = torchrot.rigid_registration(x, y, w.contiguous(), scale=True)
    for a, b, name in zip(out, ref, "Rts"):
        assert_close(a, b, 1e-13, name)
    for before, after in zip(copies, (xt, y, w)):
        assert torch.equal(before, after)


@pytest.mark.parametrize("low", [torch.float16, torch.bfloat16], ids=str)
def test_half_precision_is_computed_in_float32(low):
    x, y, (R, _, _) = registration_problem((3,), n=20, seed=13, with_scale=False)
    out = torchrot.rigid_registration(x.to(low), y.to(low))
    assert out.R.dtype == out.t.dtype == out.s.dtype == low
    ref = torchrot.rigid_registration(x.to(low).float(), y.to(low).float())
    assert torch.equal(out.R, ref.R.to(low))
    # a half-precision warm start (a rotation only to its own precision) is accepted
    warm = torchrot.rigid_registration(x.to(low), y.to(low), init=R.to(low))
    assert_close(warm.R, ref.R, 1e-2, "R from a half-precision init")


def test_autocast_keeps_float32():
    x, y, _ = registration_problem((5,), n=20, seed=14, noise=0.2, dtype=torch.float32)
    plain = torchrot.rigid_registration(x, y, scale=True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        auto = torchrot.rigid_registration(x, y, scale=True)
    for a, b, name in zip(auto, plain, "Rts"):
        assert a.dtype == torch.float32
        assert_close(a, b, 1e-6, name)


def test_init_is_forwarded_as_warm_start(monkeypatch):
    x, y, (R, _, _) = registration_problem((8,), n=20, seed=15, with_scale=False)
    cold = torchrot.rigid_registration(x, y)
    seen = []
    fit = torchrot.fit_rotation

    def recording_fit(M, init=None, **options):
        seen.append(init)
        return fit(M, init, **options)

    monkeypatch.setattr(torchrot.registration, "fit_rotation", recording_fit)
    warm = torchrot.rigid_registration(x, y, init=R)
    assert seen and seen[-1] is R
    assert_close(warm.R, cold.R, 1e-12, "R")
    with pytest.raises(ValueError,
                       match=r"init must have shape \(\.\.\., 3, 3\) broadcastable to the batch shape \[8\]"):
        torchrot.rigid_registration(x, y, init=torch.eye(3, dtype=torch.float64).expand(3, 3, 3))
    with pytest.raises(TypeError, match="init must be float32, float64, float16 or bfloat16, got torch.int64"):
        torchrot.rigid_registration(x, y, init=R.long())
    with pytest.raises(ValueError, match="init must hold rotations"):
        torchrot.rigid_registration(x, y, init=2 * R)


@pytest.mark.parametrize("init_dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16], ids=str)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16], ids=str)
def test_init_of_any_float_dtype_goes_to_fit_rotation_as_it_is(dtype, init_dtype, monkeypatch):
    """init is fit_rotation's to check and cast (any float dtype, as
    fit_rotation takes it): the same warm start whatever the inputs' dtype."""
    x, y, (R, _, _) = registration_problem((4,), n=20, seed=16, with_scale=False)
    init = R.to(init_dtype)
    seen = []
    fit = torchrot.fit_rotation
    monkeypatch.setattr(torchrot.registration, "fit_rotation",
                        lambda M, init=None, **kw: seen.append(init) or fit(M, init, **kw))
    out = torchrot.rigid_registration(x.to(dtype), y.to(dtype), init=init)
    assert seen[-1] is init
    assert out.R.dtype == dtype
    assert_close(out.R, R, {torch.float64: 1e-12, torch.float32: 1e-5}.get(dtype, 1e-2), "R")


def _not_a_rotation(what, dtype):
    R = torchrot.fit_rotation(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(17)))
    if what == "3 I":
        return (3 * torch.eye(3, dtype=torch.float64)).to(dtype)
    if what == "reflection":
        return (R * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)).to(dtype)
    return (R + 0.2).to(dtype)


@pytest.mark.parametrize("layer", [False, True])
@pytest.mark.parametrize("what", ["3 I", "reflection", "skewed"])
@pytest.mark.parametrize("init_dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16], ids=str)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16], ids=str)
def test_init_that_is_not_a_rotation_raises_in_every_dtype(dtype, init_dtype, what, layer):
    """A half-precision init was projected onto a rotation by a cold fit
    before any check, so 3 I or a reflection passed; every dtype is checked
    by fit_rotation now, the registration function and its layer alike."""
    x, y, _ = registration_problem((), n=20, seed=18, with_scale=False)
    register = torchrot.nn.RigidRegistration() if layer else torchrot.rigid_registration
    with pytest.raises(ValueError, match="init must hold rotations"):
        register(x.to(dtype), y.to(dtype), init=_not_a_rotation(what, init_dtype))


@pytest.mark.parametrize("weight", [1e38, 3e38, 1e-40, 1e-44])
def test_extreme_finite_weights(weight):
    """Weights whose sum overflows float32 (1e38 each: it made p zero, and R =
    I, t = 0 came back without an error), and subnormal ones: only the
    weights' ratios matter, so all-equal weights give the unweighted fit."""
    x, y, (R, t, _) = registration_problem((), n=40, seed=19, with_scale=False, dtype=torch.float32)
    w = torch.full((40,), weight, dtype=torch.float32)
    assert torch.isinf(w.sum()) or weight < 1
    out = torchrot.rigid_registration(x, y, w, scale=True)
    plain = torchrot.rigid_registration(x, y, scale=True)
    for a, b, name in zip(out, plain, "Rts"):
        assert_close(a, b, 1e-5, name)
    assert_close(out.R, R, 1e-5, "R")
    # unequal extreme weights: the same as the weights scaled to ordinary values
    w = torch.linspace(1, 2, 40, dtype=torch.float32) * 1.5e38
    scaled = torchrot.rigid_registration(x, y, w / 1e38, scale=True)
    for a, b, name in zip(torchrot.rigid_registration(x, y, w, scale=True), scaled, "Rts"):
        assert_close(a, b, 1e-5, name)


def test_extreme_weights_gradient_is_finite_and_scale_free():
    x, y, _ = registration_problem((), n=12, seed=20, noise=0.3, dtype=torch.float32)
    grads = []
    for scale in (1.0, 1e37):
        w = (torch.linspace(1, 2, 12) * scale).requires_grad_()
        torchrot.rigid_registration(x, y, w, scale=True).t.sum().backward()
        grads.append(w.grad * scale)  # d/dw of a function of w / sum(w) scales as 1 / scale
    assert torch.isfinite(grads[1]).all()
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-4, atol=1e-6)


def test_compiles_fullgraph():
    x, y, _ = registration_problem((4,), n=10, seed=16, noise=0.1)
    w = torch.rand(4, 10, dtype=torch.float64) + 0.1
    compiled = torch.compile(torchrot.rigid_registration, backend="aot_eager", fullgraph=True)
    out = compiled(x, y, w, scale=True)
    ref = torchrot.rigid_registration(x, y, w, scale=True)
    for a, b, name in zip(out, ref, "Rts"):
        assert_close(a, b, 1e-12, name)


# ---------------------------------------------------------------------------
# allow_reflection: the orthogonal fit (PyTorch3D's allow_reflection=True)
# ---------------------------------------------------------------------------


def _reflection_reference(x, y, w, scale):
    """Umeyama without the determinant correction, by SVD in float64: Q = U V^T
    of the weighted cross-covariance, s = sum of its singular values / var."""
    x, y, w = x.double(), y.double(), w.double()
    p = w / w.sum(-1, keepdim=True)
    x_mean, y_mean = (p[..., None] * x).sum(-2), (p[..., None] * y).sum(-2)
    xc, yc = x - x_mean[..., None, :], y - y_mean[..., None, :]
    M = (p[..., None] * yc).mT @ xc
    U, S, Vh = torch.linalg.svd(M)
    Q = U @ Vh
    s = S.sum(-1) / (p * xc.square().sum(-1)).sum(-1) if scale else torch.ones_like(S[..., 0])
    t = y_mean - s[..., None] * (Q @ x_mean[..., None]).squeeze(-1)
    return Q, t, s


@pytest.mark.parametrize("scale", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
def test_allow_reflection_fits_a_mirror_image(scale, dtype):
    gen = torch.Generator().manual_seed(31)
    x = torch.randn(6, 20, 3, generator=gen, dtype=torch.float64)
    mirror = torchrot.fit_orthogonal(torch.randn(6, 3, 3, generator=gen, dtype=torch.float64))
    mirror = mirror * torch.linalg.det(mirror).sign()[:, None, None] * -1  # det -1: reflections
    y = 1.7 * x @ mirror.mT + torch.randn(6, 1, 3, generator=gen, dtype=torch.float64)
    y = y + 0.01 * torch.randn(y.shape, generator=gen, dtype=torch.float64)
    w = torch.rand(6, 20, generator=gen, dtype=torch.float64) + 0.2
    x, y, w = x.to(dtype), y.to(dtype), w.to(dtype)
    Q, t, s = torchrot.rigid_registration(x, y, w, scale=scale, allow_reflection=True)
    assert (torch.linalg.det(Q.double()) < 0).all()
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    for got, want, what in zip((Q, t, s), _reflection_reference(x, y, w, scale), "Qts"):
        assert_close(got, want, tol * max(1.0, want.abs().max().item()), what)
    # without it: the nearest rotation, as before
    R = torchrot.rigid_registration(x, y, w, scale=scale).R
    assert (torch.linalg.det(R.double()) > 0).all()
    assert torch.equal(R, torchrot.rigid_registration(x, y, w, scale=scale, allow_reflection=False).R)


def test_allow_reflection_layer_and_warm_start():
    x, y, _ = registration_problem((4,), n=12, seed=32, noise=0.05)
    y = y * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)  # mirrored in z
    w = torch.rand(4, 12, generator=torch.Generator().manual_seed(33), dtype=torch.float64) + 0.2
    out = torchrot.rigid_registration(x, y, w, allow_reflection=True)
    layer = torchrot.nn.RigidRegistration(allow_reflection=True)
    for a, b in zip(layer(x, y, w), out):
        assert torch.equal(a, b)
    warm = torchrot.rigid_registration(x, y, w, init=out.R, allow_reflection=True)
    assert_close(warm.R, out.R, 1e-12, "R from its own warm start")
