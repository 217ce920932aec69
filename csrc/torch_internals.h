// Every torch internal (impl and detail namespaces, thread-local dispatch
// state, underscored methods, the Python bindings of torch/csrc) that the C++
// side uses, in one place, each behind a wrapper or alias of its own;
// torchrot/_torch_private.py has the Python side's. They have no public
// equivalent and may change in any torch release: CI builds and tests against
// the oldest and the newest supported torch, where a change fails the build or
// tests/test_torch_private.py, which tests each wrapper here on the installed
// torch through the test-only functions torchrot._C._torch_internals_*
// (module.cpp), and checks that no other source of csrc/ names these
// internals.
//
// The second part, the Python bindings' internals, is compiled only where
// TORCHROT_TORCH_INTERNALS_PYTHON is defined before the include (module.cpp):
// it brings Python's and pybind11's headers, which the other sources (the
// unity build of the operator sources among them) do without.
#ifndef TORCHROT_TORCH_INTERNALS_H_
#define TORCHROT_TORCH_INTERNALS_H_

#include <ATen/PythonTorchFunctionTLS.h>
#include <ATen/TensorUtils.h>
#include <ATen/core/Tensor.h>
#include <c10/core/AutogradState.h>
#include <c10/core/DispatchKey.h>
#include <c10/core/impl/LocalDispatchKeySet.h>

#include <cstdint>
#include <optional>

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

// The forward-mode tangent of `tensor` at `level`: an undefined tensor where
// it has none (Tensor::_fw_grad).
inline const at::Tensor& forward_tangent(const at::Tensor& tensor, uint64_t level) { return tensor._fw_grad(level); }

// The strides with which a tensor of `sizes` and `strides` is viewed as
// `new_sizes` without a copy, or nullopt where no such view exists: what
// Tensor.view computes (at::detail::computeStride).
inline std::optional<at::DimVector> view_strides(at::IntArrayRef sizes, at::IntArrayRef strides,
                                                 const at::DimVector& new_sizes) {
  return at::detail::computeStride(sizes, strides, new_sizes);
}

}  // namespace torch_internals
}  // namespace torchrot

#endif  // TORCHROT_TORCH_INTERNALS_H_

#if defined(TORCHROT_TORCH_INTERNALS_PYTHON) && !defined(TORCHROT_TORCH_INTERNALS_PYTHON_H_)
#define TORCHROT_TORCH_INTERNALS_PYTHON_H_

#include <torch/csrc/Exceptions.h>
#include <torch/csrc/autograd/python_variable.h>

#include <utility>

namespace torchrot {
namespace torch_internals {

// Whether `object` is a torch.Tensor itself (or an nn.Parameter, which torch
// treats as one), not a subclass (THPVariable_CheckExact).
inline bool is_exact_tensor(PyObject* object) { return THPVariable_CheckExact(object); }

// The tensor of a Python tensor object (one is_exact_tensor accepts),
// borrowed from it (THPVariable_Unpack).
inline const at::Tensor& unpack_tensor(PyObject* object) { return THPVariable_Unpack(object); }

// A new reference to the Python object of `tensor`: the one it already has,
// or a new torch.Tensor (THPVariable_Wrap).
inline PyObject* wrap_tensor(at::Tensor&& tensor) { return THPVariable_Wrap(std::move(tensor)); }
inline PyObject* wrap_tensor(const at::Tensor& tensor) { return THPVariable_Wrap(tensor); }

}  // namespace torch_internals
}  // namespace torchrot

// The body of a Python C function between these two turns the C++ exceptions
// it throws into Python's (TORCH_CHECK's RuntimeError, TORCH_CHECK_VALUE's
// ValueError, ...; the function then returns null) and TORCH_WARN into Python
// warnings (torch's HANDLE_TH_ERRORS and END_HANDLE_TH_ERRORS).
#define TORCHROT_BEGIN_TORCH_ERRORS HANDLE_TH_ERRORS
#define TORCHROT_END_TORCH_ERRORS END_HANDLE_TH_ERRORS

#endif  // TORCHROT_TORCH_INTERNALS_PYTHON_H_
