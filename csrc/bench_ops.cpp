// Operators for the benchmarks only, outside the library's schema
// (torch.ops.torchrot_bench.*, CPU kernels only: the benchmarks call them
// eagerly on CPU tensors): the check of the warm starts that fit_rotation_out makes before writing,
// timed on its own (benchmarks/atomic_cost.py, speed_targets.py), and
// operators that do nothing, the yardsticks for the fixed cost of a
// custom-op call, with one argument, and with fit_rotation's signature and an
// (uninitialised) output of M's shape.
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <cstdint>
#include <optional>

#include "ops/checks.h"
#include "ops/layout.h"
#include "ops/schemas.h"
#include "ops/warm_starts.h"

namespace {

// The warm starts of `init` that are finite but not rotations.
int64_t count_bad_warm_starts(const at::Tensor& init) {
  torchrot::ops::check_matrix_arg(init, "init");
  return torchrot::ops::count_bad_warm_starts(init, torchrot::ops::compute_dtype(init.scalar_type())).bad;
}

}  // namespace

TORCH_LIBRARY(torchrot_bench, m) {
  m.def("count_bad_warm_starts(Tensor init) -> int");
  m.def("empty_op(Tensor M) -> ()");
  m.def("empty_fit_rotation" TORCHROT_FIT_ROTATION_SCHEMA);
}

TORCH_LIBRARY_IMPL(torchrot_bench, CPU, m) {
  m.impl("count_bad_warm_starts", &count_bad_warm_starts);
  m.impl("empty_op", [](const at::Tensor&) {});
  m.impl("empty_fit_rotation", [](const at::Tensor& M, const std::optional<at::Tensor>&, std::optional<int64_t>,
                                  c10::string_view, double) { return at::empty(M.sizes(), M.options()); });
}
