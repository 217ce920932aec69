// The names torchrot's errors give the operators, and the messages raised by
// more than one source file, defined once. (The Python checks,
// torchrot/_checks.py, raise the same messages on the other paths.)
#pragma once

namespace torchrot {
namespace messages {

constexpr const char* kOpName = "torchrot.fit_rotation";
constexpr const char* kBackwardName = "torchrot.fit_rotation_backward";

// out= refuses a call that would have to record a derivative, as torch's
// out= functions do.
constexpr const char* kOutAutograd =
    ": out= does not support automatic differentiation (as torch's out= functions), but M or out requires grad "
    "or carries a forward-mode tangent: call it without out, or under torch.no_grad()";

// An inference tensor can be written in place only in inference mode
// (torch's rule, checked before anything is written).
constexpr const char* kOutInference =
    ": out is an inference tensor, which can only be written in place inside torch.inference_mode(): pass a "
    "normal tensor (e.g. a clone), or call it in inference mode";

}  // namespace messages
}  // namespace torchrot
