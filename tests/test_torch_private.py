"""The private torch names torchrot uses (torchrot/_torch_private.py), each
checked for what torchrot relies on, on the installed torch: CI runs this on
the oldest and the newest supported release, so that a name that moves or
changes fails here, loudly, rather than in a user's torch.func transform.

Also: no other module of torchrot reaches into torch's private modules."""
from __future__ import annotations

import pathlib
import re

import torch
from torch.autograd import forward_ad

import torchrot
from torchrot import _torch_private as private

PACKAGE = pathlib.Path(torchrot.__file__).parent
M = torch.randn(6, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))


def test_every_name_is_exported_and_exists():
    for name in private.__all__:
        assert getattr(private, name) is not None, name


def test_no_other_module_uses_private_torch_names():
    """Private torch modules and attributes (torch._X, torch.x._y) appear only
    in _torch_private.py."""
    pattern = re.compile(r"\btorch(\.[A-Za-z]\w*)*\._[A-Za-z]\w*|forward_ad\._\w+")
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.name == "_torch_private.py":
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#")[0].replace("torch.__version__", "")
            if any(not m.group(0).startswith("torch.ops.") for m in pattern.finditer(code)):
                offenders.append(f"{path.relative_to(PACKAGE)}:{number}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_below_autograd_and_keysets():
    x = M.clone().requires_grad_()
    with private.below_autograd():
        assert not torch.ops.torchrot.fit_rotation(x).requires_grad
    keys = torch._C._dispatch_keys(x)
    assert not (keys & private.after_autograd_keyset).has(torch._C.DispatchKey.AutogradCPU)
    assert (keys & private.after_autograd_keyset).has(torch._C.DispatchKey.CPU)
    assert private.any_requires_grad(M, x) and not private.any_requires_grad(M, 1.0)


def test_forward_mode_state():
    assert private.forward_level() == -1 and private.forward_grad_enabled()
    with forward_ad.dual_level():
        assert private.forward_level() == 0
    assert private.forward_level() == -1
    with private.forward_grad_mode(False):
        assert not private.forward_grad_enabled()
        with private.forward_grad_mode(True):
            assert private.forward_grad_enabled()
        assert not private.forward_grad_enabled()
    assert private.forward_grad_enabled()
    with forward_ad.dual_level(), private.forward_grad_mode(False):  # no tangent is recorded
        assert forward_ad.unpack_dual(forward_ad.make_dual(M, M) * 2).tangent is None


def test_functorch_state_inside_transforms():
    seen = {}

    def probe(x):
        seen["active"] = private.functorch_transforms_active()
        seen["excluded"] = private.functorch_front_excluded()
        seen["wrapped"] = private.is_functorch_wrapped(x)
        return x.sum()

    assert not private.functorch_transforms_active() and not private.is_functorch_wrapped(M)
    torch.func.vmap(torch.func.grad(probe))(M)
    assert seen["active"] and seen["wrapped"] and not seen["excluded"]


def test_functorch_front_excluded_inside_an_autograd_kernel_of_a_level(monkeypatch):
    """Where the operators' Python Autograd kernel runs for one torch.func
    level (FitRotationFunction's forward and jvp rule), the front key is
    excluded: torchrot._autograd then dispatches past the Autograd keys to
    reach the levels below (second derivatives)."""
    seen = []
    original = torchrot._autograd._at_levels_below

    def spy(op, *args):
        seen.append(private.functorch_front_excluded())
        return original(op, *args)

    monkeypatch.setattr(torchrot._autograd, "_at_levels_below", spy)
    torch.func.jvp(torchrot.fit_rotation, (M,), (M,))
    assert seen and all(seen)


def test_single_level_function_records_at_each_level():
    """A single-level Function applied in an Autograd kernel gives the first
    derivatives of every transform (torch 2.14 routes Function.apply under
    torch.func to custom_function_call, which raised there)."""
    x = M.clone()
    expected = torch.autograd.functional.jacobian(lambda m: torchrot.fit_rotation(m).sum(), x)
    assert torch.allclose(torch.func.grad(lambda m: torchrot.fit_rotation(m).sum())(x), expected)
    tangent = torch.randn_like(x)
    _, jvp = torch.func.jvp(torchrot.fit_rotation, (x,), (tangent,))
    _, vjp_fn = torch.func.vjp(torchrot.fit_rotation, x)
    assert torch.allclose((jvp * tangent).sum(), (vjp_fn(tangent)[0] * tangent).sum())  # self-adjoint
    single = private.single_level_function(torchrot._autograd.FitRotationFunction)
    assert single.__name__ == "FitRotationFunction"
    assert issubclass(single, torch.autograd.function._SingleLevelFunction)


def test_autocast_available_traces_as_a_constant():
    """torch.compile(fullgraph=True) traces autocast_available (torch 2.11's
    dynamo cannot trace torch.amp.is_autocast_available) and gives its eager
    answer: CPU has autocast, meta has none."""
    assert private.autocast_available("cpu") and not private.autocast_available("meta")

    @torch.compile(fullgraph=True, backend="eager")
    def available(x):
        return x + 1, private.autocast_available(x.device.type)

    assert available(torch.zeros(2))[1] is True
    assert available(torch.zeros(2, device="meta"))[1] is False


def test_non_overlapping_and_dense():
    assert private.is_non_overlapping_and_dense(M) and private.is_non_overlapping_and_dense(M.mT)
    assert not private.is_non_overlapping_and_dense(M[::2])
    assert not private.is_non_overlapping_and_dense(M[:1].expand(3, 3, 3))


def test_unwrap_dead_wrappers_and_single_level_mode():
    assert private.unwrap_dead_wrappers((M,))[0] is M
    with private.enable_single_level_autograd_function():
        pass
