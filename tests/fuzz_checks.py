"""Running every kernel the CPU has and checking the properties that
tests/test_fuzz.py fuzzes (see its docstring): of the scalar kernel's results
and of those of any kernel that rounds differently (x86-64's default,
``rounds_like_scalar``), the others bit for bit against the scalar kernel's;
for the fit and for its derivatives. ``CHECKED`` counts what was checked
(printed by the long profile).
"""
from __future__ import annotations

import pytest
import torch

import torchrot
from torchrot._constants import CPU_KERNELS
from torchrot.reference import rotation_svd
from torchrot.testing import CRITERIA, bits, cpu_kernel, rounds_like_scalar

ISAS = CPU_KERNELS


def _supported_isas() -> tuple[str, ...]:
    """The kernels this CPU can run (ATen's level, as csrc/cpu/dispatch.cpp maps it)."""
    cap = torch.backends.cpu.get_cpu_capability()
    top = {"AVX512": "avx512", "AVX2": "avx2"}.get(cap, "default")
    return ISAS[: ISAS.index(top) + 1]


SUPPORTED_ISAS = _supported_isas()
ROUNDS_LIKE_SCALAR = {isa: rounds_like_scalar(isa) for isa in SUPPORTED_ISAS}


# ---------------------------------------------------------------------------
# Counting what was checked (printed by the long profile)
# ---------------------------------------------------------------------------

CHECKED = {"matrices": 0, "non_finite": 0, "derivative_matrices": 0, "kernel_calls": 0}


# ---------------------------------------------------------------------------
# Running every kernel and checking the properties
# ---------------------------------------------------------------------------


def _kernel(isa: str):
    return cpu_kernel(isa)


def fit_every_kernel(M, init, max_iter, variant) -> dict:
    """isa -> (R, iterations, status) of ``fit_rotation_info`` at each kernel."""
    results = {}
    for isa in SUPPORTED_ISAS:
        with _kernel(isa):
            assert torch.ops.torchrot.cpu_kernel() == isa
            results[isa] = tuple(torchrot.fit_rotation_info(M, init, max_iter=max_iter, variant=variant))
        CHECKED["kernel_calls"] += 1
    return results


def scale_pow2(x: torch.Tensor, exponent) -> torch.Tensor:
    """x * 2^exponent, exact unless the result over/underflows (torch.ldexp
    multiplies by 2.0 ** exponent, which overflows for |exponent| > 1023:
    split into two factors)."""
    e = torch.as_tensor(exponent, dtype=torch.float64)
    half = torch.trunc(e / 2)
    return torch.ldexp(torch.ldexp(x, half), e - half)


def exactly_rescaled(M: torch.Tensor) -> torch.Tensor:
    """Float64 copy of finite ``(n, 3, 3)`` M, each matrix scaled by a power of
    two to max |entry| in [0.5, 1) (same maximiser; no over/underflow in the
    SVD reference or the norms)."""
    M64 = M.double()
    max_abs = M64.abs().amax((-2, -1))
    _, exponent = torch.frexp(torch.where(max_abs > 0, max_abs, torch.ones_like(max_abs)))
    return scale_pow2(M64, -exponent.to(torch.float64)[:, None, None])


def rotation_failures(R: torch.Tensor, M: torch.Tensor, dtype, converged: bool) -> list[str]:
    """Why the finite results R (n, 3, 3) for finite M are not (optimal) rotations."""
    limits = CRITERIA[dtype]
    failures = []
    if not bool(torch.isfinite(R).all()):
        bad = (~torch.isfinite(R)).reshape(-1, 9).any(1).nonzero().flatten().tolist()
        return [f"non-finite R for finite input at {bad[:5]}: M={M[bad[0]].tolist()}"]
    Rd = R.double()
    orth = (Rd.mT @ Rd - torch.eye(3, dtype=torch.float64)).abs().amax((-2, -1))
    det = (torch.linalg.det(Rd) - 1).abs()
    metrics = {"orthonormality": orth, "det": det}
    if converged:
        A = exactly_rescaled(M)
        norm = A.norm(dim=(-2, -1))
        objective = lambda Q: (Q * A).sum((-2, -1))  # noqa: E731
        shortfall = (objective(rotation_svd(A)) - objective(Rd)) / torch.where(norm > 0, norm, 1.0)
        metrics["shortfall"] = shortfall
    for name, values in metrics.items():
        if values.numel() and not bool((values <= limits[name]).all()):
            i = int(values.argmax())
            failures.append(f"{name} {values[i].item():.3g} > {limits[name]:g} at matrix {i}: M={M[i].tolist()}")
    return failures


def check_fit(M: torch.Tensor, init: torch.Tensor | None, max_iter, variant, what: str = "") -> None:
    """All properties for ``(n, 3, 3)`` M and optional init broadcastable to it:
    of the scalar kernel's results, and of those of any kernel that rounds
    differently (x86-64's default, ``rounds_like_scalar``); every other kernel
    must reproduce the scalar kernel's bit for bit."""
    n = M.shape[0]
    results = fit_every_kernel(M, init, max_iter, variant)
    context = f"{what} {M.dtype} n={n} max_iter={max_iter} variant={variant} warm={init is not None}"
    CHECKED["matrices"] += n
    CHECKED["non_finite"] += int((results["scalar"][2] == 3).sum())  # status 3 is exactly that (checked below)
    for isa, got in results.items():
        if isa == "scalar" or not ROUNDS_LIKE_SCALAR[isa]:
            check_fit_properties(M, init, max_iter, got, f"{context} {isa}")
    R, iterations, status = results["scalar"]
    for isa, got in results.items():
        if not ROUNDS_LIKE_SCALAR[isa]:
            continue
        for name, a, b in zip(("R", "iterations", "status"), got, (R, iterations, status)):
            same = torch.equal(bits(a), bits(b)) if name == "R" else torch.equal(a, b)
            if not same:
                bad = (bits(a) != bits(b)).reshape(n, -1).any(1) if name == "R" else (a != b)
                i = int(bad.nonzero()[0])
                pytest.fail(f"{context}: {isa} {name} differs from scalar at matrix {i}: M={M[i].tolist()}, "
                            f"{isa} {a[i].tolist()} vs scalar {b[i].tolist()}")


