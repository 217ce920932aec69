// How the CPU operators see their tensors: (N, 3, 3) batches with strides
// (or tiles) that the kernels read and write where they lie, and the layout
// of a fresh result.
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>
#include <optional>

#include "../fit_rotation.h"

namespace torchrot {
namespace ops {

// The dtype the kernels compute a tensor of dtype `t` in: float32 for
// float16 and bfloat16.
inline at::ScalarType compute_dtype(at::ScalarType t) { return t == at::kHalf || t == at::kBFloat16 ? at::kFloat : t; }

// (N, 3, 3) view of a tensor with the given (possibly broadcast) geometry,
// without creating a tensor: its batch dimensions flattened into one stride,
// or else into tiles (Layout::tile), the trailing ones (as many as can be)
// into a tile's matrices and the leading ones into the tiles, as in the
// paper authors' (N / 8, 8, 3, 3) blocks of 8 matrices in structure of
// arrays; nullopt if neither can be.
std::optional<MatrixBatch> batch_view(const at::Tensor& t, at::IntArrayRef sizes, at::IntArrayRef strides, int64_t n);

// Whether `t` is in structure-of-arrays layout: dense, the matrix index of
// stride 1 across all its batch dimensions (a permuted (3, 3, N) tensor) or
// within tiles (the paper authors' (N / 8, 8, 3, 3) blocks): its trailing
// batch dimensions flatten to one of stride 1 and more than one matrix, its
// leading ones (if any) to one stride, so that batch_view reads it in place.
// The kernels load and store such tensors as plain vectors. (The fake
// kernels' has_soa_layout, torchrot/_layout.py, decides the same.)
bool has_soa_layout(const at::Tensor& t);

// A new result of `t`'s shape: in t's layout where that is structure of
// arrays (so solvers that assemble their matrices that way keep it, and the
// kernels store plain vectors), contiguous otherwise. The kernel fills it
// right after: on huge pages where it is large (cpu/huge_pages.h).
at::Tensor new_result(const at::Tensor& t);

// A contiguous (n, 3, 3) buffer for the kernel to fill, of dtype `compute`.
at::Tensor new_kernel_buffer(int64_t n, const at::Tensor& like, at::ScalarType compute);

// The view of a contiguous (n, 3, 3) tensor.
MatrixBatch contiguous_view(const at::Tensor& contiguous);

// (N, 3, 3) view of `t` broadcast to `shape` (its geometry, no copy), or of a
// contiguous copy in the `compute` dtype kept in `keep` (for another dtype, or
// a batch that cannot be flattened).
MatrixBatch broadcast_view(const at::Tensor& t, at::IntArrayRef shape, int64_t n, at::ScalarType compute,
                           at::Tensor& keep);

}  // namespace ops
}  // namespace torchrot
