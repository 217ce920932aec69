"""The operators on the Triton kernels as a user meets them: autograd through
the Triton backward (gradcheck, forward mode, torch.func), the nn layers and
rigid registration, a compiled caller, opcheck, and which kernels the devices
run (torchrot._device_kernels). CPU tensors under Triton's interpreter
(torchrot.testing.triton_kernel)."""
from __future__ import annotations

import pytest
import torch
from kernel_paths import TRITON_MARKS

import torchrot
from torchrot import _device_kernels
from torchrot.testing import (
    cpu_kernel,
    make_matrices,
    registration_problem,
    rotations,
    triton_kernel,
)

pytestmark = list(TRITON_MARKS)
op = torch.ops.torchrot


def test_backward_bit_identical_to_scalar_kernel(dtype):
    M = make_matrices("gaussian", 64, 50, dtype)
    G = make_matrices("gaussian", 64, 51, dtype)
    R = torchrot.fit_rotation(M)
    huge = G.clone()
    huge[3] *= 2.0 ** (torch.finfo(dtype).max.__trunc__().bit_length() // 2 + 2)  # the rescaling of a huge dL/dR
    for grad, eps in ((G, 0.0), (G, 1e-3), (huge, 1e-12)):
        with triton_kernel():
            triton = op.fit_rotation_backward(grad, R, M, eps)
        with cpu_kernel("scalar"):
            scalar = op.fit_rotation_backward(grad, R, M, eps)
        assert torch.equal(triton, scalar)


def test_gradcheck_through_the_triton_backward():
    """Reverse and forward mode through the Triton derivative kernel, well
    separated singular values (float64)."""
    M = make_matrices("rot60", 2, 52, torch.float64).requires_grad_()
    with triton_kernel():
        assert torch.autograd.gradcheck(torchrot.fit_rotation, (M,), check_forward_ad=True)


def test_torch_func_transforms():
    M = make_matrices("rot60", 8, 53, torch.float64)
    loss = lambda m: (torchrot.fit_rotation(m) * torch.arange(9.0, dtype=m.dtype).reshape(3, 3)).sum()
    with cpu_kernel("scalar"):
        expected = torch.func.grad(loss)(M), torch.func.vmap(torchrot.fit_rotation)(M.reshape(2, 4, 3, 3))
    with triton_kernel():
        got = torch.func.grad(loss)(M), torch.func.vmap(torchrot.fit_rotation)(M.reshape(2, 4, 3, 3))
    assert all(torch.equal(a, b) for a, b in zip(got, expected))


def test_nn_layers_and_registration():
    x, y, _ = registration_problem((4,), 30, 54, noise=0.01)[:3]
    v = make_matrices("gaussian", 16, 55, torch.float64).reshape(16, 9)

    def run():
        v_ = v.clone().requires_grad_()
        R = torchrot.nn.RotationFit()(v_)
        R.sum().backward()
        R2, t, s = torchrot.nn.RigidRegistration(scale=True)(x, y)
        return R, v_.grad, R2, t, s

    with cpu_kernel("scalar"):
        expected = run()
    with triton_kernel():
        got = run()
    assert all(torch.equal(a, b) for a, b in zip(got, expected))


def test_compiled_caller_has_no_graph_break():
    """torch.compile of a user's function that calls the operators: the fake
    kernels trace it, the Triton kernel runs as one opaque call."""
    M = make_matrices("uniform", 64, 56, torch.float32)
    f = lambda M: torchrot.fit_rotation(M) @ M.mT
    with triton_kernel():
        got = torch.compile(f, fullgraph=True)(M)
    torch._dynamo.reset()
    with cpu_kernel("scalar"):
        assert torch.equal(got, f(M))


@pytest.mark.parametrize("name", ["fit_rotation", "fit_rotation_info"])
def test_opcheck(name):
    M = make_matrices("rot60", 6, 57, torch.float64)
    init = rotations(6, 58, torch.float64)
    with triton_kernel():
        for args in ((M, None, None, "conservative"), (M.mT, init, 1, "newton"), (M.float(), init, 3, "gershgorin")):
            torch.library.opcheck(getattr(op, name).default, args)


def test_devices_run_triton_where_it_has_a_backend(monkeypatch):
    """CUDA and XPU tensors run the Triton kernels where Triton has a backend
    for them (decided at the device's first call), the device-generic ones
    elsewhere and on MPS; every device type has the operators registered."""
    from triton.backends import backends

    from torchrot.triton.operators import TRITON_KERNELS

    monkeypatch.setattr(_device_kernels, "_chosen", {})
    for device_type, names in _device_kernels.TRITON_BACKENDS.items():
        expected = TRITON_KERNELS if any(name in backends for name in names) else _device_kernels.GENERIC_KERNELS
        assert _device_kernels.kernels_for(device_type) is expected
    assert _device_kernels.kernels_for("mps") is _device_kernels.GENERIC_KERNELS
    monkeypatch.setattr(_device_kernels, "_chosen", {})
    monkeypatch.setattr(_device_kernels.importlib.util, "find_spec", lambda name: None)
    assert _device_kernels.kernels_for("cuda") is _device_kernels.GENERIC_KERNELS
    for name in _device_kernels.OPERATOR_NAMES:
        for key in ("CUDA", "XPU", "MPS"):
            assert torch._C._dispatch_has_kernel_for_dispatch_key(f"torchrot::{name}", key)


def test_interpreter_fma_rounds_once():
    """torchrot.testing.triton_interpreter's use of Triton's private
    interpreter classes, on the installed Triton: the probe of tl.fma's
    rounding answers, and under fma_rounded_once it rounds once (Triton 3.6's
    interpreter rounds twice; 3.9's once)."""
    from triton.runtime.interpreter import interpreter_builder

    from torchrot.testing.triton_interpreter import fma_rounded_once, fma_rounds_once

    assert isinstance(fma_rounds_once(interpreter_builder), bool)
    with fma_rounded_once():
        assert fma_rounds_once(interpreter_builder)
