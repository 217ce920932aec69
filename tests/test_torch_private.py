"""The private torch names torchrot uses, each checked for what torchrot
relies on, on the installed torch: Python's (torchrot/_torch_private.py) and
C++'s (csrc/torch_internals.h, through the extension's test-only functions
torchrot._C._torch_internals_*, one per wrapper). CI runs this on the oldest
and the newest supported release, so that a name that moves or changes fails
here, loudly, rather than in a user's torch.func transform.

Also: no other module of torchrot reaches into torch's private modules, and
no other source of csrc/ names torch's internals."""
from __future__ import annotations

import pathlib
import re
import warnings

import pytest
import torch
from torch.autograd import forward_ad

import torchrot
from torchrot import _C
from torchrot import _torch_private as private

PACKAGE = pathlib.Path(torchrot.__file__).parent
CSRC = pathlib.Path(__file__).resolve().parents[1] / "csrc"
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


# The C++ side: csrc/torch_internals.h, one test per wrapper.

#: What names a torch internal in C++: impl and detail namespaces, thread-local
#: state, underscored Tensor methods, the Python bindings of torch/csrc.
CPP_INTERNAL = re.compile(
    r"\b(?:at|c10)::(?:impl|detail)::|\bget_tls_state\b|\btls_\w+|\._fw_grad\b|\bTHP\w+|"
    r"\b(?:END_)?HANDLE_TH_ERRORS\b|torch/csrc/(?!autograd/custom_function\.h)")


@pytest.mark.skipif(not CSRC.is_dir(), reason="needs the source tree")
def test_no_other_source_uses_torch_internals():
    """Outside csrc/torch_internals.h, csrc/ names no torch internal (comments
    aside): the rest of the C++ side calls the wrappers."""
    offenders = []
    for path in sorted(CSRC.rglob("*")):
        if path.suffix not in (".h", ".cpp") or path.name == "torch_internals.h":
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if CPP_INTERNAL.search(line.split("//")[0]):
                offenders.append(f"{path.relative_to(CSRC)}:{number}: {line.strip()}")
    assert not offenders, "\n".join(offenders)
    header = (CSRC / "torch_internals.h").read_text()
    for name in ("tls_local_dispatch_key_set", "get_tls_state", "at::impl::torch_function_mode_enabled", "_fw_grad",
                 "at::detail::computeStride", "THPVariable_CheckExact", "THPVariable_Unpack", "THPVariable_Wrap",
                 "HANDLE_TH_ERRORS", "END_HANDLE_TH_ERRORS"):
        assert name in header, name


def test_cpp_functorch_transforms_active():
    """torch_internals::functorch_transforms_active (the dispatch keys of
    c10::impl::tls_local_dispatch_key_set) agrees with torch's own test,
    outside and inside transforms."""
    seen = []

    def probe(x):
        seen.append((_C._torch_internals_functorch_transforms_active(), private.functorch_transforms_active()))
        return x.sum()

    assert _C._torch_internals_functorch_transforms_active() is False
    torch.func.grad(probe)(M)
    torch.func.vmap(probe)(M)
    assert seen == [(True, True), (True, True)]
    assert _C._torch_internals_functorch_transforms_active() is False


def test_cpp_forward_grad_mode_enabled():
    """torch_internals::forward_grad_mode_enabled
    (c10::AutogradState::get_tls_state().get_fw_grad_mode()) follows torch's
    switch of forward-mode AD."""
    assert _C._torch_internals_forward_grad_mode_enabled() is True
    previous = torch._C._is_fwd_grad_enabled()
    torch._C._set_fwd_grad_enabled(False)
    try:
        assert _C._torch_internals_forward_grad_mode_enabled() is False
    finally:
        torch._C._set_fwd_grad_enabled(previous)
    assert _C._torch_internals_forward_grad_mode_enabled() is True


def test_cpp_torch_function_mode_enabled():
    """torch_internals::torch_function_mode_enabled
    (at::impl::torch_function_mode_enabled) sees a Python torch function mode."""

    class Mode(torch.overrides.TorchFunctionMode):
        def __torch_function__(self, func, types, args=(), kwargs=None):
            return func(*args, **(kwargs or {}))

    assert _C._torch_internals_torch_function_mode_enabled() is False
    with Mode():
        assert _C._torch_internals_torch_function_mode_enabled() is True
    assert _C._torch_internals_torch_function_mode_enabled() is False


