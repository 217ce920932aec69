"""Warm starts across precisions: a rotation rounded to any float dtype (fitted
in float32 and cast to float64, cast up from float16/bfloat16, ...) is
accepted as a warm start of a fit in any dtype, brought to the compute dtype's
precision, and gives rotations at that precision and the same optimum; only
what is clearly not a rotation (det <= 0, |R^T R - I|_F >= INIT_TOLERANCE) is
rejected, with a message that says what to do. Both the C++ kernel and the
device-generic kernel.

Convention: R (det +1) maximises tr(R^T M); column vectors.
"""
from __future__ import annotations

import pytest
import torch
from kernel_paths import KERNEL_PATHS, kernel_path_params

import torchrot
from torchrot._constants import INIT_TOLERANCE
from torchrot.testing import (
    CRITERIA,
    available_cpu_kernels,
    bits,
    conditioning,
    cpu_kernel,
    generic_kernel,
    make_matrices,
    random_rotations,
    rotation_errors,
    rotation_svd,
)

LOW = (torch.float32, torch.float16, torch.bfloat16)
N = 20_000  # per call on the C++ kernel; the generic kernel (batched PyTorch) gets N_GENERIC
N_GENERIC = 1000


def _assert_rotations_at_precision(R, M, dtype, what):
    errors = rotation_errors(R, M)
    for metric in ("orthonormality", "det", "shortfall"):
        worst = errors[metric].max().item()
        assert worst <= CRITERIA[dtype][metric], f"{what}: {metric} {worst:.3g} > {CRITERIA[dtype][metric]:g}"


def _low_precision_warm_starts(low, dtype, n=N):
    """M (dtype) and the previous rotations fitted in `low` (float32 fits of
    M rounded to `low`), cast to dtype: the rotations a solver that changed
    precision hands over."""
    M = make_matrices("warm", n, 31, torch.float64)
    R_low = torchrot.fit_rotation(M.float()).to(low)
    return M.to(dtype), R_low.to(dtype)


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("low", LOW, ids=str)
@pytest.mark.parametrize("max_iter", [None, 1])
def test_lower_precision_rotations_accepted(low, max_iter, kernel, dtype):
    M, init = _low_precision_warm_starts(low, dtype, N if kernel == "cpu" else N_GENERIC)
    with KERNEL_PATHS[kernel]():
        R = torchrot.fit_rotation(M, init, max_iter=max_iter)
    if max_iter is None:  # converged: rotations at dtype's precision, the optimum
        _assert_rotations_at_precision(R, M, dtype, f"{low} warm start")
    else:  # one step: a rotation at dtype's precision (the step itself is not exact)
        errors = rotation_errors(R, M)
        assert errors["orthonormality"].max() <= CRITERIA[dtype]["orthonormality"]
        assert errors["det"].max() <= CRITERIA[dtype]["det"]


#: A converged fit is within EXACTNESS eps (of its dtype) times M's
#: conditioning of the exact rotation (float64 SVD), from a cold start or any
#: accepted warm start. Measured on Gaussian M: cold fits at most 42 (float64,
#: where the SVD reference's own rounding is of the same order) and 1.3
#: (float32); float32 rotations as float64 warm starts reached 2e8 before the
#: warm start was cleaned to the compute precision.
EXACTNESS = 64


def _distance_in_eps_kappa(R, M, dtype):
    """|R - R*|_F in units of eps(dtype) times M's conditioning."""
    distance = (R.double() - rotation_svd(M.double())).norm(dim=(-2, -1))
    return distance / (torch.finfo(dtype).eps * conditioning(M))


WARM_KERNELS = [f"cpu-{name}" for name in available_cpu_kernels()] + ["generic"]


def _kernel_context(kernel):
    return generic_kernel() if kernel == "generic" else cpu_kernel(kernel.removeprefix("cpu-"))