def check_fit_properties(M, init, max_iter, result, context: str) -> None:
    """NaN exactly for non-finite input, statuses, step counts and the
    accuracy criteria of one kernel's ``(R, iterations, status)``."""
    dtype = M.dtype
    n = M.shape[0]
    R, iterations, status = result
    non_finite = ~torch.isfinite(M).reshape(n, 9).all(1)
    if init is not None:
        non_finite |= ~torch.isfinite(init.expand(M.shape)).reshape(n, 9).all(1)

    # NaN exactly where the input had NaN/Inf, in all nine entries
    R_nan = torch.isnan(R).reshape(n, 9)
    assert bool(R_nan[non_finite].all()), f"{context}: non-finite input without an all-NaN result"
    assert torch.equal(status == 3, non_finite), f"{context}: status 3 != non-finite input"
    finite = ~non_finite
    assert not bool(R_nan[finite].any()), (
        f"{context}: NaN for finite input at {R_nan[finite].any(1).nonzero().flatten().tolist()[:5]}"
    )
    assert bool((status[finite] <= 1).all()), f"{context}: status {status[finite].unique().tolist()}"

    converged = max_iter is None
    cap = 36 if converged else max_iter
    most = int(iterations.max()) if n else 0
    assert most <= cap, f"{context}: {most} steps > {cap}"
    if not converged:
        assert not bool((status == 1).any()), f"{context}: fallback outside converged mode"

    failures = rotation_failures(R[finite], M[finite], dtype, converged)
    assert not failures, f"{context}: " + "; ".join(failures)


#: damping values the derivative is fuzzed with (0: undamped; the default 1e-6)
GRADIENT_EPS_VALUES = (0.0, 1e-12, 1e-7, 1e-6, 1e-3, 1.0, 1e3)  # 1e3: the largest accepted


def _rows_finite(t: torch.Tensor, n: int) -> torch.Tensor:
    return torch.isfinite(t).reshape(n, 9).all(1)


def check_derivatives(M, init, max_iter, variant, G, gradient_eps, what: str = "") -> None:
    """Backward (dL/dM for dL/dR = G) and forward-mode tangent (dR for
    dM = G) at every kernel: finite where M, init and G are finite, and
    bit-identical to the scalar kernel (NaN vs NaN where an input was not)
    at the kernels that round like it (``rounds_like_scalar``)."""
    n = M.shape[0]
    context = (f"{what} {M.dtype} n={n} max_iter={max_iter} variant={variant} warm={init is not None} "
               f"gradient_eps={gradient_eps}")
    finite_in = _rows_finite(M, n) & _rows_finite(G, n)
    if init is not None:
        finite_in &= _rows_finite(init.expand(M.shape), n)
    results = {}
    for isa in SUPPORTED_ISAS:
        with _kernel(isa):
            assert torch.ops.torchrot.cpu_kernel() == isa
            M_leaf = M.clone().requires_grad_()
            R = torchrot.fit_rotation(M_leaf, init, max_iter=max_iter, variant=variant, gradient_eps=gradient_eps)
            assert R.grad_fn is not None
            R.backward(G)
            _, tangent = torch.func.jvp(
                lambda X: torchrot.fit_rotation(X, init, max_iter=max_iter, variant=variant,
                                                gradient_eps=gradient_eps), (M,), (G,))
        results[isa] = (M_leaf.grad, tangent)
        CHECKED["kernel_calls"] += 4
    CHECKED["derivative_matrices"] += n
    for isa, got in results.items():
        if isa != "scalar" and ROUNDS_LIKE_SCALAR[isa]:
            continue  # compared with the scalar kernel's below
        for name, value in zip(("backward", "tangent"), got):
            finite_out = _rows_finite(value, n)
            bad = (finite_in & ~finite_out).nonzero().flatten().tolist()
            assert not bad, (f"{context}: {isa}: non-finite {name} for finite input at {bad[:5]}: "
                             f"M={M[bad[0]].tolist()} G={G[bad[0]].tolist()} -> {value[bad[0]].tolist()}")
    for isa, got in results.items():
        if not ROUNDS_LIKE_SCALAR[isa]:
            continue
        for name, a, b in zip(("backward", "tangent"), got, results["scalar"]):
            # entrywise: equal bits, or NaN in both (the NaN's sign may differ
            # between the scalar and SIMD min/max for NaN/Inf inputs)
            same = ((bits(a) == bits(b)) | (torch.isnan(a) & torch.isnan(b))).reshape(n, 9).all(1)
            if not bool(same.all()):
                i = int((~same).nonzero()[0])
                pytest.fail(f"{context}: {isa} {name} differs from scalar at matrix {i}: M={M[i].tolist()} "
                            f"G={G[i].tolist()}: {a[i].tolist()} vs {b[i].tolist()}")
