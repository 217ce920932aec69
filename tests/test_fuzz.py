"""Property-based tests (hypothesis) of the operator on arbitrary 3x3 matrices.

Properties, for float32 and float64, at every instruction set the CPU has:

* a matrix whose M (or warm start) is finite gives a rotation: finite,
  orthonormal and det +1 to ``CRITERIA[dtype]``; in converged mode it also
  attains the maximum of tr(R^T M) (objective shortfall against float64 SVD);
* a matrix whose M or warm start holds NaN/Inf gives NaN in all nine entries
  and status 3, and nothing else: its neighbours in the same SIMD block are
  unaffected;
* every kernel (default, avx2, avx512) gives bit-identical R, iterations and
  status to the scalar kernel (which fits one matrix at a time); but x86-64's
  default kernel, which rounds a * b + c twice (csrc/kernel/mul_add.h), is
  held to the properties above on its own results instead;
* scaling M by a power of two (entries staying normal) changes nothing, bit
  for bit: the kernel normalises exactly;
* derivatives (autograd backward through ``fit_rotation`` and the forward-mode
  tangent, both ``torch.ops.torchrot.fit_rotation_backward``): finite for
  every matrix whose M, warm start and incoming gradient are finite, for any
  ``gradient_eps`` in GRADIENT_EPS_VALUES (0 = undamped included); NaN/Inf
  only where an input had NaN/Inf; bit-identical at every kernel (but for
  the sign of NaN, for NaN/Inf input).

Inputs mix hypothesis's own "nasty" floats (signed zeros, subnormals, the
largest finite values), matrices scaled by 2^e over the whole exponent range,
rank-1 matrices, matrices with exactly repeated singular values (built from
signed permutations, so that the repetition is exact in floating point),
near-rotations and NaN/Inf entries; ``test_batched_recipes`` expands drawn
recipes into large batches from ``torchrot.testing``'s distributions.

Profiles: the default run is short and derandomised (reproducible in CI).
``TORCHROT_FUZZ=long`` runs the long profile (random, several million
matrices; ``.ci/fuzz-long``) and prints how many matrices were checked;
``TORCHROT_FUZZ_SCALE=k`` multiplies its example counts by k.

Convention: R (det +1) maximises tr(R^T M); column vectors.
"""
from __future__ import annotations

import itertools
import math
import os

import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import torchrot
from torchrot._constants import CPU_KERNELS, VARIANTS
from torchrot.reference import quaternion_rotation, rotation_svd
from torchrot.testing import CRITERIA, DISTRIBUTIONS, bits, cpu_kernel, dtype_id, random_rotations, rounds_like_scalar

DTYPES = (torch.float32, torch.float64)
ISAS = CPU_KERNELS


def _supported_isas() -> tuple[str, ...]:
    """The kernels this CPU can run (ATen's level, as csrc/cpu/dispatch.cpp maps it)."""
    cap = torch.backends.cpu.get_cpu_capability()
    top = {"AVX512": "avx512", "AVX2": "avx2"}.get(cap, "default")
    return ISAS[: ISAS.index(top) + 1]


SUPPORTED_ISAS = _supported_isas()
ROUNDS_LIKE_SCALAR = {isa: rounds_like_scalar(isa) for isa in SUPPORTED_ISAS}
LONG = os.environ.get("TORCHROT_FUZZ", "") == "long"
SCALE = int(os.environ.get("TORCHROT_FUZZ_SCALE", "1"))


