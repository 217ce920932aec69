"""torchrot.nn: RotationFit and RigidRegistration modules: values, the (..., 9)
input path, argument errors, pickling / state_dict, DistributedDataParallel
(gloo, 2 CPU processes) and (once fit_rotation has autograd) gradients."""
from __future__ import annotations

import copy
import math
import os
import pickle

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import nn

import torchrot
from torchrot.nn import RigidRegistration, RotationFit
from torchrot.testing import make_matrices, random_rotations


def gaussian(batch, seed=0, dtype=torch.float64):
    return make_matrices("gaussian", math.prod(batch), seed, dtype).reshape(*batch, 3, 3)


# ---------------------------------------------------------------------------
# RotationFit
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("batch", [(), (5,), (2, 4)], ids=str)
def test_rotation_fit_matches_fit_rotation(batch, dtype):
    M = gaussian(batch, 1, dtype)
    R = RotationFit()(M)
    assert R.shape == (*batch, 3, 3) and R.dtype == dtype
    assert torch.equal(R, torchrot.fit_rotation(M))


@pytest.mark.parametrize("batch", [(), (5,), (2, 4)], ids=str)
def test_nine_vector_is_read_row_major(batch, dtype):
    M = gaussian(batch, 2, dtype)
    v = M.reshape(*batch, 9)
    assert torch.equal(v[..., 1], M[..., 0, 1])  # row-major, as reshape
    R = RotationFit()(v)
    assert R.shape == (*batch, 3, 3)
    assert torch.equal(R, torchrot.fit_rotation(M))
    # a non-contiguous (..., 9) view, as a slice of a wider network output
    wide = torch.cat([v, torch.zeros(*batch, 4, dtype=dtype)], -1)
    assert torch.equal(RotationFit()(wide[..., :9]), R)


def test_options_and_init_are_forwarded():
    M = gaussian((16,), 3)
    init = random_rotations(16, torch.Generator().manual_seed(4))
    layer = RotationFit(max_iter=1, variant="newton")
    expected = torchrot.fit_rotation(M, init, max_iter=1, variant="newton")
    assert torch.equal(layer(M, init), expected)
    assert torch.equal(layer(M.reshape(16, 9), init), expected)
    assert not torch.equal(layer(M, init), torchrot.fit_rotation(M))  # one step is not converged


CONSTRUCTOR_ERRORS = [
    ({"max_iter": 0}, ValueError, "max_iter must be None"),
    ({"max_iter": -3}, ValueError, "max_iter must be None"),
    ({"max_iter": 1001}, ValueError, r"max_iter must be None \(iterate to convergence\) or an int >= 1 and <= 1000"),
    ({"max_iter": 2.0}, TypeError, "max_iter must be None or an int"),
    ({"max_iter": True}, TypeError, "max_iter must be None or an int"),
    ({"variant": "svd"}, ValueError, "variant must be one of"),
    ({"gradient_eps": -1e-3}, ValueError, "gradient_eps must be a finite number >= 0"),
    ({"gradient_eps": float("nan")}, ValueError, "gradient_eps must be a finite number >= 0"),
    ({"gradient_eps": float("inf")}, ValueError, "gradient_eps must be a finite number >= 0"),
    ({"gradient_eps": "1e-3"}, TypeError, "gradient_eps must be a float >= 0"),
    ({"gradient_eps": True}, TypeError, "gradient_eps must be a float >= 0"),
]


@pytest.mark.parametrize("kwargs, error, message", CONSTRUCTOR_ERRORS, ids=str)
def test_rotation_fit_constructor_errors(kwargs, error, message):
    with pytest.raises(error, match=f"^RotationFit: {message}"):
        RotationFit(**kwargs)


def test_gradient_eps_default_applies_unless_set(monkeypatch):
    seen = []
    fit = torchrot.fit_rotation

    def recording_fit(M, init=None, **options):
        seen.append(dict(options))
        return fit(M, init, **options)

    M = gaussian((3,), 5)
    monkeypatch.setattr(torchrot.nn, "fit_rotation", recording_fit)
    RotationFit(gradient_eps=1e-4)(M)
    assert seen[-1]["gradient_eps"] == 1e-4
    RotationFit()(M)
    # fit_rotation's own default (None: torchrot.DEFAULT_GRADIENT_EPS), the one sentinel both share
    assert seen[-1].get("gradient_eps") is None


