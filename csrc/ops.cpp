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

#include <cmath>
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

void check_matrix_shape(const at::Tensor& t, const char* name, const char* op = kOpName) {
  TORCH_CHECK(t.defined(), op, ": ", name, " must be a tensor of shape (..., 3, 3), got None");
  TORCH_CHECK(t.dim() >= 2 && t.size(-1) == 3 && t.size(-2) == 3, op, ": ", name,
              " must have shape (..., 3, 3), got ", t.sizes());
}

void check_matrix_arg(const at::Tensor& t, const char* name, const char* op = kOpName) {
  check_matrix_shape(t, name, op);
  TORCH_CHECK(is_supported_dtype(t.scalar_type()), op, ": ", name,
              " must be float32, float64, float16 or bfloat16, got ", t.scalar_type());
}

// `t` (argument `name`) must be on `ref`'s device and have its dtype.
void check_like(const at::Tensor& t, const char* name, const at::Tensor& ref, const char* ref_name,
                const char* op = kOpName) {
  TORCH_CHECK(t.device() == ref.device(), op, ": ", name, " must be on ", ref_name, "'s device (", ref.device(),
              "), got ", t.device());
  TORCH_CHECK(t.scalar_type() == ref.scalar_type(), op, ": ", name, " must have ", ref_name, "'s dtype (",
              ref.scalar_type(), "), got ", t.scalar_type());
}

// Largest step count accepted: more steps never help (max_iter=None converges
// with a guaranteed fallback), and on flat problems (rank-1 M) a lane can
// step without converging until its cap, which made huge values hang.
constexpr int64_t kMaxIter = 1000;

FitOptions parse_options(std::optional<int64_t> max_iter, c10::string_view variant) {
  FitOptions options;
  if (max_iter.has_value()) {
    TORCH_CHECK(*max_iter >= 1 && *max_iter <= kMaxIter, kOpName,
                ": max_iter must be None (iterate to convergence) or >= 1 and <= ", kMaxIter, ", got ", *max_iter);
    options.max_iter = *max_iter;
  }
  options.variant = parse_variant(variant);
  return options;
}

// Checks M and init; returns init (undefined if none), which broadcasts to M.
at::Tensor checked_init(const at::Tensor& M, const std::optional<at::Tensor>& init) {
  check_matrix_arg(M, "M");
  if (!init.has_value() || !init->defined()) return at::Tensor();
  check_matrix_arg(*init, "init");
  check_like(*init, "init", M, "M");
  const auto m_batch = M.sizes().slice(0, M.dim() - 2);
  const auto init_batch = init->sizes().slice(0, init->dim() - 2);
  const bool broadcastable = at::is_expandable_to(init_batch, m_batch);
  TORCH_CHECK(broadcastable, kOpName, ": init of shape ", init->sizes(),
              " must broadcast to M's shape ", M.sizes());
  return *init;
}

void check_out(const at::Tensor& M, const at::Tensor& out) {
  TORCH_CHECK(out.defined(), kOpName, ": out must be a tensor of M's shape, got None");
  check_like(out, "out", M, "M");
  TORCH_CHECK(out.sizes() == M.sizes(), kOpName, ": out must have M's shape ", M.sizes(), ", got ",
              out.sizes());
  TORCH_CHECK(at::has_internal_overlap(out) != at::MemOverlap::Yes, kOpName,
              ": out must not have overlapping elements (e.g. an expanded tensor)");
}

// Largest damping accepted: beyond it the derivative is ~0 anyway, and the
// kernel's eps^4 terms would overflow float (NaN gradients from 1e10 on).
constexpr double kMaxGradientEps = 1e3;

void check_gradient_eps(double gradient_eps, const char* op_name) {
  TORCH_CHECK(std::isfinite(gradient_eps) && gradient_eps >= 0 && gradient_eps <= kMaxGradientEps, op_name,
              ": gradient_eps must be a finite number >= 0 and <= ", kMaxGradientEps, ", got ", gradient_eps);
}

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

