// Scaling a matrix to max |entry| 1, exactly where it matters: the maximiser
// of tr(R^T M) is unchanged, and no product in a Cayley step or in the
// derivative can over- or underflow. Shared by the fit (begin_fit) and the
// derivative (rotation_tangent); torchrot/generic/unit_scale.py and
// torchrot/triton/unit_scale.py mirror it.
#pragma once

#include <cmath>
#include <limits>

#include "force_inline.h"
#include "lanes.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

template <typename V>
struct UnitScale {
  Mat3<V> A;  // (M * lift) * inv: M scaled to max |entry| 1 (0 for M = 0)
  V lift;     // an exact power of two: 2^digits, 2^-digits or 1
  V inv;      // 1 / (max_abs * lift), 0 for M = 0
};

// The lanes whose largest |entry| max_abs (max_abs_entry(M)) has no normal
// reciprocal, which unit_scale lifts or drops before it scales: below the
// normal range (M = 0 included; 1 / subnormal may overflow) or above its
// reciprocal (1 / max_abs is subnormal and has lost bits). Callers that skip
// unit_scale's special case read it here.
template <typename L>
struct OutsideNormalRange {
  typename L::Mask below_normal;
  typename L::Mask above_reciprocal;
};

template <typename L>
TORCHROT_INLINE OutsideNormalRange<L> outside_normal_range(typename L::V max_abs) {
  using T = typename L::Scalar;
  using V = typename L::V;
  constexpr T tiny = std::numeric_limits<T>::min();
  return {L::lt(max_abs, V(tiny)), L::gt(max_abs, V(T(1) / tiny))};
}

// M scaled by 1 / max_abs (max_abs = max_abs_entry(M)). Lanes outside the
// normal range (outside_normal_range) are first lifted by 2^digits or
// dropped by 2^-digits (exact but for entries far below the maximum). Blocks
// without such lanes skip it.
template <typename L>
TORCHROT_INLINE UnitScale<typename L::V> unit_scale(const Mat3<typename L::V>& M, typename L::V max_abs) {
  using T = typename L::Scalar;
  using V = typename L::V;
  UnitScale<V> s;
  const auto zero = L::eq(max_abs, V(0));
  const auto [below_normal, above_reciprocal] = outside_normal_range<L>(max_abs);
  const auto special = L::mask_or(below_normal, above_reciprocal);
  if (L::any(special)) {
    constexpr int kDigits = std::numeric_limits<T>::digits;
    s.lift = L::select(below_normal, V(std::ldexp(T(1), kDigits)),
                       L::select(above_reciprocal, V(std::ldexp(T(1), -kDigits)), V(1)));
    s.inv = L::select(zero, V(0), V(1) / (max_abs * s.lift));
    // The other lanes take M * inv, as in blocks without such lanes: M * 1
    // would flush a subnormal entry (cpu/flush_to_zero.h) that M * inv keeps.
    for (int k = 0; k < 9; ++k) s.A.a[k] = L::select(special, (M.a[k] * s.lift) * s.inv, M.a[k] * s.inv);
  } else {
    s.lift = V(1);
    s.inv = V(1) / max_abs;
    for (int k = 0; k < 9; ++k) s.A.a[k] = M.a[k] * s.inv;
  }
  return s;
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
