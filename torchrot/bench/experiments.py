"""The paper's application experiments (Sec. 6.3, Figs. 6 and 7) and the
ARAP validation against libigl.

- :func:`arap_phase_times`, :func:`elasticity_phase_times`: time per
  local-global iteration of each phase (covariance assembly, rotation fit,
  right-hand side, back-substitution) with each rotation fit: Fig. 6.
- :func:`arap_energy_trace`, :func:`elasticity_energy_trace`: energy after
  every local and global step against the accumulated solver time, from the
  same starting state for each rotation fit: Fig. 7 (and the check that the
  energy never increases).
- :func:`validate_arap_against_libigl`: the converged ARAP energy of every
  rotation fit and of ``igl.arap_solve`` on the same mesh, handles and start.

Solver times exclude the energy evaluations (which only the experiments do).
Each run passes its rotation fit and its :class:`PhaseTimer` to the solver
calls as arguments: no solver is modified. Every function returns plain
Python data (for JSON).
"""
from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import torch

from torchrot.apps.arap import ArapSolver, ArapState
from torchrot.apps.elasticity import ElasticitySolver, ElasticState
from torchrot.apps.local_step import LocalStep
from torchrot.apps.meshes import Mesh
from torchrot.bench.sessions import DropScript, HandleScript, run_arap_session, run_elasticity_session
from torchrot.bench.timing import PhaseTimer

__all__ = [
    "FITS", "GLOBAL", "LOCAL", "arap_energy_trace", "arap_phase_times", "arap_solver", "arap_start_state",
    "elasticity_energy_trace", "elasticity_phase_times", "elasticity_start_state", "torch_threads",
    "validate_arap_against_libigl"
]

FITS = ("svd", "one_step", "converged")
LOCAL = ("assembly", "fit")
GLOBAL = ("rhs", "solve")


@contextlib.contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """Runs the block with ``threads`` torch threads (None: unchanged)."""
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _summary(timer: PhaseTimer, skip: int = 1) -> dict:
    """Median ms per phase over the iterations after the first ``skip``
    (the first local step of a run has no warm start), local/global totals."""
    per_phase = {name: values[skip:] or values for name, values in timer.seconds.items() if name != "refactor"}
    count = min(len(v) for v in per_phase.values())
    local = [sum(per_phase[p][i] for p in LOCAL) for i in range(count)]
    global_ = [sum(per_phase[p][i] for p in GLOBAL) for i in range(count)]
    ms = {name: float(np.median(v)) * 1e3 for name, v in per_phase.items()}
    ms["local"] = float(np.median(local)) * 1e3
    ms["global"] = float(np.median(global_)) * 1e3
    ms["iterations"] = count
    return ms


def _iteration_seconds(timer: PhaseTimer) -> list[float]:
    """Solver seconds of each iteration (the four phases, refactorization excluded)."""
    count = len(timer.seconds["fit"])
    return [sum(timer.seconds[p][i] for p in LOCAL + GLOBAL) for i in range(count)]


# -- ARAP -------------------------------------------------------------------------
def arap_solver(mesh: Mesh, script: HandleScript, fit: str = "one_step",
                dtype: torch.dtype = torch.float64) -> ArapSolver:
    """The ARAP solver of ``mesh`` with ``script``'s handles, local step in ``dtype``."""
    handles, _ = script.handles(mesh.V)
    return ArapSolver(mesh.V, mesh.F, handles, LocalStep(fit), dtype=dtype)


def arap_start_state(solver: ArapSolver, script: HandleScript, frames: int, iterations: int) -> ArapState:
    """The state after the first ``frames`` frames of ``script`` (its handle
    path at its own pace), ``iterations`` converged-fit iterations each."""
    converged = LocalStep("converged")
    V = solver.rest.numpy()
    handles, moving = script.handles(V)
    state = solver.initial_state()
    for frame in range(frames):
        targets = script.targets_at(V, handles, moving, frame / max(script.frames - 1, 1))
        for _ in range(iterations):
            state = solver.iterate(state, targets, fit=converged)
    return state


def arap_phase_times(mesh: Mesh, script: HandleScript, frames: int = 6, iterations: int = 4,
                     fits: tuple[str, ...] = FITS, threads: int | None = 1,
                     dtype: torch.dtype = torch.float32) -> dict:
    """Fig. 6 for ARAP: median ms per phase per iteration for each rotation
    fit, over ``frames`` frames (the script compressed to them) of
    ``iterations`` iterations each, local step in ``dtype``."""
    with torch_threads(threads):
        start = time.perf_counter()
        solver = arap_solver(mesh, script, dtype=dtype)
        precompute = time.perf_counter() - start
        short = replace(script, frames=frames)
        result = {"mesh": mesh.name, "vertices": len(mesh.V), "faces": len(mesh.F), "handles": len(solver.handles),
                  "precompute_s": precompute, "factor_fill": solver._K_free.fill, "threads": threads,
                  "dtype": str(dtype).replace("torch.", ""),
                  "frames": frames, "iterations_per_frame": iterations, "fits": {}}
        for fit in fits:
            timer = PhaseTimer()
            run_arap_session(solver, short, iterations, fit=LocalStep(fit), timer=timer)
            result["fits"][fit] = _summary(timer)
    return result


