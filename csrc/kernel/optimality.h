// Per-lane predicates of the driver: is a fixed point the maximum, and is a
// warm start a rotation.
#pragma once

#include "lanes.h"
#include "mat3.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

// Second-order check at a fixed point S = R^T M (S symmetric): R is the global
// maximum iff the two smallest eigenvalues of sym(S) sum to >= 0, i.e. iff
// tr(S) I - sym(S) is positive semidefinite (Sec. 3, analysis of g_S). Other
// fixed points are saddles or minima that a Newton-type iteration can reach.
// Tested by Sylvester's criterion on tr(S) I - sym(S) + slack I; a fixed point
// that passes falls short of the maximum by at most 2 slack.
template <typename L>
inline typename L::Mask is_maximum(const Mat3<typename L::V>& S, typename L::Scalar slack) {
  using V = typename L::V;
  const V t = S(0, 0) + S(1, 1) + S(2, 2) + V(slack);
  const V p00 = t - S(0, 0), p11 = t - S(1, 1), p22 = t - S(2, 2);
  const V p01 = V(-0.5) * (S(0, 1) + S(1, 0));
  const V p02 = V(-0.5) * (S(0, 2) + S(2, 0));
  const V p12 = V(-0.5) * (S(1, 2) + S(2, 1));
  const V minor2 = p00 * p11 - p01 * p01;
  const V det = p00 * (p11 * p22 - p12 * p12) - p01 * (p01 * p22 - p12 * p02) + p02 * (p01 * p12 - p11 * p02);
  const V zero(0);
  return L::mask_and(L::gt(p00, zero), L::mask_and(L::gt(minor2, zero), L::gt(det, zero)));
}

// Is R, with Gram matrix G = R^T R, a proper rotation up to `tol`:
// |R^T R - I|_F < tol and det R > 0? NaN fails.
template <typename L>
inline typename L::Mask is_rotation(const Mat3<typename L::V>& R, const Mat3<typename L::V>& G,
                                    typename L::Scalar tol) {
  using V = typename L::V;
  const V d0 = G(0, 0) - V(1), d1 = G(1, 1) - V(1), d2 = G(2, 2) - V(1);
  const V off = G(0, 1) * G(0, 1) + G(0, 2) * G(0, 2) + G(1, 2) * G(1, 2);
  const V deviation2 = d0 * d0 + d1 * d1 + d2 * d2 + V(2) * off;
  const V det = R(0, 0) * (R(1, 1) * R(2, 2) - R(1, 2) * R(2, 1)) -
                R(0, 1) * (R(1, 0) * R(2, 2) - R(1, 2) * R(2, 0)) +
                R(0, 2) * (R(1, 0) * R(2, 1) - R(1, 1) * R(2, 0));
  return L::mask_and(L::lt(deviation2, V(tol * tol)), L::gt(det, V(0)));
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
