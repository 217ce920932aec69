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
recipes into large batches from ``torchrot.testing``'s distributions
(the strategies: tests/fuzz_strategies.py; running every kernel and checking
the properties: tests/fuzz_checks.py).

Profiles: the default run is short and derandomised (reproducible in CI).
``TORCHROT_FUZZ=long`` runs the long profile (random, several million
matrices; ``.ci/fuzz-long``) and prints how many matrices were checked;
``TORCHROT_FUZZ_SCALE=k`` multiplies its example counts by k.

Convention: R (det +1) maximises tr(R^T M); column vectors.
"""
from __future__ import annotations

import math
import os

import pytest
import torch
from fuzz_checks import (
    CHECKED,
    GRADIENT_EPS_VALUES,
    SUPPORTED_ISAS,
    _kernel,
    check_derivatives,
    check_fit,
    scale_pow2,
)
from fuzz_strategies import (
    SIGNED_PERMUTATIONS,
    _elementwise,
    _exponent_range,
    _near_rotation,
    _repeated_singular_values,
    _scaled,
    incoming_gradients,
    problems,
)
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import torchrot
from torchrot._constants import VARIANTS
from torchrot.testing import DISTRIBUTIONS, bits, dtype_id, random_rotations

DTYPES = (torch.float32, torch.float64)
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
# Printing what was checked (tests/fuzz_checks.py counts it)
# ---------------------------------------------------------------------------


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
