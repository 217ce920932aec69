"""Concurrency and resource use: calls from several Python threads at once
(the operator runs without the GIL), while another thread changes
``torch.set_num_threads``, give bit-identical results; 1e5 calls leak no
memory (resident set flat).

Convention: R (det +1) maximises tr(R^T M); column vectors.
"""
from __future__ import annotations

import gc
import os
import threading

import pytest
import torch

import torchrot
from torchrot.testing import bits, make_matrices, make_warm_start


def _same(a, b) -> bool:
    a = a if isinstance(a, tuple) else (a,)
    b = b if isinstance(b, tuple) else (b,)
    return len(a) == len(b) and all(
        x.shape == y.shape and x.dtype == y.dtype and torch.equal(bits(x), bits(y)) for x, y in zip(a, b)
    )


def _calls() -> list:
    """(name, fn) pairs: every entry point (fit, info, out=, warm start,
    strided input, backward), sizes from 1 to 20k matrices (several parallel
    chunks), both dtypes."""
    calls = []
    for dtype in (torch.float32, torch.float64):
        big = make_matrices("gaussian", 20_011, 1, dtype)
        M, init = make_warm_start("warm", 3_001, 2, dtype)
        small = make_matrices("rank1", 7, 3, dtype)
        strided = make_matrices("uniform", 2 * 4_099, 4, dtype)[::2]
        grad_M = make_matrices("ill_conditioned", 5_003, 5, dtype)
        G = make_matrices("gaussian", 5_003, 6, dtype)
        tag = str(dtype).removeprefix("torch.")

        def backward(M=grad_M, G=G):
            X = M.clone().requires_grad_()
            torchrot.fit_rotation(X).backward(G)
            return X.grad

        def out_call(M=M, init=init):
            out = torch.empty_like(M)
            torchrot.fit_rotation(M, init, max_iter=1, variant="gershgorin", out=out)
            return out

        calls += [
            (f"fit big {tag}", lambda M=big: torchrot.fit_rotation(M)),
            (f"info warm {tag}", lambda M=M, init=init: tuple(torchrot.fit_rotation_info(M, init))),
            (f"small newton {tag}", lambda M=small: torchrot.fit_rotation(M, variant="newton")),
            (f"strided {tag}", lambda M=strided: torchrot.fit_rotation(M, max_iter=3)),
            (f"out= {tag}", out_call),
            (f"backward {tag}", backward),
        ]
    return calls


def test_concurrent_calls_and_thread_count_changes(restore_threads):
    """4 Python threads run every call 6 times (or more, until the count has
    cycled) in different orders while the main thread cycles
    torch.set_num_threads through 1, 2, 3: every result is
    bit-identical to the sequential single-threaded one."""
    calls = _calls()
    torch.set_num_threads(1)
    expected = {name: fn() for name, fn in calls}
    failures, errors = [], []

    switched = threading.Event()  # every thread count has been set at least once during the calls

    def worker(seed: int):
        order = [calls[(seed + 5 * i) % len(calls)] for i in range(6 * len(calls))]
        try:
            # Every call 6 times, then again until the main thread has cycled
            # the thread count (fast calls could otherwise all finish first).
            while True:
                for name, fn in order:
                    if not _same(fn(), expected[name]):
                        failures.append(f"thread {seed}: {name}")
                if switched.is_set():
                    break
        except Exception as exc:  # surfaced in the main thread
            errors.append(f"thread {seed}: {exc!r}")

    workers = [threading.Thread(target=worker, args=(seed,)) for seed in range(4)]
    for t in workers:
        t.start()
    switches = 0
    while any(t.is_alive() for t in workers):
        torch.set_num_threads(1 + switches % 3)
        switches += 1
        if switches >= 3:
            switched.set()
        for t in workers:
            t.join(timeout=0.005)
    assert not errors, errors
    assert not failures, f"{len(failures)} results differ: {failures[:10]}"
    assert switches >= 3, "the thread count never changed during the run"


def _resident_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists("/proc/self/statm"), reason="needs /proc (Linux)")
def test_no_leak_over_1e5_calls():
    """1e5 calls through every entry point (including ones that raise)
    leave the resident set where it was after a warm-up: a leak of even 40
    bytes per call would show as 4 MB."""
    M = make_matrices("gaussian", 4, 0)
    M32 = M.float()
    init = torchrot.fit_rotation(M32)
    bad_init = torch.full((4, 3, 3), 2.0)
    out = torch.empty_like(M32)
    G = torch.ones_like(M)

    def one_round(i: int) -> None:
        kind = i % 7
        if i % 100 == 99:  # autograd (slower per call): 1,000 of the calls
            X = M.clone().requires_grad_()
            torchrot.fit_rotation(X).backward(G)
        elif kind == 0:
            torchrot.fit_rotation(M)
        elif kind == 1:
            torchrot.fit_rotation_info(M32, init, max_iter=1)
        elif kind == 2:
            torchrot.fit_rotation(M32, init, max_iter=2, variant="newton", out=out)
        elif kind == 3:
            torch.ops.torchrot.fit_rotation(M32, None, None, "gershgorin")
        elif kind == 4:
            torch.ops.torchrot.fit_rotation_backward(G, M, M, 1e-6)
        elif kind == 5:
            try:  # error path: C++ exception through the dispatcher
                torchrot.fit_rotation(M32, bad_init)
            except (RuntimeError, ValueError):
                pass
        else:
            try:
                torchrot.fit_rotation(M32, variant="nope")
            except (RuntimeError, ValueError):
                pass

    for i in range(10_000):  # warm-up: allocator pools, dispatcher caches
        one_round(i)
    gc.collect()
    before = _resident_bytes()
    for i in range(100_000):
        one_round(i)
    gc.collect()
    grown = _resident_bytes() - before
    assert grown < 4 * 2**20, f"resident set grew by {grown / 2**20:.1f} MB over 1e5 calls"
