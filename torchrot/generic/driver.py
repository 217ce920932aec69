"""The driver of the device-generic kernel: (..., 3, 3) tensors in and out,
begin (normalise, warm or cold start), the schedule, finish (NaN lanes,
status codes), and the entry points of torchrot.reference
(fit_rotation_generic, fit_rotation_backward_generic). No counterpart in
csrc/kernel/ (the CPU operators' drivers are csrc/ops/ and csrc/cpu/;
begin_fit and finish are csrc/kernel/fit_rotation_impl.h's, here spelled
out in _fit_core with that module's pieces).

It runs eagerly where the operators call it (MPS tensors, and CUDA and XPU
tensors without Triton, torchrot._device_kernels); _fit_core also traces
without a graph break, so a caller may torch.compile it
(torchrot.generic.control_flow).
"""
from __future__ import annotations

import math

import torch

from torchrot._constants import INIT_CLEAN, FitStatus, compute_dtype, dtype_name
from torchrot.generic.cold_start import best_start_rotation
from torchrot.generic.control_flow import _compiling
from torchrot.generic.lanes import max_abs_entry, select
from torchrot.generic.maximal_objective import maximal_objective
from torchrot.generic.optimality import check_warm_start, clean_warm_start
from torchrot.generic.rotation_gradient import rotation_tangent
from torchrot.generic.schedule import fit_soa
from torchrot.generic.unit_scale import unit_scale

__all__ = [
    "STATUS_CAYLEY",
    "STATUS_FALLBACK",
    "STATUS_BAD_INIT",
    "STATUS_NON_FINITE",
    "fit_rotation_generic",
    "fit_rotation_backward_generic",
    "_components",
    "_warm_start_components",
    "_fit_core",
]

# The status codes (torchrot.FitStatus) as plain ints, which tracing takes as constants.
STATUS_CAYLEY, STATUS_FALLBACK, STATUS_BAD_INIT, STATUS_NON_FINITE = (
    int(FitStatus.CAYLEY), int(FitStatus.FALLBACK), int(FitStatus.BAD_INIT), int(FitStatus.NON_FINITE))


def _components(X, n):
    """(..., 3, 3) -> 9 contiguous (n,) tensors."""
    flat = X.reshape(n, 9).t().contiguous()
    if _compiling() and X.device.type == "cpu" and X.dtype == torch.float32:
        # Inductor must store an as_strided view's input: the transposed
        # entries are written once (a tiled, vectorised transpose) and the
        # kernels that read them load contiguous vectors. Inlined instead,
        # each read is a stride-9 load of X, and inductor's CPU code then runs
        # the whole consuming kernel (normalisation and cold start) one lane at
        # a time, markedly slower (benchmarks/generic_path.py times it; the
        # figures: benchmarks/lab_notes.md). Not in float64: there inductor's
        # vector code (two AVX2 registers per value) ran slower than its scalar
        # loop (benchmarks/lab_notes.md).
        # Not on accelerators: nothing measured there.
        flat = flat.as_strided((9, n), (n, 1))
    return list(flat.unbind(0))


def _warm_start_components(init, compute):
    """init's 9 components in ``compute``, in init's batch shape, with its
    Gram matrix, finiteness, rejection (check_warm_start, optimality.h) and
    squared deviation from orthonormality."""
    batch = init.shape[:-2]
    I = [x.reshape(batch) for x in _components(init.to(compute), math.prod(batch))]
    G, finite, bad, dev2 = check_warm_start(I)
    return I, G, finite, bad, dev2


def _fit_core(M, init, max_iter, variant, warm=None):
    """(R, iterations, status) for M: the whole algorithm as tensor operations
    (no host read when compiled; see torchrot.generic.control_flow). ``warm``:
    init's _warm_start_components if the caller has them already."""
    compute = compute_dtype(M.dtype)
    shape = M.shape
    batch = shape[:-2]
    n = math.prod(batch)
    eps = torch.finfo(compute).eps
    M_lanes = _components(M.to(compute), n)
    max_abs = max_abs_entry(M_lanes)
    zero = max_abs == 0
    A = unit_scale(M_lanes, max_abs)[0]
    finite = torch.isfinite(max_abs)
    bad_init = torch.zeros_like(finite)
    objective = None  # the first step's estimate c: cold starts only
    if init is not None:
        I, G, init_finite, init_bad, dev2 = warm if warm is not None else _warm_start_components(init, compute)
        ex = lambda t: t.expand(batch).reshape(n)
        init_finite, init_bad, dev2 = ex(init_finite), ex(init_bad), ex(dev2)
        R, G = [ex(x) for x in I], [ex(g) for g in G]
        finite = finite & init_finite
        bad_init = init_bad
        # clean_warm_start: lanes above the dtype's clean threshold (eager: only while some lane needs a step).
        R = clean_warm_start(R, G, init_finite, init_bad, dev2, INIT_CLEAN[dtype_name(compute)])
    else:
        R, start_objective = best_start_rotation(A)
        objective = maximal_objective(A, start_objective)
    A = select(finite, A, [torch.zeros_like(a) for a in A])  # NaN stays in its lane
    running = finite & ~zero & ~bad_init
    R, iterations, fallback = fit_soa(A, R, running, variant, max_iter, eps, objective)
    nan_lane = ~finite | bad_init
    R = [torch.where(nan_lane, float("nan"), r) for r in R]
    out = torch.stack(R, -1).reshape(shape).to(M.dtype)
    status = torch.where(fallback, STATUS_FALLBACK, STATUS_CAYLEY)
    status = torch.where(bad_init, STATUS_BAD_INIT, status)
    status = torch.where(finite, status, STATUS_NON_FINITE).to(torch.uint8)
    return out, iterations.reshape(batch), status.reshape(batch)


def fit_rotation_generic(M, init, max_iter, variant, return_info, bad_init_error):
    """The body of fit_rotation_reference (arguments already checked): raises
    ``bad_init_error(count, total)`` for a finite warm start that is not a
    rotation (eager, before anything else; not on ``meta`` tensors nor while
    traced, where such lanes come back NaN with status STATUS_BAD_INIT)."""
    warm = None
    if init is not None and M.device.type != "meta" and not _compiling():
        warm = _warm_start_components(init, compute_dtype(M.dtype))
        init_bad = warm[3]
        if bool(init_bad.any()):
            raise bad_init_error(int(init_bad.sum()), init_bad.numel())  # counted in init's own shape
    R, iterations, status = _fit_core(M, init, max_iter, variant, warm)
    return (R, iterations, status) if return_info else R


def fit_rotation_backward_generic(grad, R, M, gradient_eps):
    """The body of fit_rotation_backward_reference (arguments already checked)."""
    out_dtype = R.dtype
    compute = compute_dtype(R.dtype)
    shape = R.shape
    n = math.prod(shape[:-2])
    Gc = _components(grad.to(compute), n)
    Rc = _components(R.to(compute), n)
    Mc = _components(M.to(compute).expand(shape), n)
    T = rotation_tangent(Gc, Rc, Mc, gradient_eps)
    return torch.stack(T, -1).reshape(shape).to(out_dtype)
