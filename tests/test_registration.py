"""torchrot.rigid_registration: recovery of known transforms, agreement with a
float64 SVD/Umeyama reference, weights, broadcasting, dtypes, errors, and (once
fit_rotation has autograd) gradients."""
from __future__ import annotations

import pytest
import torch

import torchrot
from torchrot.reference import rigid_registration_svd
from torchrot.testing import registration_problem

TOL = {torch.float32: 2e-5, torch.float64: 1e-11}


def umeyama_reference(x, y, weights=None, scale=False):
    """Independent float64 reference: Umeyama by SVD (torchrot.rigid_registration_svd)."""
    return rigid_registration_svd(x.double(), y.double(), None if weights is None else weights.double(), scale)


def assert_close(actual, expected, tol, what):
    err = (actual.double() - expected.double()).abs().max().item()
    assert err <= tol, f"{what}: max error {err:.3g} > {tol:g}"


# ---------------------------------------------------------------------------
# Values
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("scale", [False, True])
def test_recovers_known_transform_noiseless(dtype, scale):
    x, y, (R, t, s) = registration_problem((6,), seed=1, dtype=dtype, with_scale=scale)
    out = torchrot.rigid_registration(x, y, scale=scale)
    assert isinstance(out, torchrot.RigidTransform)
    assert out.R.shape == (6, 3, 3) and out.t.shape == (6, 3) and out.s.shape == (6,)
    assert out.R.dtype == out.t.dtype == out.s.dtype == dtype
    tol = TOL[dtype]
    assert_close(out.R, R, tol, "R")
    assert_close(out.s, s, tol, "s")
    assert_close(out.t, t, 20 * tol, "t")  # |t| ~ 3 and |x| ~ 4: absolute error scales with them
    if not scale:
        assert torch.equal(out.s, torch.ones(6, dtype=dtype))


@pytest.mark.parametrize("scale", [False, True])
def test_matches_umeyama_reference_on_noisy_data(dtype, scale):
    x, y, _ = registration_problem((20,), n=25, seed=2, noise=0.5, dtype=dtype)
    weights = torch.rand(20, 25, generator=torch.Generator().manual_seed(3), dtype=dtype) + 0.1
    out = torchrot.rigid_registration(x, y, weights, scale=scale)
    R, t, s = umeyama_reference(x, y, weights, scale)
    tol = TOL[dtype] * 10
    assert_close(out.R, R, tol, "R")
    assert_close(out.t, t, 20 * tol, "t")
    assert_close(out.s, s, tol, "s")


@pytest.mark.parametrize("scale", [False, True])
def test_points_far_from_the_origin_lose_no_accuracy(dtype, scale):
    """The covariance is of centred points: far from the origin, R and s are as
    accurate as near it (sum p y x^T - ȳ x̄^T would cancel ~|offset|^2 / spread^2
    of the digits: R off by ~0.3 in float32 here)."""
    x, y, _ = registration_problem((50,), n=40, seed=5, noise=0.1, dtype=torch.float64, with_scale=scale)
    offset = torch.tensor([1e3, -2e3, 5e2], dtype=torch.float64)
    x, y = (x + offset).to(dtype), (y - 2 * offset).to(dtype)
    out = torchrot.rigid_registration(x, y, scale=scale)
    R, t, s = umeyama_reference(x, y, scale=scale)  # on the same rounded points
    tol = TOL[dtype]
    assert_close(out.R, R, tol, "R")
    assert_close(out.s, s, tol, "s")
    assert_close(out.t, t, tol * offset.abs().sum().item(), "t")  # t = ȳ - s R x̄ carries R's error times |x̄|


def test_result_minimises_the_weighted_cost():
    """The returned (R, t, s) beats nearby perturbations of itself."""
    x, y, _ = registration_problem((), n=30, seed=4, noise=1.0)
    w = torch.rand(30, generator=torch.Generator().manual_seed(5), dtype=torch.float64)

    def cost(R, t, s):
        return (w * (s * x @ R.mT + t - y).square().sum(-1)).sum()

    R, t, s = torchrot.rigid_registration(x, y, w, scale=True)
    best = cost(R, t, s)
    gen = torch.Generator().manual_seed(6)
    for _ in range(20):
        dR = torchrot.fit_rotation(torch.eye(3, dtype=torch.float64) + 1e-3 * torch.randn(3, 3, generator=gen,
                                                                                              dtype=torch.float64))
        dt = 1e-3 * torch.randn(3, generator=gen, dtype=torch.float64)
        ds = 1e-3 * torch.randn((), generator=gen, dtype=torch.float64)
        assert cost(dR @ R, t + dt, s + ds) > best