def _settings(default_examples: int, long_examples: int) -> settings:
    """Default: few, derandomised examples; long profile: many random ones."""
    common = dict(
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    if LONG:
        return settings(max_examples=long_examples * SCALE, derandomize=False, **common)
    return settings(max_examples=default_examples, derandomize=True, **common)


# ---------------------------------------------------------------------------
# Counting what was checked (printed by the long profile)
# ---------------------------------------------------------------------------

CHECKED = {"matrices": 0, "non_finite": 0, "derivative_matrices": 0, "kernel_calls": 0}


@pytest.fixture(scope="module", autouse=True)
def _report_counts(request):
    yield
    plugins = request.config.pluginmanager
    reporter, capture = plugins.get_plugin("terminalreporter"), plugins.get_plugin("capturemanager")
    if reporter is not None and capture is not None and (LONG or request.config.getoption("verbose") > 0):
        with capture.global_and_fixture_disabled():
            reporter.write_line(
                f"\ntest_fuzz: {CHECKED['matrices']:,} matrices checked ({CHECKED['non_finite']:,} with NaN/Inf), "
                f"each at {len(SUPPORTED_ISAS)} kernels {SUPPORTED_ISAS}; derivatives of "
                f"{CHECKED['derivative_matrices']:,}; {CHECKED['kernel_calls']:,} kernel calls"
            )


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


# ---------------------------------------------------------------------------
# Strategies
# ---------------------------------------------------------------------------


def _signed_permutations() -> list[torch.Tensor]:
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            P = torch.zeros(3, 3, dtype=torch.float64)
            for row, col in enumerate(perm):
                P[row, col] = signs[row]
            mats.append(P)
    return mats


SIGNED_PERMUTATIONS = _signed_permutations()  # 48, exact in any precision
CUBE_ROTATIONS = [P for P in SIGNED_PERMUTATIONS if torch.linalg.det(P) > 0]  # 24


def _floats(dtype, **kw):
    return st.floats(width=32 if dtype == torch.float32 else 64, **kw)


def _exponent_range(dtype):
    """(lo, hi): 2^lo is the smallest subnormal, 2^hi overflows."""
    info = torch.finfo(dtype)
    mantissa_bits = round(-math.log2(info.eps))
    return round(math.log2(info.smallest_normal)) - mantissa_bits, round(math.log2(info.max)) + 1


@st.composite
def _elementwise(draw, dtype):
    """Nine independent floats: hypothesis favours 0, -0, subnormals, max, ..."""
    return torch.tensor(draw(st.lists(_floats(dtype, allow_nan=False, allow_infinity=False), min_size=9,
                                      max_size=9)), dtype=torch.float64).view(3, 3)


@st.composite
def _scaled(draw, dtype):
    """A matrix of O(1) entries (some exactly 0) times 2^e over the whole
    exponent range of the dtype, down to subnormals (where entries lose
    bits or vanish) and up to overflow (Inf after the cast, expected NaN)."""
    lo, hi = _exponent_range(dtype)
    entries = draw(st.lists(st.one_of(st.just(0.0), st.floats(-1, 1)), min_size=9, max_size=9))
    exponent = draw(st.integers(lo, hi))
    return scale_pow2(torch.tensor(entries, dtype=torch.float64), exponent).view(3, 3)


@st.composite
def _repeated_singular_values(draw, dtype):
    """P1 B P2 with signed permutations P1, P2 and B = diag(a, a, b),
    a I, or a similarity block [[a, -b], [b, a]] (+) c (singular values
    sqrt(a^2 + b^2) twice): repeated singular values, exact in floating point."""
    value = _floats(dtype, allow_nan=False, allow_infinity=False)
    a, b, c = draw(value), draw(value), draw(value)
    kind = draw(st.sampled_from(["aab", "aaa", "similarity"]))
    if kind == "aab":
        B = torch.diag(torch.tensor([a, a, b], dtype=torch.float64))
    elif kind == "aaa":
        B = a * torch.eye(3, dtype=torch.float64)
    else:
        B = torch.tensor([[a, -b, 0.0], [b, a, 0.0], [0.0, 0.0, c]], dtype=torch.float64)
    P1, P2 = draw(st.sampled_from(SIGNED_PERMUTATIONS)), draw(st.sampled_from(SIGNED_PERMUTATIONS))
    return P1 @ B @ P2


@st.composite
def _rank_one(draw, dtype):
    unit = st.one_of(st.just(0.0), st.floats(-1, 1))
    u = torch.tensor(draw(st.lists(unit, min_size=3, max_size=3)), dtype=torch.float64)
    v = torch.tensor(draw(st.lists(unit, min_size=3, max_size=3)), dtype=torch.float64)
    lo, hi = _exponent_range(dtype)
    return scale_pow2(torch.outer(u, v), draw(st.integers(lo, hi)))


@st.composite
def _quaternion_rotation(draw):
    """A rotation from a drawn quaternion (float64), or a cube rotation (exact)."""
    if draw(st.booleans()):
        return draw(st.sampled_from(CUBE_ROTATIONS))
    q = torch.tensor(draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4)), dtype=torch.float64)
    if float(q.norm()) < 1e-3:
        q = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    q = q / q.norm()
    return quaternion_rotation(q)


