"""Named data sets of covariance matrices recorded from the solvers, cached.

``"arap"``: an interactive ARAP session (:class:`~torchrot.bench.sessions.HandleScript`)
on the built-in 57,346-vertex capsule (or a user surface); ``"elasticity"``:
the built-in tetrahedral octopus (24,054 tets) dropped onto the ground
(:class:`~torchrot.bench.sessions.DropScript`). Each is recorded with
:class:`~torchrot.bench.recording.Recorder` (M, the warm start R_prev and
M_local = R_prev^T M of every local step) into a cache folder named after a
hash of its configuration, so the second request loads it instead of running
the solver again.

Cache root: the ``cache`` argument, else ``$TORCHROT_CACHE``, else
``$XDG_CACHE_HOME/torchrot``, else ``~/.cache/torchrot``.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import shutil
import time
from dataclasses import dataclass

import torch

from torchrot.bench.progress import progress_bar
from torchrot.bench.recording import Recorder, Recording, is_complete, load_recording

__all__ = [
    "ArapDataConfig", "DATA_VERSION", "DEFAULTS", "ElasticityDataConfig", "RECORDED", "cache_root",
    "dataset_folder", "ensure_dataset", "load_dataset", "pairs", "warm_start_pairs"
]

#: Bumped whenever the generators change what they record (old caches are then ignored).
DATA_VERSION = 1


@dataclass(frozen=True)
class ArapDataConfig:
    """What the "arap" data set records.

    resolution: of the built-in capsule (64: 57,346 vertices); ignored with
        ``mesh_path`` (any OBJ/OFF/PLY/STL surface).
    frames, iterations: the session's frames and local-global iterations per frame.
    fit: the local step that drives the session ("converged", "one_step", "svd").
    max_per_step: vertices recorded per local step (a fixed random subset); None: all.
    """

    resolution: int = 64
    mesh_path: str | None = None
    frames: int = 40
    iterations: int = 3
    fit: str = "converged"
    max_per_step: int | None = 2000


@dataclass(frozen=True)
class ElasticityDataConfig:
    """What the "elasticity" data set records: the built-in octopus at
    ``resolution`` (24: 24,054 tets), ``frames`` time steps of ``iterations``
    local-global iterations, ``max_per_step`` tets recorded per local step."""

    resolution: int = 24
    frames: int = 60
    iterations: int = 5
    fit: str = "converged"
    max_per_step: int | None = 800


#: data set name -> its default configuration.
DEFAULTS = {"arap": ArapDataConfig(), "elasticity": ElasticityDataConfig()}
RECORDED = tuple(DEFAULTS)


def cache_root(cache: str | None = None) -> str:
    """The cache folder (see the module docstring)."""
    if cache:
        return os.path.abspath(os.path.expanduser(cache))
    if os.environ.get("TORCHROT_CACHE"):
        return os.path.abspath(os.path.expanduser(os.environ["TORCHROT_CACHE"]))
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "torchrot")


def _config(name: str, config=None):
    if name not in DEFAULTS:
        raise ValueError(f"unknown recorded data set {name!r}; known: {', '.join(RECORDED)}")
    config = DEFAULTS[name] if config is None else config
    if type(config) is not type(DEFAULTS[name]):
        raise TypeError(f"data set {name!r} takes a {type(DEFAULTS[name]).__name__}, got {type(config).__name__}")
    return config


def _key(name: str, config) -> dict:
    key = {"name": name, "version": DATA_VERSION, **dataclasses.asdict(config)}
    path = key.get("mesh_path")
    if path:  # a user mesh: its identity is its content's size and time
        stat = os.stat(path)
        key.update(mesh_path=os.path.abspath(path), mesh_size=stat.st_size, mesh_mtime=stat.st_mtime)
    return key


def dataset_folder(name: str, config=None, cache: str | None = None) -> str:
    """The cache folder of data set ``name`` with ``config``."""
    key = _key(name, _config(name, config))
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
    return os.path.join(cache_root(cache), "datasets", f"{name}-{digest}")


def _generate_arap(config: ArapDataConfig, folder: str, progress: bool) -> dict:
    from torchrot.apps.arap import ArapSolver
    from torchrot.apps.local_step import LocalStep
    from torchrot.apps.meshes import capsule, load_surface
    from torchrot.bench.sessions import HandleScript, run_arap_session

    mesh = load_surface(config.mesh_path) if config.mesh_path else capsule(config.resolution)
    script = HandleScript(frames=config.frames)
    handles, _ = script.handles(mesh.V)
    solver = ArapSolver(mesh.V, mesh.F, handles, LocalStep(config.fit))
    recorder = Recorder(folder, "arap", mesh.name, config.max_per_step)
    bar = progress_bar(config.frames, f"recording arap ({len(mesh.V):,} vertices), frames", progress)
    run_arap_session(solver, script, config.iterations, recorder, bar.update if bar else None)
    if bar:
        bar.close()
    return recorder.finish({**_key("arap", config), "vertices": len(mesh.V), "faces": len(mesh.F),
                            "script": dataclasses.asdict(script)})


def _generate_elasticity(config: ElasticityDataConfig, folder: str, progress: bool) -> dict:
    from torchrot.apps.elasticity import ElasticitySolver
    from torchrot.apps.local_step import LocalStep
    from torchrot.apps.meshes import octopus
    from torchrot.bench.sessions import DropScript, run_elasticity_session

    mesh = octopus(config.resolution)
    solver = ElasticitySolver(mesh.V, mesh.F, fit=LocalStep(config.fit), iterations=config.iterations)
    script = DropScript(frames=config.frames)
    recorder = Recorder(folder, "elasticity", mesh.name, config.max_per_step)
    bar = progress_bar(config.frames, f"recording elasticity ({len(mesh.F):,} tets), frames", progress)
    run_elasticity_session(solver, script, recorder, bar.update if bar else None)
    if bar:
        bar.close()
    return recorder.finish({**_key("elasticity", config), "vertices": len(mesh.V), "tets": len(mesh.F),
                            "script": dataclasses.asdict(script),
                            "material": dataclasses.asdict(solver.material)})


def ensure_dataset(name: str, config=None, cache: str | None = None, progress: bool = True) -> str:
    """The folder of a finished recording of ``name``: from the cache, or
    recorded now (written to a temporary folder and renamed when complete,
    so an interrupted run never leaves a half data set behind)."""
    config = _config(name, config)
    folder = dataset_folder(name, config, cache)
    if is_complete(folder):
        return folder
    partial = f"{folder}.partial-{os.getpid()}"
    shutil.rmtree(partial, ignore_errors=True)
    start = time.perf_counter()
    generate = _generate_arap if name == "arap" else _generate_elasticity
    manifest = generate(config, partial, progress)
    manifest["generation_seconds"] = time.perf_counter() - start
    with open(os.path.join(partial, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=1)
    if is_complete(folder):  # another process finished first
        shutil.rmtree(partial, ignore_errors=True)
    else:
        shutil.rmtree(folder, ignore_errors=True)
        os.replace(partial, folder)
    return folder


@functools.lru_cache(maxsize=4)
def _load(folder: str) -> Recording:
    return load_recording(folder)


def load_dataset(name: str, config=None, cache: str | None = None, progress: bool = True) -> Recording:
    """The recording of ``name`` (recorded first if not cached)."""
    return _load(ensure_dataset(name, config, cache, progress))


def warm_start_pairs(name: str, n: int, seed: int = 0, dtype: torch.dtype = torch.float64,
                     config=None, cache: str | None = None,
                     progress: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """``(M, init)`` ``(n, 3, 3)`` for the benchmark, like
    :func:`torchrot.testing.make_warm_start`: recorded covariances M and the
    warm starts R_prev the solver had for them, so the answer is close to init.

    n matrices drawn without replacement (seeded) from the whole recording;
    when n exceeds the recording, it is repeated (whole copies, then a draw).
    """
    if n < 1:
        raise ValueError(f"warm_start_pairs: n must be >= 1, got {n}")
    recording = load_dataset(name, config, cache, progress)
    total = len(recording)
    gen = torch.Generator().manual_seed(seed)
    copies, rest = divmod(n, total)
    index = torch.cat([torch.arange(total).repeat(copies), torch.randperm(total, generator=gen)[:rest]])
    return recording.M[index].to(dtype), recording.R_prev[index].to(dtype)


def pairs(name: str, n: int, dtype: torch.dtype = torch.float64, seed: int = 0, configs: dict | None = None,
          cache: str | None = None, progress: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """``(M, init)`` ``(n, 3, 3)`` of data set ``name``: a recorded data set
    (:data:`RECORDED`, with its configuration from ``configs``, name ->
    config, else the default, from ``cache``) or any distribution of
    :func:`torchrot.testing.make_warm_start`."""
    if name in RECORDED:
        return warm_start_pairs(name, n, seed, dtype, (configs or {}).get(name), cache, progress)
    from torchrot.testing.data import make_warm_start

    return make_warm_start(name, n, seed, dtype)
