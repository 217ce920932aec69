"""Sharding strategies of the operators for DTensor (torch.distributed.tensor),
registered through its public ``register_sharding``.

Every operator works matrix by matrix, so (per mesh dimension):

* a tensor sharded along a batch dimension stays so: the result, and
  fit_rotation_info's iterations and status, are sharded along the same
  dimension; init (fit_rotation, fit_rotation_out, fit_rotation_info) and M
  (fit_rotation_backward, against R) follow, sharded along their own copy of
  that dimension, or replicated where they broadcast along it;
* replicated tensors give replicated results;
* the two 3x3 dimensions are never split: a tensor sharded along one of them,
  or partial, is redistributed (by DTensor) to one of the above first.

fit_rotation_out writes ``out`` in place, so its placements are kept: M and
init are redistributed to out's (out follows M where M's are out's; out must
be replicated or sharded along a batch dimension, the same on every mesh
dimension: otherwise a ValueError names it).

Importing torch.distributed.tensor takes about a second, so torchrot does not
import it: :func:`install` registers the strategies at once where it has been
imported already, else as soon as it is (an import hook; nothing else is
imported or run before that).
"""
from __future__ import annotations

import importlib.abc
import importlib.util
import sys

import torch

from torchrot._constants import MESSAGES

__all__ = ["install", "registered"]

_MODULE = "torch.distributed.tensor"
_state = {"registered": False}


def registered() -> bool:
    """Whether the strategies are registered (torch.distributed.tensor was imported)."""
    return _state["registered"]


def _follow(spec, dim: int, ndim: int, size: int, shard, replicate):
    """The placement of an argument ``spec`` (broadcast against a tensor of
    ``ndim`` dimensions) for that tensor sharded along batch dimension
    ``dim`` of size ``size``: sharded along its own copy of it, replicated
    where it lacks it or broadcasts along it (None for an absent argument)."""
    if spec is None:
        return None
    own = dim - (ndim - len(spec.shape))
    if own < 0 or spec.shape[own] != size:
        return replicate
    return shard(own)


def _strategies(ref, others, outputs: int):
    """Single-mesh-dimension strategies for an operator on matrices: every
    tensor replicated, or sharded along each batch dimension of ``ref`` (the
    tensor whose shape the result has), ``others`` following it. Each
    strategy: ``outputs`` result placements, then ref's, then the others'."""
    from torch.distributed.tensor import Replicate, Shard

    ndim = len(ref.shape)
    result = [[Replicate()] * outputs + [Replicate()] + [None if o is None else Replicate() for o in others]]
    for dim in range(ndim - 2):
        placements = [_follow(o, dim, ndim, ref.shape[dim], Shard, Replicate()) for o in others]
        result.append([Shard(dim)] * outputs + [Shard(dim)] + placements)
    return result


def _out_strategy(M, init, out):
    """fit_rotation_out's one strategy: out's own placement (see the module docstring)."""
    from torch.distributed.tensor import Replicate, Shard

    placements = set(out.placements)
    placement = next(iter(placements))
    batch = isinstance(placement, Shard) and placement.dim < len(out.shape) - 2
    if len(placements) != 1 or not (batch or isinstance(placement, Replicate)):
        raise ValueError(MESSAGES["OUT_PLACEMENT"].format(op=MESSAGES["OP_NAME"], placements=list(out.placements)))
    if isinstance(placement, Replicate):
        return [[Replicate(), None if init is None else Replicate(), Replicate()]]
    dim, size = placement.dim, out.shape[placement.dim]
    follow = [_follow(t, dim, len(out.shape), size, Shard, Replicate()) for t in (M, init)]
    return [[*follow, Shard(dim)]]


def _register() -> None:
    from torch.distributed.tensor.experimental import register_sharding

    ops = torch.ops.torchrot

    @register_sharding(ops.fit_rotation.default)
    def _fit_rotation(M, init=None, max_iter=None, variant=None, gradient_eps=None):
        return [(s[:1], s[1:] + [None, None, None]) for s in _strategies(M, [init], 1)]

    @register_sharding(ops.fit_rotation_info.default)
    def _fit_rotation_info(M, init=None, max_iter=None, variant=None):
        return [(s[:3], s[3:] + [None, None]) for s in _strategies(M, [init], 3)]

    @register_sharding(ops.fit_rotation_backward.default)
    def _fit_rotation_backward(grad, R, M, gradient_eps=None):
        # R's shape is the result's; grad has it too, M broadcasts to it.
        return [(s[:1], [s[2], s[1], s[3], None]) for s in _strategies(R, [grad, M], 1)]

    @register_sharding(ops.fit_rotation_out.default)
    def _fit_rotation_out(M, init, max_iter, variant, out):
        return [([], [m, i, None, None, o]) for m, i, o in _out_strategy(M, init, out)]

    _state["registered"] = True


class _RegisterAfterImport(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Registers the strategies right after torch.distributed.tensor is
    imported: it finds the module's spec through the other finders and runs
    the module's own loader, then _register."""

    def find_spec(self, fullname, path, target=None):
        if fullname != _MODULE:
            return None
        sys.meta_path.remove(self)  # once: the other finders find the real module
        spec = importlib.util.find_spec(fullname)
        if spec is None or spec.loader is None:
            return spec
        self._loader = spec.loader
        spec.loader = self
        return spec

    def create_module(self, spec):
        return self._loader.create_module(spec)

    def exec_module(self, module):
        self._loader.exec_module(module)
        _register()


def install() -> None:
    """Registers the strategies now if torch.distributed.tensor is imported,
    else when it is; nothing where torch has no distributed support."""
    if _state["registered"] or not torch.distributed.is_available():
        return
    if _MODULE in sys.modules:
        _register()
    elif not any(isinstance(finder, _RegisterAfterImport) for finder in sys.meta_path):
        sys.meta_path.insert(0, _RegisterAfterImport())
