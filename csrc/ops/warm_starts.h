// The check of the warm starts that fit_rotation_out makes before it writes
// anything (a call that raises must leave the caller's out, possibly init
// itself, as it was).
#pragma once

#include <ATen/core/Tensor.h>

#include "../fit_rotation.h"

namespace torchrot {
namespace ops {

// What the fit's own check finds in the warm starts of `init` (any shape
// (..., 3, 3)), computed in `compute`, the dtype of the fit.
WarmStartCount count_bad_warm_starts(const at::Tensor& init, at::ScalarType compute);

// Raises (ValueError) if a warm start of `init`, taken in its own shape
// (not broadcast), is not a rotation. Returns whether every warm start is
// clean (FitOptions::init_known_clean): the fit then skips its own check, so
// the validation costs the call one pass, not two checks.
bool check_warm_starts(const at::Tensor& init, at::ScalarType compute);

}  // namespace ops
}  // namespace torchrot
