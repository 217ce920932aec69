"""torchrot's limits, defaults, tolerances, status codes and shared error
messages, read from the C++ extension.

They are defined once, in csrc/limits.h, csrc/fit_rotation.h and
csrc/messages.h (explained there), and handed over by
``torchrot._C.constants()``: the argument checks, the fake kernels and the
pure-PyTorch path use exactly the kernel's values.
"""
from __future__ import annotations

import enum

import torch

from torchrot import _C

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
"""

#: Error messages shared by the C++ operator and the Python checks, by name.
MESSAGES: dict = _CONSTANTS["MESSAGES"]

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
