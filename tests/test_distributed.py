"""DTensor (torch.distributed.tensor): the operators' sharding strategies
(torchrot/_sharding.py) and the functions on DTensors sharded along the batch.

Spawned (gloo, 2 CPU processes, marked slow): fit_rotation, fit_orthogonal,
fit_rotation_info, out=, the warm start, the derivative operator and
rigid_registration / nn.RigidRegistration on a batch-sharded DTensor give
the unsharded call's results and gradients, sharded as documented
(docs/distributed.md): a batch-sharded input stays sharded along that
dimension, a replicated one replicated, one sharded along a 3x3 dimension
is replicated first. In the default run: the strategies themselves, on specs
of each layout, and (slow, a subprocess) their registration when
torch.distributed.tensor is imported after torchrot.
"""
from __future__ import annotations

import os
import subprocess
import sys
from types import SimpleNamespace

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

import torchrot
from torchrot import _sharding

pytestmark = pytest.mark.skipif(not dist.is_available(), reason="torch without distributed support")

WORLD = 2
_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the checkout, for the subprocess


# ---------------------------------------------------------------------------
# The strategies, on specs (no process group)
# ---------------------------------------------------------------------------


def _spec(shape, *placements):
    return SimpleNamespace(shape=torch.Size(shape), placements=tuple(placements))


def test_strategies_shard_batch_dimensions_and_follow():
    from torch.distributed.tensor import Replicate, Shard

    M, init_full, init_broadcast = _spec((4, 5, 3, 3)), _spec((4, 5, 3, 3)), _spec((1, 5, 3, 3))
    strategies = _sharding._strategies(M, [init_full], 1)
    assert strategies == [[Replicate(), Replicate(), Replicate()], [Shard(0), Shard(0), Shard(0)],
                          [Shard(1), Shard(1), Shard(1)]]
    # init broadcast along dim 0, or without it: replicated there; sharded along its own copy of dim 1
    for init, dim1 in ((init_broadcast, Shard(1)), (_spec((5, 3, 3)), Shard(0)), (_spec((3, 3)), Replicate())):
        assert _sharding._strategies(M, [init], 1)[1:] == [[Shard(0), Shard(0), Replicate()],
                                                           [Shard(1), Shard(1), dim1]]
    assert _sharding._strategies(M, [None], 3)[1] == [Shard(0)] * 4 + [None]
    assert _sharding._strategies(_spec((3, 3)), [None], 1) == [[Replicate(), Replicate(), None]]


def test_out_strategy_keeps_outs_placement():
    from torch.distributed.tensor import Partial, Replicate, Shard

    M = _spec((4, 5, 3, 3))
    assert _sharding._out_strategy(M, None, _spec((4, 5, 3, 3), Shard(1), Shard(1))) == [[Shard(1), None, Shard(1)]]
    assert _sharding._out_strategy(M, _spec((3, 3)), _spec((4, 5, 3, 3), Replicate())) == [
        [Replicate(), Replicate(), Replicate()]]
    for bad in ((Shard(2),), (Shard(3),), (Partial(),), (Shard(0), Replicate())):
        with pytest.raises(ValueError, match=r"^torchrot\.fit_rotation: on a DTensor, out must be replicated or "
                                             r"sharded along a batch dimension.*got \["):
            _sharding._out_strategy(M, None, _spec((4, 5, 3, 3), *bad))


