// Escape from a saddle point of the objective (a fixed point of Algorithm 1
// that is not the maximum).
//
// At a fixed point S = R^T M is symmetric. The paper's analysis of g_S
// (Sec. 3, Eq. 18) says the objective restricted to rotations about the
// eigenvector v of sym(S)'s largest eigenvalue lambda_2 is maximised by the
// half-turn about v whenever lambda_0 + lambda_1 < 0, which is exactly when the
// second-order check (optimality.h) fails. So R <- R (2 v v^T / v.v - I) jumps
// from the saddle to (near) the maximum, and Cayley steps finish the job.
//
// v is found without an eigensolver: sym(S) shifted by its Gershgorin lower
// bound is positive semidefinite with the same eigenvectors, and repeated
// squaring (normalised by the trace) makes its largest column parallel to v.
// An approximate v suffices, since the Cayley iteration corrects the rest.
#pragma once

#include "lanes.h"
#include "mat3.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

constexpr int kEscapeSquarings = 4;  // B^16: eigenvalue ratios to the 16th power

template <typename L>
inline Mat3<typename L::V> saddle_escape_rotation(const Mat3<typename L::V>& S) {
  using V = typename L::V;
  Mat3<V> B;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) B(r, c) = V(0.5) * (S(r, c) + S(c, r));
  V lower = B(0, 0);
  for (int r = 0; r < 3; ++r) {  // Gershgorin lower bound of the spectrum
    V radius(0);
    for (int c = 0; c < 3; ++c)
      if (c != r) radius = radius + L::abs(B(r, c));
    const V bound = B(r, r) - radius;
    lower = L::select(L::lt(bound, lower), bound, lower);
  }
  for (int i = 0; i < 3; ++i) B(i, i) = B(i, i) - lower;
  for (int k = 0; k < kEscapeSquarings; ++k) {
    const V inv_trace = V(1) / (B(0, 0) + B(1, 1) + B(2, 2));
    for (int i = 0; i < 9; ++i) B.a[i] = B.a[i] * inv_trace;
    B = times(B, B);
  }
  V v[3] = {B(0, 0), B(1, 0), B(2, 0)};  // the column of largest norm
  V vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
  for (int c = 1; c < 3; ++c) {
    const V norm = B(0, c) * B(0, c) + B(1, c) * B(1, c) + B(2, c) * B(2, c);
    const typename L::Mask larger = L::gt(norm, vv);
    for (int r = 0; r < 3; ++r) v[r] = L::select(larger, B(r, c), v[r]);
    vv = L::select(larger, norm, vv);
  }
  const V two_over_vv = V(2) / vv;
  Mat3<V> H;  // the half-turn 2 v v^T / v.v - I
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) H(r, c) = two_over_vv * v[r] * v[c] - V(r == c ? 1 : 0);
  return H;
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
