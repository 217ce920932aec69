"""Every CPU kernel (instruction set) against the "scalar" build, bit for bit
(R, iterations and status), at every batch size 0..70 (SIMD tails) and in
every layout: contiguous (fast path with in-register transposes), offset,
transposed, strided, broadcast, structure of arrays, tiled, and out= in
strided and structure-of-arrays layouts; and a tiled batch split between two
threads. x86-64's "default" build, which rounds a * b + c twice
(csrc/kernel/mul_add.h), is held to its own contiguous results instead
(torchrot.testing.rounding_reference).
"""
from __future__ import annotations

import functools
import math

import pytest
import torch
from isa_helpers import ALL_ISA_PARAMS, DTYPES, _cpu_kernel, _describe, _info, _run_info, _same, _tail_pool

import torchrot
from torchrot._constants import VARIANTS
from torchrot.testing import bits, dtype_id, make_warm_start, random_rotations, rounding_reference, soa_view, tiled_view

# ---------------------------------------------------------------------------
# 3. Every tail length, contiguous and strided layouts
# ---------------------------------------------------------------------------

TAIL_SIZES = range(0, 71)  # every remainder mod 16 (and mod 8, 4), several full blocks


def _strided_copy(A: torch.Tensor) -> torch.Tensor:
    """A copy of A as ``big[::2]`` with NaN in the gaps (reading a wrong
    element shows)."""
    big = torch.full((2 * A.shape[0], 3, 3), math.nan, dtype=A.dtype)
    big[::2] = A
    return big[::2]


def _offset_copy(A: torch.Tensor) -> torch.Tensor:
    """A contiguous copy of A starting one element into its storage
    (misaligned for vector loads)."""
    flat = torch.full((A.numel() + 1,), math.nan, dtype=A.dtype)
    view = flat[1:].view(A.shape)
    view.copy_(A)
    assert view.is_contiguous() and view.storage_offset() == 1
    return view


def _one_rotation(dtype) -> torch.Tensor:
    return random_rotations(1, torch.Generator().manual_seed(4242)).to(dtype)


# layout -> (M, init) -> (M_layout, init_layout); values equal the inputs'
# except for "transposed", which fits the transposed matrices (M.mT)
LAYOUTS = {
    "contiguous": lambda M, init: (M.clone(), init.clone()),
    "offset": lambda M, init: (_offset_copy(M), _offset_copy(init)),
    "transposed": lambda M, init: (M.clone().mT, init.clone().mT),
    "strided": lambda M, init: (_strided_copy(M), _strided_copy(init)),
    # contiguous M, broadcast (stride-0) init: the strided path for all inputs
    "expanded_init": lambda M, init: (M.clone(), _one_rotation(M.dtype).expand(M.shape)),
    # contiguous M and init, strided out=
    "strided_out": lambda M, init: (M.clone(), init.clone()),
    # structure of arrays (plain vector loads and stores), fresh results in it too
    "soa": lambda M, init: (soa_view(M), soa_view(init)),
    # structure of arrays for M, init and out=
    "soa_out": lambda M, init: (soa_view(M), soa_view(init)),
}
OUT_LAYOUTS = {"strided_out": _strided_copy, "soa_out": soa_view}


