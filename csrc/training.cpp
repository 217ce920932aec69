// Plain eager calls in C++, their derivative included: torchrot::_fit_rotation_autograd.
//
// torchrot.fit_rotation calls this operator for plain eager calls (a
// float32/float64 tensor; no torch.func transform, forward AD or tracing),
// with or without a derivative to record: where M requires grad, the same
// derivative as the Python Autograd kernel of fit_rotation
// (torchrot/_autograd.py), FitRotationFunction, whose Python forward, context
// and backward cost several times the fit of a small batch; otherwise the
// kernel below autograd, without a Python context manager. Every other mode
// goes through the Python kernel. The derivative is the optimality-condition
// tangent of csrc/kernel/rotation_gradient.h, the operator
// torchrot::fit_rotation_backward.
// torch's autograd headers use C++20 bit-field initialisers (a warning in C++17).
#pragma GCC diagnostic push
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 12
#pragma GCC diagnostic ignored "-Wc++20-extensions"
#endif
#include <ATen/ATen.h>
#include <ATen/core/dispatch/Dispatcher.h>
#include <torch/csrc/autograd/custom_function.h>
#include <torch/library.h>
#pragma GCC diagnostic pop

#include <optional>

#include "fit_rotation.h"

namespace torchrot {
namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

at::Tensor call_fit_rotation(const at::Tensor& M, const std::optional<at::Tensor>& init,
                             std::optional<int64_t> max_iter, c10::string_view variant, double gradient_eps) {
  static auto op = c10::Dispatcher::singleton()
                       .findSchemaOrThrow("torchrot::fit_rotation", "")
                       .typed<FitRotationSignature>();
  return op.call(M, init, max_iter, variant, gradient_eps);
}

at::Tensor call_fit_rotation_backward(const at::Tensor& grad, const at::Tensor& R, const at::Tensor& M,
                                      double gradient_eps) {
  static auto op = c10::Dispatcher::singleton()
                       .findSchemaOrThrow("torchrot::fit_rotation_backward", "")
                       .typed<at::Tensor(const at::Tensor&, const at::Tensor&, const at::Tensor&, double)>();
  return op.call(grad, R, M, gradient_eps);
}

struct FitRotationAutograd : public torch::autograd::Function<FitRotationAutograd> {
  // Straight to the device kernel: Function::apply only turns grad mode off,
  // which would still pass through the operator's Autograd kernel.
  static at::Tensor forward(AutogradContext* ctx, const at::Tensor& M, const std::optional<at::Tensor>& init,
                            std::optional<int64_t> max_iter, c10::string_view variant, double gradient_eps) {
    at::Tensor R;
    {
      at::AutoDispatchBelowAutograd below;
      R = call_fit_rotation(M, init, max_iter, variant, gradient_eps);
    }
    ctx->save_for_backward({R, M});
    ctx->saved_data["gradient_eps"] = gradient_eps;
    return R;
  }

  // dL/dM = R [u]x (self-adjoint map; init, max_iter, variant and
  // gradient_eps get no gradient). With create_graph the operator's own
  // Autograd kernel records the tangent, which refuses to be differentiated
  // again (second derivatives raise, as on every other path).
  static variable_list backward(AutogradContext* ctx, variable_list grads) {
    const auto saved = ctx->get_saved_variables();
    const double gradient_eps = ctx->saved_data["gradient_eps"].toDouble();
    at::Tensor grad_M;
    if (ctx->needs_input_grad(0)) {
      if (at::GradMode::is_enabled()) {
        grad_M = call_fit_rotation_backward(grads[0], saved[0], saved[1], gradient_eps);
      } else {
        at::AutoDispatchBelowAutograd below;
        grad_M = call_fit_rotation_backward(grads[0], saved[0], saved[1], gradient_eps);
      }
    }
    return {grad_M, at::Tensor(), at::Tensor(), at::Tensor(), at::Tensor()};
  }
};

// With nothing to record (grad mode off, or M not requiring grad: init gets
// no gradient) straight to the device kernel, without the autograd node that
// Function::apply builds even then.
at::Tensor fit_rotation_autograd(const at::Tensor& M, const std::optional<at::Tensor>& init,
                                 std::optional<int64_t> max_iter, c10::string_view variant, double gradient_eps) {
  if (at::GradMode::is_enabled() && M.requires_grad()) {
    return FitRotationAutograd::apply(M, init, max_iter, variant, gradient_eps);
  }
  at::AutoDispatchBelowAutograd below;
  return call_fit_rotation(M, init, max_iter, variant, gradient_eps);
}

}  // namespace

TORCH_LIBRARY_IMPL(torchrot, CompositeImplicitAutograd, m) {
  m.impl("_fit_rotation_autograd", &fit_rotation_autograd);
}

}  // namespace torchrot