@pytest.mark.slow  # a subprocess (~5 s)
def test_registered_when_torch_distributed_tensor_is_imported_later():
    code = (
        "import sys, torch, torchrot\n"
        "assert 'torch.distributed.tensor' not in sys.modules, 'torchrot imported it'\n"
        "assert not torchrot._sharding.registered()\n"
        "import torch.distributed.tensor\n"
        "assert torchrot._sharding.registered()\n"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(_ROOT), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr


# ---------------------------------------------------------------------------
# Two processes (gloo): sharded calls against unsharded ones
# ---------------------------------------------------------------------------


def _data():
    gen = torch.Generator().manual_seed(3)
    M = torch.randn(6, 5, 3, 3, generator=gen, dtype=torch.float64)
    W = torch.randn(6, 5, 3, 3, generator=gen, dtype=torch.float64)
    x = torch.randn(6, 12, 3, generator=gen, dtype=torch.float64)
    y = 2.0 * x @ torchrot.fit_orthogonal(M[:, 0]).mT + 0.1 * torch.randn(6, 12, 3, generator=gen,
                                                                           dtype=torch.float64)
    w = torch.rand(6, 12, generator=gen, dtype=torch.float64) + 0.5
    return M, W, x, y, w


def _sharded_cases(mesh, placement):
    """name -> (the sharded call's result as (full tensor, placements) pairs, the unsharded result)."""
    from torch.distributed.tensor import Replicate, distribute_tensor

    M, W, x, y, w = _data()
    Md = distribute_tensor(M, mesh, [placement])
    Wd = distribute_tensor(W, mesh, [placement])
    init = torchrot.fit_rotation(M)
    results = {}

    def record(name, sharded, plain):
        sharded = sharded if isinstance(sharded, tuple) else (sharded,)
        plain = plain if isinstance(plain, tuple) else (plain,)
        results[name] = ([(t.full_tensor(), tuple(t.placements)) for t in sharded], list(plain))

    record("fit_rotation", torchrot.fit_rotation(Md), torchrot.fit_rotation(M))
    record("fit_orthogonal", torchrot.fit_orthogonal(Md), torchrot.fit_orthogonal(M))
    record("fit_rotation_info", tuple(torchrot.fit_rotation_info(Md)), tuple(torchrot.fit_rotation_info(M)))
    record("init_sharded", torchrot.fit_rotation(Md, distribute_tensor(init, mesh, [placement]), max_iter=1),
           torchrot.fit_rotation(M, init, max_iter=1))
    record("init_broadcast", torchrot.fit_rotation(Md, distribute_tensor(init[0], mesh, [Replicate()]), max_iter=1),
           torchrot.fit_rotation(M, init[0], max_iter=1))
    Q0 = torchrot.fit_orthogonal(M)
    record("orthogonal_init", torchrot.fit_orthogonal(Md, distribute_tensor(Q0, mesh, [placement]), max_iter=1),
           torchrot.fit_orthogonal(M, Q0, max_iter=1))
    Rd, R = torchrot.fit_rotation(Md), torchrot.fit_rotation(M)
    record("fit_rotation_backward", torch.ops.torchrot.fit_rotation_backward(Wd, Rd, Md),
           torch.ops.torchrot.fit_rotation_backward(W, R, M))
    for fit in (torchrot.fit_rotation, torchrot.fit_orthogonal):
        Mg, M0 = Md.detach().requires_grad_(), M.clone().requires_grad_()
        (fit(Mg) * Wd).sum().backward()
        (fit(M0) * W).sum().backward()
        record(f"{fit.__name__}_gradient", Mg.grad, M0.grad)
    if placement.is_shard() and placement.dim >= 2:  # out is written in place: it must not be split within matrices
        return results
    for fit in (torchrot.fit_rotation, torchrot.fit_orthogonal):
        out = distribute_tensor(torch.zeros_like(M), mesh, [placement])
        fit(Md, out=out)
        record(f"{fit.__name__}_out", out, fit(M))
    return results


def _registration_cases(mesh):
    from torch.distributed.tensor import Shard, distribute_tensor

    _, _, x, y, w = _data()
    results = {}
    for scale in (False, True):
        for allow_reflection in (False, True):
            for weighted in (False, True):
                xs, ys, ws = (distribute_tensor(t, mesh, [Shard(0)]).requires_grad_() for t in (x, y, w))
                x0, y0, w0 = (t.clone().requires_grad_() for t in (x, y, w))
                layer = torchrot.nn.RigidRegistration(scale=scale, allow_reflection=allow_reflection)
                sharded = layer(xs, ys, ws if weighted else None)
                plain = layer(x0, y0, w0 if weighted else None)
                sum(t.sum() for t in sharded).backward()
                sum(t.sum() for t in plain).backward()
                grads = [(xs.grad, x0.grad), (ys.grad, y0.grad)] + ([(ws.grad, w0.grad)] if weighted else [])
                results[(scale, allow_reflection, weighted)] = (
                    [(t.full_tensor(), tuple(t.placements)) for t in (*sharded, *(g for g, _ in grads))],
                    [*plain, *(g for _, g in grads)])
    return results


def _out_placement_error(mesh):
    from torch.distributed.tensor import Shard, distribute_tensor

    M = distribute_tensor(_data()[0], mesh, [Shard(0)])
    out = distribute_tensor(torch.zeros(6, 5, 3, 3, dtype=torch.float64), mesh, [Shard(3)])
    try:
        torchrot.fit_rotation(M, out=out)
    except RuntimeError as error:
        return type(error.__cause__).__name__, str(error.__cause__)
    return None


def _worker(rank: int, init_file: str, result_file: str) -> None:
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=WORLD)
    try:
        from torch.distributed.tensor import Replicate, Shard, init_device_mesh

        mesh = init_device_mesh("cpu", (WORLD,))
        result = {repr(p): _sharded_cases(mesh, p) for p in (Shard(0), Shard(1), Replicate(), Shard(2), Shard(3))}
        result["registration"] = _registration_cases(mesh)
        result["out_error"] = _out_placement_error(mesh)
        torch.save(result, f"{result_file}.{rank}")
    finally:
        dist.destroy_process_group()
    os._exit(0)  # as tests/test_nn.py's workers: no gloo teardown abort after the results are saved


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    folder = tmp_path_factory.mktemp("dtensor")
    mp.spawn(_worker, args=(str(folder / "init"), str(folder / "result")), nprocs=WORLD, join=True)
    return [torch.load(f"{folder / 'result'}.{rank}", weights_only=False) for rank in range(WORLD)]


