// The Autograd kernels of torchrot::fit_rotation and ::fit_rotation_backward.
//
// Every call of them passes here: torch.ops.torchrot.*, torchrot.fit_rotation
// (whose plain eager call enters from C++, csrc/module.cpp) and the calls in
// torch.compile'd graphs, which come with grad mode off. A call that can record
// no derivative runs below autograd; a plain reverse-mode fit (M requires grad)
// records FitRotationAutograd, a C++ node with the derivative of the Python
// Autograd kernel (torchrot/_autograd.py, FitRotationFunction), whose Python
// forward, context and backward cost several times the fit of a small batch;
// every other call (a torch.func transform, a tangent, a traced or
// torch_dispatch tensor, a backward to be differentiated) goes on to that
// Python kernel, registered on the operator's twin
// torchrot::_<name>_python_autograd (the same schema): the
// torch.autograd.Functions that record the derivatives in both modes and at
// every torch.func level. (That Python kernel once ran on every call of the
// operators, also those with nothing to record, and cost more than the fit of a
// small batch: benchmarks/lab_notes.md.) The derivative is the
// optimality-condition tangent of csrc/kernel/rotation_gradient.h, the operator
// torchrot::fit_rotation_backward.

#include <ATen/core/LegacyTypeDispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/core/grad_mode.h>
#include <torch/csrc/autograd/custom_function.h>
#include <torch/library.h>

#include <optional>

#include "messages.h"
#include "operators.h"
#include "torch_internals.h"

namespace torchrot {
namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

const c10::TypedOperatorHandle<FitRotationSignature>& fit_rotation_op() {
  static const auto op = find_operator<FitRotationSignature>("torchrot::fit_rotation");
  return op;
}

const c10::TypedOperatorHandle<FitRotationBackwardSignature>& fit_rotation_backward_op() {
  static const auto op = find_operator<FitRotationBackwardSignature>("torchrot::fit_rotation_backward");
  return op;
}

struct FitRotationAutograd : public torch::autograd::Function<FitRotationAutograd> {
  // Straight to the device kernel: Function::apply only turns grad mode off,
  // which would still pass through the operator's Autograd kernel.
  static at::Tensor forward(AutogradContext* ctx, const at::Tensor& M, const std::optional<at::Tensor>& init,
                            std::optional<int64_t> max_iter, c10::string_view variant, double gradient_eps) {
    at::Tensor R;
    {
      at::AutoDispatchBelowAutograd below;
      R = fit_rotation_op().call(M, init, max_iter, variant, gradient_eps);
    }
    ctx->save_for_backward({R, M});
    ctx->saved_data["gradient_eps"] = gradient_eps;
    return R;
  }

