// Every error message of torchrot's operators, defined once. The C++ checks
// (ops/checks.cpp, autograd.cpp, cpu/dispatch.cpp) fill them with format();
// the Python checks of the other paths (torchrot/_checks.py: fake kernels,
// the device-generic kernels, torch.compile) receive the same templates
// through torchrot._C.constants()["MESSAGES"], their static fields filled,
// and fill the rest with str.format. So every path raises the same text.
//
// Fields: {op} the operator's name (kOpName, kBackwardName), {name} the
// argument; static fields (messages.cpp: the limits of limits.h, the
// variants, dtypes and CPU kernels) are filled by format() itself.
#pragma once

#include <initializer_list>
#include <string>
#include <utility>

namespace torchrot {
namespace messages {

constexpr const char* kOpName = "torchrot.fit_rotation";
constexpr const char* kBackwardName = "torchrot.fit_rotation_backward";
constexpr const char* kOrthogonalName = "torchrot.fit_orthogonal";

// A message template and the key under which Python finds it.
struct Message {
  const char* key;
  const char* text;
};

inline constexpr Message kNotATensor{"NOT_A_TENSOR", "{op}: {name} must be a torch.Tensor, got {type}"};
inline constexpr Message kMatrixShape{"MATRIX_SHAPE", "{op}: {name} must have shape (..., 3, 3), got {shape}"};
inline constexpr Message kMatrixDtype{"MATRIX_DTYPE", "{op}: {name} must be {dtypes}, got {dtype}"};
inline constexpr Message kDeviceLike{"DEVICE_LIKE", "{op}: {name} must be on {ref}'s device ({device}), got {got}"};
inline constexpr Message kDtypeLike{"DTYPE_LIKE", "{op}: {name} must have {ref}'s dtype ({dtype}), got {got}"};
inline constexpr Message kMaxIterType{"MAX_ITER_TYPE", "{op}: max_iter must be None or an int >= 1, got {value}"};
inline constexpr Message kMaxIterRange{
    "MAX_ITER_RANGE",
    "{op}: max_iter must be None (iterate to convergence) or an int >= 1 and <= {max_iter}, got {value}"};
inline constexpr Message kVariantType{"VARIANT_TYPE", "{op}: variant must be a str, got {type}"};
inline constexpr Message kVariantValue{"VARIANT_VALUE", "{op}: variant must be one of {variants}, got '{value}'"};
inline constexpr Message kInitBroadcast{"INIT_BROADCAST",
                                        "{op}: init of shape {shape} must broadcast to M's shape {m_shape}"};
inline constexpr Message kInitNotRotations{
    "INIT_NOT_ROTATIONS",
    "{op}: init must hold rotations (|R^T R - I|_F < {init_tolerance} and det R > 0; rotations of any float dtype "
    "qualify); {bad} of {n} are not: pass rotations, or no init for a cold start"};
// The warm starts of torchrot.fit_orthogonal (checked in Python, torchrot/orthogonal.py, before the
// rotation fit that it runs): orthogonal matrices of either determinant.
inline constexpr Message kInitNotOrthogonal{
    "INIT_NOT_ORTHOGONAL",
    "{op}: init must hold orthogonal matrices (|Q^T Q - I|_F < {init_tolerance}, det +1 or -1; orthogonal matrices "
    "of any float dtype qualify); {bad} of {n} are not: pass orthogonal matrices, or no init for a cold start"};
inline constexpr Message kOutShape{"OUT_SHAPE", "{op}: out must have M's shape {m_shape}, got {shape}"};
inline constexpr Message kOutOverlap{"OUT_OVERLAP",
                                     "{op}: out must not have overlapping elements (e.g. an expanded tensor)"};
// out= refuses a call that would have to record a derivative, as torch's
// out= functions do.
inline constexpr Message kOutAutograd{
    "OUT_AUTOGRAD",
    "{op}: out= does not support automatic differentiation (as torch's out= functions), but M or out requires grad "
    "or carries a forward-mode tangent: call it without out, or under torch.no_grad()"};
// An inference tensor can be written in place only in inference mode
// (torch's rule, checked before anything is written).
inline constexpr Message kOutInference{
    "OUT_INFERENCE",
    "{op}: out is an inference tensor, which can only be written in place inside torch.inference_mode(): pass a "
    "normal tensor (e.g. a clone), or call it in inference mode"};
// fit_rotation_out on a DTensor (torchrot/_sharding.py): out is written in place, so it keeps its placements.
inline constexpr Message kOutPlacement{
    "OUT_PLACEMENT",
    "{op}: on a DTensor, out must be replicated or sharded along a batch dimension, the same on every mesh "
    "dimension (it is written in place and keeps its placements), got {placements}"};
inline constexpr Message kGradientEpsType{"GRADIENT_EPS_TYPE", "{op}: gradient_eps must be a float >= 0, got {value}"};
inline constexpr Message kGradientEpsRange{
    "GRADIENT_EPS_RANGE", "{op}: gradient_eps must be a finite number >= 0 and <= {max_gradient_eps}, got {value}"};
inline constexpr Message kGradShape{"GRAD_SHAPE", "{op}: grad must have R's shape {r_shape}, got {shape}"};
inline constexpr Message kBackwardBroadcast{"BACKWARD_BROADCAST",
                                            "{op}: M of shape {shape} must broadcast to R's shape {r_shape}"};
inline constexpr Message kCpuKernel{"CPU_KERNEL", "{what} must be one of {cpu_kernels}; got '{value}'"};

inline constexpr Message kAll[] = {
    kNotATensor,       kMatrixShape, kMatrixDtype,       kDeviceLike,    kDtypeLike,        kMaxIterType,
    kMaxIterRange,     kVariantType, kVariantValue,      kInitBroadcast, kInitNotRotations, kInitNotOrthogonal,
    kOutShape,         kOutOverlap,  kOutAutograd,       kOutInference,  kOutPlacement,     kGradientEpsType,
    kGradientEpsRange, kGradShape,   kBackwardBroadcast, kCpuKernel,
};

// `message` with its static fields and the given ones filled in (a field
// neither fills is left as it is).
std::string format(const Message& message, std::initializer_list<std::pair<const char*, std::string>> fields = {});

}  // namespace messages
}  // namespace torchrot