#: How a DTensor input placed along the key comes out (docs/distributed.md).
EXPECTED_PLACEMENT = {"Shard(dim=0)": "Shard(dim=0)", "Shard(dim=1)": "Shard(dim=1)", "Replicate()": "Replicate()",
                      "Shard(dim=2)": "Replicate()", "Shard(dim=3)": "Replicate()"}


@pytest.mark.slow  # spawns 2 processes (~20 s)
@pytest.mark.parametrize("placement", sorted(EXPECTED_PLACEMENT))
def test_sharded_operators_equal_the_unsharded_call(results, placement):
    for rank_result in results:
        for name, (sharded, plain) in rank_result[placement].items():
            for (got, placements), want in zip(sharded, plain, strict=True):
                assert [repr(p) for p in placements] == [EXPECTED_PLACEMENT[placement]], (name, placements)
                if name.endswith("gradient"):  # summed in another order where the loss is reduced
                    torch.testing.assert_close(got, want, rtol=1e-13, atol=1e-13)
                else:
                    assert torch.equal(got, want), name


@pytest.mark.slow  # spawns 2 processes (~20 s)
def test_sharded_registration_equals_the_unsharded_call(results):
    for rank_result in results:
        for options, (sharded, plain) in rank_result["registration"].items():
            for (got, placements), want in zip(sharded, plain, strict=True):
                assert [repr(p) for p in placements] == ["Shard(dim=0)"], options
                torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.slow  # spawns 2 processes (~20 s)
def test_out_split_within_matrices_raises_naming_out(results):
    for rank_result in results:
        kind, message = rank_result["out_error"]
        assert kind == "ValueError"
        assert message.startswith("torchrot.fit_rotation: on a DTensor, out must be replicated or sharded along a "
                                  "batch dimension") and "got [Shard(dim=3)]" in message
