// Lanes: the one abstraction that lets the kernel be written once for a
// single matrix and for a SIMD block of matrices.
//
// A lane type L provides the value type L::V (one matrix entry for each of
// L::width matrices), a mask type L::Mask, and the few mask operations the
// driver needs. ScalarLanes<T> is one matrix in plain T with bool masks (the
// scalar path); VectorLanes<T> is at::vec::Vectorized<T> (one matrix per SIMD
// lane), compiled once per instruction set, with its masks as vectors
// (VectorMasks) or, with AVX-512, in mask registers (RegisterMasks);
// PairedLanes<L> is two blocks of L as one, for code whose dependency chains
// leave the floating-point units idle (the derivative kernel).
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
  static constexpr bool stream_one_step = false;    // see VectorLanes
  static constexpr bool integer_max = false;        // see VectorLanes

  static V load(const T* p) { return *p; }
  static void store(V v, T* p) { *p = v; }
  static V select(Mask m, V if_true, V if_false) { return m ? if_true : if_false; }
  static V abs(V x) { return std::fabs(x); }
  static V sqrt(V x) { return std::sqrt(x); }
  static V max(V a, V b) { return (a != a || a > b) ? a : b; }  // NaN-propagating, as Vectorized
  static V min(V a, V b) { return (a != a || a < b) ? a : b; }
  static V clamp(V x, V lo, V hi) { return std::min(std::max(x, lo), hi); }  // as at::vec::clamp
  // max / min of numbers: with a NaN operand the result is either operand (one
  // instruction where max / min test for NaN). unordered: a or b is NaN.
  static V max_number(V a, V b) { return a > b ? a : b; }
  static V min_number(V a, V b) { return a < b ? a : b; }
  static Mask unordered(V a, V b) { return a != a || b != b; }
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
      // choice made x86's default kernel's cold fits markedly slower:
      // benchmarks/lab_notes.md).
      return if_false ^ ((if_false ^ if_true) & m);
    } else {
      return V::blendv(if_false, if_true, m);
    }
  }
  static V max(V a, V b) { return at::vec::maximum(a, b); }
  static V min(V a, V b) { return at::vec::minimum(a, b); }
  static V max_number(V a, V b) { return at::vec::clamp_min(a, b); }
  static V min_number(V a, V b) { return at::vec::clamp_max(a, b); }
  static Mask unordered(V a, V b) { return mask_not(mask_and(a == a, b == b)); }
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
// a vpmovm2d and every select a vpcmpeqd back, and mask logic ran on vectors
// (counted: benchmarks/lab_notes.md). Here a mask stays a
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
  static V max(V a, V b) { return select(unordered(a, b), all_bits(), max_number(a, b)); }
  static V min(V a, V b) { return select(unordered(a, b), all_bits(), min_number(a, b)); }
  static V max_number(V a, V b) {
    if constexpr (sizeof(T) == 4) {
      return _mm512_max_ps(a, b);
    } else {
      return _mm512_max_pd(a, b);
    }
  }
  static V min_number(V a, V b) {
    if constexpr (sizeof(T) == 4) {
      return _mm512_min_ps(a, b);
    } else {
      return _mm512_min_pd(a, b);
    }
  }
  static Mask unordered(V a, V b) { return compare<_CMP_UNORD_Q>(a, b); }
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
  // Whether the batched one-step warm update reads M and the warm start from
  // memory where each step of it uses them (kernel::one_step_warm_from_memory)
  // rather than holding them in registers from the loads to the update: with
  // AVX2's 16 vector registers, the 9 entries of R0 held across the whole step
  // (Algorithm 2 and the Cayley map, Eq. 10, in between) and the 9 of M held
  // from the scaling to S = R0^T A left GCC spilling the step's own values to
  // the stack (benchmarks/lab_notes.md). AVX-512 has 32 registers.
#if defined(CPU_CAPABILITY_AVX2)
  static constexpr bool stream_one_step = true;
#else
  static constexpr bool stream_one_step = false;
