"""torchrot on accelerators: CUDA and XPU tensors run torchrot's Triton
kernels (torchrot.triton) where Triton has a backend for them, MPS tensors
(and the others without Triton) the device-generic kernels
(torchrot.generic). Each test runs on every accelerator present and is
skipped where there is none (CI's machines have no GPU;
benchmarks/gpu_check.sh runs them on a lent one). The same kernels run on
CPU tensors in tests/test_triton_kernels.py (under Triton's interpreter) and
tests/test_generic_path.py.

Answers are compared with the C++ kernel on the CPU: the same status codes,
the accuracy criteria of testing.CRITERIA, NaN exactly where the input had
it; on the Triton kernels, which round as the scalar kernel does, the same
iteration counts and (but for the fallback's matrices) results within an
ulp or two, most of them bit for bit.
"""
from __future__ import annotations

import warnings

import pytest
import torch

import torchrot
from torchrot import _device_kernels
from torchrot.reference import fit_rotation_backward_reference
from torchrot.testing import DISTRIBUTIONS, cpu_kernel, dtype_id, edge_case_matrices, make_matrices, make_warm_start


def _accelerators() -> list[str]:
    present = []
    if torch.cuda.is_available():
        present.append("cuda")
    if hasattr(torch, "xpu") and torch.xpu.is_available():
        present.append("xpu")
    if torch.backends.mps.is_available():
        present.append("mps")
    return present


ACCELERATORS = _accelerators()
DEVICES = ACCELERATORS or [pytest.param("cuda", marks=pytest.mark.skip(reason="no accelerator (CUDA, XPU, MPS)"))]
N = 2048


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param


def _dtypes(device: str):
    return (torch.float32,) if device == "mps" else (torch.float32, torch.float64)


@pytest.mark.parametrize("name", list(DISTRIBUTIONS) + ["edge_cases"])
def test_fit_matches_cpu_kernel(device, name, assert_meets_criteria):
    for dtype in _dtypes(device):
        M = edge_case_matrices(dtype) if name == "edge_cases" else make_matrices(name, N, 31, dtype)
        finite = torch.isfinite(M).all(-1).all(-1)
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # a failed compile falls back with a warning
            R, iterations, status = torchrot.fit_rotation_info(M.to(device))
        assert R.device.type == device and R.dtype == dtype
        R_cpu, _, status_cpu = torchrot.fit_rotation_info(M)
        assert torch.equal(status.cpu(), status_cpu)
        assert torch.isnan(R.cpu()[~finite]).all() and torch.isfinite(R.cpu()[finite]).all()
        assert_meets_criteria(R.cpu()[finite], M[finite], dtype, f"{device} {dtype_id(dtype)} {name}")


@pytest.mark.parametrize("max_iter", [1, 3])
def test_warm_start_matches_cpu_kernel(device, max_iter):
    for dtype in _dtypes(device):
        M = make_matrices("warm", N, 32, dtype)
        init = torchrot.fit_rotation(M + 0.05 * make_matrices("gaussian", N, 33, dtype))
        R = torchrot.fit_rotation(M.to(device), init.to(device), max_iter=max_iter)
        tol = 1e-4 if dtype == torch.float32 else 1e-10
        torch.testing.assert_close(R.cpu(), torchrot.fit_rotation(M, init, max_iter=max_iter), rtol=0, atol=tol)


def test_backward_matches_cpu_kernel(device):
    for dtype in _dtypes(device):
        M = make_matrices("gaussian", N, 34, dtype)
        G = make_matrices("gaussian", N, 35, dtype)
        M_dev = M.to(device).detach().requires_grad_()
        (torchrot.fit_rotation(M_dev) * G.to(device)).sum().backward()
        M_cpu = M.detach().clone().requires_grad_()
        (torchrot.fit_rotation(M_cpu) * G).sum().backward()
        exact = fit_rotation_backward_reference(G.double(), torchrot.fit_rotation(M.double()), M.double())
        rel = lambda g, exact=exact: ((g.double().cpu() - exact).norm(dim=(-2, -1))
                                      / exact.norm(dim=(-2, -1))).median().item()
        assert rel(M_dev.grad) <= 3 * rel(M_cpu.grad) + 10 * torch.finfo(dtype).eps


def test_out_and_errors(device):
    M = make_matrices("rot60", 64, 36, torch.float32).to(device)
    out = torch.full_like(M, 7.0)
    torchrot.fit_rotation(M, out=out)
    torch.testing.assert_close(out.cpu(), torchrot.fit_rotation(M.cpu()), rtol=0, atol=1e-5)
    bad = torch.eye(3, device=device).expand(64, 3, 3).clone()
    bad[5] *= 2
    before = out.clone()
    with pytest.raises(ValueError, match=r"init must hold rotations.*1 of 64 are not"):
        torchrot.fit_rotation(M, bad, max_iter=1, out=out)
    assert torch.equal(out, before)  # an error changes nothing


def test_compiled_caller(device):
    """Inside a compiled function the operator runs as one opaque call."""
    M = make_matrices("uniform", 256, 37, torch.float32).to(device)
    f = torch.compile(lambda M: torchrot.fit_rotation(M) @ M.mT, fullgraph=True)
    torch.testing.assert_close(f(M).cpu(), (torchrot.fit_rotation(M.cpu()) @ M.cpu().mT), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("mode", ["cold", "warm", "one step", "max_iter=3"])
@pytest.mark.parametrize("name", ["uniform", "gaussian", "warm", "rot60", "rank2"])
def test_triton_kernels_round_as_the_scalar_kernel(device, name, mode):
    """Where the Triton kernels run: the scalar kernel's iteration counts and
    statuses, and its results to within 4 ulps (bit for bit but where a
    subnormal intermediate is flushed on the CPU and kept on the GPU, and on
    the fallback's matrices, which the criteria check above)."""
    if _device_kernels.kernels_for(torch.device(device).type) is _device_kernels.GENERIC_KERNELS:
        pytest.skip(f"{device} tensors run the device-generic kernels here")
    for dtype in _dtypes(device):
        M, init = make_warm_start(name, N, 38, dtype)
        args = {"cold": (M, None, None), "warm": (M, init, None), "one step": (M, init, 1),
                "max_iter=3": (M, None, 3)}[mode]
        R, iterations, status = torchrot.fit_rotation_info(*(a.to(device) if a is not None else None
                                                             for a in args[:2]), max_iter=args[2])
        with cpu_kernel("scalar"):
            R_cpu, iterations_cpu, status_cpu = torchrot.fit_rotation_info(*args[:2], max_iter=args[2])
        assert torch.equal(status.cpu(), status_cpu) and torch.equal(iterations.cpu(), iterations_cpu)
        cayley = status_cpu == 0
        torch.testing.assert_close(R.cpu()[cayley], R_cpu[cayley], rtol=0, atol=4 * torch.finfo(dtype).eps)
        same = (R.cpu() == R_cpu).flatten(-2).all(-1)[cayley].float().mean().item()
        assert same >= 0.99, f"{dtype_id(dtype)}: {same:.4f} of the results bit for bit"