@pytest.mark.parametrize("layout", list(LAYOUTS))
@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", ALL_ISA_PARAMS)
def test_tails_and_layouts(isa, dtype, layout, use_isa):
    """Every batch size 0..70, in each layout: identical to the scalar kernel
    on a contiguous copy (so both the SIMD tails and the strided path are
    checked against the plain one-matrix-at-a-time result). A kernel that
    rounds differently from the scalar kernel (rounding_reference) is checked
    against its own result for the whole pool, contiguous: a matrix's result
    does not depend on its block."""
    pool_M, pool_init = _tail_pool(dtype)
    reference = rounding_reference(isa)
    pool_refs = {}

    def reference_info(Mc, initc, n, mode, use_init, max_iter, variant):
        if reference == "scalar":
            return _run_info(use_isa, "scalar", Mc, initc if use_init else None, max_iter, variant)
        key = (mode, variant)
        if key not in pool_refs:
            M_all, init_all = LAYOUTS[layout](pool_M, pool_init)
            M_all, init_all = M_all.contiguous(), init_all.contiguous()
            pool_refs[key] = _run_info(use_isa, reference, M_all, init_all if use_init else None, max_iter, variant)
        return tuple(t[:n] for t in pool_refs[key])

    failures = []
    for n in TAIL_SIZES:
        variant = VARIANTS[n % 3]
        M, init = LAYOUTS[layout](pool_M[:n], pool_init[:n])
        if layout in ("transposed", "strided", "expanded_init", "soa", "soa_out") and n > 1:  # the strided path
            assert not (M.is_contiguous() and init.is_contiguous())
        Mc, initc = M.contiguous(), init.contiguous()
        for mode, use_init, max_iter in (("cold", False, None), ("warm-iter1", True, 1), ("warm", True, None)):
            ref = reference_info(Mc, initc, n, mode, use_init, max_iter, variant)
            with use_isa(isa):
                assert _cpu_kernel() == isa
                if layout in OUT_LAYOUTS:
                    out = OUT_LAYOUTS[layout](torch.zeros_like(Mc))
                    gaps = None  # the NaN between the matrices of a strided out=
                    if layout == "strided_out" and n:
                        gaps = out.as_strided((n, 3, 3), out.stride(), out.storage_offset() + 9)
                    returned = torchrot.fit_rotation(
                        M, init if use_init else None, max_iter=max_iter, variant=variant, out=out
                    )
                    assert returned is out
                    if not _same(out, ref[0]):
                        failures.append(f"n={n} {mode} {variant}:\n" + _describe(out, ref[0], Mc, initc))
                    if gaps is not None and not torch.isnan(gaps).all():
                        failures.append(f"n={n} {mode} {variant}: out= wrote into the gaps of the strided view")
                    continue
                got = _info(M, init if use_init else None, max_iter, variant)
            if layout == "soa" and n > 1 and got[0].stride() != M.stride():
                failures.append(f"n={n} {mode}: result strides {got[0].stride()}, not M's {M.stride()}")
            if not _same(got, ref):
                failures.append(f"n={n} {mode} {variant}:\n" + _describe(got, ref, Mc, initc))
    assert not failures, f"{isa} {dtype_id(dtype)} layout={layout}: {len(failures)} failing cases\n" + "\n".join(
        failures[:5]
    )


TILES = (2, 3, 4, 8, 16, 32)


@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", ALL_ISA_PARAMS)
def test_tiled_layouts(isa, dtype, use_isa):
    """Tiled inputs (torchrot.testing.tiled_view: tiles of 2 to 32 matrices in
    structure of arrays, narrower and wider than every block, up to 70
    matrices): fresh results (in M's layout), out= a tiled tensor and
    out=init in place are the scalar kernel's on contiguous copies
    (rounding_reference)."""
    pool_M, pool_init = _tail_pool(dtype)
    reference = rounding_reference(isa)
    failures = []
    for tile in TILES:
        for n in range(tile, 71, tile):
            variant = VARIANTS[n % 3]
            Mc, initc = pool_M[:n].contiguous(), pool_init[:n].contiguous()
            M, init = tiled_view(Mc, tile), tiled_view(initc, tile)
            for mode, use_init, max_iter in (("cold", False, None), ("warm-iter1", True, 1), ("warm", True, None)):
                ref = _run_info(use_isa, reference, Mc, initc if use_init else None, max_iter, variant)
                with use_isa(isa):
                    fresh = _info(M, init if use_init else None, max_iter, variant)
                    if fresh[0].stride() != M.stride():
                        failures.append(f"tile={tile} n={n}: result strides {fresh[0].stride()}, not M's {M.stride()}")
                    got = tuple(t.reshape(ref_t.shape) for t, ref_t in zip(fresh, ref))
                    out = tiled_view(torch.zeros_like(Mc), tile)
                    torchrot.fit_rotation(M, init if use_init else None, max_iter=max_iter, variant=variant, out=out)
                    in_place = init.clone()
                    if use_init:
                        torchrot.fit_rotation(M, in_place, max_iter=max_iter, variant=variant, out=in_place)
                for what, result in (("result", got), ("out=", out.reshape(n, 3, 3)),
                                     ("out=init", in_place.reshape(n, 3, 3) if use_init else ref[0])):
                    if not _same(result, ref if what == "result" else ref[0]):
                        failures.append(f"tile={tile} n={n} {mode} {variant} {what}:\n" +
                                        _describe(result, ref if what == "result" else ref[0], Mc, initc))
    assert not failures, f"{isa} {dtype_id(dtype)}: {len(failures)} failing cases\n" + "\n".join(failures[:5])


