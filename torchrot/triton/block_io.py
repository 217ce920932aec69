"""Loading and storing a block of matrices: the Triton twin of
csrc/cpu/block_io.h. Lane i of a block is matrix ``pid * BLOCK + i`` of a
batch flattened to one dimension (stride ``stride_n``; entry (r, c) at
``r * stride_r + c * stride_c`` from it); each entry is one load or store of
BLOCK lanes, contiguous where the batch is in structure-of-arrays layout
(stride_n = 1) and within a few cache lines otherwise (the 9 loads of a block
share them). Values are converted to the compute dtype on load and back to
the tensor's dtype on store (float16 and bfloat16 are computed in float32)."""
from __future__ import annotations

import triton
import triton.language as tl

__all__ = ["block_lanes", "load_block", "store_block", "store_lanes"]


@triton.jit
def block_lanes(n, BLOCK: tl.constexpr):
    """(lane, mask): the batch indices of this program's lanes (int64) and
    which of them are in the batch (the last block's tail is masked)."""
    lane = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    return lane, lane < n


@triton.jit
def _load_entry(base, mask, offset, COMPUTE: tl.constexpr):
    return tl.load(base + offset, mask=mask, other=0.0).to(COMPUTE)


@triton.jit
def load_block(ptr, lane, mask, stride_n, stride_r, stride_c, COMPUTE: tl.constexpr):
    """The block's matrices as a 9-tuple of lanes in dtype COMPUTE (masked
    lanes: 0)."""
    base = ptr + lane * stride_n
    return (_load_entry(base, mask, 0, COMPUTE), _load_entry(base, mask, stride_c, COMPUTE),
            _load_entry(base, mask, 2 * stride_c, COMPUTE),
            _load_entry(base, mask, stride_r, COMPUTE), _load_entry(base, mask, stride_r + stride_c, COMPUTE),
            _load_entry(base, mask, stride_r + 2 * stride_c, COMPUTE),
            _load_entry(base, mask, 2 * stride_r, COMPUTE), _load_entry(base, mask, 2 * stride_r + stride_c, COMPUTE),
            _load_entry(base, mask, 2 * stride_r + 2 * stride_c, COMPUTE))


@triton.jit
def store_block(ptr, lane, mask, stride_n, stride_r, stride_c, R):
    """Stores the 9-tuple R into the block's matrices, in the tensor's dtype."""
    base = ptr + lane * stride_n
    dtype = ptr.dtype.element_ty
    tl.store(base, R[0].to(dtype), mask=mask)
    tl.store(base + stride_c, R[1].to(dtype), mask=mask)
    tl.store(base + 2 * stride_c, R[2].to(dtype), mask=mask)
    tl.store(base + stride_r, R[3].to(dtype), mask=mask)
    tl.store(base + stride_r + stride_c, R[4].to(dtype), mask=mask)
    tl.store(base + stride_r + 2 * stride_c, R[5].to(dtype), mask=mask)
    tl.store(base + 2 * stride_r, R[6].to(dtype), mask=mask)
    tl.store(base + 2 * stride_r + stride_c, R[7].to(dtype), mask=mask)
    tl.store(base + 2 * stride_r + 2 * stride_c, R[8].to(dtype), mask=mask)


@triton.jit
def store_lanes(ptr, lane, mask, values):
    """One value per lane into a contiguous (n,) buffer of ptr's dtype."""
    tl.store(ptr + lane, values.to(ptr.dtype.element_ty), mask=mask)
