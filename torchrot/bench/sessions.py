"""Scripted sessions that drive the solvers frame by frame.

ARAP: an "interactive editing session" on a surface: the vertices at the low
end of its longest axis stay put, those at the high end are dragged (bent
forth and back about an axis across the surface, twisted about the long axis,
pulled sideways) over a number of frames; each frame runs a few local-global
iterations from the previous frame's positions and rotations, as an
interactive tool would.

Elasticity: a tetrahedral body dropped onto the ground plane, tilted and
spinning; each frame is one implicit time step.

Both take an optional recorder (:class:`torchrot.bench.recording.Recorder`)
that sees every local step.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from torchrot.apps.arap import ArapSolver, ArapState
from torchrot.apps.elasticity import ElasticitySolver, ElasticState
from torchrot.apps.local_step import LocalStep
from torchrot.apps.meshes import end_regions

__all__ = ["DropScript", "HandleScript", "run_arap_session", "run_elasticity_session"]


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` (radians) about the unit ``axis`` (Rodrigues)."""
    x, y, z = axis
    K = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


@dataclass
class HandleScript:
    """The scripted drag of an ARAP session.

    At time s = frame / (frames - 1) in [0, 1] the high-end handle is bent by
    ``bend_degrees * sin(1.5 pi s)`` (forth, then back past the rest pose)
    about an axis across the surface through the fixed handle, twisted by
    ``twist_degrees * s`` about the long axis and shifted sideways by
    ``shift * s`` times the surface's length. The low-end handle stays fixed.
    """

    frames: int = 40
    bend_degrees: float = 50.0
    twist_degrees: float = 60.0
    shift: float = 0.15
    handle_fraction: float = 0.1

    def handles(self, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(sorted handle indices, mask of the moving ones among them)."""
        low, high, _ = end_regions(V, self.handle_fraction)
        handles = np.union1d(low, high)
        return handles, np.isin(handles, high)

    def targets(self, V: np.ndarray, frame: int) -> np.ndarray:
        """Handle positions ``(h, 3)`` at ``frame`` (in :meth:`handles` order)."""
        handles, moving = self.handles(V)
        s = frame / max(self.frames - 1, 1)
        return self.targets_at(V, handles, moving, s)

    def targets_at(self, V: np.ndarray, handles: np.ndarray, moving: np.ndarray, s: float) -> np.ndarray:
        """Handle positions at script time ``s`` in [0, 1]."""
        extent = V.max(0) - V.min(0)
        long_axis = int(np.argmax(extent))
        across = (long_axis + 1) % 3
        sideways = (long_axis + 2) % 3
        u_long, u_across, u_side = np.eye(3)[long_axis], np.eye(3)[across], np.eye(3)[sideways]
        pivot = V[handles[~moving]].mean(0)  # the fixed handle: the surface bends like a cantilever
        bend = _axis_rotation(u_across, math.radians(self.bend_degrees) * math.sin(1.5 * math.pi * s))
        twist = _axis_rotation(u_long, math.radians(self.twist_degrees) * s)
        P = V[handles].copy()
        top = P[moving]
        top_centre = top.mean(0)
        top = (top - top_centre) @ twist.T + top_centre  # twist the handle about its own centre
        top = (top - pivot) @ bend.T + pivot  # swing it about the fixed end
        P[moving] = top + self.shift * s * extent[long_axis] * u_side
        return P


def run_arap_session(solver: ArapSolver, script: HandleScript, iterations: int,
                     recorder: Callable | None = None, progress: Callable[[int], None] | None = None,
                     energies: list | None = None, state: ArapState | None = None, *,
                     fit: LocalStep | None = None, timer=None) -> ArapState:
    """Runs every frame of ``script`` with ``iterations`` local-global
    iterations each; returns the last state. ``energies`` receives
    (frame, iteration, E after the local step, E after the global step)."""
    V = solver.rest.numpy()
    handles, moving = script.handles(V)
    if not np.array_equal(handles, solver.handles):
        raise ValueError("run_arap_session: the solver's handles are not the script's")
    state = state or solver.initial_state()
    for frame in range(script.frames):
        targets = script.targets_at(V, handles, moving, frame / max(script.frames - 1, 1))
        for iteration in range(iterations):
            Rt = solver.local_step(state, recorder, {"frame": frame, "iteration": iteration}, fit=fit, timer=timer)
            after_local = solver.energy(state.P, Rt) if energies is not None else None
            state = ArapState(solver.global_step(Rt, targets, timer=timer), Rt)
            if energies is not None:
                energies.append((frame, iteration, after_local, solver.energy(state.P, Rt)))
        if progress is not None:
            progress(1)
    return state


@dataclass
class DropScript:
    """The elasticity session: ``frames`` time steps of a body dropped from
    ``lift`` above the ground, tilted by ``tilt_degrees``, spinning at ``spin`` rad/s."""

    frames: int = 60
    lift: float = 0.25
    tilt_degrees: float = 20.0
    spin: float = 1.0


def run_elasticity_session(solver: ElasticitySolver, script: DropScript, recorder: Callable | None = None,
                           progress: Callable[[int], None] | None = None,
                           state: ElasticState | None = None, *, fit: LocalStep | None = None,
                           timer=None) -> ElasticState:
    """Runs ``script.frames`` time steps; returns the last state."""
    state = state or solver.initial_state(script.lift, script.tilt_degrees, script.spin)
    for frame in range(script.frames):
        state = solver.step(state, recorder, frame, fit=fit, timer=timer)
        if progress is not None:
            progress(1)
    return state
