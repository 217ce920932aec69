#include "overlap.h"

#include <ATen/TensorOperators.h>
#include <ATen/ops/arange.h>
#include <ATen/ops/zeros.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <utility>
#include <vector>

namespace torchrot {
namespace ops {
namespace {

// [first, last] byte address that an element of `t` occupies (numel > 0).
std::pair<uintptr_t, uintptr_t> byte_range(const at::Tensor& t) {
  int64_t low = 0, high = 0;
  for (int64_t d = 0; d < t.dim(); ++d) {
    const int64_t span = (t.size(d) - 1) * t.stride(d);
    (span < 0 ? low : high) += span;
  }
  const auto base = reinterpret_cast<uintptr_t>(t.data_ptr());
  const int64_t item = static_cast<int64_t>(t.element_size());
  return {base + low * item, base + high * item + item - 1};
}

}  // namespace

// Exact: strides that nest (each at least the extent of the smaller ones:
// every dense or sliced tensor) are decided at once, others by sorting their
// element offsets.
bool has_overlapping_elements(const at::Tensor& t) {
  std::vector<std::pair<int64_t, int64_t>> dims;  // (|stride|, size) of dims with size > 1
  for (int64_t d = 0; d < t.dim(); ++d) {
    if (t.size(d) > 1) dims.emplace_back(std::abs(t.stride(d)), t.size(d));
  }
  std::sort(dims.begin(), dims.end());
  int64_t extent = 1;
  bool nested = true;
  for (const auto& [stride, size] : dims) {
    if (stride == 0) return true;
    if (stride < extent) nested = false;
    extent += (size - 1) * stride;
  }
  if (nested) return false;
  at::Tensor offsets = at::zeros(t.sizes(), at::TensorOptions().dtype(at::kLong));
  for (int64_t d = 0; d < t.dim(); ++d) {
    std::vector<int64_t> shape(t.dim(), 1);
    shape[d] = t.size(d);
    offsets = offsets + (at::arange(t.size(d), at::kLong) * t.stride(d)).view(shape);
  }
  const at::Tensor sorted = std::get<0>(offsets.flatten().sort());
  return sorted.slice(0, 1).eq(sorted.slice(0, 0, -1)).any().item<bool>();
}

bool overlaps_other_than_identity(const at::Tensor& out, const at::Tensor& input) {
  if (!input.defined() || out.numel() == 0 || input.numel() == 0) return false;
  if (out.data_ptr() == input.data_ptr() && out.sizes() == input.sizes() && out.strides() == input.strides()) {
    return false;
  }
  const auto a = byte_range(out), b = byte_range(input);
  return a.first <= b.second && b.first <= a.second;
}

}  // namespace ops
}  // namespace torchrot
