// Lanes: the one abstraction that lets the kernel be written once for a
// single matrix and for a SIMD block of matrices.
//
// A lane type L provides the value type L::V (one matrix entry for each of
// L::width matrices), a mask type L::Mask, and the few mask operations the
// driver needs. ScalarLanes<T> is one matrix in plain T with bool masks (the
// scalar path); VectorLanes<T> is at::vec::Vectorized<T> with bit masks (one
// matrix per SIMD lane), compiled once per instruction set.
#pragma once

#include <ATen/cpu/vec/vec.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <type_traits>

#include "force_inline.h"
#include "mat3.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

template <typename T>
struct ScalarLanes {
  using Scalar = T;
  using V = T;
  using Mask = bool;
  static constexpr int width = 1;
  static constexpr bool fused_multiply_add = true;  // mul_add.h: std::fma

  static V load(const T* p) { return *p; }
  static void store(V v, T* p) { *p = v; }
  static V select(Mask m, V if_true, V if_false) { return m ? if_true : if_false; }
  static V abs(V x) { return std::fabs(x); }
  static V sqrt(V x) { return std::sqrt(x); }
  static V max(V a, V b) { return (a != a || a > b) ? a : b; }  // NaN-propagating, as Vectorized
  static V min(V a, V b) { return (a != a || a < b) ? a : b; }
  static V clamp(V x, V lo, V hi) { return std::min(std::max(x, lo), hi); }  // as at::vec::clamp
  static Mask lt(V a, V b) { return a < b; }
  static Mask gt(V a, V b) { return a > b; }
  static Mask eq(V a, V b) { return a == b; }
  static Mask is_finite(V x) { return std::isfinite(x); }
  static Mask mask_and(Mask a, Mask b) { return a && b; }
  static Mask mask_or(Mask a, Mask b) { return a || b; }
  static Mask mask_not(Mask a) { return !a; }
  static Mask mask_xor(Mask a, Mask b) { return a != b; }
  static Mask all_true() { return true; }
  static Mask all_false() { return false; }
  static bool all(Mask m) { return m; }
  static bool any(Mask m) { return m; }
  static bool lane_set(Mask m, int) { return m; }
  static T lane(V v, int) { return v; }
  static void set_lane(V& v, int, T x) { v = x; }
};

// How VectorLanes holds a mask. By default as a vector with all bits set in
// the selected lanes: Vectorized's own compares and blendv, which is what
// AVX2's and NEON's compare and blend instructions read and write.
template <typename T>
struct VectorMasks {
  using V = at::vec::Vectorized<T>;
  using Mask = V;
  static constexpr int width = V::size();

  static Mask lt(V a, V b) { return a < b; }
  static Mask gt(V a, V b) { return a > b; }
  static Mask eq(V a, V b) { return a == b; }
  static V select(Mask m, V if_true, V if_false) {
    if constexpr (kGenericVectorized) {
      // Bitwise: the generic blendv tests each lane's mask with a branch,
      // mispredicted half the time on data-dependent masks (the cold start's
      // choice cost x86's default kernel ~25% of a cold fit, measured).
      return if_false ^ ((if_false ^ if_true) & m);
    } else {
      return V::blendv(if_false, if_true, m);
    }
  }
  static V max(V a, V b) { return at::vec::maximum(a, b); }
  static V min(V a, V b) { return at::vec::minimum(a, b); }
  static Mask mask_and(Mask a, Mask b) { return a & b; }
  static Mask mask_or(Mask a, Mask b) { return a | b; }
  static Mask mask_not(Mask a) { return a ^ all_true(); }
  static Mask mask_xor(Mask a, Mask b) { return a ^ b; }
  static Mask all_true() { return V(T(0)) == V(T(0)); }
  static Mask all_false() { return V(T(0)) != V(T(0)); }
  // zero_mask() has bit i set where lane i is +-0, i.e. where the mask is clear.
  static bool all(Mask m) { return m.zero_mask() == 0; }
  static bool any(Mask m) { return m.zero_mask() != (1 << width) - 1; }
  static bool lane_set(Mask m, int i) { return !((m.zero_mask() >> i) & 1); }
};

#if defined(CPU_CAPABILITY_AVX512)
// AVX-512 compares write a mask register (one bit per lane) and its blends
// read one. Vectorized<T> returns compares as vectors, so every compare cost
// a vpmovm2d and every select a vpcmpeqd back, and mask logic ran on vectors:
// ~100 of the ~1,000 instructions of a one-step block. Here a mask stays a
// __mmask16 / __mmask8, with the same predicates as Vectorized's operators
// (ordered, quiet), so every value is the same bit for bit.
template <typename T>
struct RegisterMasks {
  using V = at::vec::Vectorized<T>;
  using Mask = std::conditional_t<sizeof(T) == 4, __mmask16, __mmask8>;
  static constexpr int width = V::size();

