// Operator schemas (TORCH_LIBRARY) and their CPU implementations
// (TORCH_LIBRARY_IMPL): argument checking, broadcasting of the warm start,
// flattening of the batch, reduced-precision inputs, and the call into the
// kernels. Fake (meta) kernels and other devices are registered in Python
// (torchrot/_ops.py).
#include <ATen/ATen.h>
#include <ATen/ExpandUtils.h>
#include <ATen/MemoryOverlap.h>
#include <ATen/TensorUtils.h>
#include <torch/library.h>

#include <string>
#include <tuple>

#include "fit_rotation.h"

namespace torchrot {
namespace {

constexpr const char* kOpName = "torchrot.fit_rotation";

Variant parse_variant(c10::string_view variant) {
  if (variant == "newton") return Variant::kNewton;
  if (variant == "conservative") return Variant::kConservative;
  if (variant == "gershgorin") return Variant::kGershgorin;
  TORCH_CHECK(false, kOpName, ": variant must be one of 'newton', 'conservative', 'gershgorin', got '",
              std::string(variant), "'");
}

bool is_supported_dtype(at::ScalarType t) {
  return t == at::kFloat || t == at::kDouble || t == at::kHalf || t == at::kBFloat16;
}

void check_matrix_arg(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.dim() >= 2 && t.size(-1) == 3 && t.size(-2) == 3, kOpName, ": ", name,
              " must have shape (..., 3, 3), got ", t.sizes());
  TORCH_CHECK(is_supported_dtype(t.scalar_type()), kOpName, ": ", name,
              " must be float32, float64, float16 or bfloat16, got ", t.scalar_type());
}

FitOptions parse_options(std::optional<int64_t> max_iter, c10::string_view variant) {
  FitOptions options;
  if (max_iter.has_value()) {
    TORCH_CHECK(*max_iter >= 1, kOpName, ": max_iter must be None (iterate to convergence) or >= 1, got ",
                *max_iter);
    options.max_iter = *max_iter;
  }
  options.variant = parse_variant(variant);
  return options;
}

// Checks M and init and returns init broadcast to M's shape (undefined if none).
at::Tensor checked_init(const at::Tensor& M, const std::optional<at::Tensor>& init) {
  check_matrix_arg(M, "M");
  if (!init.has_value() || !init->defined()) return at::Tensor();
  check_matrix_arg(*init, "init");
  TORCH_CHECK(init->device() == M.device(), kOpName, ": init must be on M's device (", M.device(),
              "), got ", init->device());
  TORCH_CHECK(init->scalar_type() == M.scalar_type(), kOpName, ": init must have M's dtype (",
              M.scalar_type(), "), got ", init->scalar_type());
  const auto m_batch = M.sizes().slice(0, M.dim() - 2);
  const auto init_batch = init->sizes().slice(0, init->dim() - 2);
  const bool broadcastable = at::is_expandable_to(init_batch, m_batch);
  TORCH_CHECK(broadcastable, kOpName, ": init of shape ", init->sizes(),
              " must broadcast to M's shape ", M.sizes());
  return init->expand(M.sizes());
}

void check_out(const at::Tensor& M, const at::Tensor& out) {
  TORCH_CHECK(out.device() == M.device(), kOpName, ": out must be on M's device (", M.device(), "), got ",
              out.device());
  TORCH_CHECK(out.scalar_type() == M.scalar_type(), kOpName, ": out must have M's dtype (",
              M.scalar_type(), "), got ", out.scalar_type());
  TORCH_CHECK(out.sizes() == M.sizes(), kOpName, ": out must have M's shape ", M.sizes(), ", got ",
              out.sizes());
  TORCH_CHECK(at::has_internal_overlap(out) != at::MemOverlap::Yes, kOpName,
              ": out must not have overlapping elements (e.g. an expanded tensor)");
}

// Runs the kernel on (N, 3, 3) views, converting reduced precision to float32.
// `out` has M's shape and dtype; it may alias M or init exactly.
// Orthonormality tolerance of warm starts by the caller's dtype: reduced
// precision rotations carry their own rounding (eps 1e-3 / 8e-3).
double init_tolerance(at::ScalarType dtype) {
  switch (dtype) {
    case at::kHalf:
      return 1e-2;
    case at::kBFloat16:
      return 5e-2;
    case at::kFloat:
      return 1e-4;
    default:
      return 1e-7;
  }
}

void run_fit(const at::Tensor& M, const at::Tensor& init, const at::Tensor& out, FitOptions options,
             const at::Tensor* iterations, const at::Tensor* status) {
  const bool reduced = M.scalar_type() == at::kHalf || M.scalar_type() == at::kBFloat16;
  options.init_tolerance = init_tolerance(M.scalar_type());
  const int64_t n = M.numel() / 9;
  at::Tensor m3 = M.reshape({n, 3, 3});
  at::Tensor init3 = init.defined() ? init.reshape({n, 3, 3}) : at::Tensor();
  if (reduced) {
    m3 = m3.to(at::kFloat);
    if (init3.defined()) init3 = init3.to(at::kFloat);
  }
  // Write straight into out when it can be viewed as (N, 3, 3) in the compute
  // dtype; otherwise into a temporary that is copied back.
  at::Tensor out3;
  if (!reduced) {
    const auto strides = at::detail::computeStride(out.sizes(), out.strides(), at::IntArrayRef{n, 3, 3});
    if (strides.has_value()) out3 = out.as_strided({n, 3, 3}, *strides);
  }
  const bool direct = out3.defined();
  if (!direct) out3 = at::empty({n, 3, 3}, m3.options());
  const int64_t bad_inits = fit_rotation_cpu(m3, init3.defined() ? &init3 : nullptr, out3, options,
                                             iterations, status);
  if (!direct) out.copy_(out3.view(out.sizes()));
  TORCH_CHECK(bad_inits == 0, kOpName, ": init must hold rotations (|R^T R - I|_F < ",
              options.init_tolerance, " for ", M.scalar_type(), ", det R > 0); ", bad_inits, " of ", n,
              " matrices do not (out has NaN in their place)");
}

at::Tensor fit_rotation_cpu_op(const at::Tensor& M, const std::optional<at::Tensor>& init,
                               std::optional<int64_t> max_iter, c10::string_view variant) {
  const at::Tensor init_b = checked_init(M, init);
  const FitOptions options = parse_options(max_iter, variant);
  at::Tensor out = at::empty(M.sizes(), M.options().memory_format(at::MemoryFormat::Contiguous));
  run_fit(M, init_b, out, options, nullptr, nullptr);
  return out;
}

void fit_rotation_out_cpu_op(const at::Tensor& M, const std::optional<at::Tensor>& init,
                             std::optional<int64_t> max_iter, c10::string_view variant,
                             const at::Tensor& out) {
  const at::Tensor init_b = checked_init(M, init);
  const FitOptions options = parse_options(max_iter, variant);
  check_out(M, out);
  // out may be M or init itself (an in-place warm-start update), but not a
  // partial overlap, which would let one matrix's output clobber another's input.
  TORCH_CHECK(at::get_overlap_status(out, M) != at::MemOverlapStatus::Partial, kOpName,
              ": out must be M itself or not overlap it; it partially overlaps M");
  TORCH_CHECK(!init.has_value() || !init->defined() ||
                  at::get_overlap_status(out, *init) != at::MemOverlapStatus::Partial,
              kOpName, ": out must be init itself or not overlap it; it partially overlaps init");
  run_fit(M, init_b, out, options, nullptr, nullptr);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> fit_rotation_info_cpu_op(
    const at::Tensor& M, const std::optional<at::Tensor>& init, std::optional<int64_t> max_iter,
    c10::string_view variant) {
  const at::Tensor init_b = checked_init(M, init);
  const FitOptions options = parse_options(max_iter, variant);
  at::Tensor out = at::empty(M.sizes(), M.options().memory_format(at::MemoryFormat::Contiguous));
  const auto batch = M.sizes().slice(0, M.dim() - 2);
  at::Tensor iterations = at::empty(batch, M.options().dtype(at::kInt));
  at::Tensor status = at::empty(batch, M.options().dtype(at::kByte));
  run_fit(M, init_b, out, options, &iterations, &status);
  return {out, iterations, status};
}

}  // namespace

TORCH_LIBRARY(torchrot, m) {
  m.def("fit_rotation(Tensor M, Tensor? init=None, int? max_iter=None, str variant=\"conservative\") -> Tensor");
  m.def(
      "fit_rotation_out(Tensor M, Tensor? init, int? max_iter, str variant, Tensor(a!) out) -> ()");
  m.def(
      "fit_rotation_info(Tensor M, Tensor? init=None, int? max_iter=None, str variant=\"conservative\") "
      "-> (Tensor R, Tensor iterations, Tensor status)");
  // Which CPU kernel object runs: "scalar", "default", "avx2" or "avx512".
  m.def("cpu_kernel() -> str", [] { return cpu_kernel_name(); });
}

TORCH_LIBRARY_IMPL(torchrot, CPU, m) {
  m.impl("fit_rotation", &fit_rotation_cpu_op);
  m.impl("fit_rotation_out", &fit_rotation_out_cpu_op);
  m.impl("fit_rotation_info", &fit_rotation_info_cpu_op);
}

}  // namespace torchrot
