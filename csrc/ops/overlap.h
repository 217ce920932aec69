// Memory overlap of the tensors an operator writes and reads.
#pragma once

#include <ATen/core/Tensor.h>

namespace torchrot {
namespace ops {

// Whether two distinct elements of `t` share memory (an expanded tensor, or
// strides that make two matrices share entries).
bool has_overlapping_elements(const at::Tensor& t);

// Whether `out` must be computed through a temporary because writing it
// could change `input` before it is read: any overlap except the exact
// identity (same elements in the same layout, which the kernels allow: a
// block's inputs are in registers before its result is stored).
bool overlaps_other_than_identity(const at::Tensor& out, const at::Tensor& input);

}  // namespace ops
}  // namespace torchrot
