"""In-place updates at every CPU kernel (instruction set): ``out=init`` and
``out=M``, contiguous and transposed, give the out-of-place result of the
"scalar" build bit for bit (x86-64's "default" build, which rounds
a * b + c twice: its own; torchrot.testing.rounding_reference), and write
nothing but the aliased buffer.
"""
from __future__ import annotations

import pytest
import torch
from isa_helpers import ALL_ISA_PARAMS, DTYPES, _cpu_kernel, _describe, _same, _tail_pool

import torchrot
from torchrot._constants import VARIANTS
from torchrot.testing import bits, dtype_id, rounding_reference

# ---------------------------------------------------------------------------
# 4. out= aliasing init or M (in-place updates)
# ---------------------------------------------------------------------------

ALIAS_SIZES = range(1, 41)


@pytest.mark.parametrize("layout", ["contiguous", "transposed"])
@pytest.mark.parametrize("target", ["init", "M"])
@pytest.mark.parametrize("dtype", DTYPES, ids=dtype_id)
@pytest.mark.parametrize("isa", ALL_ISA_PARAMS)
def test_out_aliasing_inputs(isa, dtype, target, layout, use_isa):
    """``out=init`` (warm-start update in place) and ``out=M`` give the
    out-of-place scalar result (rounding_reference); the aliased buffer is the
    only thing written."""
    pool_M, pool_init = _tail_pool(dtype)
    failures = []
    for n in ALIAS_SIZES:
        variant = VARIANTS[n % 3]
        M, init = pool_M[:n].contiguous(), pool_init[:n].contiguous()
        cases = [("warm-iter1", True, 1), ("warm", True, None)]
        if target == "M":
            cases.append(("cold", False, None))
        for mode, use_init, max_iter in cases:
            reference = rounding_reference(isa)  # out-of-place, without aliasing
            with use_isa(reference):
                assert _cpu_kernel() == reference
                ref = torchrot.fit_rotation(M, init if use_init else None, max_iter=max_iter, variant=variant)
            # the aliased buffer, with the input's values, in the layout tested
            source = init if target == "init" else M
            buf = source.mT.contiguous().mT if layout == "transposed" else source.clone()
            assert torch.equal(bits(buf), bits(source))
            M_arg = buf if target == "M" else M.clone()
            init_arg = buf if target == "init" else init.clone()
            other_before = (init_arg if target == "M" else M_arg).clone()
            with use_isa(isa):
                assert _cpu_kernel() == isa
                torchrot.fit_rotation(
                    M_arg, init_arg if use_init else None, max_iter=max_iter, variant=variant, out=buf
                )
            if not _same(buf, ref):
                failures.append(f"n={n} {mode} {variant} out={target}:\n" + _describe(buf.clone(), ref, M, init))
            other = init_arg if target == "M" else M_arg
            if not _same(other, other_before):
                failures.append(f"n={n} {mode} {variant}: the non-aliased input was modified")
    assert not failures, f"{isa} {dtype_id(dtype)} out={target} {layout}: {len(failures)} failing cases\n" + (
        "\n".join(failures[:5])
    )