@pytest.mark.parametrize("kernel", WARM_KERNELS)
@pytest.mark.parametrize("variant", ["newton", "conservative", "gershgorin"])
@pytest.mark.parametrize(
    ("dtype", "low"),
    [(dtype, low) for dtype in (torch.float32, torch.float64)
     for low in LOW if torch.finfo(low).eps > torch.finfo(dtype).eps],  # only lower precisions
    ids=lambda d: str(d).removeprefix("torch."),
)
def test_converged_from_lower_precision_as_exact_as_cold(low, variant, kernel, dtype):
    """The converged fit from a warm start of lower precision (a rotation
    fitted in float32 and cast, or rounded to float16/bfloat16) is as exact in
    the rotation itself as a cold fit, conditioning taken into account: the
    objective hides the difference (it is quadratic in it), the rotation
    does not."""
    n = N if kernel.startswith("cpu") else N_GENERIC
    M = make_matrices("gaussian", n, 37, torch.float64).to(dtype)
    init = torchrot.fit_rotation(M.float()).to(low)
    with _kernel_context(kernel):
        warm = torchrot.fit_rotation(M, init, variant=variant)
        cold = torchrot.fit_rotation(M, variant=variant)
    assert _distance_in_eps_kappa(cold, M, dtype).max() <= EXACTNESS  # the criterion is fair
    worst = _distance_in_eps_kappa(warm, M, dtype).max().item()
    assert worst <= EXACTNESS, f"{low} warm start: |R - R*| = {worst:.3g} eps kappa"


