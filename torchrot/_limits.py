"""torchrot's limits, defaults and tolerances, read from the C++ extension.

They are defined once, in csrc/limits.h (explained there), and handed over by
``torchrot._C.constants()``: the argument checks, the fake kernels and the
pure-PyTorch path use exactly the kernel's values.
"""
from __future__ import annotations

from torchrot import _C

_CONSTANTS = _C.constants()

#: Default damping of the derivative (the operator schemas' default).
GRADIENT_EPS: float = _CONSTANTS["DEFAULT_GRADIENT_EPS"]
#: Largest ``gradient_eps`` accepted.
MAX_GRADIENT_EPS: float = _CONSTANTS["MAX_GRADIENT_EPS"]
#: Largest ``max_iter`` accepted.
MAX_ITER: int = _CONSTANTS["MAX_ITER"]
#: A warm start is accepted when |R^T R - I|_F is below this and det R > 0.
INIT_TOLERANCE: float = _CONSTANTS["INIT_TOLERANCE"]
#: Below this deviation (float32 / float64 compute) a warm start is used as
#: it is; above it, it first takes up to INIT_CLEAN_STEPS Newton-Schulz steps.
INIT_CLEAN: dict = {"float32": _CONSTANTS["INIT_CLEAN_FLOAT"], "float64": _CONSTANTS["INIT_CLEAN_DOUBLE"]}
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
