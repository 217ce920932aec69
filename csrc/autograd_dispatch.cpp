// The Autograd kernels of torchrot::fit_rotation and torchrot::fit_rotation_backward.
//
// A call that can record no derivative goes straight below autograd, in C++.
// Every other call goes on to the operator's Python Autograd kernel
// (torchrot/_autograd.py), registered on its twin torchrot::_<name>_python_autograd
// (the same schema): a torch.autograd.Function that records the derivatives
// in both modes, at every torch.func level and where torch.compile traces the
// operator. That Python kernel used to run on every call, also on those with
// nothing to record: about 6 us of Python per call of torch.ops.torchrot.*,
// and per call of the operators in a torch.compile'd graph, which calls them
// with grad mode off; more than the fit of a 64-matrix batch takes.
// torch's autograd state header uses C++20 bit-field initialisers (a warning in C++17).
#pragma GCC diagnostic push
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 12
#pragma GCC diagnostic ignored "-Wc++20-extensions"
#endif
#include <ATen/core/LegacyTypeDispatch.h>
#include <ATen/core/dispatch/Dispatcher.h>
#include <ATen/core/stack.h>
#include <c10/core/AutogradState.h>
#include <c10/core/GradMode.h>
#include <c10/core/impl/LocalDispatchKeySet.h>
#include <torch/library.h>
#pragma GCC diagnostic pop

namespace torchrot {
namespace {

// Whether a torch.func transform is active, as torch._C._are_functorch_transforms_active
// tells it: functorch includes its dynamic-layer keys while it has a level.
bool functorch_transforms_active() {
  const c10::DispatchKeySet included = c10::impl::tls_local_dispatch_key_set().included_;
  return included.has(c10::DispatchKey::FuncTorchDynamicLayerFrontMode) ||
         included.has(c10::DispatchKey::FuncTorchDynamicLayerBackMode);
}

// Whether a call may record a derivative, decided as the Python kernel
// decides it, erring towards yes (the Python kernel then decides again):
// under a torch.func transform always; otherwise reverse mode with grad mode
// on and a tensor argument that requires grad, or forward mode with a tensor
// argument that carries a tangent (outside torch.func forward AD opens level
// 0 only; a dual level open around tensors without tangents records nothing,
// in either kernel).
bool may_record_derivative(const torch::jit::Stack& stack, size_t num_arguments) {
  if (functorch_transforms_active()) return true;
  const bool reverse = at::GradMode::is_enabled();
  const bool forward = c10::AutogradState::get_tls_state().get_fw_grad_mode();
  for (const c10::IValue& argument : torch::jit::last(stack, num_arguments)) {
    if (!argument.isTensor()) continue;  // None for an absent init
    const at::Tensor& tensor = argument.toTensor();
    if ((reverse && tensor.requires_grad()) || (forward && tensor._fw_grad(/*level=*/0).defined())) return true;
  }
  return false;
}

// torchrot::_<name>_python_autograd for torchrot::<name>, each looked up once.
const c10::OperatorHandle& python_autograd_twin(const c10::OperatorHandle& op) {
  static const c10::OperatorHandle fit =
      c10::Dispatcher::singleton().findSchemaOrThrow("torchrot::fit_rotation", "");
  static const c10::OperatorHandle fit_twin =
      c10::Dispatcher::singleton().findSchemaOrThrow("torchrot::_fit_rotation_python_autograd", "");
  static const c10::OperatorHandle backward_twin =
      c10::Dispatcher::singleton().findSchemaOrThrow("torchrot::_fit_rotation_backward_python_autograd", "");
  return op == fit ? fit_twin : backward_twin;
}

void autograd_kernel(const c10::OperatorHandle& op, c10::DispatchKeySet keys, torch::jit::Stack* stack) {
  if (may_record_derivative(*stack, op.schema().arguments().size())) {
    // The twin's Autograd kernel is the first of this call's keys.
    python_autograd_twin(op).redispatchBoxed(keys, stack);
    return;
  }
  at::AutoDispatchBelowAutograd below;
  op.redispatchBoxed(keys & c10::after_autograd_keyset, stack);
}

}  // namespace

TORCH_LIBRARY_IMPL(torchrot, Autograd, m) {
  m.impl("fit_rotation", torch::CppFunction::makeFromBoxedFunction<&autograd_kernel>());
  m.impl("fit_rotation_backward", torch::CppFunction::makeFromBoxedFunction<&autograd_kernel>());
}

}  // namespace torchrot