// (N, 3, 3) view of a tensor with the given (possibly broadcast) geometry,
// without creating a tensor; nullopt if the batch dimensions cannot be
// flattened into one stride.
std::optional<MatrixBatch> batch_view(const at::Tensor& t, at::IntArrayRef sizes, at::IntArrayRef strides,
                                      int64_t n) {
  const auto flat = at::detail::computeStride(sizes, strides, at::DimVector{n, 3, 3});
  if (!flat.has_value()) return std::nullopt;
  MatrixBatch view;
  view.data = t.data_ptr();
  for (int d = 0; d < 3; ++d) view.stride[d] = (*flat)[d];
  return view;
}

MatrixBatch contiguous_view(const at::Tensor& contiguous) {
  MatrixBatch view;
  view.data = contiguous.data_ptr();
  return view;
}

// (N, 3, 3) view of `t` broadcast to `shape` (its geometry, no copy), or of a
// contiguous compute-dtype copy kept in `keep`.
MatrixBatch broadcast_view(const at::Tensor& t, at::IntArrayRef shape, int64_t n, bool reduced,
                           at::ScalarType compute, at::Tensor& keep) {
  if (!reduced) {
    const auto geometry = at::inferExpandGeometry_dimvector(t.sizes(), t.strides(), shape);
    if (auto view = batch_view(t, geometry.sizes, geometry.strides, n)) return *view;
  }
  keep = t.expand(shape).to(compute).contiguous();
  return contiguous_view(keep);
}

// Runs the kernel on (N, 3, 3) views of M, init (broadcast to M) and out,
// converting reduced precision to float32. `out` has M's shape and dtype; it
// may alias M or init exactly. Tensors are only materialised (copied) for
// reduced precision and for layouts whose batch cannot be flattened.
void run_fit(const at::Tensor& M, const at::Tensor& init, const at::Tensor& out, FitOptions options,
             int32_t* iterations, uint8_t* status) {
  const at::ScalarType dtype = M.scalar_type();
  const bool reduced = dtype == at::kHalf || dtype == at::kBFloat16;
  const at::ScalarType compute = reduced ? at::kFloat : dtype;
  options.init_tolerance = init_tolerance(dtype);
  const int64_t n = M.numel() / 9;
  if (n == 0) return;

  at::Tensor m_keep, init_keep, out_keep;  // own any materialised copies
  const MatrixBatch m_view = broadcast_view(M, M.sizes(), n, reduced, compute, m_keep);
  MatrixBatch init_view;
  if (init.defined()) init_view = broadcast_view(init, M.sizes(), n, reduced, compute, init_keep);
  std::optional<MatrixBatch> out_view = reduced ? std::nullopt : batch_view(out, out.sizes(), out.strides(), n);
  if (!out_view) {
    out_keep = at::empty({n, 3, 3}, M.options().dtype(compute));
    out_view = contiguous_view(out_keep);
  }
  const int64_t bad_inits = fit_rotation_cpu(compute, n, m_view, init.defined() ? &init_view : nullptr,
                                             *out_view, options, iterations, status);
  if (out_keep.defined()) out.copy_(out_keep.view(out.sizes()));
  TORCH_CHECK(bad_inits == 0, kOpName, ": init must hold rotations (|R^T R - I|_F < ",
              options.init_tolerance, " for ", dtype, ", det R > 0); ", bad_inits, " of ", n,
              " matrices do not (out has NaN in their place)");
}

at::Tensor fit_rotation_cpu_op(const at::Tensor& M, const std::optional<at::Tensor>& init,
                               std::optional<int64_t> max_iter, c10::string_view variant, double gradient_eps) {
  const at::Tensor init_b = checked_init(M, init);
  const FitOptions options = parse_options(max_iter, variant);
  check_gradient_eps(gradient_eps, kOpName);
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
  run_fit(M, init_b, out, options, iterations.data_ptr<int32_t>(), status.data_ptr<uint8_t>());
  return {out, iterations, status};
}

// ---- the derivative (fit_rotation_backward) ----

constexpr const char* kBackwardName = "torchrot.fit_rotation_backward";

