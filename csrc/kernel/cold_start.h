// Cold start: a pre-rotation that puts the remaining rotation well inside the
// range of the Cayley map.
//
// The Cayley parameters z = tan(theta / 2) axis (Eq. 7) blow up as the remaining
// rotation approaches pi, where the iteration stalls. We therefore start from
// the best of the 12 rotations of the tetrahedral group: the identity, the
// half-turns about the coordinate axes and the third-turns about the cube
// diagonals. Their quaternions are e_w, e_x, e_y, e_z and (1, +-1, +-1, +-1) / 2;
// each is a signed permutation matrix, so it is exact in any precision. Their
// objectives q^T K q are sums of entries of Horn's matrix K (quaternion.h).
#pragma once

#include "lanes.h"
#include "quaternion.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

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

// The candidate with the largest objective tr(R_k^T M), per lane; ties go to
// the lowest index, so the choice is deterministic.
template <typename L>
inline Mat3<typename L::V> best_start_rotation(const Mat3<typename L::V>& M) {
  using V = typename L::V;
  V K[16];
  horn_matrix(M, K);
  V best_value = K[0];
  V best_q[4] = {V(2), V(0), V(0), V(0)};
  for (int k = 1; k < kNumStartCandidates; ++k) {
    int q[4];
    start_candidate_quaternion_x2(k, q);
    V value = V(0);  // (2q)^T K (2q) / 4 = q^T K q, summed over nonzero terms
    for (int i = 0; i < 4; ++i)
      for (int j = 0; j < 4; ++j)
        if (q[i] * q[j] != 0) value = value + V(q[i] * q[j]) * K[4 * i + j];
    value = value * V(0.25);
    const typename L::Mask better = L::gt(value, best_value);
    best_value = L::select(better, value, best_value);
    for (int i = 0; i < 4; ++i) best_q[i] = L::select(better, V(q[i]), best_q[i]);
  }
  const V h(0.5);
  return quaternion_rotation(h * best_q[0], h * best_q[1], h * best_q[2], h * best_q[3]);
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
