// The contract between the ISA dispatch (dispatch.cpp) and the per-ISA kernel
// objects (kernel_*.cpp). Nothing here depends on the instruction set.
#pragma once

#include <cstdint>

#include "../fit_rotation.h"

// The AVX2 and AVX-512 kernel objects exist on x86-64 only: setup.py compiles
// them when its compiler targets x86-64 (the same test as this one), and
// elsewhere (aarch64: scalar and default, the latter ATen's Vectorized<T> on
// NEON) nothing may reference them.
#if defined(__x86_64__) || defined(_M_X64)
#define TORCHROT_X86_64_KERNELS 1
#else
#define TORCHROT_X86_64_KERNELS 0
#endif

namespace torchrot {
namespace cpu {

// N matrices of 3x3 in any layout.
template <typename T>
struct BatchArgs {
  const T* M;
  Layout m_layout;
  const T* init;  // null: cold start
  Layout init_layout;
  T* out;  // may alias M or init exactly
  Layout out_layout;
  int64_t n;
  FitOptions options;
  int32_t* iterations;  // optional, n entries
  uint8_t* status;      // optional, n entries (FitStatus)
};

// The derivative of N fits (see kernel/rotation_gradient.h): out = R [u]x
// with u the damped solution of the optimality condition's linearisation
// for X = dL/dR or dM. All four are N 3x3 matrices in any layout;
// out may alias X exactly.
template <typename T>
struct TangentArgs {
  const T* X;
  Layout x_layout;
  const T* R;
  Layout r_layout;
  const T* M;
  Layout m_layout;
  T* out;
  Layout out_layout;
  int64_t n;
  T damping;  // eps of lambda = eps |M|_F
};

// N warm starts (3x3, any layout) to check without fitting.
template <typename T>
struct WarmStartArgs {
  const T* init;
  Layout layout;
  int64_t n;
};

struct KernelTable {
  const char* name;
  int width_float;  // matrices per SIMD block
  int width_double;
  // Rounds a * b + c once, as the scalar kernel does, so its results are the
  // scalar kernel's bit for bit (false only for x86-64's default object, see
  // kernel/mul_add.h).
  bool fused_multiply_add;
  // Each returns the number of matrices whose warm start was not a rotation.
  int64_t (*fit_float)(const BatchArgs<float>&);
  int64_t (*fit_double)(const BatchArgs<double>&);
  void (*tangent_float)(const TangentArgs<float>&);
  void (*tangent_double)(const TangentArgs<double>&);
  // What the fit's own check finds in the warm starts.
  WarmStartCount (*bad_warm_starts_float)(const WarmStartArgs<float>&);
  WarmStartCount (*bad_warm_starts_double)(const WarmStartArgs<double>&);
};

// One per kernel object; the SIMD ones must only be called on CPUs that
// support their instruction set.
const KernelTable& scalar_kernels();
const KernelTable& default_kernels();
#if TORCHROT_X86_64_KERNELS
const KernelTable& avx2_kernels();
const KernelTable& avx512_kernels();
#endif

}  // namespace cpu
}  // namespace torchrot