// dL/dM for dL/dR = grad at R = fit_rotation(M); with grad = dM instead, the
// forward-mode dR (the linear map is self-adjoint, see
// kernel/rotation_gradient.h). grad has R's shape; M broadcasts to it.
at::Tensor fit_rotation_backward_cpu_op(const at::Tensor& grad, const at::Tensor& R, const at::Tensor& M,
                                        double gradient_eps) {
  check_matrix_arg(R, "R", kBackwardName);
  const auto check_input = [&R](const at::Tensor& t, const char* name) {
    check_matrix_shape(t, name, kBackwardName);
    check_like(t, name, R, "R", kBackwardName);
  };
  check_input(grad, "grad");
  check_input(M, "M");
  TORCH_CHECK(grad.sizes() == R.sizes(), kBackwardName, ": grad must have R's shape ", R.sizes(), ", got ",
              grad.sizes());
  TORCH_CHECK(at::is_expandable_to(M.sizes(), R.sizes()), kBackwardName, ": M of shape ", M.sizes(),
              " must broadcast to R's shape ", R.sizes());
  check_gradient_eps(gradient_eps, kBackwardName);
  const at::ScalarType dtype = R.scalar_type();
  const bool reduced = dtype == at::kHalf || dtype == at::kBFloat16;
  const at::ScalarType compute = reduced ? at::kFloat : dtype;
  at::Tensor out = at::empty(R.sizes(), R.options().memory_format(at::MemoryFormat::Contiguous));
  const int64_t n = R.numel() / 9;
  if (n == 0) return out;
  at::Tensor grad_keep, r_keep, m_keep;
  const MatrixBatch grad_view = broadcast_view(grad, R.sizes(), n, reduced, compute, grad_keep);
  const MatrixBatch r_view = broadcast_view(R, R.sizes(), n, reduced, compute, r_keep);
  const MatrixBatch m_view = broadcast_view(M, R.sizes(), n, reduced, compute, m_keep);
  if (!reduced) {
    rotation_tangent_cpu(compute, n, grad_view, r_view, m_view, contiguous_view(out), gradient_eps);
    return out;
  }
  at::Tensor out_float = at::empty({n, 3, 3}, R.options().dtype(compute));
  rotation_tangent_cpu(compute, n, grad_view, r_view, m_view, contiguous_view(out_float), gradient_eps);
  out.copy_(out_float.view(R.sizes()));
  return out;
}

}  // namespace

TORCH_LIBRARY(torchrot, m) {
  // gradient_eps only affects the derivative (see fit_rotation_backward).
  m.def(
      "fit_rotation(Tensor M, Tensor? init=None, int? max_iter=None, str variant=\"conservative\", "
      "float gradient_eps=1e-6) -> Tensor");
  m.def(
      "fit_rotation_out(Tensor M, Tensor? init, int? max_iter, str variant, Tensor(a!) out) -> ()");
  m.def(
      "fit_rotation_info(Tensor M, Tensor? init=None, int? max_iter=None, str variant=\"conservative\") "
      "-> (Tensor R, Tensor iterations, Tensor status)");
  // dL/dM given dL/dR = grad at R = fit_rotation(M), through the optimality
  // condition (R^T M symmetric) with Tikhonov damping gradient_eps; the same
  // map gives the forward-mode tangent dR from dM.
  m.def("fit_rotation_backward(Tensor grad, Tensor R, Tensor M, float gradient_eps=1e-6) -> Tensor");
  // Which CPU kernel object runs: "scalar", "default", "avx2" or "avx512".
  m.def("cpu_kernel() -> str", [] { return cpu_kernel_name(); });
  // Operators that do nothing: the benchmark's yardsticks for the fixed cost
  // of a custom-op call, with one argument, and with fit_rotation's
  // signature and an (uninitialised) output of M's shape.
  m.def("_empty_op(Tensor M) -> ()");
  m.def(
      "_empty_fit_rotation(Tensor M, Tensor? init=None, int? max_iter=None, str variant=\"conservative\", "
      "float gradient_eps=1e-6) -> Tensor");
}

TORCH_LIBRARY_IMPL(torchrot, CPU, m) {
  m.impl("fit_rotation", &fit_rotation_cpu_op);
  m.impl("fit_rotation_out", &fit_rotation_out_cpu_op);
  m.impl("fit_rotation_info", &fit_rotation_info_cpu_op);
  m.impl("fit_rotation_backward", &fit_rotation_backward_cpu_op);
  m.impl("_empty_op", [](const at::Tensor&) {});
  m.impl("_empty_fit_rotation", [](const at::Tensor& M, const std::optional<at::Tensor>&, std::optional<int64_t>,
                                   c10::string_view, double) { return at::empty(M.sizes(), M.options()); });
}

}  // namespace torchrot
