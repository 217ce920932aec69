// Escape from a saddle point of the objective (a fixed point of Algorithm 1
// that is not the maximum).
//
// At a fixed point S = R^T M is symmetric. The paper's analysis of g_S
// (Sec. 3, Eq. 18) says the objective restricted to rotations about the
// eigenvector v of sym(S)'s largest eigenvalue lambda_2 is maximised by the
// half-turn about v whenever lambda_0 + lambda_1 < 0, which is exactly when the
// second-order check fails. So R <- R (2 v v^T / v.v - I) jumps from the
// saddle to (near) the maximum, and Cayley steps finish the job.
//
// v is found without an eigensolver: sym(S) shifted by its Gershgorin lower
// bound is positive semidefinite with the same eigenvectors, and repeated
// squaring (normalised by the trace) makes its largest column parallel to v.
// An approximate v suffices, since the Cayley iteration corrects the rest.
#pragma once

#include "mat3.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {

constexpr int kEscapeSquarings = 4;  // B^16: eigenvalue ratios to the 16th power

template <typename T>
inline Mat3<T> saddle_escape_rotation(const Mat3<T>& S) {
  Mat3<T> B;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) B(r, c) = T(0.5) * (S(r, c) + S(c, r));
  T lower = B(0, 0);  // Gershgorin lower bound of the spectrum
  for (int r = 0; r < 3; ++r) {
    T radius = T(0);
    for (int c = 0; c < 3; ++c)
      if (c != r) radius += lane_abs(B(r, c));
    const T bound = B(r, r) - radius;
    lower = bound < lower ? bound : lower;
  }
  for (int i = 0; i < 3; ++i) B(i, i) -= lower;
  for (int k = 0; k < kEscapeSquarings; ++k) {
    const T inv_trace = T(1) / (B(0, 0) + B(1, 1) + B(2, 2));
    for (int i = 0; i < 9; ++i) B.a[i] *= inv_trace;
    B = times(B, B);
  }
  int best = 0;
  T best_norm = T(-1);
  for (int c = 0; c < 3; ++c) {
    const T norm = B(0, c) * B(0, c) + B(1, c) * B(1, c) + B(2, c) * B(2, c);
    if (norm > best_norm) {
      best_norm = norm;
      best = c;
    }
  }
  const T v[3] = {B(0, best), B(1, best), B(2, best)};
  const T two_over_vv = T(2) / best_norm;
  Mat3<T> H;  // the half-turn 2 v v^T / v.v - I
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) H(r, c) = two_over_vv * v[r] * v[c] - T(r == c ? 1 : 0);
  return H;
}

}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