def test_reflection_data_gives_a_rotation():
    """y a mirror image of x: the best *rotation* (det +1), as Umeyama's reference."""
    x, _, _ = registration_problem((), n=30, seed=7)
    y = x * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    out = torchrot.rigid_registration(x, y, scale=True)
    R, t, s = umeyama_reference(x, y, scale=True)
    assert torch.linalg.det(out.R).item() == pytest.approx(1.0, abs=1e-12)
    assert_close(out.R, R, 1e-10, "R")
    assert_close(out.t, t, 1e-10, "t")
    assert_close(out.s, s, 1e-10, "s")


# ---------------------------------------------------------------------------
# Weights
# ---------------------------------------------------------------------------


def test_zero_weights_drop_points(dtype):
    x, y, (R, t, s) = registration_problem((), n=20, seed=8, dtype=dtype)
    # wreck some points and give them zero weight
    y_bad = y.clone()
    y_bad[::3] += 100.0
    w = torch.ones(20, dtype=dtype)
    w[::3] = 0
    out = torchrot.rigid_registration(x, y_bad, w, scale=True)
    subset = torchrot.rigid_registration(x[w > 0], y_bad[w > 0], scale=True)
    tol = TOL[dtype] * 10
    for a, b, name in zip(out, subset, "Rts"):
        assert_close(a, b, 20 * tol, name)
    assert_close(out.R, R, tol, "R")


def test_weights_are_not_squared_and_scale_free():
    """Weight 2 on a point == the point listed twice; w and 10 w agree."""
    x, y, _ = registration_problem((), n=12, seed=9, noise=0.3)
    w = torch.ones(12, dtype=torch.float64)
    w[0] = 2.0
    doubled = torchrot.rigid_registration(torch.cat([x, x[:1]]), torch.cat([y, y[:1]]), scale=True)
    weighted = torchrot.rigid_registration(x, y, w, scale=True)
    scaled = torchrot.rigid_registration(x, y, 10 * w, scale=True)
    for a, b, c, name in zip(weighted, doubled, scaled, "Rts"):
        assert_close(a, b, 1e-11, name)
        assert_close(a, c, 1e-11, name)


def test_exactly_three_points():
    x, y, (R, t, s) = registration_problem((), n=3, seed=10)
    out = torchrot.rigid_registration(x, y, scale=True)
    assert_close(out.R, R, 1e-10, "R")
    assert_close(out.s, s, 1e-10, "s")


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
# Errors
# ---------------------------------------------------------------------------

_X = torch.randn(5, 10, 3, dtype=torch.float64)
_W = torch.ones(5, 10, dtype=torch.float64)

ERRORS = [
    ("x not a tensor", lambda: torchrot.rigid_registration(_X.tolist(), _X), TypeError, "x must be a torch.Tensor"),
    ("y wrong last dim", lambda: torchrot.rigid_registration(_X, _X[..., :2]), ValueError,
     r"y must have shape \(\.\.\., N, 3\)"),
    ("x 1-D", lambda: torchrot.rigid_registration(_X[0, 0], _X), ValueError, r"x must have shape"),
    ("N differs", lambda: torchrot.rigid_registration(_X, _X[:, :9]), ValueError, "same number of points"),
    ("integer x", lambda: torchrot.rigid_registration(_X.long(), _X.long()), TypeError, "x must be float32"),
    ("dtypes differ", lambda: torchrot.rigid_registration(_X, _X.float()), TypeError, "y must have x's dtype"),
    ("batch mismatch", lambda: torchrot.rigid_registration(_X, _X[:4]), ValueError,
     "batch dimensions must broadcast"),
    ("weights batch mismatch", lambda: torchrot.rigid_registration(_X, _X, _W[:3]), ValueError, "batch dimensions"),
    ("weights wrong N", lambda: torchrot.rigid_registration(_X, _X, _W[:, :9]), ValueError,
     r"weights must have shape \(\.\.\., N\)"),
    ("weights dtype", lambda: torchrot.rigid_registration(_X, _X, _W.float()), TypeError,
     "weights must have x's dtype"),
    ("weights not a tensor", lambda: torchrot.rigid_registration(_X, _X, [1.0] * 10), TypeError,
     "weights must be None or a torch.Tensor"),
    ("negative weight", lambda: torchrot.rigid_registration(_X, _X, _W - 2 * (torch.arange(10) == 4)), ValueError,
     "weights must be >= 0"),
    ("all-zero weights", lambda: torchrot.rigid_registration(_X, _X, _W * (torch.arange(5) != 3)[:, None]), ValueError,
     r"problem \(3,\).*all weights are zero"),
    ("two effective points", lambda: torchrot.rigid_registration(_X, _X, _W * (torch.arange(10) < 2)), ValueError,
     r"at least 3 points of nonzero weight.*only 2 point"),
    ("two points", lambda: torchrot.rigid_registration(_X[:, :2], _X[:, :2]), ValueError,
     "at least 3 points, got N = 2"),
    ("scale not bool", lambda: torchrot.rigid_registration(_X, _X, scale=1), TypeError, "scale must be a bool"),
    ("coincident x with scale", lambda: torchrot.rigid_registration(_X[:, :1].expand(5, 10, 3), _X, scale=True),
     ValueError, "must not all coincide"),
]


