// Typed handles of torchrot's own operators, for the C++ code that calls
// them through the dispatcher (autograd.cpp, module.cpp) rather than
// through Python. The schemas themselves are defined once, in ops/schemas.cpp
// (their argument lists in ops/schemas.h).
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/core/dispatch/Dispatcher.h>

#include <cstdint>
#include <optional>
#include <tuple>

namespace torchrot {

// The C++ signatures of the schemas torchrot::fit_rotation (M, init,
// max_iter, variant, gradient_eps), torchrot::fit_rotation_backward (grad,
// R, M, gradient_eps), torchrot::fit_rotation_out (M, init, max_iter,
// variant, out) and torchrot::fit_rotation_info (M, init, max_iter, variant),
// for typed dispatcher calls.
using FitRotationSignature = at::Tensor(const at::Tensor&, const std::optional<at::Tensor>&, std::optional<int64_t>,
                                        c10::string_view, double);
using FitRotationBackwardSignature = at::Tensor(const at::Tensor&, const at::Tensor&, const at::Tensor&, double);
using FitRotationOutSignature = void(const at::Tensor&, const std::optional<at::Tensor>&, std::optional<int64_t>,
                                     c10::string_view, const at::Tensor&);
using FitRotationInfoSignature = std::tuple<at::Tensor, at::Tensor, at::Tensor>(const at::Tensor&,
                                                                                const std::optional<at::Tensor>&,
                                                                                std::optional<int64_t>,
                                                                                c10::string_view);

// The operator `name` ("torchrot::fit_rotation", ...), typed; throws if it
// is not registered or its schema does not match Signature. Callers keep
// the handle in a function-local static: the lookup takes a lock.
template <class Signature>
c10::TypedOperatorHandle<Signature> find_operator(const char* name) {
  return c10::Dispatcher::singleton().findSchemaOrThrow(name, "").typed<Signature>();
}

}  // namespace torchrot
