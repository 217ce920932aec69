// Interface between the CPU operators (ops/fit_rotation_cpu.cpp) and the CPU
// kernels (cpu/dispatch.cpp).
// Nothing here depends on the instruction set the kernels are compiled for.
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>
#include <optional>
#include <string>

namespace torchrot {

// How the Cayley step estimates the maximal objective c (paper, Sec. 4.2).
enum class Variant : int8_t {
  kNewton = 0,        // c = tr S: the plain Newton step (Eq. 21, [KKB18]).
  kConservative = 1,  // c = sqrt(tr(S)^2 + m.m)   (Eq. 26 with g_S ~ tr S).
  kGershgorin = 2,    // c from Eq. 27 with lambda_2 bounded by Eq. 28.
};

// The variants by the names the operators take (variant="..."), and the one
// used when none is given (the schemas' default, ops/schemas.cpp; Python's
// through torchrot._C.constants()).
struct VariantName {
  const char* name;
  Variant variant;
};
inline constexpr VariantName kVariantNames[] = {
    {"newton", Variant::kNewton}, {"conservative", Variant::kConservative}, {"gershgorin", Variant::kGershgorin}};
#define TORCHROT_DEFAULT_VARIANT "conservative"

// The dtypes the operators take: float32 and float64 are computed as they
// are, float16 and bfloat16 in float32.
inline constexpr at::ScalarType kSupportedDtypes[] = {at::kFloat, at::kDouble, at::kHalf, at::kBFloat16};

// max_iter <= 0 means "iterate each matrix to convergence".
struct FitOptions {
  int64_t max_iter = 0;
  Variant variant = Variant::kConservative;
  // Every warm start is known finite, a rotation and at the compute precision
  // (WarmStartCount::unclean == 0 for exactly these values): the fit uses
  // them as they are, without its own check. The results are those of the
  // checked fit, which would find the same and use them as they are too.
  bool init_known_clean = false;
};

// Per-matrix outcome, as reported by torchrot.fit_rotation_info.
enum class FitStatus : uint8_t {
  kCayley = 0,     // the Cayley iteration produced the result
  kFallback = 1,   // converged mode: the Horn/Jacobi fallback produced it
  kBadInit = 2,    // the warm start was finite but not a rotation
  kNonFinite = 3,  // M or init held NaN/Inf: the result is NaN
};

// The names of the CPU kernel objects, lowest level first: "scalar",
// "default", "avx2", "avx512" (see cpu/dispatch.cpp).
inline constexpr const char* kCpuKernelNames[] = {"scalar", "default", "avx2", "avx512"};

// The kernel object fit_rotation_cpu uses now in the calling thread (one of
// kCpuKernelNames).
std::string cpu_kernel_name();

// Whether that kernel rounds a * b + c once, as the scalar kernel does: then
// its results are the scalar kernel's bit for bit. False only for x86-64's
// "default" kernel (CPUs without AVX2 and FMA; see kernel/mul_add.h).
bool cpu_kernel_fuses_multiply_add();

// Forces the kernel object `name` (capped at the hardware's level) for the
// calling thread's calls; "" returns to the process-wide choice. Returns the
// previously forced name ("" if none). ValueError for an unknown name.
std::string set_thread_cpu_kernel(const std::string& name);

// Where N row-major 3x3 matrices are, in elements: entry (r, c) of matrix i
// at offset(i) + r * stride[1] + c * stride[2], with offset(i) = i * stride[0],
// or in a tiled layout (tile > 0: matrices in tiles of `tile`, e.g. the paper
// authors' blocks of 8 matrices in structure of arrays) offset(i) =
// (i / tile) * tile_stride + (i % tile) * stride[0] (cpu/block_io.h).
struct Layout {
  int64_t stride[3] = {9, 3, 1};
  int64_t tile = 0;
  int64_t tile_stride = 0;
};

// N row-major 3x3 matrices at `data`, laid out as `layout`.
struct MatrixBatch {
  void* data = nullptr;
  Layout layout;
};

// Fits out[i] = argmax_R tr(R^T M[i]) for n float or double matrices (dtype)
// with any strides; init is optional (null: cold start). out may alias M or
// init exactly. `iterations` (n int32) and `status` (n FitStatus bytes) are
// optional per-matrix diagnostics. Returns the number of matrices whose warm
// start was not a rotation.
int64_t fit_rotation_cpu(at::ScalarType dtype, int64_t n, const MatrixBatch& M, const MatrixBatch* init,
                         const MatrixBatch& out, const FitOptions& options, int32_t* iterations, uint8_t* status);

// What the check the fit applies finds in n warm starts.
struct WarmStartCount {
  int64_t bad = 0;      // finite but not rotations (limits::kInitTolerance, det <= 0): the call raises
  int64_t unclean = 0;  // not finite, not rotations, or rotations the fit first cleans up
                        // (deviation >= limits::kInitCleanEps eps, see kernel::clean_warm_start)
};

// The check of n warm starts, without fitting (NaN/Inf ones are data, not errors).
WarmStartCount count_bad_warm_starts_cpu(at::ScalarType dtype, int64_t n, const MatrixBatch& init);

// The derivative of n fits R = fit_rotation(M), from the optimality condition
// (kernel/rotation_gradient.h): out = R [u]x with u the damped solution of
// (tr(S) I - S) u = vex(R^T X - X^T R), S = R^T M, for X = dL/dR (the
// backward; out = dL/dM) or X = dM (forward mode; out = dR). `damping` is eps
// in lambda = eps |M|_F. out may alias X exactly.
void rotation_tangent_cpu(at::ScalarType dtype, int64_t n, const MatrixBatch& X, const MatrixBatch& R,
                          const MatrixBatch& M, const MatrixBatch& out, double damping);

}  // namespace torchrot