@pytest.mark.parametrize("what, call, error, message", ERRORS, ids=[e[0] for e in ERRORS])
def test_errors(what, call, error, message):
    with pytest.raises(error, match=message):
        call()


def test_errors_name_the_function():
    with pytest.raises(ValueError, match=r"^torchrot\.rigid_registration: "):
        torchrot.rigid_registration(_X, _X[:, :9])


def test_nan_stays_in_its_problem():
    x, y, (R, _, _) = registration_problem((3,), n=10, seed=17, with_scale=False)
    y = y.clone()
    y[1, 4, 0] = float("nan")
    out = torchrot.rigid_registration(x, y)
    assert torch.isnan(out.R[1]).all() and torch.isnan(out.t[1]).all()
    assert_close(out.R[[0, 2]], R[[0, 2]], 1e-12, "R of the other problems")


# ---------------------------------------------------------------------------
# Gradients (need fit_rotation's autograd)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("scale", [False, True])
def test_gradcheck(scale):
    x, y, _ = registration_problem((2,), n=6, seed=18, noise=0.3)
    w = torch.rand(2, 6, generator=torch.Generator().manual_seed(19), dtype=torch.float64) + 0.5
    inputs = tuple(t.clone().requires_grad_() for t in (x, y, w))

    def fn(x, y, w):
        return tuple(torchrot.rigid_registration(x, y, w, scale=scale))

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("scale", [False, True])
def test_gradients_match_svd_reference(scale):
    x, y, _ = registration_problem((16,), n=20, seed=20, noise=0.5)
    w = torch.rand(16, 20, generator=torch.Generator().manual_seed(21), dtype=torch.float64) + 0.1
    gen = torch.Generator().manual_seed(22)
    probes = [torch.randn(16, *shape, generator=gen, dtype=torch.float64) for shape in ((3, 3), (3,), ())]

    def grads(fn):
        leaves = [t.clone().requires_grad_() for t in (x, y, w)]
        outputs = fn(*leaves, scale=scale)
        loss = sum((o * p).sum() for o, p in zip(outputs, probes))
        return torch.autograd.grad(loss, leaves)

    ours = grads(torchrot.rigid_registration)
    reference = grads(umeyama_reference)
    for a, b, name in zip(ours, reference, ("x", "y", "weights")):
        assert torch.isfinite(a).all()
        assert_close(a, b, 1e-9 * max(1.0, b.abs().max().item()), f"d/d{name}")


def test_torch_func_vmap_and_grad():
    """vmap over problems equals the batched call; func.grad equals autograd
    (the value checks are skipped inside the transforms)."""
    x, y, _ = registration_problem((4,), n=10, seed=23, noise=0.3)
    w = torch.rand(4, 10, generator=torch.Generator().manual_seed(24), dtype=torch.float64) + 0.1

    def fn(x, y, w):
        return tuple(torchrot.rigid_registration(x, y, w, scale=True))

    for a, b in zip(torch.func.vmap(fn)(x, y, w), fn(x, y, w)):
        assert_close(a, b, 1e-13, "vmap")
    grad = torch.func.grad(lambda x: torchrot.rigid_registration(x, y[0], w[0], scale=True).t.sum())(x[0])
    leaf = x[0].clone().requires_grad_()
    torchrot.rigid_registration(leaf, y[0], w[0], scale=True).t.sum().backward()
    assert_close(grad, leaf.grad, 1e-13, "func.grad")