#endif

  static V load(const T* p) { return V::loadu(p); }
  static void store(V v, T* p) { v.store(p); }
  // A vector whose first half of lanes is read from `lo` and second half from
  // `hi` (block_io.h: tiles half a block wide), and the store that splits it
  // so: a load and an insert (an extract and two stores) on AVX-512 and AVX2,
  // through a buffer elsewhere.
  static V load_halves(const T* lo, const T* hi) {
#if defined(CPU_CAPABILITY_AVX512)
    if constexpr (std::is_same_v<T, float>) {
      return _mm512_insertf32x8(_mm512_castps256_ps512(_mm256_loadu_ps(lo)), _mm256_loadu_ps(hi), 1);
    } else {
      return _mm512_insertf64x4(_mm512_castpd256_pd512(_mm256_loadu_pd(lo)), _mm256_loadu_pd(hi), 1);
    }
#elif defined(CPU_CAPABILITY_AVX2)
    if constexpr (std::is_same_v<T, float>) {
      return _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(lo)), _mm_loadu_ps(hi), 1);
    } else {
      return _mm256_insertf128_pd(_mm256_castpd128_pd256(_mm_loadu_pd(lo)), _mm_loadu_pd(hi), 1);
    }
#else
    T buf[width];
    std::copy(lo, lo + width / 2, buf);
    std::copy(hi, hi + width / 2, buf + width / 2);
    return V::loadu(buf);
#endif
  }
  static void store_halves(V v, T* lo, T* hi) {
#if defined(CPU_CAPABILITY_AVX512)
    if constexpr (std::is_same_v<T, float>) {
      _mm256_storeu_ps(lo, _mm512_castps512_ps256(v));
      _mm256_storeu_ps(hi, _mm512_extractf32x8_ps(v, 1));
    } else {
      _mm256_storeu_pd(lo, _mm512_castpd512_pd256(v));
      _mm256_storeu_pd(hi, _mm512_extractf64x4_pd(v, 1));
    }
#elif defined(CPU_CAPABILITY_AVX2)
    if constexpr (std::is_same_v<T, float>) {
      _mm_storeu_ps(lo, _mm256_castps256_ps128(v));
      _mm_storeu_ps(hi, _mm256_extractf128_ps(v, 1));
    } else {
      _mm_storeu_pd(lo, _mm256_castpd256_pd128(v));
      _mm_storeu_pd(hi, _mm256_extractf128_pd(v, 1));
    }
#else
    T buf[width];
    v.store(buf);
    std::copy(buf, buf + width / 2, lo);
    std::copy(buf + width / 2, buf + width, hi);
#endif
  }
  static V abs(V x) { return x.abs(); }
  static V sqrt(V x) { return x.sqrt(); }
  // x limited to [lo, hi] (lo <= hi, neither NaN); a NaN x is returned as it
  // is. One max and one min instruction where there are SIMD ones (unlike
  // max / min, which test for NaN), and the same values in every object:
  // x86's max(lo, x) and min(hi, x) return x when it is NaN, as NEON's and
  // std::max / std::min (the generic one) do.
  static V clamp(V x, V lo, V hi) { return at::vec::clamp(x, lo, hi); }
  // The larger of two values whose sign bits are clear (absolute values), a
  // NaN where either is a NaN, as one integer maximum of their bits: those of
  // a non-negative number order as its value, and a NaN's lie above +Inf's.
  // integer_max: where the instruction set has that maximum for T's width
  // (AVX-512; AVX2 for float); max_abs_entry's other way elsewhere.
#if defined(CPU_CAPABILITY_AVX512)
  static constexpr bool integer_max = true;
  static V max_nonnegative(V a, V b) {
    if constexpr (std::is_same_v<T, float>) {
      return _mm512_castsi512_ps(_mm512_max_epi32(_mm512_castps_si512(a), _mm512_castps_si512(b)));
    } else {
      return _mm512_castsi512_pd(_mm512_max_epi64(_mm512_castpd_si512(a), _mm512_castpd_si512(b)));
    }
  }
#elif defined(CPU_CAPABILITY_AVX2)
  static constexpr bool integer_max = std::is_same_v<T, float>;
  static V max_nonnegative(V a, V b) {
    static_assert(std::is_same_v<T, float>, "AVX2 has no 64-bit integer maximum");
    return _mm256_castsi256_ps(_mm256_max_epi32(_mm256_castps_si256(a), _mm256_castps_si256(b)));
  }
