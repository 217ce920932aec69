"""Shared fixtures for the torchrot tests.

Test data always comes from ``torchrot.testing`` (the distributions, edge cases
and metrics shared with the benchmarks); this file only holds the parameter
lists and small helpers that several test modules use; the helpers of one family
of test modules are in its own module (tests/isa_helpers.py for tests/test_isa_*.py, ...).
"""
from __future__ import annotations

import functools
import importlib.util

import pytest
import torch
from fits import FITS, Fit

import torchrot  # noqa: F401  (registers torch.ops.torchrot.*)
from torchrot._constants import VARIANTS
from torchrot.testing import CRITERIA, dtype_id, make_matrices, rotation_errors
from torchrot.testing import cpu_kernel as forced_kernel
from torchrot.testing.triton_interpreter import triton_interpreter

# The tests of the Triton kernels run them under Triton's interpreter (torchrot.testing.triton_kernel), which
# must be on where Triton is first imported: Triton's own library functions (tl.max, tl.zeros, ...) are
# interpreted or compiled then, and some test modules import torch._dynamo, which imports Triton, as they are
# collected. Without a CUDA or XPU device nothing in this process can run Triton compiled: Triton is imported
# here, interpreted (tests/test_triton_compile.py compiles for GPUs in a child process).
if importlib.util.find_spec("triton") is not None and not (torch.cuda.is_available() or torch.xpu.is_available()):
    with triton_interpreter():
        import triton  # noqa: F401

# The helper modules shared by several test modules assert too: pytest rewrites their asserts as it does the
# tests' (values in the failure messages).
pytest.register_assert_rewrite("accuracy_helpers", "fuzz_checks", "isa_helpers", "registration_helpers")

DTYPES = (torch.float32, torch.float64)


@pytest.fixture
def restore_threads():
    """Restores torch's thread count after a test that changes it."""
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


@pytest.fixture
def use_isa():
    """``with use_isa(name): ...`` runs its body on kernel ``name`` (None or
    "": the process default), in this thread only (torchrot.testing.cpu_kernel)."""
    return forced_kernel


@pytest.fixture(params=DTYPES, ids=dtype_id)
def dtype(request) -> torch.dtype:
    """The two compute dtypes of the kernel."""
    return request.param


@pytest.fixture(params=sorted(FITS))
def fit(request) -> Fit:
    """The two public fits, rotation and orthogonal (tests/fits.py): a
    contract test that takes this fixture runs on both."""
    return FITS[request.param]


@pytest.fixture(params=VARIANTS)
def variant(request) -> str:
    """The three Cayley-step variants."""
    return request.param


@functools.cache
def _cached_matrices(name: str, n: int, seed: int, dtype: torch.dtype) -> torch.Tensor:
    return make_matrices(name, n, seed, dtype)


@pytest.fixture(scope="session")
def matrices():
    """``matrices(name, n, seed=0, dtype=float64)``: ``make_matrices`` with a
    session cache (tests must not modify the returned tensor in place)."""

    def get(name: str, n: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        return _cached_matrices(name, n, seed, dtype)

    return get


@pytest.fixture(scope="session")
def assert_meets_criteria():
    """``assert_meets_criteria(R, M, dtype, what="", errors=rotation_errors)``:
    every matrix of R meets ``CRITERIA[dtype]`` (orthonormality, det,
    shortfall) for M, as ``errors`` measures them (``orthogonal_errors`` for
    the orthogonal fit); the message names the worst matrix of each failing
    metric."""

    def check(R: torch.Tensor, M: torch.Tensor, dtype: torch.dtype, what: str = "", errors=rotation_errors) -> dict:
        assert torch.isfinite(R).all(), f"{what}: non-finite result"
        errors = errors(R, M)
        failures = []
        for metric, limit in CRITERIA[dtype].items():
            err = errors[metric].flatten()
            if err.numel() and not bool((err <= limit).all()):
                worst = int(err.argmax())
                failures.append(
                    f"{metric}: max {err[worst].item():.3g} > {limit:g} at matrix {worst} "
                    f"({int((err > limit).sum())} of {err.numel()} fail); "
                    f"M={M.reshape(-1, 3, 3)[worst].tolist()}"
                )
        assert not failures, f"{what}: " + "; ".join(failures)
        return errors

    return check