def test_cpp_forward_tangent():
    """torch_internals::forward_tangent (Tensor::_fw_grad) gives the tangent of
    a dual tensor at level 0, and none for a plain one."""
    tangent = torch.randn_like(M)
    assert _C._torch_internals_forward_tangent(M) is None
    with forward_ad.dual_level():
        dual = forward_ad.make_dual(M, tangent)
        assert torch.equal(_C._torch_internals_forward_tangent(dual), tangent)
        assert _C._torch_internals_forward_tangent(M) is None


def test_cpp_view_strides():
    """torch_internals::view_strides (at::detail::computeStride) gives the
    strides Tensor.view gives, and None exactly where view raises, for the
    batch views of csrc/ops/layout.cpp."""
    base = torch.zeros(4, 6, 3, 3)
    tensors = [base, base.transpose(0, 1), base[:, ::2], base.permute(2, 3, 0, 1).contiguous().permute(2, 3, 0, 1),
               base.mT, base[:1].expand(4, 6, 3, 3), base.unsqueeze(1)]
    shapes = [(-1, 3, 3), (4, 6, 3, 3), (4, -1, 3, 3), (8, 3, 3, 3)]
    checked = 0
    for t in tensors:
        for shape in shapes:
            new = list(shape)
            if -1 in new:
                new[new.index(-1)] = t.numel() // (-torch.tensor(shape).prod().item())
            if torch.Size(new).numel() != t.numel():
                continue
            try:
                expected = tuple(t.view(new).stride())
            except RuntimeError:
                expected = None
            assert _C._torch_internals_view_strides(t.shape, t.stride(), new) == expected, (t.stride(), new)
            checked += 1
    assert checked >= 20


def test_cpp_is_exact_tensor():
    """torch_internals::is_exact_tensor (THPVariable_CheckExact): a tensor or
    a Parameter, not a subclass nor anything else."""

    class Sub(torch.Tensor):
        pass

    assert _C._torch_internals_is_exact_tensor(M) is True
    assert _C._torch_internals_is_exact_tensor(torch.nn.Parameter(M.clone())) is True
    assert _C._torch_internals_is_exact_tensor(M.as_subclass(Sub)) is False
    assert _C._torch_internals_is_exact_tensor(M.numpy()) is False
    assert _C._torch_internals_is_exact_tensor(None) is False


def test_cpp_unpack_tensor():
    """torch_internals::unpack_tensor (THPVariable_Unpack) gives the tensor of
    the Python object: its data and sizes."""
    view = M[1:, :, 1]
    assert _C._torch_internals_unpack_tensor(view) == (view.data_ptr(), tuple(view.shape))
    assert _C._torch_internals_unpack_tensor(M) == (M.data_ptr(), tuple(M.shape))


def test_cpp_wrap_tensor():
    """torch_internals::wrap_tensor (THPVariable_Wrap) gives a tensor's own
    Python object back, and a new torch.Tensor for a new tensor."""
    same, copy = _C._torch_internals_wrap_tensor(M)
    assert same is M
    assert type(copy) is torch.Tensor and copy is not M and torch.equal(copy, M)
    assert copy.data_ptr() != M.data_ptr()


@pytest.mark.parametrize(("kind", "error"), [("runtime", RuntimeError), ("value", ValueError), ("type", TypeError),
                                             ("index", IndexError)])
def test_cpp_torch_errors(kind, error):
    """TORCHROT_BEGIN_TORCH_ERRORS / TORCHROT_END_TORCH_ERRORS (HANDLE_TH_ERRORS,
    END_HANDLE_TH_ERRORS) raise TORCH_CHECK's errors as the Python exceptions
    docs/errors.md promises, with their messages, and TORCH_WARN as a warning."""
    with pytest.raises(error, match=f"torchrot test error: {kind}"):
        _C._torch_internals_raise(kind)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert _C._torch_internals_raise("warn") is None
    assert [str(w.message).startswith("torchrot test warning") for w in caught] == [True]