  // dL/dM = R [u]x (self-adjoint map; init, max_iter, variant and
  // gradient_eps get no gradient). With create_graph the operator's own
  // Autograd kernel records the tangent, whose Python twin is differentiable
  // in turn (torchrot/_tangent_derivative.py): second derivatives.
  static variable_list backward(AutogradContext* ctx, variable_list grads) {
    const auto saved = ctx->get_saved_variables();
    const double gradient_eps = ctx->saved_data["gradient_eps"].toDouble();
    at::Tensor grad_M;
    if (ctx->needs_input_grad(0)) {
      if (at::GradMode::is_enabled()) {
        grad_M = fit_rotation_backward_op().call(grads[0], saved[0], saved[1], gradient_eps);
      } else {
        at::AutoDispatchBelowAutograd below;
        grad_M = fit_rotation_backward_op().call(grads[0], saved[0], saved[1], gradient_eps);
      }
    }
    return {grad_M, at::Tensor(), at::Tensor(), at::Tensor(), at::Tensor()};
  }
};

using torch_internals::functorch_transforms_active;

// Whether forward mode records a tangent for `tensor` (outside torch.func,
// forward AD opens level 0 only; a dual level open around tensors without
// tangents records nothing, in either kernel).
bool has_tangent(const at::Tensor& tensor) {
  return torch_internals::forward_grad_mode_enabled() &&
         torch_internals::forward_tangent(tensor, /*level=*/0).defined();
}

bool records_reverse(const at::Tensor& tensor) { return at::GradMode::is_enabled() && tensor.requires_grad(); }

enum class Recording {
  kNothing,         // below autograd
  kCppNode,         // FitRotationAutograd
  kPythonFunction,  // the Python Autograd kernel, which decides again
};

// What a fit records, as the Python kernel would decide it, erring towards
// that kernel: the C++ node where M requires grad (init receives no
// gradient, so a call where only init requires grad records nothing) and
// the tensors are plain, not traced nor torch_dispatch subclasses (their
// Python dispatch key: the Python kernel records those as the tracer
// expects); the Python kernel under a torch.func transform or with a tangent.
Recording fit_recording(c10::DispatchKeySet keys, const at::Tensor& M, const std::optional<at::Tensor>& init) {
  if (functorch_transforms_active() || has_tangent(M) || (init.has_value() && has_tangent(*init))) {
    return Recording::kPythonFunction;
  }
  if (!records_reverse(M)) return Recording::kNothing;
  return keys.has(c10::DispatchKey::Python) ? Recording::kPythonFunction : Recording::kCppNode;
}

// The Autograd kernel of torchrot::fit_rotation.
at::Tensor fit_rotation_autograd(c10::DispatchKeySet keys, const at::Tensor& M, const std::optional<at::Tensor>& init,
                                 std::optional<int64_t> max_iter, c10::string_view variant, double gradient_eps) {
  static const auto python_twin = find_operator<FitRotationSignature>("torchrot::_fit_rotation_python_autograd");
  switch (fit_recording(keys, M, init)) {
    case Recording::kNothing: {
      at::AutoDispatchBelowAutograd below;
      return fit_rotation_op().redispatch(keys & c10::after_autograd_keyset, M, init, max_iter, variant, gradient_eps);
    }
    case Recording::kCppNode:
      return FitRotationAutograd::apply(M, init, max_iter, variant, gradient_eps);
    case Recording::kPythonFunction:
      break;
  }
  // The twin's Autograd kernel is the first of this call's keys.
  return python_twin.redispatch(keys, M, init, max_iter, variant, gradient_eps);
}

// The Autograd kernel of torchrot::fit_rotation_backward: below autograd
// unless it may record (a torch.func transform, a tangent, a tensor requiring
// grad: create_graph), where the Python kernel records the tangent operator
// with its own derivatives (torchrot/_autograd.py, _TangentFunction).
at::Tensor fit_rotation_backward_autograd(c10::DispatchKeySet keys, const at::Tensor& grad, const at::Tensor& R,
                                          const at::Tensor& M, double gradient_eps) {
  static const auto python_twin =
      find_operator<FitRotationBackwardSignature>("torchrot::_fit_rotation_backward_python_autograd");
  const bool may_record = functorch_transforms_active() || has_tangent(grad) || has_tangent(R) || has_tangent(M) ||
                          records_reverse(grad) || records_reverse(R) || records_reverse(M);
  if (may_record) return python_twin.redispatch(keys, grad, R, M, gradient_eps);
  at::AutoDispatchBelowAutograd below;
  return fit_rotation_backward_op().redispatch(keys & c10::after_autograd_keyset, grad, R, M, gradient_eps);
}

// ---- fit_rotation_out and fit_rotation_info: not differentiable ----
//
// fit_rotation_out writes `out` in place, as torch's out= operators do, and
// follows their rules: it records no derivative and refuses a call that
// would need one (M or out requiring grad in grad mode, or carrying a
// forward-mode tangent; torch.func transforms reach here with their wrapped
// tensors, which do); its ADInplaceOrView kernel bumps out's version counter
// once out is written, so that autograd refuses to differentiate through
// values it overwrote (a saved R, say); an inference tensor is written only
// in inference mode (checked with the other arguments, before anything is
// written: check_out in ops/checks.cpp, torchrot/_checks.py). No gradient flows to
// init, so an init that requires grad is allowed, as in fit_rotation.

bool out_needs_derivative(const at::Tensor& M, const at::Tensor& out) {
  return records_reverse(M) || records_reverse(out) || has_tangent(M) || has_tangent(out);
}

void fit_rotation_out_autograd(c10::DispatchKeySet keys, const at::Tensor& M, const std::optional<at::Tensor>& init,
                               std::optional<int64_t> max_iter, c10::string_view variant, const at::Tensor& out) {
  TORCH_CHECK_VALUE(!out_needs_derivative(M, out),
                    messages::format(messages::kOutAutograd, {{"op", messages::kOpName}}));
  static const auto op = find_operator<FitRotationOutSignature>("torchrot::fit_rotation_out");
  at::AutoDispatchBelowAutograd below;
  op.redispatch(keys & c10::after_autograd_keyset, M, init, max_iter, variant, out);
}

void fit_rotation_out_inplace(c10::DispatchKeySet keys, const at::Tensor& M, const std::optional<at::Tensor>& init,
                              std::optional<int64_t> max_iter, c10::string_view variant, const at::Tensor& out) {
  static const auto op = find_operator<FitRotationOutSignature>("torchrot::fit_rotation_out");
  {
    at::AutoDispatchBelowADInplaceOrView below;
    op.redispatch(keys & c10::after_ADInplaceOrView_keyset, M, init, max_iter, variant, out);
  }
  out.unsafeGetTensorImpl()->bump_version();
}

// fit_rotation_info's outputs carry no gradient (R, iterations and status
// are diagnostics): below autograd on every call, so they never require grad.
std::tuple<at::Tensor, at::Tensor, at::Tensor> fit_rotation_info_autograd(c10::DispatchKeySet keys, const at::Tensor& M,
                                                                          const std::optional<at::Tensor>& init,
                                                                          std::optional<int64_t> max_iter,
                                                                          c10::string_view variant) {
  static const auto op = find_operator<FitRotationInfoSignature>("torchrot::fit_rotation_info");
  at::AutoDispatchBelowADInplaceOrView below;
  return op.redispatch(keys & c10::after_ADInplaceOrView_keyset, M, init, max_iter, variant);
}

}  // namespace

TORCH_LIBRARY_IMPL(torchrot, Autograd, m) {
  m.impl("fit_rotation", TORCH_FN(fit_rotation_autograd));
  m.impl("fit_rotation_backward", TORCH_FN(fit_rotation_backward_autograd));
  m.impl("fit_rotation_out", TORCH_FN(fit_rotation_out_autograd));
  m.impl("fit_rotation_info", TORCH_FN(fit_rotation_info_autograd));
}

TORCH_LIBRARY_IMPL(torchrot, ADInplaceOrView, m) { m.impl("fit_rotation_out", TORCH_FN(fit_rotation_out_inplace)); }

}  // namespace torchrot