@st.composite
def _near_rotation(draw, dtype):
    """A rotation times a positive scale plus a tiny perturbation (the warm
    data of local-global solvers, at any magnitude)."""
    R = draw(_quaternion_rotation())
    noise = torch.tensor(draw(st.lists(st.floats(-1e-6, 1e-6), min_size=9, max_size=9)), dtype=torch.float64)
    lo, hi = _exponent_range(dtype)
    return scale_pow2(R + noise.view(3, 3), draw(st.integers(lo + 30, hi - 2)))


@st.composite
def _with_non_finite(draw, base):
    """``base`` with 1-9 entries replaced by NaN, +Inf or -Inf."""
    M = draw(base).clone().view(9)
    for index in draw(st.lists(st.integers(0, 8), min_size=1, max_size=9)):
        M[index] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    return M.view(3, 3)


def matrices(dtype):
    finite = st.one_of(
        _elementwise(dtype), _scaled(dtype), _repeated_singular_values(dtype), _rank_one(dtype),
        _near_rotation(dtype),
    )
    return st.one_of(finite, _with_non_finite(finite))


@st.composite
def warm_starts(draw, n: int, dtype):
    """``(n, 3, 3)`` rotations (a few with NaN/Inf entries), or one ``(3, 3)``
    rotation broadcast to the batch."""
    if n and draw(st.integers(0, 4)) == 0:
        return draw(_quaternion_rotation()).to(dtype)
    inits = []
    for _ in range(n):
        R = draw(_quaternion_rotation())
        if draw(st.integers(0, 9)) == 0:
            R = draw(_with_non_finite(st.just(R)))
        inits.append(R)
    return torch.stack(inits).to(dtype) if inits else torch.empty(0, 3, 3, dtype=dtype)


@st.composite
def problems(draw, dtype, max_size=40):
    """(M (n, 3, 3), init or None, max_iter, variant) for n in 0..max_size."""
    Ms = draw(st.lists(matrices(dtype), min_size=0, max_size=max_size))
    M = torch.stack(Ms).to(dtype) if Ms else torch.empty(0, 3, 3, dtype=dtype)
    init = draw(warm_starts(M.shape[0], dtype)) if draw(st.booleans()) else None
    max_iter = draw(st.sampled_from([None, None, 1, 2, 5]))
    variant = draw(st.sampled_from(VARIANTS))
    return M, init, max_iter, variant


@st.composite
def incoming_gradients(draw, n: int, dtype):
    """``(n, 3, 3)`` dL/dR (or dM): O(1) values, arbitrary floats (huge,
    subnormal, +-0) or, rarely, NaN/Inf entries."""
    kind = draw(st.sampled_from(["unit", "unit", "arbitrary", "with_non_finite"]))
    if kind == "unit":
        seed = draw(st.integers(0, 2**32 - 1))
        return torch.randn(n, 3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64).to(dtype)
    entries = draw(st.lists(_floats(dtype, allow_nan=kind == "with_non_finite",
                                    allow_infinity=kind == "with_non_finite"), min_size=9 * n, max_size=9 * n))
    return torch.tensor(entries, dtype=torch.float64).view(n, 3, 3).to(dtype)


