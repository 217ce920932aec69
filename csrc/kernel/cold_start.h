// Cold start: a pre-rotation that puts the remaining rotation well inside the
// range of the Cayley map.
//
// The Cayley parameters z = tan(theta / 2) axis (Eq. 7) blow up as the remaining
// rotation approaches pi, and the iteration then stalls or lands on a saddle
// point of the objective. We therefore start from the best of the 12 rotations
// of the tetrahedral group: the identity, the half-turns about the coordinate
// axes and the third-turns about the cube diagonals. Their quaternions are
// e_w, e_x, e_y, e_z and (1, +-1, +-1, +-1) / 2; each is a signed permutation
// matrix, so applying it costs no arithmetic and loses no precision. Their
// objectives q^T K q are sums of entries of Horn's matrix K (quaternion.h).
#pragma once

#include "quaternion.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {

constexpr int kNumStartCandidates = 12;

// Quaternion (w, x, y, z) of candidate `k`, times 2 so the entries are exact.
inline void start_candidate_quaternion_x2(int k, int q[4]) {
  if (k < 4) {
    for (int i = 0; i < 4; ++i) q[i] = (i == k) ? 2 : 0;
    return;
  }
  const int signs = k - 4;  // bit b set: component b + 1 is negative
  q[0] = 1;
  for (int b = 0; b < 3; ++b) q[b + 1] = (signs >> b) & 1 ? -1 : 1;
}

// Index of the candidate with the largest objective tr(R_k^T M); ties go to
// the lowest index so the result is deterministic.
template <typename T>
inline int best_start_candidate(const Mat3<T>& M) {
  T K[16];
  horn_matrix(M, K);
  int best = 0;
  T best_value = K[0];
  for (int k = 1; k < kNumStartCandidates; ++k) {
    int q[4];
    start_candidate_quaternion_x2(k, q);
    T value = T(0);  // (2q)^T K (2q) / 4 = q^T K q
    for (int i = 0; i < 4; ++i) {
      for (int j = 0; j < 4; ++j) value += T(q[i] * q[j]) * K[4 * i + j];
    }
    value *= T(0.25);
    if (value > best_value) {
      best_value = value;
      best = k;
    }
  }
  return best;
}

template <typename T>
inline Mat3<T> start_candidate_rotation(int k) {
  int q[4];
  start_candidate_quaternion_x2(k, q);
  const T h = T(0.5);
  return quaternion_rotation<T>(h * T(q[0]), h * T(q[1]), h * T(q[2]), h * T(q[3]));
}

}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