def arap_energy_trace(mesh: Mesh, script: HandleScript, start_frame: int = 10, jump_frames: int = 4,
                      iterations: int = 60, reference_iterations: int = 200, fits: tuple[str, ...] = FITS,
                      threads: int | None = 1, warmup_iterations: int = 4) -> dict:
    """Fig. 7 for ARAP. From the converged state at frame ``start_frame`` of
    ``script`` (rotations included, as an interactive tool has them), the
    handle jumps ``jump_frames`` frames ahead and each fit iterates
    ``iterations`` times. Records the energy after every local and global
    step and the accumulated solver time. The reference energy is the
    converged fit's after ``reference_iterations`` more iterations."""
    with torch_threads(threads):
        solver = arap_solver(mesh, script)
        start = arap_start_state(solver, script, start_frame + 1, warmup_iterations)
        V = solver.rest.numpy()
        handles, moving = script.handles(V)
        targets = script.targets_at(V, handles, moving, (start_frame + jump_frames) / max(script.frames - 1, 1))
        result = {"mesh": mesh.name, "vertices": len(mesh.V), "start_frame": start_frame,
                  "jump_frames": jump_frames, "iterations": iterations, "threads": threads,
                  "start_energy": solver.energy(start.P, start.Rt), "fits": {}}
        for fit in fits:
            local, timer = LocalStep(fit), PhaseTimer()
            state = ArapState(start.P.clone(), start.Rt.clone())
            after_local, after_global = [], []
            for _ in range(iterations):
                Rt = solver.local_step(state, fit=local, timer=timer)
                after_local.append(solver.energy(state.P, Rt))
                state = ArapState(solver.global_step(Rt, targets, timer=timer), Rt)
                after_global.append(solver.energy(state.P, Rt))
            result["fits"][fit] = _trace(timer, after_local, after_global, result["start_energy"])
            result["fits"][fit]["final_optimal_energy"] = solver.energy(state.P)
            if fit == "converged" or "converged" not in fits:
                reference = state
        state, converged = reference, LocalStep("converged")
        for _ in range(reference_iterations):
            state = solver.iterate(state, targets, fit=converged)
        result["reference_energy"] = solver.energy(state.P)  # the converged fit's, continued
        result["reference_iterations"] = iterations + reference_iterations
    return result


def _trace(timer: PhaseTimer, after_local: list[float], after_global: list[float],
           before: float | None = None) -> dict:
    """The energy sequence of a run (``before`` it, then after each local and
    global step) with its largest relative increase between consecutive
    entries. With ``before`` (ARAP), the first global step moves the handles,
    which changes the problem: the check skips that one transition."""
    seconds = np.cumsum(_iteration_seconds(timer)).tolist()
    sequence = [e for pair in zip(after_local, after_global) for e in pair]
    diffs = np.diff(sequence)
    if before is not None:
        diffs = np.concatenate([[sequence[0] - before], diffs[1:]])  # skip local 1 -> global 1 (handles move)
    scale = max(abs(sequence[-1]), 1e-300)
    return {"seconds": seconds, "energy": after_global, "energy_after_local": after_local,
            "max_relative_increase": float(max(diffs.max(initial=0.0), 0.0) / scale),
            "increases": int(np.sum(diffs > 0)), "phase_ms": _summary(timer, skip=0)}


