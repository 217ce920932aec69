// The operators' autograd in C++.
//
// 1. torchrot::_fit_rotation_autograd, torchrot.fit_rotation's plain eager
//    call (a float32/float64 tensor; no torch.func transform, forward AD or
//    tracing), with or without a derivative to record: where M requires grad
//    it records FitRotationAutograd below, a C++ node with the derivative of
//    the Python Autograd kernel of fit_rotation (torchrot/_autograd.py,
//    FitRotationFunction), whose Python forward, context and backward cost
//    several times the fit of a small batch; otherwise it runs the kernel
//    below autograd, without a Python context manager.
// 2. The Autograd kernels of torchrot::fit_rotation and ::fit_rotation_backward
//    themselves (torch.ops.torchrot.*, also the calls in torch.compile'd
//    graphs, which come with grad mode off): a call that can record no
//    derivative runs below autograd, and a plain reverse-mode fit in M records
//    the same C++ node; every other call (a torch.func transform, a tangent,
//    a traced or torch_dispatch tensor, another argument requiring grad) goes
//    on to the Python Autograd kernel, registered on the operator's twin
//    torchrot::_<name>_python_autograd (the same schema): the
//    torch.autograd.Functions that record the derivatives in both modes and
//    at every torch.func level. That Python kernel used to run on every call,
//    also those with nothing to record: ~6 us per call, more than the fit of
//    64 matrices.
// The derivative is the optimality-condition tangent of
// csrc/kernel/rotation_gradient.h, the operator torchrot::fit_rotation_backward.

// torch's autograd headers use C++20 bit-field initialisers (a warning in C++17).
#pragma GCC diagnostic push
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 12
#pragma GCC diagnostic ignored "-Wc++20-extensions"
#endif
#include <ATen/ATen.h>
#include <ATen/core/dispatch/Dispatcher.h>
#include <ATen/core/stack.h>
#include <c10/core/AutogradState.h>
#include <c10/core/impl/LocalDispatchKeySet.h>
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

// Whether a torch.func transform is active, as torch._C._are_functorch_transforms_active
// tells it: functorch includes its dynamic-layer keys while it has a level.
bool functorch_transforms_active() {
  const c10::DispatchKeySet included = c10::impl::tls_local_dispatch_key_set().included_;
  return included.has(c10::DispatchKey::FuncTorchDynamicLayerFrontMode) ||
         included.has(c10::DispatchKey::FuncTorchDynamicLayerBackMode);
}

enum class Recording {
  kNothing,         // below autograd
  kReverseInM,      // fit_rotation's C++ node (FitRotationAutograd)
  kPythonFunction,  // the Python Autograd kernel, which decides again
};

// What a call of torchrot::fit_rotation (is_fit) or ::fit_rotation_backward
// records, decided as the Python kernel would, erring towards it. Nothing
// outside torch.func without reverse mode (grad mode on, a tensor argument
// requiring grad) or forward mode (a tensor argument with a tangent; outside
// torch.func forward AD opens level 0 only, and a dual level open around
// tensors without tangents records nothing, in either kernel). The C++ node
// only for a fit whose M alone requires grad, of plain tensors: not traced
// nor torch_dispatch subclasses (their Python dispatch key; the Python
// kernel records those as the tracer expects).
Recording recording(bool is_fit, c10::DispatchKeySet keys, at::ArrayRef<c10::IValue> arguments) {
  if (functorch_transforms_active()) return Recording::kPythonFunction;
  const bool reverse = at::GradMode::is_enabled();
  const bool forward = c10::AutogradState::get_tls_state().get_fw_grad_mode();
  bool M_requires_grad = false;
  bool other_requires_grad_or_tangent = false;
  for (size_t i = 0; i < arguments.size(); ++i) {
    if (!arguments[i].isTensor()) continue;  // None for an absent init
    const at::Tensor& tensor = arguments[i].toTensor();
    const bool requires_grad = reverse && tensor.requires_grad();
    if (i == 0 && is_fit) {
      M_requires_grad = requires_grad;
    } else {
      other_requires_grad_or_tangent |= requires_grad;
    }
    other_requires_grad_or_tangent |= forward && tensor._fw_grad(/*level=*/0).defined();
  }
  if (other_requires_grad_or_tangent) return Recording::kPythonFunction;
  if (!M_requires_grad) return Recording::kNothing;
  return keys.has(c10::DispatchKey::Python) ? Recording::kPythonFunction : Recording::kReverseInM;
}

void autograd_kernel(const c10::OperatorHandle& op, c10::DispatchKeySet keys, torch::jit::Stack* stack) {
  static const c10::OperatorHandle fit = c10::Dispatcher::singleton().findSchemaOrThrow("torchrot::fit_rotation", "");
  static const c10::OperatorHandle fit_twin =
      c10::Dispatcher::singleton().findSchemaOrThrow("torchrot::_fit_rotation_python_autograd", "");
  static const c10::OperatorHandle backward_twin =
      c10::Dispatcher::singleton().findSchemaOrThrow("torchrot::_fit_rotation_backward_python_autograd", "");
  const bool is_fit = op == fit;
  const size_t num_arguments = op.schema().arguments().size();
  switch (recording(is_fit, keys, torch::jit::last(*stack, num_arguments))) {
    case Recording::kNothing: {
      at::AutoDispatchBelowAutograd below;
      op.redispatchBoxed(keys & c10::after_autograd_keyset, stack);
      return;
    }
    case Recording::kReverseInM: {
      const auto arguments = torch::jit::last(*stack, num_arguments);
      at::Tensor R = FitRotationAutograd::apply(arguments[0].toTensor(), arguments[1].toOptional<at::Tensor>(),
                                                arguments[2].toOptional<int64_t>(), arguments[3].toStringView(),
                                                arguments[4].toDouble());
      torch::jit::drop(*stack, num_arguments);
      torch::jit::push(*stack, std::move(R));
      return;
    }
    case Recording::kPythonFunction:
      // The twin's Autograd kernel is the first of this call's keys.
      (is_fit ? fit_twin : backward_twin).redispatchBoxed(keys, stack);
      return;
  }
}

}  // namespace

TORCH_LIBRARY_IMPL(torchrot, CompositeImplicitAutograd, m) {
  m.impl("_fit_rotation_autograd", &fit_rotation_autograd);
}

TORCH_LIBRARY_IMPL(torchrot, Autograd, m) {
  m.impl("fit_rotation", torch::CppFunction::makeFromBoxedFunction<&autograd_kernel>());
  m.impl("fit_rotation_backward", torch::CppFunction::makeFromBoxedFunction<&autograd_kernel>());
}

}  // namespace torchrot