@pytest.mark.parametrize("shape", [(3,), (4, 3), (2, 3, 4), (8,), (10,)], ids=str)
def test_rotation_fit_rejects_other_shapes(shape):
    with pytest.raises(ValueError, match=r"M must have shape \(\.\.\., 3, 3\) or \(\.\.\., 9\)"):
        RotationFit()(torch.zeros(shape))


def test_rotation_fit_rejects_non_tensors():
    with pytest.raises(TypeError, match="M must be a torch.Tensor"):
        RotationFit()([[1.0, 0, 0], [0, 1, 0], [0, 0, 1]])


# ---------------------------------------------------------------------------
# RigidRegistration
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("scale", [False, True])
def test_rigid_registration_module_matches_function(scale, dtype):
    gen = torch.Generator().manual_seed(6)
    x = torch.randn(4, 12, 3, generator=gen, dtype=torch.float64).to(dtype)
    y = torch.randn(4, 12, 3, generator=gen, dtype=torch.float64).to(dtype)
    w = torch.rand(4, 12, generator=gen, dtype=torch.float64).to(dtype)
    out = RigidRegistration(scale=scale)(x, y, w)
    ref = torchrot.rigid_registration(x, y, w, scale=scale)
    assert isinstance(out, torchrot.RigidTransform)
    for a, b in zip(out, ref):
        assert torch.equal(a, b)
    init = ref.R
    warm = RigidRegistration(scale=scale)(x, y, init=init)
    assert torch.allclose(warm.R, torchrot.rigid_registration(x, y, scale=scale).R, atol=1e-5)


def test_rigid_registration_constructor_error():
    with pytest.raises(TypeError, match="^RigidRegistration: scale must be a bool"):
        RigidRegistration(scale=1)


# ---------------------------------------------------------------------------
# Module hygiene: pickle, state_dict, repr
# ---------------------------------------------------------------------------

MODULES = [
    lambda: RotationFit(),
    lambda: RotationFit(max_iter=2, variant="gershgorin"),
    lambda: RigidRegistration(),
    lambda: RigidRegistration(scale=True),
]


@pytest.mark.parametrize("make", MODULES, ids=["fit", "fit-options", "registration", "registration-scale"])
def test_modules_are_stateless_and_picklable(make):
    module = make()
    assert list(module.parameters()) == [] and list(module.buffers()) == []
    assert module.state_dict() == {}
    module.load_state_dict({}, strict=True)
    for clone in (pickle.loads(pickle.dumps(module)), copy.deepcopy(module)):
        assert type(clone) is type(module) and repr(clone) == repr(module)
        assert vars(clone).keys() == vars(module).keys()


def test_extra_repr():
    assert repr(RotationFit(max_iter=1, variant="newton")) == \
        "RotationFit(max_iter=1, variant='newton', gradient_eps=None)"
    assert repr(RigidRegistration(scale=True)) == "RigidRegistration(scale=True, allow_reflection=False)"
    assert repr(RigidRegistration(allow_reflection=True)) == "RigidRegistration(scale=False, allow_reflection=True)"
    model = nn.Sequential(nn.Linear(4, 9), RotationFit())
    assert "RotationFit(max_iter=None" in repr(model)
    assert set(model.state_dict()) == {"0.weight", "0.bias"}


def test_pickled_model_gives_the_same_output():
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(4, 9), RotationFit())
    x = torch.randn(7, 4)
    clone = pickle.loads(pickle.dumps(model))
    assert torch.equal(clone(x), model(x))


# ---------------------------------------------------------------------------
# Gradients (need fit_rotation's autograd)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("data", ["rot60", "rot180"])
def test_gradient_matches_svd_autograd(data):
    """d(sum G * R)/dM through RotationFit vs autograd through float64 SVD, on
    matrices with well-separated singular values (where the SVD gradient exists)
    and sigma_i + sigma_j well away from 0 (a rotation times a stretch of
    condition number 10)."""
    M = make_matrices(data, 64, seed=7)
    G = torch.randn(64, 3, 3, generator=torch.Generator().manual_seed(8), dtype=torch.float64)

    def grad_of(fn, M):
        M = M.clone().requires_grad_()
        (fn(M) * G).sum().backward()
        return M.grad

    ours = grad_of(RotationFit(), M)
    reference = grad_of(torchrot.rotation_svd, M)
    assert torch.isfinite(ours).all()
    err = ((ours - reference).norm(dim=(-2, -1)) / reference.norm(dim=(-2, -1)).clamp_min(1e-300)).max().item()
    assert err < 1e-8, f"relative gradient error {err:.3g}"
    # the (..., 9) path gives the same gradient, reshaped
    assert torch.allclose(grad_of(lambda m: RotationFit()(m.reshape(64, 9)), M), ours, rtol=0, atol=0)


