// Interface between the operator registration (ops.cpp) and the CPU kernels.
// Nothing here depends on the instruction set the kernels are compiled for.
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>
#include <string>

namespace torchrot {

// How the Cayley step estimates the maximal objective c (paper, Sec. 4.2).
enum class Variant : int8_t {
  kNewton = 0,        // c = tr S: the plain Newton step (Eq. 21, [KKB18]).
  kConservative = 1,  // c = sqrt(tr(S)^2 + m.m)   (Eq. 26 with g_S ~ tr S).
  kGershgorin = 2,    // c from Eq. 27 with lambda_2 bounded by Eq. 28.
};

// max_iter <= 0 means "iterate each matrix to convergence".
struct FitOptions {
  int64_t max_iter = 0;
  Variant variant = Variant::kConservative;
  // Orthonormality a warm start must have (|R^T R - I|_F); <= 0 means the
  // compute dtype's default (1e-4 float, 1e-7 double). Inputs of reduced
  // precision are computed in float but carry their own rounding.
  double init_tolerance = 0;
};

// Per-matrix outcome, as reported by torchrot.fit_rotation_info.
enum class FitStatus : uint8_t {
  kCayley = 0,     // the Cayley iteration produced the result
  kFallback = 1,   // converged mode: the Horn/Jacobi fallback produced it
  kBadInit = 2,    // the warm start was finite but not a rotation
  kNonFinite = 3,  // M or init held NaN/Inf: the result is NaN
};

// Fits out[i] = argmax_R tr(R^T M[i]) for the (N, 3, 3) float or double
// tensors M, init (optional, same shape) and out, with any strides. out may
// alias M or init exactly. `iterations` (int32, N) and `status` (uint8, N)
// are optional per-matrix diagnostics. Returns the number of matrices whose
// warm start was not a rotation.
// The kernel object fit_rotation_cpu uses now: "scalar", "default", "avx2"
// or "avx512" (see cpu/dispatch.cpp).
std::string cpu_kernel_name();

int64_t fit_rotation_cpu(const at::Tensor& M, const at::Tensor* init,
                         const at::Tensor& out, const FitOptions& options,
                         const at::Tensor* iterations, const at::Tensor* status);

}  // namespace torchrot
