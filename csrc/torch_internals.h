// Every torch internal (impl namespaces, thread-local dispatch state) that the
// C++ side uses, in one place; torchrot/_torch_private.py has the Python
// side's. They have no public equivalent and may change in any torch
// release: CI builds and tests against the oldest and the newest supported
// torch, where a change fails the build or tests/test_torch_private.py.
#pragma once

#include <ATen/PythonTorchFunctionTLS.h>
#include <c10/core/AutogradState.h>
#include <c10/core/DispatchKey.h>
#include <c10/core/impl/LocalDispatchKeySet.h>

namespace torchrot {
namespace torch_internals {

// Whether a torch.func transform is active, as Python's
// torch._C._are_functorch_transforms_active tells it: functorch includes its
// dynamic-layer keys while it has a level.
inline bool functorch_transforms_active() {
  const c10::DispatchKeySet included = c10::impl::tls_local_dispatch_key_set().included_;
  return included.has(c10::DispatchKey::FuncTorchDynamicLayerFrontMode) ||
         included.has(c10::DispatchKey::FuncTorchDynamicLayerBackMode);
}

// Whether forward-mode AD records tangents in this thread.
inline bool forward_grad_mode_enabled() { return c10::AutogradState::get_tls_state().get_fw_grad_mode(); }

// Whether a Python torch function mode is active (torch.ops would call it).
inline bool torch_function_mode_enabled() { return at::impl::torch_function_mode_enabled(); }

}  // namespace torch_internals
}  // namespace torchrot