def validate_arap_against_libigl(mesh: Mesh, script: HandleScript, iterations: int = 1000,
                                 start_frame: int = 10, jump_frames: int = 2, fits: tuple[str, ...] = FITS,
                                 threads: int | None = 1, dtype: torch.dtype = torch.float64) -> dict:
    """Converged ARAP energy of every rotation fit vs ``igl.arap_solve``
    (spokes energy, same cotangent weights), from the same start: the state
    at frame ``start_frame`` of the session (rotations included), handles
    then moved ``jump_frames`` frames ahead, as between two frames of an
    interactive session. Each solver runs ``iterations`` iterations;
    energies are evaluated by :meth:`ArapSolver.energy` with optimal rotations
    (float64); ``dtype`` is the local step's precision."""
    import igl

    with torch_threads(threads):
        solver = arap_solver(mesh, script, dtype=dtype)
        start = arap_start_state(solver, script, start_frame + 1, 4)
        V = solver.rest.numpy()
        handles, moving = script.handles(V)
        targets = script.targets_at(V, handles, moving, (start_frame + jump_frames) / max(script.frames - 1, 1))
        result = {"mesh": mesh.name, "vertices": len(mesh.V), "iterations": iterations, "start_frame": start_frame,
                  "jump_frames": jump_frames, "dtype": str(dtype).replace("torch.", ""), "fits": {}}
        for fit in fits:
            local = LocalStep(fit)
            state = ArapState(start.P.clone(), start.Rt.clone())
            energies = []
            for _ in range(iterations):
                state = solver.iterate(state, targets, fit=local)
                energies.append(solver.energy(state.P, state.Rt))
            diffs = np.diff(energies)
            result["fits"][fit] = {"energy": solver.energy(state.P),
                                   "last_relative_change": float(abs(diffs[-1]) / energies[-1]),
                                   "max_relative_increase": float(max(diffs.max(), 0.0) / energies[-1])}
        data = igl.ARAPData()
        data.energy = igl.ARAP_ENERGY_TYPE_SPOKES
        data.max_iter = iterations
        igl.arap_precomputation(V, np.ascontiguousarray(mesh.F, dtype=np.int64), 3,
                                solver.handles.astype(np.int32), data)
        U0 = start.P.numpy().copy()
        U0[solver.handles] = targets
        clock = time.perf_counter()
        U = igl.arap_solve(np.ascontiguousarray(targets), data, U0)
        result["libigl"] = {"energy": solver.energy(torch.from_numpy(np.ascontiguousarray(U))),
                            "seconds": time.perf_counter() - clock}
        reference = result["libigl"]["energy"]
        for fit in fits:
            result["fits"][fit]["relative_difference_to_libigl"] = \
                (result["fits"][fit]["energy"] - reference) / reference
        svd = result["fits"].get("svd", {}).get("energy")
        if svd is not None:
            for fit in fits:
                result["fits"][fit]["relative_difference_to_svd"] = (result["fits"][fit]["energy"] - svd) / svd
    return result


# -- elasticity --------------------------------------------------------------------
def elasticity_start_state(solver: ElasticitySolver, script: DropScript, frames: int) -> ElasticState:
    """The state after the first ``frames`` time steps (converged fits)."""
    return run_elasticity_session(solver, replace(script, frames=frames), fit=LocalStep("converged"))


def elasticity_phase_times(mesh: Mesh, script: DropScript, start_frame: int = 20, frames: int = 8,
                           iterations: int = 5, fits: tuple[str, ...] = FITS, threads: int | None = 1,
                           dtype: torch.dtype = torch.float32) -> dict:
    """Fig. 6 for elasticity: median ms per phase per iteration for each fit,
    over ``frames`` time steps after ``start_frame`` (the body on the
    ground), local step in ``dtype``."""
    with torch_threads(threads):
        clock = time.perf_counter()
        solver = ElasticitySolver(mesh.V, mesh.F, iterations=iterations, dtype=dtype)
        precompute = time.perf_counter() - clock
        start = elasticity_start_state(solver, script, start_frame)
        result = {"mesh": mesh.name, "vertices": len(mesh.V), "tets": len(mesh.F), "precompute_s": precompute,
                  "factor_fill": solver._solver.fill, "threads": threads, "start_frame": start_frame,
                  "dtype": str(dtype).replace("torch.", ""),
                  "frames": frames, "iterations_per_frame": iterations, "fits": {}}
        for fit in fits:
            local, timer = LocalStep(fit), PhaseTimer()
            refactors = solver.refactorizations
            state = start
            for frame in range(frames):
                state = solver.step(state, frame=start_frame + frame, fit=local, timer=timer)
            summary = _summary(timer)
            refactor = timer.seconds.get("refactor", [])
            summary["contact_refactorizations"] = solver.refactorizations - refactors
            summary["refactor_ms_median"] = float(np.median(refactor)) * 1e3 if refactor else 0.0
            result["fits"][fit] = summary
    return result


def elasticity_energy_trace(mesh: Mesh, script: DropScript, frame: int = 18, iterations: int = 30,
                            fits: tuple[str, ...] = FITS, threads: int | None = 1) -> dict:
    """Fig. 7 for elasticity: one implicit time step (``frame``, around the
    impact) solved with ``iterations`` local-global iterations by each fit,
    from the same state: the incremental potential after every local and
    global step against the accumulated solver time."""
    with torch_threads(threads):
        solver = ElasticitySolver(mesh.V, mesh.F, iterations=iterations)
        start = elasticity_start_state(solver, script, frame)
        result = {"mesh": mesh.name, "tets": len(mesh.F), "frame": frame, "iterations": iterations,
                  "threads": threads, "fits": {}}
        for fit in fits:
            timer = PhaseTimer()
            energies: list[float] = []
            solver.step(start, frame=frame, energies=energies, fit=LocalStep(fit), timer=timer)
            result["fits"][fit] = _trace(timer, energies[0::2], energies[1::2])
        finals = [result["fits"][f]["energy"][-1] for f in fits]
        result["reference_energy"] = float(min(finals))
    return result
