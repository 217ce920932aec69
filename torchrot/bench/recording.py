"""Recording a solver's local steps, as the paper's Section 6.1 describes.

Each local step's covariances M are saved with the warm start R_prev (the
rotation of the previous iteration or frame; the identity before the first
step) and M_local = R_prev^T M, the covariance with that rotation factored out,
whose optimal rotation R_prev^T R* is close to the identity. Convention:
R* maximises tr(R^T M) (column vectors; M = sum_i w_i y_i x_i^T gives
R x_i ~ y_i), so the optimal rotation of M_local is R_prev^T R*.

Layout of a recording folder::

    step_00000.pt ...   one file per local step: {"M", "R_prev", "M_local",
                        "index", "meta"}; M, R_prev, M_local (k, 3, 3) float64,
                        index (k,) the recorded elements (vertices or tets),
                        meta {"app", "mesh", "frame", "iteration", "step"
                        (the local step's number), "elements" (recorded),
                        "elements_total"}
    manifest.json       written last: the configuration and counts; a folder
                        without it is an interrupted recording
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass

import torch

__all__ = ["MANIFEST", "Recorder", "Recording", "is_complete", "load_recording"]

Tensor = torch.Tensor
MANIFEST = "manifest.json"


class Recorder:
    """Callable hook ``recorder(M, R_prev, meta)`` for the solvers' local steps.

    Args:
        folder: where the ``.pt`` files go (created; must not hold a finished
            recording).
        app, mesh: stored in every file's metadata.
        max_per_step: record only this many elements per local step, the same
            random subset (fixed by ``seed``) at every step; None records all.
        every: record every ``every``-th local step only.
    """

    def __init__(self, folder: str, app: str, mesh: str, max_per_step: int | None = None,
                 every: int = 1, seed: int = 0):
        if max_per_step is not None and max_per_step < 1:
            raise ValueError(f"Recorder: max_per_step must be None or >= 1, got {max_per_step}")
        if every < 1:
            raise ValueError(f"Recorder: every must be >= 1, got {every}")
        os.makedirs(folder, exist_ok=True)
        if os.path.exists(os.path.join(folder, MANIFEST)):
            raise FileExistsError(f"Recorder: {folder!r} already holds a finished recording")
        self.folder, self.app, self.mesh = folder, app, mesh
        self.max_per_step, self.every, self.seed = max_per_step, every, seed
        self.calls = 0
        self.steps = 0
        self.matrices = 0
        self._index: Tensor | None = None
        self._elements = 0

    def _subset(self, n: int) -> Tensor:
        """The recorded elements: chosen at the first step, the same ever after."""
        if self._index is None:
            if self.max_per_step is None or self.max_per_step >= n:
                self._index = torch.arange(n)
            else:
                gen = torch.Generator().manual_seed(self.seed)
                self._index = torch.randperm(n, generator=gen)[: self.max_per_step].sort().values
            self._elements = n
        elif n != self._elements:
            raise ValueError(f"Recorder: a step has {n} matrices, the first had {self._elements}")
        return self._index

    def __call__(self, M: Tensor, R_prev: Tensor | None, meta: dict) -> None:
        """Saves one local step: ``M`` ``(n, 3, 3)``, ``R_prev`` ``(n, 3, 3)``
        or None (identity), ``meta`` (frame, iteration, ...)."""
        call = self.calls
        self.calls += 1
        if call % self.every:
            return
        index = self._subset(M.shape[0])
        M = M[index].to(torch.float64).contiguous()
        if R_prev is None:
            R = torch.eye(3, dtype=torch.float64).expand_as(M).contiguous()
        else:
            R = R_prev[index].to(torch.float64).contiguous()
        record = {
            "M": M,
            "R_prev": R,
            "M_local": R.mT @ M,
            "index": index.clone(),
            "meta": {"app": self.app, "mesh": self.mesh, "step": call, "elements": int(M.shape[0]),
                     "elements_total": self._elements, **meta},
        }
        torch.save(record, os.path.join(self.folder, f"step_{self.steps:05d}.pt"))
        self.steps += 1
        self.matrices += int(M.shape[0])

    def finish(self, config: dict) -> dict:
        """Writes the manifest (the recording is complete); returns it."""
        manifest = {"app": self.app, "mesh": self.mesh, "steps": self.steps, "matrices": self.matrices,
                    "max_per_step": self.max_per_step, "every": self.every, "seed": self.seed, "config": config}
        tmp = os.path.join(self.folder, MANIFEST + ".tmp")
        with open(tmp, "w") as f:
            json.dump(manifest, f, indent=1)
        os.replace(tmp, os.path.join(self.folder, MANIFEST))
        return manifest


@dataclass
class Recording:
    """A loaded recording, every step concatenated: ``M``, ``R_prev``,
    ``M_local`` ``(N, 3, 3)`` float64; ``frame``, ``iteration``, ``step``
    ``(N,)`` int64; ``manifest`` the folder's manifest."""

    M: Tensor
    R_prev: Tensor
    M_local: Tensor
    frame: Tensor
    iteration: Tensor
    step: Tensor
    manifest: dict

    def __len__(self) -> int:
        return self.M.shape[0]


def is_complete(folder: str) -> bool:
    """Whether ``folder`` holds a finished recording."""
    return os.path.isfile(os.path.join(folder, MANIFEST))


def load_recording(folder: str) -> Recording:
    """Loads and concatenates every step of a finished recording."""
    if not is_complete(folder):
        raise FileNotFoundError(f"load_recording: no finished recording in {folder!r} (no {MANIFEST})")
    with open(os.path.join(folder, MANIFEST)) as f:
        manifest = json.load(f)
    parts: dict[str, list[Tensor]] = {k: [] for k in ("M", "R_prev", "M_local", "frame", "iteration", "step")}
    for k in range(manifest["steps"]):
        record = torch.load(os.path.join(folder, f"step_{k:05d}.pt"), weights_only=True)
        count = record["M"].shape[0]
        for key in ("M", "R_prev", "M_local"):
            parts[key].append(record[key])
        for key in ("frame", "iteration", "step"):
            parts[key].append(torch.full((count,), int(record["meta"].get(key, -1)), dtype=torch.int64))
    if not parts["M"]:
        raise ValueError(f"load_recording: {folder!r} recorded no steps")
    return Recording(**{k: torch.cat(v) for k, v in parts.items()}, manifest=manifest)
