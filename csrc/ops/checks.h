// The argument checks of the CPU operators, in the order every path makes
// them. Each raises what the Python checks of the other paths
// (torchrot/_checks.py: fake kernels, other devices, torch.compile) raise,
// with the same message (messages.h): TypeError (TORCH_CHECK_TYPE) for a
// wrong type or dtype, ValueError (TORCH_CHECK_VALUE) for a wrong value,
// shape or device. Limits come from limits.h.
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/string_view.h>

#include <cstdint>
#include <optional>

#include "../fit_rotation.h"
#include "../messages.h"

namespace torchrot {
namespace ops {

// `t` (argument `name` of operator `op`) is a tensor of shape (..., 3, 3).
void check_matrix_shape(const at::Tensor& t, const char* name, const char* op = messages::kOpName);

// ... and of a supported dtype (kSupportedDtypes).
void check_matrix_arg(const at::Tensor& t, const char* name, const char* op = messages::kOpName);

// M, then init if given: returns init (undefined if none), which broadcasts to M.
at::Tensor checked_init(const at::Tensor& M, const std::optional<at::Tensor>& init);

// max_iter and variant.
FitOptions parse_options(std::optional<int64_t> max_iter, c10::string_view variant);

// out of fit_rotation_out: M's shape, dtype and device, no overlapping
// elements, not an inference tensor outside inference mode.
void check_out(const at::Tensor& M, const at::Tensor& out);

void check_gradient_eps(double gradient_eps, const char* op = messages::kOpName);

// The arguments of fit_rotation_backward(grad, R, M, gradient_eps).
void check_backward(const at::Tensor& grad, const at::Tensor& R, const at::Tensor& M, double gradient_eps);

// The error for `bad` of `n` warm starts that are not rotations.
[[noreturn]] void throw_bad_init(int64_t bad, int64_t n);

}  // namespace ops
}  // namespace torchrot
