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

#include <cmath>
#include <limits>

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

template <typename T>
struct VectorLanes {
  using Scalar = T;
  using V = at::vec::Vectorized<T>;
  using Mask = V;  // all bits set in selected lanes
  static constexpr int width = V::size();
  static constexpr bool fused_multiply_add = kFusedMultiplyAdd;  // mul_add.h

  static V load(const T* p) { return V::loadu(p); }
  static void store(V v, T* p) { v.store(p); }
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
  static V abs(V x) { return x.abs(); }
  static V sqrt(V x) { return x.sqrt(); }
  static V max(V a, V b) { return at::vec::maximum(a, b); }  // NaN-propagating
  static V min(V a, V b) { return at::vec::minimum(a, b); }
  static Mask lt(V a, V b) { return a < b; }
  static Mask gt(V a, V b) { return a > b; }
  static Mask eq(V a, V b) { return a == b; }
  static Mask is_finite(V x) { return x.abs() < V(std::numeric_limits<T>::infinity()); }
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
