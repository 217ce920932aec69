// The CPU kernels of the operators (TORCH_LIBRARY_IMPL(torchrot, CPU)): the
// checks (checks.h), then the call into the ISA-dispatched kernels
// (../cpu/dispatch.cpp) on (N, 3, 3) views of the tensors (layout.h),
// converting reduced precision to float32 and init to M's compute dtype.
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <cstdint>
#include <optional>
#include <tuple>

#include "../fit_rotation.h"
#include "checks.h"
#include "layout.h"
#include "overlap.h"
#include "warm_starts.h"

namespace torchrot {
namespace ops {
namespace {

// Where run_fit writes: `out` itself, given by the caller or allocated for
// them.
enum class Output { kFresh, kCallers };

// Runs the kernel on (N, 3, 3) views of M, init (broadcast to M) and out.
// `out` has M's shape and dtype. Tensors are only materialised (copied) for
// reduced precision, an init of another dtype, for layouts whose batch cannot
// be flattened, and for a caller's out that overlaps M or init other than
// exactly. A caller's out is written only once the call can no longer fail:
// its warm starts are checked first (warm_starts.h).
void run_fit(const at::Tensor& M, const at::Tensor& init, const at::Tensor& out, FitOptions options, Output output,
             int32_t* iterations, uint8_t* status) {
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
      output == Output::kCallers && (overlaps_other_than_identity(out, M) || overlaps_other_than_identity(out, init));
  std::optional<MatrixBatch> out_view;
  if (!reduced && !through_temporary) out_view = batch_view(out, out.sizes(), out.strides(), n);
  if (!out_view) {
    out_keep = new_kernel_buffer(n, M, compute);
    out_view = contiguous_view(out_keep);
  }
  const int64_t bad_inits = fit_rotation_cpu(compute, n, m_view, init.defined() ? &init_view : nullptr, *out_view,
                                             options, iterations, status);
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
  check_gradient_eps(gradient_eps);
  at::Tensor out = new_result(M);
  run_fit(M, init_b, out, options, Output::kFresh, nullptr, nullptr);
  return out;
}

// out may be M or init itself (an in-place warm-start update); any other
// overlap with them is computed through a temporary.
void fit_rotation_out_cpu_op(const at::Tensor& M, const std::optional<at::Tensor>& init,
                             std::optional<int64_t> max_iter, c10::string_view variant, const at::Tensor& out) {
  const at::Tensor init_b = checked_init(M, init);
  const FitOptions options = parse_options(max_iter, variant);
  check_out(M, out);
  run_fit(M, init_b, out, options, Output::kCallers, nullptr, nullptr);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> fit_rotation_info_cpu_op(const at::Tensor& M,
                                                                        const std::optional<at::Tensor>& init,
                                                                        std::optional<int64_t> max_iter,
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

// dL/dM for dL/dR = grad at R = fit_rotation(M); with grad = dM instead, the
// forward-mode dR (the linear map is self-adjoint, see
// kernel/rotation_gradient.h). grad has R's shape; M broadcasts to it.
at::Tensor fit_rotation_backward_cpu_op(const at::Tensor& grad, const at::Tensor& R, const at::Tensor& M,
                                        double gradient_eps) {
  check_backward(grad, R, M, gradient_eps);
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
}  // namespace ops
}  // namespace torchrot

TORCH_LIBRARY_IMPL(torchrot, CPU, m) {
  m.impl("fit_rotation", &torchrot::ops::fit_rotation_cpu_op);
  m.impl("fit_rotation_out", &torchrot::ops::fit_rotation_out_cpu_op);
  m.impl("fit_rotation_info", &torchrot::ops::fit_rotation_info_cpu_op);
  m.impl("fit_rotation_backward", &torchrot::ops::fit_rotation_backward_cpu_op);
}