def test_issue_case_float32_fits_as_float64_warm_start():
    """200,000 float32 fits cast to float64: all accepted (150,591 raised before)."""
    M = torch.randn(200_000, 3, 3, generator=torch.Generator().manual_seed(0))
    R32 = torchrot.fit_rotation(M)
    R = torchrot.fit_rotation(M.double(), init=R32.double())
    _assert_rotations_at_precision(R, M.double(), torch.float64, "float32 fits as float64 warm starts")
    # the same optimum as the cold float64 fit
    cold = torchrot.fit_rotation(M.double())
    gap = (rotation_errors(R, M.double())["shortfall"] - rotation_errors(cold, M.double())["shortfall"]).abs()
    assert gap.max() <= CRITERIA[torch.float64]["shortfall"]


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("init_dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16], ids=str)
def test_init_of_another_dtype_is_cast(init_dtype, kernel, dtype):
    """A warm start of any float dtype is accepted as it is (no cast needed by
    the caller): the result equals the fit from the init cast to M's dtype."""
    M = make_matrices("warm", 500, 36, torch.float64).to(dtype)
    init = torchrot.fit_rotation(M.double()).to(init_dtype)
    with KERNEL_PATHS[kernel]():
        for max_iter in (None, 1):
            R = torchrot.fit_rotation(M, init, max_iter=max_iter)
            assert R.dtype == dtype
            assert torch.equal(R, torchrot.fit_rotation(M, init.to(dtype), max_iter=max_iter))
        out = torch.empty_like(M)
        torchrot.fit_rotation(M, init, max_iter=1, out=out)
        assert torch.equal(out, torchrot.fit_rotation(M, init.to(dtype), max_iter=1))


def test_repeated_one_step_updates_do_not_drift():
    """Results fed back as the next warm start stay rotations at full precision."""
    M = make_matrices("warm", 2000, 32, torch.float64)
    R = torchrot.fit_rotation(M.float()).to(torch.bfloat16).double()
    for _ in range(5):
        torchrot.fit_rotation(M, R, max_iter=1, out=R)
    errors = rotation_errors(R, M)
    assert errors["orthonormality"].max() <= CRITERIA[torch.float64]["orthonormality"]


def _not_rotations(dtype):
    R = random_rotations(6, torch.Generator().manual_seed(33)).to(dtype)
    reflection = R.clone()
    reflection[0, :, 0] *= -1  # det -1, orthonormal
    scaled = 1.1 * R[1]  # |R^T R - I|_F = 0.21 * sqrt(3)
    skewed = R[2] + 0.05  # far from orthonormal
    zero = torch.zeros(3, 3, dtype=dtype)
    return {"reflection": reflection[0], "scaled": scaled, "skewed": skewed, "zero": zero}


@pytest.mark.parametrize("kernel", kernel_path_params())
@pytest.mark.parametrize("case", ["reflection", "scaled", "skewed", "zero"])
def test_clearly_not_rotations_rejected(case, kernel, dtype):
    bad = _not_rotations(dtype)[case]
    eye = torch.eye(3, dtype=torch.float64)
    deviation = (bad.double().mT @ bad.double() - eye).norm().item()
    assert deviation >= INIT_TOLERANCE or torch.linalg.det(bad.double()) <= 0  # the case is what it says
    M = make_matrices("warm", 8, 34, torch.float64).to(dtype)
    init = random_rotations(8, torch.Generator().manual_seed(35)).to(dtype)
    init[3] = bad
    with KERNEL_PATHS[kernel]():
        with pytest.raises(ValueError, match=r"init must hold rotations .* 1 of 8 are not: pass rotations, or no init"):
            torchrot.fit_rotation(M, init)


@pytest.mark.parametrize("max_iter", [None, 1, 3])
@pytest.mark.parametrize("warm_starts", ["clean", "one lower precision", "one NaN"])
def test_out_path_gives_the_fresh_results(warm_starts, max_iter, dtype):
    """out= validates every warm start before it writes; when all are clean
    (finite rotations at the compute precision) the fit skips its own check
    (FitOptions::init_known_clean). Its results are the checked fit's bit for
    bit, whichever warm starts the batch holds (a lower-precision or NaN one
    keeps the check on)."""
    M = make_matrices("warm", 203, 5, dtype)
    init = torchrot.fit_rotation(M)
    if warm_starts == "one lower precision":
        init[101] = init[101].to(torch.bfloat16).to(dtype)
    elif warm_starts == "one NaN":
        init[17, 1, 2] = float("nan")
    fresh = torchrot.fit_rotation_info(M + 0.1, init, max_iter=max_iter)
    out = torch.full_like(M, 7.0)
    torchrot.fit_rotation(M + 0.1, init, max_iter=max_iter, out=out)
    assert torch.equal(bits(out), bits(fresh.R))
    in_place = init.clone()
    torchrot.fit_rotation(M + 0.1, in_place, max_iter=max_iter, out=in_place)
    assert torch.equal(bits(in_place), bits(fresh.R))


#: ||R^T R - I||_F that 1,000 chained in-place one-step updates must keep
#: every R within (issue #38's drift bound), and det R > 0.
DRIFT_BOUND = {torch.float32: 1e-6, torch.float64: 1e-14}


@pytest.mark.parametrize("kernel", ["cpu", "generic"])
def test_chained_in_place_one_steps_do_not_drift(kernel, dtype):
    """A local-global solver's loop: 1,000 one-step updates in place, each from
    the previous result, on covariances that move a little every iteration.
    Every intermediate R stays a rotation to working precision (measured in
    float64), whether the results are cleaned up at each step or only the
    warm starts that need it."""
    n = 64 if kernel == "cpu" else 16
    gen = torch.Generator().manual_seed(40)
    base = make_matrices("warm", n, 41, torch.float64)
    R = torchrot.fit_rotation(base).to(dtype)
    M = base.to(dtype)
    eye = torch.eye(3, dtype=torch.float64)
    worst = 0.0
    with KERNEL_PATHS[kernel]():
        for step in range(1000):
            M = M + 0.01 * torch.randn(M.shape, generator=gen, dtype=torch.float64).to(dtype)
            torchrot.fit_rotation(M, R, max_iter=1, out=R)
            Rd = R.double()
            deviation = (Rd.mT @ Rd - eye).norm(dim=(-2, -1))
            worst = max(worst, deviation.max().item())
            assert (torch.linalg.det(Rd) > 0).all(), f"step {step}: det <= 0"
    assert worst <= DRIFT_BOUND[dtype], f"{kernel}: |R^T R - I|_F reached {worst:.3g} > {DRIFT_BOUND[dtype]:g}"
