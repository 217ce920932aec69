"""torchrot's constants, read from the C++ extension: the limits, defaults
and tolerances (csrc/limits.h), the variants, supported dtypes, CPU kernel
names and status codes (csrc/fit_rotation.h), and the error messages
(csrc/messages.h).

Each is defined once, in C++ (explained there), and handed over by
``torchrot._C.constants()``: the argument checks, the fake kernels and the
pure-PyTorch path use exactly the kernel's values and words.
"""
from __future__ import annotations

import enum

import torch

from torchrot import _C

__all__ = [
    "CONVERGED_CAP", "CPU_KERNELS", "DEFAULT_VARIANT", "ESTIMATE_SWITCH", "FitStatus", "GERSHGORIN_STEPS",
    "GRADIENT_EPS", "INIT_CLEAN", "INIT_CLEAN_EPS", "INIT_CLEAN_STEPS", "INIT_TOLERANCE", "MAX_CHECK_SLACK_EPS",
    "LARGE_STEP", "MAX_ESCAPES", "MAX_GRADIENT_EPS", "MAX_ITER", "MESSAGES", "OBJECTIVE_LAGUERRE_STEPS",
    "STEPS_WITHOUT_CLEAN_UP", "SUPPORTED_DTYPES",
    "UNDAMPED", "VARIANTS", "compute_dtype", "dtype_name",
]

_CONSTANTS = _C.constants()

FitStatus = enum.IntEnum("FitStatus", _CONSTANTS["FIT_STATUS"], module=__name__)
FitStatus.__doc__ = """Per-matrix outcome of a fit, as :func:`torchrot.fit_rotation_info` reports it
(its ``status``, a uint8 tensor; compare with these members):

- ``CAYLEY``: the Cayley iteration produced R;
- ``FALLBACK``: converged mode only, the Horn/Jacobi fallback produced R (a
  lane that did not converge within its steps or stopped at a saddle);
- ``BAD_INIT``: the warm start was finite but not a rotation (the call raises,
  but for traced and ``meta`` calls, where R is NaN);
- ``NON_FINITE``: M or init held NaN/Inf; R is NaN.

Examples:
    >>> M = torch.stack([torch.eye(3), torch.full((3, 3), float("inf"))])
    >>> status = torchrot.fit_rotation_info(M).status
    >>> status == torchrot.FitStatus.NON_FINITE
    tensor([False,  True])
    >>> [torchrot.FitStatus(code).name for code in status.tolist()]
    ['CAYLEY', 'NON_FINITE']
"""

#: Every error message of the operators, by key, with its static fields
#: (limits, variants, dtypes) filled: ``MESSAGES[key].format(op=..., name=...)``.
MESSAGES: dict = _CONSTANTS["MESSAGES"]
#: The Cayley-step variants by name (``variant="..."``), and the default.
VARIANTS: tuple = _CONSTANTS["VARIANTS"]
DEFAULT_VARIANT: str = _CONSTANTS["DEFAULT_VARIANT"]
#: The dtypes the operators take (float16 and bfloat16 are computed in float32).
SUPPORTED_DTYPES: tuple = tuple(getattr(torch, name) for name in _CONSTANTS["DTYPES"])
#: The CPU kernel objects, lowest level first (torchrot.testing.cpu_kernel).
CPU_KERNELS: tuple = _CONSTANTS["CPU_KERNELS"]

#: Default damping of the derivative (the operator schemas' default).
GRADIENT_EPS: float = _CONSTANTS["DEFAULT_GRADIENT_EPS"]
#: Largest ``gradient_eps`` accepted.
MAX_GRADIENT_EPS: float = _CONSTANTS["MAX_GRADIENT_EPS"]
#: Largest ``max_iter`` accepted.
MAX_ITER: int = _CONSTANTS["MAX_ITER"]
#: A warm start is accepted when |R^T R - I|_F is below this and det R > 0.
INIT_TOLERANCE: float = _CONSTANTS["INIT_TOLERANCE"]
#: Below this deviation (INIT_CLEAN_EPS times the compute dtype's eps,
#: float32 / float64) a warm start is used as it is; above it, it first takes
#: up to INIT_CLEAN_STEPS Newton-Schulz steps.
INIT_CLEAN_EPS: float = _CONSTANTS["INIT_CLEAN_EPS"]
INIT_CLEAN: dict = {name: INIT_CLEAN_EPS * torch.finfo(getattr(torch, name)).eps for name in ("float32", "float64")}
INIT_CLEAN_STEPS: int = _CONSTANTS["INIT_CLEAN_STEPS"]
#: A result is cleaned up (a Newton-Schulz step) where a step was at least this
#: large (tan^2(theta / 2)) or it took more than STEPS_WITHOUT_CLEAN_UP steps.
LARGE_STEP: float = _CONSTANTS["LARGE_STEP"]
STEPS_WITHOUT_CLEAN_UP: int = _CONSTANTS["STEPS_WITHOUT_CLEAN_UP"]
#: A step is the last only if undamped: c - tr S <= UNDAMPED |tr S| (sqrt(eps),
#: float32 / float64 compute).
UNDAMPED: dict = {"float32": _CONSTANTS["UNDAMPED_FLOAT"], "float64": _CONSTANTS["UNDAMPED_DOUBLE"]}
#: Laguerre steps at most for the maximal objective of a cold start.
OBJECTIVE_LAGUERRE_STEPS: int = _CONSTANTS["OBJECTIVE_LAGUERRE_STEPS"]
#: Converged mode: steps per start or escape, saddle escapes, Gershgorin
#: steps, early switch of the estimate, maximum-check slack (units of eps).
CONVERGED_CAP: int = _CONSTANTS["CONVERGED_CAP"]
MAX_ESCAPES: int = _CONSTANTS["MAX_ESCAPES"]
GERSHGORIN_STEPS: int = _CONSTANTS["GERSHGORIN_STEPS"]
ESTIMATE_SWITCH: float = _CONSTANTS["ESTIMATE_SWITCH"]
MAX_CHECK_SLACK_EPS: float = _CONSTANTS["MAX_CHECK_SLACK_EPS"]


def dtype_name(dtype: torch.dtype) -> str:
    """"float32" for torch.float32: the key of the per-dtype tables above
    (INIT_CLEAN, UNDAMPED: the kernel's Tolerances<T>)."""
    return str(dtype).removeprefix("torch.")


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype a fit of ``dtype`` matrices computes in: float16 and bfloat16
    in float32 (results are rounded back to their dtype), others in their own;
    the Python twin of the C++ operators' ``compute_dtype`` (csrc/ops/layout.h)."""
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype
