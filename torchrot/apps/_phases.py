"""Optional instrumentation of the solvers' phases.

The solvers take a ``timer`` argument: any object whose ``phase(name)``
returns a context manager (e.g. ``torchrot.bench.timing.PhaseTimer``), or
None for no instrumentation.
"""
from __future__ import annotations

import contextlib

__all__ = ["phase"]


def phase(timer, name: str):
    """``timer.phase(name)``, or a no-op context without a timer."""
    return contextlib.nullcontext() if timer is None else timer.phase(name)