def test_gradient_float32_close_to_float64():
    M = make_matrices("rot60", 64, seed=9)
    G = torch.randn(64, 3, 3, generator=torch.Generator().manual_seed(10), dtype=torch.float64)
    grads = []
    for dtype in (torch.float32, torch.float64):
        Mi = M.to(dtype).requires_grad_()
        (RotationFit()(Mi.reshape(64, 9)) * G.to(dtype)).sum().backward()
        grads.append(Mi.grad.double())
    assert torch.allclose(grads[0], grads[1], rtol=1e-3, atol=1e-4)


# ---------------------------------------------------------------------------
# DistributedDataParallel (gloo, 2 processes)
# ---------------------------------------------------------------------------

WORLD = 2


def _make_model() -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(6, 9, dtype=torch.float64), RotationFit())


def _rank_data(rank: int):
    gen = torch.Generator().manual_seed(100 + rank)
    inputs = torch.randn(8, 6, generator=gen, dtype=torch.float64)
    targets = random_rotations(8, gen)
    return inputs, targets


def _loss(R, targets):
    return (R - targets).square().sum((-2, -1)).mean()


def _ddp_worker(rank: int, init_file: str, result_file: str, train: bool) -> None:
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=WORLD)
    try:
        model = nn.parallel.DistributedDataParallel(_make_model())
        inputs, targets = _rank_data(rank)
        R = model(inputs)
        result = {"R": R.detach()}
        if train:
            _loss(R, targets).backward()
            result["grads"] = [p.grad.clone() for p in model.parameters()]
            torch.optim.SGD(model.parameters(), lr=0.1).step()
            result["params"] = [p.detach().clone() for p in model.parameters()]
        torch.save(result, f"{result_file}.{rank}")
    finally:
        dist.destroy_process_group()
    # Leave without the interpreter's teardown: under torch 2.12.1 a gloo
    # thread still joinable then aborted the process ("terminate called
    # without an active exception") in 2 of 10 runs, after its results were
    # saved; with os._exit, 0 of 20. An exception above still fails the spawn.
    os._exit(0)


@pytest.fixture(scope="module")
def ddp_results(tmp_path_factory):
    """One spawn of 2 gloo processes, each with its own data; trains one step
    when fit_rotation has autograd."""
    M = torch.randn(3, 3, dtype=torch.float64).requires_grad_()
    grad_fn = torchrot.fit_rotation(M).grad_fn
    train = grad_fn is not None and "NotImplemented" not in grad_fn.name()
    folder = tmp_path_factory.mktemp("ddp")
    result_file = str(folder / "result")
    mp.spawn(_ddp_worker, args=(str(folder / "init"), result_file, train), nprocs=WORLD, join=True)
    return [torch.load(f"{result_file}.{rank}") for rank in range(WORLD)]


@pytest.mark.slow  # spawns 2 processes (~5 s)
def test_ddp_forward(ddp_results):
    model = _make_model()
    for rank, result in enumerate(ddp_results):
        inputs, _ = _rank_data(rank)
        assert torch.equal(result["R"], model(inputs).detach())


@pytest.mark.slow  # spawns 2 processes (~5 s)
def test_ddp_gradients_are_averaged(ddp_results):
    local = []
    for rank in range(WORLD):
        model = _make_model()
        inputs, targets = _rank_data(rank)
        _loss(model(inputs), targets).backward()
        local.append([p.grad for p in model.parameters()])
    expected = [sum(g) / WORLD for g in zip(*local)]
    for result in ddp_results:
        for got, want in zip(result["grads"], expected):
            assert torch.allclose(got, want, rtol=1e-10, atol=1e-12)
    for a, b in zip(ddp_results[0]["params"], ddp_results[1]["params"]):
        assert torch.equal(a, b)