# ---------------------------------------------------------------------------
# Tests
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
def test_arbitrary_matrices(dtype):
    """Batches of 0-40 drawn matrices (every kind mixed in the same SIMD
    blocks), cold or warm, every mode and variant."""

    @_settings(default_examples=60, long_examples=4000)
    @given(problems(dtype))
    def run(problem):
        check_fit(*problem, what="arbitrary")

    run()


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
def test_power_of_two_scaling_is_exact(dtype):
    """fit(2^k1 M) == fit(2^k2 M) bit for bit (R, iterations, status) for all
    k1, k2 that keep every non-zero entry normal, and the reciprocal of the
    largest: the kernel normalises by the largest entry exactly, and nothing
    else depends on the scale. (Near the largest finite value the reciprocal
    is subnormal, so bits may differ there; the result is still optimal.)"""
    info = torch.finfo(dtype)
    lo, hi = _exponent_range(dtype)
    normal_lo = round(math.log2(info.smallest_normal))  # 2^normal_lo: smallest normal

    def exponents(M: torch.Tensor) -> tuple[int, int] | None:
        """(smallest, largest) binary exponent of M's non-zero entries, if all are normal."""
        a = M.double().abs().flatten()
        a = a[a > 0]
        if a.numel() == 0 or not bool(((a >= info.smallest_normal) & (a <= info.max)).all()):
            return None
        _, e = torch.frexp(a)  # a = f 2^e, f in [0.5, 1)
        return int(e.min()) - 1, int(e.max()) - 1

    @_settings(default_examples=40, long_examples=2000)
    @given(st.one_of(_elementwise(dtype), _scaled(dtype), _repeated_singular_values(dtype), _near_rotation(dtype)),
           st.data(), st.sampled_from([None, 1]), st.sampled_from(VARIANTS))
    def run(M64, data, max_iter, variant):
        M = M64.to(dtype)
        span = exponents(M)
        assume(span is not None)
        # 2^k M is usable if its entries 2^(e+k) are normal (e_min + k >=
        # normal_lo, e_max + k <= hi - 2) and so is 1 / max (e_max + k + 1 <= -normal_lo)
        k_lo, k_hi = normal_lo - span[0], min(hi - 2, -normal_lo - 1) - span[1]
        assume(k_lo <= k_hi)
        k1 = data.draw(st.integers(k_lo, k_hi), label="k1")
        k2 = data.draw(st.integers(k_lo, k_hi), label="k2")
        A, B = (scale_pow2(M.double(), k).to(dtype) for k in (k1, k2))
        assert exponents(A) is not None and exponents(B) is not None
        for isa in SUPPORTED_ISAS:
            with _kernel(isa):
                a = torchrot.fit_rotation_info(A[None], max_iter=max_iter, variant=variant)
                b = torchrot.fit_rotation_info(B[None], max_iter=max_iter, variant=variant)
            assert torch.equal(bits(a.R), bits(b.R)), f"{isa}: 2^{k1} M and 2^{k2} M differ: M={M.tolist()}"
            assert torch.equal(a.iterations, b.iterations) and torch.equal(a.status, b.status)
        CHECKED["matrices"] += 2

    run()


# Per-matrix generators for the batched recipes: the shared distributions of
# torchrot.testing plus exact constructions that hypothesis draws one at a time.
def _exact_repeated(n: int, gen: torch.Generator) -> torch.Tensor:
    P = torch.stack(SIGNED_PERMUTATIONS)
    a = torch.randn(n, generator=gen, dtype=torch.float64)
    b = torch.where(torch.rand(n, generator=gen, dtype=torch.float64) < 0.3, a,
                    torch.randn(n, generator=gen, dtype=torch.float64))
    D = torch.diag_embed(torch.stack([a, a, b], -1))
    i, j = torch.randint(0, 48, (2, n), generator=gen)
    return P[i] @ D @ P[j]


