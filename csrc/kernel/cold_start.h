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

// Objective of the third-turn candidate q = (1, s1, s2, s3) / 2 with the
// signs given as template arguments: since tr K = 0,
// q^T K q = (s1 K01 + s2 K02 + s3 K03 + s1 s2 K12 + s1 s3 K13 + s2 s3 K23) / 2.
template <int S1, int S2, int S3, typename V>
inline V third_turn_objective(const V K[16]) {
  auto term = [](int sign, V x) { return sign > 0 ? x : V(0) - x; };
  return V(0.5) * (term(S1, K[1]) + term(S2, K[2]) + term(S3, K[3]) + term(S1 * S2, K[6]) +
                   term(S1 * S3, K[7]) + term(S2 * S3, K[11]));
}

// Keeps the candidate (quaternion times 2, exact) if its objective is larger;
// ties keep the earlier candidate, so the choice is deterministic.
template <typename L>
inline void keep_better(typename L::V value, int qw, int qx, int qy, int qz, typename L::V& best,
                        typename L::V best_q[4]) {
  using V = typename L::V;
  const typename L::Mask better = L::gt(value, best);
  best = L::select(better, value, best);
  const int q[4] = {qw, qx, qy, qz};
  for (int i = 0; i < 4; ++i) best_q[i] = L::select(better, V(q[i]), best_q[i]);
}

// The best of the 12 candidates, per lane.
template <typename L>
inline Mat3<typename L::V> best_start_rotation(const Mat3<typename L::V>& M) {
  using V = typename L::V;
  V K[16];
  horn_matrix(M, K);
  V best = K[0];  // the identity, q = e_w
  V q[4] = {V(2), V(0), V(0), V(0)};
  keep_better<L>(K[5], 0, 2, 0, 0, best, q);   // half-turns about x, y, z
  keep_better<L>(K[10], 0, 0, 2, 0, best, q);
  keep_better<L>(K[15], 0, 0, 0, 2, best, q);
  keep_better<L>(third_turn_objective<+1, +1, +1>(K), 1, +1, +1, +1, best, q);
  keep_better<L>(third_turn_objective<-1, +1, +1>(K), 1, -1, +1, +1, best, q);
  keep_better<L>(third_turn_objective<+1, -1, +1>(K), 1, +1, -1, +1, best, q);
  keep_better<L>(third_turn_objective<-1, -1, +1>(K), 1, -1, -1, +1, best, q);
  keep_better<L>(third_turn_objective<+1, +1, -1>(K), 1, +1, +1, -1, best, q);
  keep_better<L>(third_turn_objective<-1, +1, -1>(K), 1, -1, +1, -1, best, q);
  keep_better<L>(third_turn_objective<+1, -1, -1>(K), 1, +1, -1, -1, best, q);
  keep_better<L>(third_turn_objective<-1, -1, -1>(K), 1, -1, -1, -1, best, q);
  const V h(0.5);
  return quaternion_rotation(h * q[0], h * q[1], h * q[2], h * q[3]);
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