@pytest.mark.parametrize("tile", [8, 12])
def test_tiled_layout_two_threads(tile, use_isa):
    """A tiled batch larger than a parallel chunk, in 2 threads: the threads
    split it at block boundaries, and each matrix's result is the one-thread
    contiguous result (best kernel)."""
    n = 6000 - 6000 % tile
    M, init = make_warm_start("warm", n, seed=5, dtype=torch.float32)
    expected = [torchrot.fit_rotation(M, init, max_iter=k) for k in (1, None)]
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        got = [torchrot.fit_rotation(tiled_view(M, tile), tiled_view(init, tile), max_iter=k) for k in (1, None)]
    finally:
        torch.set_num_threads(previous)
    for g, e in zip(got, expected):
        assert torch.equal(g.reshape(n, 3, 3), e)



# layout -> (view, batch size): every tile a whole number of blocks wide or not
WARM_START_CHECK_LAYOUTS = {
    "soa": (soa_view, 70),
    **{f"tiles of {tile}": (functools.partial(tiled_view, tile=tile), 80) for tile in (4, 8, 16)},
}


@pytest.mark.parametrize("layout", list(WARM_START_CHECK_LAYOUTS))
@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", ALL_ISA_PARAMS)
def test_warm_start_check_in_soa_and_tiled_layouts(isa, dtype, layout, use_isa):
    """out= checks every warm start before it writes, in structure-of-arrays
    and tiled layouts too (where the check reads them as the one-step does):
    a bad warm start in any block, the last included, raises and leaves out
    and init as they were, in place or not; with a lower-precision one (which
    keeps the fit's own check on) the results are the scalar kernel's on
    contiguous copies (rounding_reference)."""
    view, n = WARM_START_CHECK_LAYOUTS[layout]
    Mc, initc = make_warm_start("warm", n, seed=8, dtype=dtype)
    for bad_at in (0, 13, n - 1):
        init = initc.clone()
        init[bad_at] = -init[bad_at]  # det -1
        M, init = view(Mc), view(init)
        for in_place in (False, True):
            out = init if in_place else view(torch.full_like(Mc, 7.0))
            before, init_before = bits(out).clone(), bits(init).clone()
            with use_isa(isa):
                with pytest.raises(ValueError, match=rf"init must hold rotations .* 1 of {n} are not"):
                    torchrot.fit_rotation(M, init, max_iter=1, out=out)
            assert torch.equal(bits(out), before), f"bad warm start {bad_at}: out= written"
            assert torch.equal(bits(init), init_before), f"bad warm start {bad_at}: init written"
    unclean = initc.clone()
    unclean[37] = unclean[37].to(torch.bfloat16).to(dtype)
    for max_iter in (1, None):
        expected = _run_info(use_isa, rounding_reference(isa), Mc, unclean, max_iter, VARIANTS[0])[0]
        for in_place in (False, True):
            init = view(unclean)
            out = init if in_place else view(torch.zeros_like(Mc))
            with use_isa(isa):
                torchrot.fit_rotation(view(Mc), init, max_iter=max_iter, variant=VARIANTS[0], out=out)
            assert _same(out.reshape(n, 3, 3), expected), f"max_iter={max_iter} in_place={in_place}"
