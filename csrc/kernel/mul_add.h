// mul_add(a, b, c) = a * b + c with one rounding (fused multiply-add) for the
// scalar and SIMD types the kernel is written in (mat3.h, lanes.h).
//
// Why. A Cayley step is mostly sums of products (S = R^T A, Cramer's rule,
// the Cayley map, R Q, the Newton-Schulz clean-up): fused, they cost one
// instruction instead of two and round once instead of twice, and the fits
// ran faster (benchmarks/lab_notes.md).
//
// Where it is fused. Results are bit-identical across kernel objects only if
// each object rounds the same way, so the choice is per type, never left to
// the compiler (every object is built with -ffp-contract=off):
//  * float / double: std::fma, exact everywhere (an instruction in the avx2
//    and avx512 objects, built with -mfma; a libm call in the scalar and
//    default objects, which glibc answers with the instruction where the CPU
//    has it).
//  * at::vec::Vectorized<T>: at::vec::fmadd, which ATen implements with the
//    fused instruction for AVX2, AVX-512 and NEON (aarch64's default object).
//    For ATen's generic Vectorized (x86-64's default object, for CPUs without
//    AVX2 and FMA; kGenericVectorized) it is a * b + c, two roundings:
//    emulating fma there (glibc's software fmaf and fma, without the
//    instruction) would make a fit slower than an SVD
//    (benchmarks/lab_notes.md). That object is therefore the one kernel whose
//    results differ from the scalar kernel's, by rounding (see
//    kFusedMultiplyAdd and tests/test_isa_bit_identity.py); it meets the same accuracy
//    criteria and is bit-identical across its own batch sizes, layouts and
//    threads.
#pragma once

#include <ATen/cpu/vec/vec.h>

#include <cmath>

#include "force_inline.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

template <typename T>
TORCHROT_INLINE T mul_add(T a, T b, T c) {
  return std::fma(a, b, c);
}

// Whether this object's at::vec::Vectorized<T> is ATen's generic one (arrays
// and loops: x86-64's default object, and any target ATen has no SIMD
// specialisation for here) rather than AVX2, AVX-512 or NEON.
#if defined(CPU_CAPABILITY_AVX2) || defined(CPU_CAPABILITY_AVX512) || defined(__aarch64__)
constexpr bool kGenericVectorized = false;
#else
constexpr bool kGenericVectorized = true;
#endif

// Whether mul_add on this object's Vectorized<T> rounds once, as the scalar
// kernel does: ATen's generic fmadd is a * b + c.
constexpr bool kFusedMultiplyAdd = !kGenericVectorized;

template <typename T>
TORCHROT_INLINE at::vec::Vectorized<T> mul_add(const at::vec::Vectorized<T>& a, const at::vec::Vectorized<T>& b,
                                               const at::vec::Vectorized<T>& c) {
  if constexpr (kGenericVectorized) {
    return a * b + c;  // at::vec::fmadd's own generic definition, written inline (GCC left it out of line)
  } else {
    return at::vec::fmadd(a, b, c);
  }
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
