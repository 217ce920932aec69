// Operator schemas (TORCH_LIBRARY) and their CPU implementations
// (TORCH_LIBRARY_IMPL): argument checking, broadcasting of the warm start,
// flattening of the batch, reduced-precision inputs, and the call into the
// kernels. Fake (meta) kernels and other devices are registered in Python
// (torchrot/_ops.py).
#include <ATen/ATen.h>
#include <ATen/ExpandUtils.h>
#include <ATen/MemoryOverlap.h>
#include <ATen/TensorUtils.h>
#include <c10/core/InferenceMode.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "cpu/huge_pages.h"
#include "fit_rotation.h"
#include "limits.h"
#include "messages.h"

namespace torchrot {
namespace {

// Every check raises what the Python-side checks (torchrot/_checks.py: fake
// kernels, other devices, torch.compile) raise, with the same message:
// TypeError (TORCH_CHECK_TYPE) for a wrong type or dtype, ValueError
// (TORCH_CHECK_VALUE) for a wrong value, shape or device. Limits and defaults
// come from limits.h.
using messages::kBackwardName;
using messages::kOpName;

// A dtype as Python prints it ("torch.float32").
std::string dtype_name(at::ScalarType t) { return "torch." + std::string(c10::getDtypeNames(t).first); }

Variant parse_variant(c10::string_view variant) {
  if (variant == "newton") return Variant::kNewton;
  if (variant == "conservative") return Variant::kConservative;
  if (variant == "gershgorin") return Variant::kGershgorin;
  TORCH_CHECK_VALUE(false, kOpName, ": variant must be one of 'newton', 'conservative', 'gershgorin', got '",
                    std::string(variant), "'");
}

bool is_supported_dtype(at::ScalarType t) {
  return t == at::kFloat || t == at::kDouble || t == at::kHalf || t == at::kBFloat16;
}

void check_matrix_shape(const at::Tensor& t, const char* name, const char* op = kOpName) {
  TORCH_CHECK_TYPE(t.defined(), op, ": ", name, " must be a torch.Tensor, got NoneType");
  TORCH_CHECK_VALUE(t.dim() >= 2 && t.size(-1) == 3 && t.size(-2) == 3, op, ": ", name,
                    " must have shape (..., 3, 3), got ", t.sizes());
}

void check_matrix_arg(const at::Tensor& t, const char* name, const char* op = kOpName) {
  check_matrix_shape(t, name, op);
  TORCH_CHECK_TYPE(is_supported_dtype(t.scalar_type()), op, ": ", name,
                   " must be float32, float64, float16 or bfloat16, got ", dtype_name(t.scalar_type()));
}

// `t` (argument `name`) must be on `ref`'s device and have its dtype.
void check_like(const at::Tensor& t, const char* name, const at::Tensor& ref, const char* ref_name,
                const char* op = kOpName) {
  TORCH_CHECK_VALUE(t.device() == ref.device(), op, ": ", name, " must be on ", ref_name, "'s device (",
                    ref.device(), "), got ", t.device());
  TORCH_CHECK_TYPE(t.scalar_type() == ref.scalar_type(), op, ": ", name, " must have ", ref_name, "'s dtype (",
                   dtype_name(ref.scalar_type()), "), got ", dtype_name(t.scalar_type()));
}

FitOptions parse_options(std::optional<int64_t> max_iter, c10::string_view variant) {
  FitOptions options;
  if (max_iter.has_value()) {
    TORCH_CHECK_VALUE(*max_iter >= 1 && *max_iter <= limits::kMaxIter, kOpName,
                      ": max_iter must be None (iterate to convergence) or an int >= 1 and <= ", limits::kMaxIter,
                      ", got ", *max_iter);
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
  // any float dtype: a warm start of another precision is cast to M's
  // compute dtype (and cleaned up to it, kernel::clean_warm_start)
  TORCH_CHECK_VALUE(init->device() == M.device(), kOpName, ": init must be on M's device (", M.device(), "), got ",
                    init->device());
  const auto m_batch = M.sizes().slice(0, M.dim() - 2);
  const auto init_batch = init->sizes().slice(0, init->dim() - 2);
  TORCH_CHECK_VALUE(at::is_expandable_to(init_batch, m_batch), kOpName, ": init of shape ", init->sizes(),
                    " must broadcast to M's shape ", M.sizes());
  return *init;
}

// Whether two distinct elements of `t` share memory. Exact: strides that nest
// (each at least the extent of the smaller ones: every dense or sliced
// tensor) are decided at once, others by sorting their element offsets.
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

void check_out(const at::Tensor& M, const at::Tensor& out) {
  TORCH_CHECK_TYPE(out.defined(), kOpName, ": out must be a torch.Tensor, got NoneType");
  check_like(out, "out", M, "M");
  TORCH_CHECK_VALUE(out.sizes() == M.sizes(), kOpName, ": out must have M's shape ", M.sizes(), ", got ",
                    out.sizes());
  TORCH_CHECK_VALUE(!has_overlapping_elements(out), kOpName,
                    ": out must not have overlapping elements (e.g. an expanded tensor)");
  TORCH_CHECK_VALUE(!out.is_inference() || c10::InferenceMode::is_enabled(), kOpName, messages::kOutInference);
}

void check_gradient_eps(double gradient_eps, const char* op_name) {
  TORCH_CHECK_VALUE(std::isfinite(gradient_eps) && gradient_eps >= 0 && gradient_eps <= limits::kMaxGradientEps,
                    op_name, ": gradient_eps must be a finite number >= 0 and <= ", limits::kMaxGradientEps,
                    ", got ", gradient_eps);
}

// The error for `bad` of `n` warm starts that are not rotations.
[[noreturn]] void throw_bad_init(int64_t bad, int64_t n) {
  TORCH_CHECK_VALUE(false, kOpName, ": init must hold rotations (|R^T R - I|_F < ", limits::kInitTolerance,
                    " and det R > 0; rotations of any float dtype qualify); ", bad, " of ", n,
                    " are not: pass rotations, or no init for a cold start");
}

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

// Whether `out` must be computed through a temporary because writing it
// could change `input` before it is read: any overlap except the exact
// identity (same elements in the same layout, which the kernels allow: a
// block's inputs are in registers before its result is stored).
bool overlaps_other_than_identity(const at::Tensor& out, const at::Tensor& input) {
  if (!input.defined() || out.numel() == 0 || input.numel() == 0) return false;
  if (out.data_ptr() == input.data_ptr() && out.sizes() == input.sizes() && out.strides() == input.strides()) {
    return false;
  }
  const auto a = byte_range(out), b = byte_range(input);
  return a.first <= b.second && b.first <= a.second;
}

// (N, 3, 3) view of a tensor with the given (possibly broadcast) geometry,
// without creating a tensor: its batch dimensions flattened into one stride,
// or else into tiles (MatrixBatch::tile), the trailing ones (as many as can
// be) into a tile's matrices and the leading ones into the tiles, as in the
// paper authors' (N / 8, 8, 3, 3) blocks of 8 matrices in structure of
// arrays; nullopt if neither can be.
std::optional<MatrixBatch> batch_view(const at::Tensor& t, at::IntArrayRef sizes, at::IntArrayRef strides,
                                      int64_t n) {
  MatrixBatch view;
  view.data = t.data_ptr();
  if (const auto flat = at::detail::computeStride(sizes, strides, at::DimVector{n, 3, 3})) {
    for (int d = 0; d < 3; ++d) view.layout.stride[d] = (*flat)[d];
    return view;
  }
  const int64_t batch_dims = static_cast<int64_t>(sizes.size()) - 2;
  for (int64_t split = 1; split < batch_dims; ++split) {
    int64_t tile = 1;
    for (int64_t d = split; d < batch_dims; ++d) tile *= sizes[d];
    const auto tiled = at::detail::computeStride(sizes, strides, at::DimVector{n / tile, tile, 3, 3});
    if (!tiled.has_value()) continue;
    view.layout.tile = tile;
    view.layout.tile_stride = (*tiled)[0];
    for (int d = 0; d < 3; ++d) view.layout.stride[d] = (*tiled)[d + 1];
    return view;
  }
  return std::nullopt;
}

// Whether `t` is in structure-of-arrays layout: dense, the matrix index of
// stride 1 across all its batch dimensions (a permuted (3, 3, N) tensor) or
// within tiles (the paper authors' (N / 8, 8, 3, 3) blocks): its trailing
// batch dimensions flatten to one of stride 1 and more than one matrix, its
// leading ones (if any) to one stride, so that batch_view reads it in place.
// The kernels load and store such tensors as plain vectors.
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

// A new result of `t`'s shape: in t's layout where that is structure of
// arrays (so solvers that assemble their matrices that way keep it, and the
// kernels store plain vectors), contiguous otherwise. The fake kernels
// (torchrot/_ops.py, _empty_result) make the same choice. The kernel fills it
// right after: on huge pages where it is large (cpu/huge_pages.h).
at::Tensor new_result(const at::Tensor& t) {
  if (has_soa_layout(t)) return cpu::advise_huge_pages(at::empty_strided(t.sizes(), t.strides(), t.options()));
  return cpu::advise_huge_pages(at::empty(t.sizes(), t.options().memory_format(at::MemoryFormat::Contiguous)));
}

// A contiguous (n, 3, 3) buffer for the kernel to fill, of dtype `compute`.
at::Tensor new_kernel_buffer(int64_t n, const at::Tensor& like, at::ScalarType compute) {
  return cpu::advise_huge_pages(at::empty({n, 3, 3}, like.options().dtype(compute)));
}

MatrixBatch contiguous_view(const at::Tensor& contiguous) {
  MatrixBatch view;
  view.data = contiguous.data_ptr();
  return view;
}

// The dtype the kernels compute a tensor of dtype `t` in: float32 for
// float16 and bfloat16.
at::ScalarType compute_dtype(at::ScalarType t) { return t == at::kHalf || t == at::kBFloat16 ? at::kFloat : t; }

// (N, 3, 3) view of `t` broadcast to `shape` (its geometry, no copy), or of a
// contiguous copy in the `compute` dtype kept in `keep` (for another dtype, or
// a batch that cannot be flattened).
MatrixBatch broadcast_view(const at::Tensor& t, at::IntArrayRef shape, int64_t n, at::ScalarType compute,
                           at::Tensor& keep) {
  if (t.scalar_type() == compute) {
    const auto geometry = at::inferExpandGeometry_dimvector(t.sizes(), t.strides(), shape);
    if (auto view = batch_view(t, geometry.sizes, geometry.strides, n)) return *view;
  }
  keep = t.expand(shape).to(compute).contiguous();
  return contiguous_view(keep);
}

// The check of the warm starts of `init` (any shape (..., 3, 3)), in
// `compute`, the dtype of the fit: the values the fit checks itself.
WarmStartCount count_bad_warm_starts(const at::Tensor& init, at::ScalarType compute) {
  const int64_t n = init.numel() / 9;
  if (n == 0) return {};
  at::Tensor keep;
  return count_bad_warm_starts_cpu(compute, n, broadcast_view(init, init.sizes(), n, compute, keep));
}

// The validation pass fit_rotation_out makes before writing, as an operator
// (torchrot::_count_bad_warm_starts) so that the benchmark can time it
// (benchmarks/atomic_cost.py).
int64_t count_bad_warm_starts_op(const at::Tensor& init) {
  check_matrix_arg(init, "init");
  return count_bad_warm_starts(init, compute_dtype(init.scalar_type())).bad;
}

// Raises (ValueError) if a warm start of `init`, taken in its own shape
// (not broadcast), is not a rotation: run before anything is written, so that
// a call that raises leaves the caller's out as it was. Returns whether every
// warm start is clean (FitOptions::init_known_clean): the fit then skips its
// own check, so the validation costs the call one pass, not two checks.
bool check_warm_starts(const at::Tensor& init, at::ScalarType compute) {
  const WarmStartCount count = count_bad_warm_starts(init, compute);
  if (count.bad != 0) throw_bad_init(count.bad, init.numel() / 9);
  return count.unclean == 0;
}

// Where run_fit writes: `out` itself, given by the caller or allocated for
// them.
enum class Output { kFresh, kCallers };

// Runs the kernel on (N, 3, 3) views of M, init (broadcast to M) and out,
// converting reduced precision to float32 and init to M's compute dtype.
// `out` has M's shape and dtype. Tensors are only materialised (copied) for
// reduced precision, an init of another dtype, for layouts
// whose batch cannot be flattened, and for a caller's out that overlaps M or
// init other than exactly. A caller's out is written only once the call can
// no longer fail.
void run_fit(const at::Tensor& M, const at::Tensor& init, const at::Tensor& out, FitOptions options,
             Output output, int32_t* iterations, uint8_t* status) {
  const at::ScalarType compute = compute_dtype(M.scalar_type());
  const bool reduced = compute != M.scalar_type();
  const int64_t n = M.numel() / 9;
  if (n == 0) return;
  if (init.defined() && output == Output::kCallers) options.init_known_clean = check_warm_starts(init, compute);

  at::Tensor m_keep, init_keep, out_keep;  // own any materialised copies
  const MatrixBatch m_view = broadcast_view(M, M.sizes(), n, compute, m_keep);
  MatrixBatch init_view;
  if (init.defined()) init_view = broadcast_view(init, M.sizes(), n, compute, init_keep);
  const bool through_temporary =
      output == Output::kCallers &&
      (overlaps_other_than_identity(out, M) || overlaps_other_than_identity(out, init));
  std::optional<MatrixBatch> out_view;
  if (!reduced && !through_temporary) out_view = batch_view(out, out.sizes(), out.strides(), n);
  if (!out_view) {
    out_keep = new_kernel_buffer(n, M, compute);
    out_view = contiguous_view(out_keep);
  }
  const int64_t bad_inits = fit_rotation_cpu(compute, n, m_view, init.defined() ? &init_view : nullptr,
                                             *out_view, options, iterations, status);
  if (bad_inits != 0) {  // only a fresh out has been written; the error counts init in its own shape
    check_warm_starts(init, compute);
    throw_bad_init(bad_inits, n);  // not reached: the same check found them
  }
  if (out_keep.defined()) out.copy_(out_keep.view(out.sizes()));
}

at::Tensor fit_rotation_cpu_op(const at::Tensor& M, const std::optional<at::Tensor>& init,
                               std::optional<int64_t> max_iter, c10::string_view variant, double gradient_eps) {
  const at::Tensor init_b = checked_init(M, init);
  const FitOptions options = parse_options(max_iter, variant);
  check_gradient_eps(gradient_eps, kOpName);
  at::Tensor out = new_result(M);
  run_fit(M, init_b, out, options, Output::kFresh, nullptr, nullptr);
  return out;
}

// out may be M or init itself (an in-place warm-start update); any other
// overlap with them is computed through a temporary.
void fit_rotation_out_cpu_op(const at::Tensor& M, const std::optional<at::Tensor>& init,
                             std::optional<int64_t> max_iter, c10::string_view variant,
                             const at::Tensor& out) {
  const at::Tensor init_b = checked_init(M, init);
  const FitOptions options = parse_options(max_iter, variant);
  check_out(M, out);
  run_fit(M, init_b, out, options, Output::kCallers, nullptr, nullptr);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> fit_rotation_info_cpu_op(
    const at::Tensor& M, const std::optional<at::Tensor>& init, std::optional<int64_t> max_iter,
    c10::string_view variant) {
  const at::Tensor init_b = checked_init(M, init);
  const FitOptions options = parse_options(max_iter, variant);
  at::Tensor out = new_result(M);
  const auto batch = M.sizes().slice(0, M.dim() - 2);
  at::Tensor iterations = at::empty(batch, M.options().dtype(at::kInt));
  at::Tensor status = at::empty(batch, M.options().dtype(at::kByte));
  run_fit(M, init_b, out, options, Output::kFresh, iterations.data_ptr<int32_t>(), status.data_ptr<uint8_t>());
  return {out, iterations, status};
}

// ---- the derivative (fit_rotation_backward) ----

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
  TORCH_CHECK_VALUE(grad.sizes() == R.sizes(), kBackwardName, ": grad must have R's shape ", R.sizes(), ", got ",
                    grad.sizes());
  TORCH_CHECK_VALUE(at::is_expandable_to(M.sizes(), R.sizes()), kBackwardName, ": M of shape ", M.sizes(),
                    " must broadcast to R's shape ", R.sizes());
  check_gradient_eps(gradient_eps, kBackwardName);
  const at::ScalarType compute = compute_dtype(R.scalar_type());
  const bool reduced = compute != R.scalar_type();
  at::Tensor out = new_result(R);
  const int64_t n = R.numel() / 9;
  if (n == 0) return out;
  at::Tensor grad_keep, r_keep, m_keep;
  const MatrixBatch grad_view = broadcast_view(grad, R.sizes(), n, compute, grad_keep);
  const MatrixBatch r_view = broadcast_view(R, R.sizes(), n, compute, r_keep);
  const MatrixBatch m_view = broadcast_view(M, R.sizes(), n, compute, m_keep);
  if (!reduced) {
    rotation_tangent_cpu(compute, n, grad_view, r_view, m_view, *batch_view(out, out.sizes(), out.strides(), n),
                         gradient_eps);
    return out;
  }
  at::Tensor out_float = new_kernel_buffer(n, R, compute);
  rotation_tangent_cpu(compute, n, grad_view, r_view, m_view, contiguous_view(out_float), gradient_eps);
  out.copy_(out_float.view(R.sizes()));
  return out;
}

}  // namespace

#define TORCHROT_STRINGIFY_(x) #x
#define TORCHROT_STRINGIFY(x) TORCHROT_STRINGIFY_(x)
#define TORCHROT_GRADIENT_EPS_ARG "float gradient_eps=" TORCHROT_STRINGIFY(TORCHROT_DEFAULT_GRADIENT_EPS)
// The arguments and results of fit_rotation and fit_rotation_backward, each
// shared with its Python Autograd twin below.
#define TORCHROT_FIT_ROTATION_SCHEMA                                                  \
  "(Tensor M, Tensor? init=None, int? max_iter=None, str variant=\"conservative\", " \
  TORCHROT_GRADIENT_EPS_ARG ") -> Tensor"
#define TORCHROT_FIT_ROTATION_BACKWARD_SCHEMA \
  "(Tensor grad, Tensor R, Tensor M, " TORCHROT_GRADIENT_EPS_ARG ") -> Tensor"

TORCH_LIBRARY(torchrot, m) {
  // gradient_eps only affects the derivative (see fit_rotation_backward).
  m.def("fit_rotation" TORCHROT_FIT_ROTATION_SCHEMA);
  m.def(
      "fit_rotation_out(Tensor M, Tensor? init, int? max_iter, str variant, Tensor(a!) out) -> ()");
  m.def(
      "fit_rotation_info(Tensor M, Tensor? init=None, int? max_iter=None, str variant=\"conservative\") "
      "-> (Tensor R, Tensor iterations, Tensor status)");
  // dL/dM given dL/dR = grad at R = fit_rotation(M), through the optimality
  // condition (R^T M symmetric) with Tikhonov damping gradient_eps; the same
  // map gives the forward-mode tangent dR from dM.
  m.def("fit_rotation_backward" TORCHROT_FIT_ROTATION_BACKWARD_SCHEMA);
  // Twins of fit_rotation and fit_rotation_backward that carry only their
  // Python Autograd kernels (torchrot/_autograd.py): the C++ Autograd kernel
  // of each (csrc/autograd.cpp) hands them the calls of torch.func, forward
  // mode and tracing.
  m.def("_fit_rotation_python_autograd" TORCHROT_FIT_ROTATION_SCHEMA);
  m.def("_fit_rotation_backward_python_autograd" TORCHROT_FIT_ROTATION_BACKWARD_SCHEMA);
  // Which CPU kernel object runs in the calling thread: "scalar", "default",
  // "avx2" or "avx512".
  m.def("cpu_kernel() -> str", [] { return cpu_kernel_name(); });
  // Whether that kernel's results are the scalar kernel's bit for bit (it
  // rounds a * b + c once, as the scalar kernel does; see kernel/mul_add.h).
  m.def("_cpu_kernel_fuses_multiply_add() -> bool", [] { return cpu_kernel_fuses_multiply_add(); });
  // Forces a kernel object for the calling thread ("" to stop); returns the
  // previously forced one. Use torchrot.testing.cpu_kernel(name).
  m.def("_set_cpu_kernel(str name) -> str",
        [](c10::string_view name) { return set_thread_cpu_kernel(std::string(name)); });
  m.def("_count_bad_warm_starts(Tensor init) -> int");
  // Operators that do nothing: the benchmark's yardsticks for the fixed cost
  // of a custom-op call, with one argument, and with fit_rotation's
  // signature and an (uninitialised) output of M's shape.
  m.def("_empty_op(Tensor M) -> ()");
  m.def("_empty_fit_rotation" TORCHROT_FIT_ROTATION_SCHEMA);
}

TORCH_LIBRARY_IMPL(torchrot, CPU, m) {
  m.impl("fit_rotation", &fit_rotation_cpu_op);
  m.impl("fit_rotation_out", &fit_rotation_out_cpu_op);
  m.impl("fit_rotation_info", &fit_rotation_info_cpu_op);
  m.impl("fit_rotation_backward", &fit_rotation_backward_cpu_op);
  m.impl("_count_bad_warm_starts", &count_bad_warm_starts_op);
  m.impl("_empty_op", [](const at::Tensor&) {});
  m.impl("_empty_fit_rotation", [](const at::Tensor& M, const std::optional<at::Tensor>&, std::optional<int64_t>,
                                   c10::string_view, double) { return at::empty(M.sizes(), M.options()); });
}

}  // namespace torchrot
