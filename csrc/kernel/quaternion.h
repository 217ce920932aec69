// Unit quaternions as rotations, and Horn's 4x4 matrix of the objective.
//
// For a unit quaternion q = (w, x, y, z), tr(R(q)^T M) = q^T K q with
//   K = [[t, m^T], [m, M + M^T - t I]],  t = tr M,  m = vee(M - M^T)
// (Horn 1987; the same t, m and T as the Cayley step, Eqs. 12 and 36).
#pragma once

#include "mat3.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

// Rotation matrix of the unit quaternion (w, x, y, z), column-vector convention.
template <typename V>
inline Mat3<V> quaternion_rotation(V w, V x, V y, V z) {
  Mat3<V> R;
  R(0, 0) = w * w + x * x - y * y - z * z;
  R(1, 1) = w * w - x * x + y * y - z * z;
  R(2, 2) = w * w - x * x - y * y + z * z;
  R(0, 1) = V(2) * (x * y - w * z);
  R(1, 0) = V(2) * (x * y + w * z);
  R(0, 2) = V(2) * (x * z + w * y);
  R(2, 0) = V(2) * (x * z - w * y);
  R(1, 2) = V(2) * (y * z - w * x);
  R(2, 1) = V(2) * (y * z + w * x);
  return R;
}

// Horn's symmetric 4x4 matrix K of the objective, row-major.
template <typename V>
inline void horn_matrix(const Mat3<V>& M, V K[16]) {
  const V t = M(0, 0) + M(1, 1) + M(2, 2);
  const V m[3] = {M(2, 1) - M(1, 2), M(0, 2) - M(2, 0), M(1, 0) - M(0, 1)};
  K[0] = t;
  for (int i = 0; i < 3; ++i) {
    K[1 + i] = m[i];
    K[4 * (1 + i)] = m[i];
    for (int j = 0; j < 3; ++j) {
      K[4 * (1 + i) + 1 + j] = M(i, j) + M(j, i) - (i == j ? t : V(0));
    }
  }
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