def _signed_permutation_matrices(n: int, gen: torch.Generator) -> torch.Tensor:
    scale = torch.randn(n, 1, 1, generator=gen, dtype=torch.float64)
    return torch.stack(SIGNED_PERMUTATIONS)[torch.randint(0, 48, (n,), generator=gen)] * scale


BATCH_KINDS = {**DISTRIBUTIONS, "exact_repeated": _exact_repeated, "signed_permutation": _signed_permutation_matrices}


def special_values(dtype) -> torch.Tensor:
    info = torch.finfo(dtype)
    sub = info.smallest_normal * info.eps  # smallest subnormal
    values = [0.0, -0.0, 1.0, -1.0, sub, -sub, 3 * sub, info.smallest_normal, -info.smallest_normal,
              info.smallest_normal / 3, info.max, -info.max, info.max / 3, info.eps, 1 + info.eps]
    return torch.tensor(values, dtype=torch.float64)


def batched_problem(seed: int, n: int, dtype, p_special: float, p_non_finite: float, exponent_spread: int,
                    warm: bool):
    """(M, init): n matrices of every kind in BATCH_KINDS, shuffled, each scaled
    by 2^e (|e| <= exponent_spread, within the dtype's range), a fraction
    p_special of entries replaced by special values (+-0, subnormals, max,
    ...) and p_non_finite by NaN/+-Inf (in init as well, when warm)."""
    gen = torch.Generator().manual_seed(seed)
    kinds = list(BATCH_KINDS.values())
    per = -(-n // len(kinds))
    M = torch.cat([kind(per, gen) for kind in kinds])[torch.randperm(per * len(kinds), generator=gen)[:n]]
    lo, hi = _exponent_range(dtype)
    e = torch.randint(-exponent_spread, exponent_spread + 1, (n, 1, 1), generator=gen).clamp(lo, hi - 4)
    M = scale_pow2(M, e.double())
    flat = M.view(n, 9)
    specials = special_values(dtype)
    mask = torch.rand(n, 9, generator=gen) < p_special
    flat[mask] = specials[torch.randint(0, len(specials), (int(mask.sum()),), generator=gen)]
    non_finite = torch.tensor([math.nan, math.inf, -math.inf], dtype=torch.float64)
    mask = torch.rand(n, 9, generator=gen) < p_non_finite
    flat[mask] = non_finite[torch.randint(0, 3, (int(mask.sum()),), generator=gen)]
    init = None
    if warm:
        init = random_rotations(n, gen).view(n, 9)
        mask = torch.rand(n, 9, generator=gen) < p_non_finite
        init[mask] = non_finite[torch.randint(0, 3, (int(mask.sum()),), generator=gen)]
        init = init.view(n, 3, 3).to(dtype)
    return M.to(dtype), init


BATCH_SIZE = 65536 if LONG else 2048


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
def test_batched_recipes(dtype):
    """Drawn recipes (seed, special-value and NaN/Inf rates, exponent spread,
    cold/warm, mode, variant, damping) expanded to batches of every
    distribution; the fit and its derivatives (incoming gradients from the
    same kind of recipe)."""
    lo, hi = _exponent_range(dtype)

    @_settings(default_examples=6, long_examples=60)
    @given(seed=st.integers(0, 2**32 - 1), p_special=st.sampled_from([0.0, 0.002, 0.05, 0.3]),
           p_non_finite=st.sampled_from([0.0, 0.0005, 0.01]), spread=st.sampled_from([0, 8, 60, hi - lo]),
           warm=st.booleans(), max_iter=st.sampled_from([None, None, 1, 3]), variant=st.sampled_from(VARIANTS),
           gradient_eps=st.sampled_from(GRADIENT_EPS_VALUES))
    def run(seed, p_special, p_non_finite, spread, warm, max_iter, variant, gradient_eps):
        M, init = batched_problem(seed, BATCH_SIZE, dtype, p_special, p_non_finite, spread, warm)
        check_fit(M, init, max_iter, variant, what=f"batched seed={seed}")
        G, _ = batched_problem(seed + 1, BATCH_SIZE, dtype, p_special, p_non_finite, spread, False)
        check_derivatives(M, init, max_iter, variant, G, gradient_eps, what=f"batched seed={seed}")

    run()


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
def test_derivatives_of_arbitrary_matrices(dtype):
    """Backward and forward-mode derivatives of batches of 0-24 drawn
    matrices (every kind, NaN/Inf included), with drawn incoming gradients
    and damping."""

    @_settings(default_examples=40, long_examples=3000)
    @given(problems(dtype, max_size=24), st.data(), st.sampled_from(GRADIENT_EPS_VALUES))
    def run(problem, data, gradient_eps):
        M, init, max_iter, variant = problem
        G = data.draw(incoming_gradients(M.shape[0], dtype), label="G")
        check_derivatives(M, init, max_iter, variant, G, gradient_eps, what="arbitrary")

    run()


#: Inputs the fuzzing found bugs with (fixed since), kept as fixed cases:
#: (dtype, M entries, max_iter, gradient_eps, G scale).
REGRESSIONS = [
    # forward: a Cayley step whose d^2 + w.w underflowed gave NaN (1 / (d^2 + w.w) = inf)
    (torch.float32, [[1.0, 0.0, -1.0427839942509576e28], [-5.758594769909921e27, -3.848373797697573e28, 1.0],
                     [-1.106119901282557e28, -3.4028234663852886e38, -9.884469107299525e27]], 1, 1e-6, 1.0),
    # backward: M = 0 with eps^6 below the smallest normal (0 * inf)
    (torch.float32, [[0.0] * 3] * 3, None, 1e-7, 1.0),
    # backward: undamped near-singular system with a huge incoming gradient (inf - inf)
    (torch.float32, [[0.0, 0.0, -0.7238574624061584], [0.41063886880874634, 0.0, 0.0],
                     [0.0, 0.41063886880874634, 0.0]], None, 0.0, 1e30),
    # backward: subnormal M whose |A|_F rounds below 1 (T_max / |A|_F = inf, 0 * inf)
    (torch.float64, [[0.0] * 3, [0.0] * 3, [0.0, 0.0, 6.339035e-317]], None, 0.0, 1.0),
]


@pytest.mark.parametrize("case", range(len(REGRESSIONS)))
def test_regressions(case):
    dtype, entries, max_iter, gradient_eps, g_scale = REGRESSIONS[case]
    M = torch.tensor(entries, dtype=torch.float64).to(dtype)[None].expand(19, 3, 3).contiguous()  # SIMD blocks + tail
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(case), dtype=torch.float64) * g_scale
    for variant in VARIANTS:
        check_fit(M, None, max_iter, variant, what=f"regression {case}")
        check_derivatives(M, None, max_iter, variant, G.to(dtype), gradient_eps, what=f"regression {case}")


def test_batched_problem_has_what_it_promises():
    """The recipes draw every distribution of torchrot.testing, and their
    knobs do what they say (guards the fuzzing against going vacuous)."""
    assert set(DISTRIBUTIONS) <= set(BATCH_KINDS)
    M, init = batched_problem(0, 4096, torch.float32, 0.0, 0.0, 0, False)
    assert init is None and bool(torch.isfinite(M).all())
    M, init = batched_problem(1, 4096, torch.float32, 0.05, 0.01, 300, True)
    entries = M.abs()[torch.isfinite(M)]
    assert bool(torch.isnan(M).any()) and bool(torch.isinf(M).any()) and bool((~torch.isfinite(init)).any())
    assert bool(((entries > 0) & (entries < torch.finfo(torch.float32).smallest_normal)).any())  # subnormals
    assert bool((entries == torch.finfo(torch.float32).max).any())
    assert bool((M == 0).any()) and bool((torch.signbit(M) & (M == 0)).any())  # +-0