#else
  static constexpr bool integer_max = false;
#endif
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

// Two vectors of lanes as one value, for PairedLanes: every operation is two
// independent instructions.
template <typename W>
struct Pair {
  W lo, hi;
  Pair() = default;
  TORCHROT_INLINE Pair(W l, W h) : lo(l), hi(h) {}
  template <typename S, std::enable_if_t<std::is_arithmetic_v<S>, int> = 0>
  TORCHROT_INLINE Pair(S x) : lo(W(x)), hi(W(x)) {}  // broadcast
};
template <typename W>
TORCHROT_INLINE Pair<W> operator+(const Pair<W>& a, const Pair<W>& b) {
  return {a.lo + b.lo, a.hi + b.hi};
}
template <typename W>
TORCHROT_INLINE Pair<W> operator-(const Pair<W>& a, const Pair<W>& b) {
  return {a.lo - b.lo, a.hi - b.hi};
}
template <typename W>
TORCHROT_INLINE Pair<W> operator*(const Pair<W>& a, const Pair<W>& b) {
  return {a.lo * b.lo, a.hi * b.hi};
}
template <typename W>
TORCHROT_INLINE Pair<W> operator/(const Pair<W>& a, const Pair<W>& b) {
  return {a.lo / b.lo, a.hi / b.hi};
}
template <typename W>
TORCHROT_INLINE Pair<W> operator-(const Pair<W>& a) {
  return {-a.lo, -a.hi};
}
template <typename W>
TORCHROT_INLINE Pair<W> mul_add(const Pair<W>& a, const Pair<W>& b, const Pair<W>& c) {
  return {mul_add(a.lo, b.lo, c.lo), mul_add(a.hi, b.hi, c.hi)};
}

// Two blocks of Base as one of twice the width. A Cayley step is one long
// chain of dependent operations (S, the estimate's square root, Cramer's rule,
// a division, the Cayley map, R Q), whose latency exceeds the time its
// operations need on the floating-point units (benchmarks/lab_notes.md), so
// one block leaves them idle; two independent halves fill them.
template <typename Base>
struct PairedLanes {
  using Scalar = typename Base::Scalar;
  using T = Scalar;
  using V = Pair<typename Base::V>;
  using Mask = Pair<typename Base::Mask>;
  static constexpr int half = Base::width;
  static constexpr int width = 2 * half;
  static constexpr bool fused_multiply_add = Base::fused_multiply_add;
  static constexpr bool stream_one_step = false;  // the derivative kernel's lanes: no fits
  static constexpr bool integer_max = Base::integer_max;
  using HalfLanes = Base;

