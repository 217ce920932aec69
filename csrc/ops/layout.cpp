#include "layout.h"

#include <ATen/ExpandUtils.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_strided.h>

#include <utility>
#include <vector>

#include "../cpu/huge_pages.h"
#include "../torch_internals.h"

namespace torchrot {
namespace ops {

std::optional<MatrixBatch> batch_view(const at::Tensor& t, at::IntArrayRef sizes, at::IntArrayRef strides, int64_t n) {
  MatrixBatch view;
  view.data = t.data_ptr();
  if (const auto flat = torch_internals::view_strides(sizes, strides, at::DimVector{n, 3, 3})) {
    for (int d = 0; d < 3; ++d) view.layout.stride[d] = (*flat)[d];
    return view;
  }
  const int64_t batch_dims = static_cast<int64_t>(sizes.size()) - 2;
  for (int64_t split = 1; split < batch_dims; ++split) {
    int64_t tile = 1;
    for (int64_t d = split; d < batch_dims; ++d) tile *= sizes[d];
    const auto tiled = torch_internals::view_strides(sizes, strides, at::DimVector{n / tile, tile, 3, 3});
    if (!tiled.has_value()) continue;
    view.layout.tile = tile;
    view.layout.tile_stride = (*tiled)[0];
    for (int d = 0; d < 3; ++d) view.layout.stride[d] = (*tiled)[d + 1];
    return view;
  }
  return std::nullopt;
}

bool has_soa_layout(const at::Tensor& t) {
  if (t.dim() < 3) return false;
  std::vector<std::pair<int64_t, int64_t>> batch;  // (size, stride) of the batch dimensions of size > 1
  for (int64_t d = 0; d < t.dim() - 2; ++d) {
    if (t.size(d) != 1) batch.emplace_back(t.size(d), t.stride(d));
  }
  size_t leading = batch.size();
  int64_t run = 1;  // the matrices of the stride-1 run
  while (leading > 0 && batch[leading - 1].second == run) run *= batch[--leading].first;
  if (run == 1) return false;
  for (size_t d = 0; d + 1 < leading; ++d) {
    if (batch[d].second != batch[d + 1].second * batch[d + 1].first) return false;
  }
  return t.is_non_overlapping_and_dense();
}

at::Tensor new_result(const at::Tensor& t) {
  if (has_soa_layout(t)) return cpu::advise_huge_pages(at::empty_strided(t.sizes(), t.strides(), t.options()));
  return cpu::advise_huge_pages(at::empty(t.sizes(), t.options().memory_format(at::MemoryFormat::Contiguous)));
}

at::Tensor new_kernel_buffer(int64_t n, const at::Tensor& like, at::ScalarType compute) {
  return cpu::advise_huge_pages(at::empty({n, 3, 3}, like.options().dtype(compute)));
}

MatrixBatch contiguous_view(const at::Tensor& contiguous) {
  MatrixBatch view;
  view.data = contiguous.data_ptr();
  return view;
}

MatrixBatch broadcast_view(const at::Tensor& t, at::IntArrayRef shape, int64_t n, at::ScalarType compute,
                           at::Tensor& keep) {
  if (t.scalar_type() == compute) {
    const auto geometry = at::inferExpandGeometry_dimvector(t.sizes(), t.strides(), shape);
    if (auto view = batch_view(t, geometry.sizes, geometry.strides, n)) return *view;
  }
  keep = t.expand(shape).to(compute).contiguous();
  return contiguous_view(keep);
}

}  // namespace ops
}  // namespace torchrot
