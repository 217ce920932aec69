#include "checks.h"

#include <ATen/ExpandUtils.h>
#include <c10/core/InferenceMode.h>
#include <c10/util/Exception.h>
#include <c10/util/StringUtil.h>

#include <cmath>
#include <string>

#include "../limits.h"
#include "overlap.h"

namespace torchrot {
namespace ops {
namespace {

using messages::kOpName;

// A dtype as Python prints it ("torch.float32").
std::string dtype_name(at::ScalarType t) { return "torch." + std::string(c10::getDtypeNames(t).first); }

bool is_supported_dtype(at::ScalarType t) {
  for (const at::ScalarType supported : kSupportedDtypes) {
    if (t == supported) return true;
  }
  return false;
}

Variant parse_variant(c10::string_view variant) {
  for (const VariantName& known : kVariantNames) {
    if (variant == known.name) return known.variant;
  }
  TORCH_CHECK_VALUE(false,
                    messages::format(messages::kVariantValue, {{"op", kOpName}, {"value", std::string(variant)}}));
}

// `t` (argument `name`) must be on `ref`'s device and have its dtype.
void check_like(const at::Tensor& t, const char* name, const at::Tensor& ref, const char* ref_name, const char* op) {
  TORCH_CHECK_VALUE(t.device() == ref.device(),
                    messages::format(messages::kDeviceLike, {{"op", op},
                                                             {"name", name},
                                                             {"ref", ref_name},
                                                             {"device", c10::str(ref.device())},
                                                             {"got", c10::str(t.device())}}));
  TORCH_CHECK_TYPE(t.scalar_type() == ref.scalar_type(),
                   messages::format(messages::kDtypeLike, {{"op", op},
                                                           {"name", name},
                                                           {"ref", ref_name},
                                                           {"dtype", dtype_name(ref.scalar_type())},
                                                           {"got", dtype_name(t.scalar_type())}}));
}

}  // namespace

void check_matrix_shape(const at::Tensor& t, const char* name, const char* op) {
  TORCH_CHECK_TYPE(t.defined(),
                   messages::format(messages::kNotATensor, {{"op", op}, {"name", name}, {"type", "NoneType"}}));
  TORCH_CHECK_VALUE(
      t.dim() >= 2 && t.size(-1) == 3 && t.size(-2) == 3,
      messages::format(messages::kMatrixShape, {{"op", op}, {"name", name}, {"shape", c10::str(t.sizes())}}));
}

void check_matrix_arg(const at::Tensor& t, const char* name, const char* op) {
  check_matrix_shape(t, name, op);
  TORCH_CHECK_TYPE(
      is_supported_dtype(t.scalar_type()),
      messages::format(messages::kMatrixDtype, {{"op", op}, {"name", name}, {"dtype", dtype_name(t.scalar_type())}}));
}

at::Tensor checked_init(const at::Tensor& M, const std::optional<at::Tensor>& init) {
  check_matrix_arg(M, "M");
  if (!init.has_value() || !init->defined()) return at::Tensor();
  check_matrix_arg(*init, "init");
  // any float dtype: a warm start of another precision is cast to M's
  // compute dtype (and cleaned up to it, kernel::clean_warm_start)
  TORCH_CHECK_VALUE(init->device() == M.device(),
                    messages::format(messages::kDeviceLike, {{"op", kOpName},
                                                             {"name", "init"},
                                                             {"ref", "M"},
                                                             {"device", c10::str(M.device())},
                                                             {"got", c10::str(init->device())}}));
  const auto m_batch = M.sizes().slice(0, M.dim() - 2);
  const auto init_batch = init->sizes().slice(0, init->dim() - 2);
  TORCH_CHECK_VALUE(
      at::is_expandable_to(init_batch, m_batch),
      messages::format(messages::kInitBroadcast,
                       {{"op", kOpName}, {"shape", c10::str(init->sizes())}, {"m_shape", c10::str(M.sizes())}}));
  return *init;
}

FitOptions parse_options(std::optional<int64_t> max_iter, c10::string_view variant) {
  FitOptions options;
  if (max_iter.has_value()) {
    TORCH_CHECK_VALUE(*max_iter >= 1 && *max_iter <= limits::kMaxIter,
                      messages::format(messages::kMaxIterRange, {{"op", kOpName}, {"value", c10::str(*max_iter)}}));
    options.max_iter = *max_iter;
  }
  options.variant = parse_variant(variant);
  return options;
}

void check_out(const at::Tensor& M, const at::Tensor& out) {
  TORCH_CHECK_TYPE(out.defined(),
                   messages::format(messages::kNotATensor, {{"op", kOpName}, {"name", "out"}, {"type", "NoneType"}}));
  check_like(out, "out", M, "M", kOpName);
  TORCH_CHECK_VALUE(
      out.sizes() == M.sizes(),
      messages::format(messages::kOutShape,
                       {{"op", kOpName}, {"m_shape", c10::str(M.sizes())}, {"shape", c10::str(out.sizes())}}));
  TORCH_CHECK_VALUE(!has_overlapping_elements(out), messages::format(messages::kOutOverlap, {{"op", kOpName}}));
  TORCH_CHECK_VALUE(!out.is_inference() || c10::InferenceMode::is_enabled(),
                    messages::format(messages::kOutInference, {{"op", kOpName}}));
}

void check_gradient_eps(double gradient_eps, const char* op) {
  TORCH_CHECK_VALUE(std::isfinite(gradient_eps) && gradient_eps >= 0 && gradient_eps <= limits::kMaxGradientEps,
                    messages::format(messages::kGradientEpsRange, {{"op", op}, {"value", c10::str(gradient_eps)}}));
}

void check_backward(const at::Tensor& grad, const at::Tensor& R, const at::Tensor& M, double gradient_eps) {
  const char* op = messages::kBackwardName;
  check_matrix_arg(R, "R", op);
  for (const auto& [t, name] : {std::pair<const at::Tensor&, const char*>{grad, "grad"}, {M, "M"}}) {
    check_matrix_shape(t, name, op);
    check_like(t, name, R, "R", op);
  }
  TORCH_CHECK_VALUE(
      grad.sizes() == R.sizes(),
      messages::format(messages::kGradShape,
                       {{"op", op}, {"r_shape", c10::str(R.sizes())}, {"shape", c10::str(grad.sizes())}}));
  TORCH_CHECK_VALUE(at::is_expandable_to(M.sizes(), R.sizes()),
                    messages::format(messages::kBackwardBroadcast,
                                     {{"op", op}, {"shape", c10::str(M.sizes())}, {"r_shape", c10::str(R.sizes())}}));
  check_gradient_eps(gradient_eps, op);
}

[[noreturn]] void throw_bad_init(int64_t bad, int64_t n) {
  TORCH_CHECK_VALUE(false, messages::format(messages::kInitNotRotations,
                                            {{"op", kOpName}, {"bad", c10::str(bad)}, {"n", c10::str(n)}}));
}

}  // namespace ops
}  // namespace torchrot