  static V load(const T* p) { return {Base::load(p), Base::load(p + half)}; }
  static void store(V v, T* p) {
    Base::store(v.lo, p);
    Base::store(v.hi, p + half);
  }
  static V select(Mask m, V a, V b) { return {Base::select(m.lo, a.lo, b.lo), Base::select(m.hi, a.hi, b.hi)}; }
  static V abs(V x) { return {Base::abs(x.lo), Base::abs(x.hi)}; }
  static V sqrt(V x) { return {Base::sqrt(x.lo), Base::sqrt(x.hi)}; }
  static V max(V a, V b) { return {Base::max(a.lo, b.lo), Base::max(a.hi, b.hi)}; }
  static V min(V a, V b) { return {Base::min(a.lo, b.lo), Base::min(a.hi, b.hi)}; }
  static V clamp(V x, V lo, V hi) { return {Base::clamp(x.lo, lo.lo, hi.lo), Base::clamp(x.hi, lo.hi, hi.hi)}; }
  static V max_number(V a, V b) { return {Base::max_number(a.lo, b.lo), Base::max_number(a.hi, b.hi)}; }
  static V max_nonnegative(V a, V b) { return {Base::max_nonnegative(a.lo, b.lo), Base::max_nonnegative(a.hi, b.hi)}; }
  static V min_number(V a, V b) { return {Base::min_number(a.lo, b.lo), Base::min_number(a.hi, b.hi)}; }
  static Mask unordered(V a, V b) { return {Base::unordered(a.lo, b.lo), Base::unordered(a.hi, b.hi)}; }
  static Mask lt(V a, V b) { return {Base::lt(a.lo, b.lo), Base::lt(a.hi, b.hi)}; }
  static Mask gt(V a, V b) { return {Base::gt(a.lo, b.lo), Base::gt(a.hi, b.hi)}; }
  static Mask eq(V a, V b) { return {Base::eq(a.lo, b.lo), Base::eq(a.hi, b.hi)}; }
  static Mask is_finite(V x) { return {Base::is_finite(x.lo), Base::is_finite(x.hi)}; }
  static Mask mask_and(Mask a, Mask b) { return {Base::mask_and(a.lo, b.lo), Base::mask_and(a.hi, b.hi)}; }
  static Mask mask_or(Mask a, Mask b) { return {Base::mask_or(a.lo, b.lo), Base::mask_or(a.hi, b.hi)}; }
  static Mask mask_xor(Mask a, Mask b) { return {Base::mask_xor(a.lo, b.lo), Base::mask_xor(a.hi, b.hi)}; }
  static Mask mask_not(Mask a) { return {Base::mask_not(a.lo), Base::mask_not(a.hi)}; }
  static Mask all_true() { return {Base::all_true(), Base::all_true()}; }
  static Mask all_false() { return {Base::all_false(), Base::all_false()}; }
  static bool all(Mask m) { return Base::all(m.lo) && Base::all(m.hi); }
  static bool any(Mask m) { return Base::any(m.lo) || Base::any(m.hi); }
  static bool lane_set(Mask m, int i) { return i < half ? Base::lane_set(m.lo, i) : Base::lane_set(m.hi, i - half); }
  static T lane(V v, int i) { return i < half ? Base::lane(v.lo, i) : Base::lane(v.hi, i - half); }
  static void set_lane(V& v, int i, T x) {
    if (i < half) {
      Base::set_lane(v.lo, i, x);
    } else {
      Base::set_lane(v.hi, i - half, x);
    }
  }
};

template <typename T>
using PairedVectorLanes = PairedLanes<VectorLanes<T>>;

template <typename L, typename = void>
struct IsPaired : std::false_type {};
template <typename L>
struct IsPaired<L, std::void_t<typename L::HalfLanes>> : std::true_type {};

// max |A_ij| over a matrix's entries, a NaN where one is NaN (the value L::max
// gives folded over them, up to the NaN's payload, which no result carries:
// such lanes do not run). As a tree, 4 maxima deep instead of 9 at the head
// of every block's dependency chain: of max_nonnegative where it is one
// instruction (L::integer_max), else of max_number (whose result with a NaN
// operand is unspecified: one instruction) with the NaN test apart; either
// is a third of the instructions of nine NaN-propagating maxima.
template <typename L>
TORCHROT_INLINE typename L::V max_abs_entry(const Mat3<typename L::V>& A) {
  using V = typename L::V;
  V a[9];
  for (int k = 0; k < 9; ++k) a[k] = L::abs(A.a[k]);
  if constexpr (L::integer_max) {
    const auto max = [](V x, V y) TORCHROT_LAMBDA_INLINE { return L::max_nonnegative(x, y); };
    return max(max(max(max(a[0], a[1]), max(a[2], a[3])), max(max(a[4], a[5]), max(a[6], a[7]))), a[8]);
  }
  const V top = L::max_number(L::max_number(L::max_number(a[0], a[1]), L::max_number(a[2], a[3])),
                              L::max_number(L::max_number(a[4], a[5]), L::max_number(a[6], a[7])));
  const auto nan =
      L::mask_or(L::mask_or(L::unordered(a[0], a[1]), L::unordered(a[2], a[3])),
                 L::mask_or(L::mask_or(L::unordered(a[4], a[5]), L::unordered(a[6], a[7])), L::unordered(a[8], a[8])));
  return L::select(nan, V(std::numeric_limits<typename L::Scalar>::quiet_NaN()), L::max_number(top, a[8]));
}

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