  template <int kPredicate>
  static Mask compare(V a, V b) {
    if constexpr (sizeof(T) == 4) {
      return _mm512_cmp_ps_mask(a, b, kPredicate);
    } else {
      return _mm512_cmp_pd_mask(a, b, kPredicate);
    }
  }
  static Mask lt(V a, V b) { return compare<_CMP_LT_OQ>(a, b); }
  static Mask gt(V a, V b) { return compare<_CMP_GT_OQ>(a, b); }
  static Mask eq(V a, V b) { return compare<_CMP_EQ_OQ>(a, b); }
  static V select(Mask m, V if_true, V if_false) {
    if constexpr (sizeof(T) == 4) {
      return _mm512_mask_blend_ps(m, if_false, if_true);
    } else {
      return _mm512_mask_blend_pd(m, if_false, if_true);
    }
  }
  // at::vec::maximum / minimum (IEEE maximum / minimum: all bits set where
  // either operand is NaN) without the round trip through a vector mask.
  static V max(V a, V b) {
    if constexpr (sizeof(T) == 4) {
      return select(compare<_CMP_UNORD_Q>(a, b), all_bits(), _mm512_max_ps(a, b));
    } else {
      return select(compare<_CMP_UNORD_Q>(a, b), all_bits(), _mm512_max_pd(a, b));
    }
  }
  static V min(V a, V b) {
    if constexpr (sizeof(T) == 4) {
      return select(compare<_CMP_UNORD_Q>(a, b), all_bits(), _mm512_min_ps(a, b));
    } else {
      return select(compare<_CMP_UNORD_Q>(a, b), all_bits(), _mm512_min_pd(a, b));
    }
  }
  static Mask mask_and(Mask a, Mask b) { return static_cast<Mask>(a & b); }
  static Mask mask_or(Mask a, Mask b) { return static_cast<Mask>(a | b); }
  static Mask mask_not(Mask a) { return static_cast<Mask>(~a); }
  static Mask mask_xor(Mask a, Mask b) { return static_cast<Mask>(a ^ b); }
  static Mask all_true() { return static_cast<Mask>(~Mask(0)); }  // 16 or 8 bits: one per lane
  static Mask all_false() { return Mask(0); }
  static bool all(Mask m) { return m == all_true(); }
  static bool any(Mask m) { return m != 0; }
  static bool lane_set(Mask m, int i) { return (m >> i) & 1; }

 private:
  static V all_bits() { return V(T(0)) == V(T(0)); }
};
template <typename T>
using Masks = RegisterMasks<T>;
#else
template <typename T>
using Masks = VectorMasks<T>;
#endif

template <typename T>
struct VectorLanes : Masks<T> {
  using Scalar = T;
  using V = at::vec::Vectorized<T>;
  using Mask = typename Masks<T>::Mask;
  static constexpr int width = V::size();
  static constexpr bool fused_multiply_add = kFusedMultiplyAdd;  // mul_add.h

  static V load(const T* p) { return V::loadu(p); }
  static void store(V v, T* p) { v.store(p); }
  static V abs(V x) { return x.abs(); }
  static V sqrt(V x) { return x.sqrt(); }
  // x limited to [lo, hi] (lo <= hi, neither NaN); a NaN x is returned as it
  // is. One max and one min instruction where there are SIMD ones (unlike
  // max / min, which test for NaN), and the same values in every object:
  // x86's max(lo, x) and min(hi, x) return x when it is NaN, as NEON's and
  // std::max / std::min (the generic one) do.
  static V clamp(V x, V lo, V hi) { return at::vec::clamp(x, lo, hi); }
  static Mask is_finite(V x) { return Masks<T>::lt(x.abs(), V(std::numeric_limits<T>::infinity())); }
  static T lane(V v, int i) {
    T buf[width];
    v.store(buf);
    return buf[i];
  }
  static void set_lane(V& v, int i, T x) {
    T buf[width];
    v.store(buf);
    buf[i] = x;
    v = V::loadu(buf);
  }
};

// One matrix of a block, as plain scalars.
template <typename L>
inline Mat3<typename L::Scalar> extract_lane(const Mat3<typename L::V>& A, int i) {
  Mat3<typename L::Scalar> a;
  for (int k = 0; k < 9; ++k) a.a[k] = L::lane(A.a[k], i);
  return a;
}

template <typename L>
inline void insert_lane(Mat3<typename L::V>& A, int i, const Mat3<typename L::Scalar>& a) {
  for (int k = 0; k < 9; ++k) L::set_lane(A.a[k], i, a.a[k]);
}

template <typename L>
TORCHROT_INLINE Mat3<typename L::V> select(typename L::Mask m, const Mat3<typename L::V>& if_true,
                                  const Mat3<typename L::V>& if_false) {
  Mat3<typename L::V> out;
  for (int k = 0; k < 9; ++k) out.a[k] = L::select(m, if_true.a[k], if_false.a[k]);
  return out;
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
