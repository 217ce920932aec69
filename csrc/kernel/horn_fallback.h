// Guaranteed fallback: Horn's method with a cyclic Jacobi eigensolver.
//
// The optimal rotation's quaternion is the eigenvector of Horn's K
// (quaternion.h) for its largest eigenvalue. Cyclic Jacobi converges for every
// symmetric matrix (quadratically in the end), so this always returns a
// rotation attaining the maximum up to rounding, whatever the conditioning, the
// sign of det M or the size of the rotation. It runs in double precision for
// both float and double inputs. Only matrices on which the Cayley iteration
// has not verifiably converged reach it, so its cost is not on the fast path.
#pragma once

#include <cmath>

#include "quaternion.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

constexpr int kJacobiMaxSweeps = 30;

// Eigen-decomposition of the symmetric 4x4 `A` (destroyed): on return the
// diagonal of A holds the eigenvalues and the columns of V the eigenvectors.
inline void jacobi_eigen4(double A[16], double V[16]) {
  for (int i = 0; i < 16; ++i) V[i] = (i % 5 == 0) ? 1.0 : 0.0;
  double norm2 = 0.0;
  for (int i = 0; i < 16; ++i) norm2 += A[i] * A[i];
  const double tiny = 1e-32 * norm2;  // (eps_double)^2 relative, squared norm
  for (int sweep = 0; sweep < kJacobiMaxSweeps; ++sweep) {
    double off2 = 0.0;
    for (int p = 0; p < 4; ++p)
      for (int q = p + 1; q < 4; ++q) off2 += A[4 * p + q] * A[4 * p + q];
    if (off2 <= tiny) return;
    for (int p = 0; p < 4; ++p) {
      for (int q = p + 1; q < 4; ++q) {
        const double apq = A[4 * p + q];
        if (apq == 0.0) continue;
        // Symmetric Schur decomposition of the (p, q) block (Golub & Van Loan).
        const double tau = (A[4 * q + q] - A[4 * p + p]) / (2.0 * apq);
        const double t = (tau >= 0 ? 1.0 : -1.0) / (std::fabs(tau) + std::sqrt(1.0 + tau * tau));
        const double c = 1.0 / std::sqrt(1.0 + t * t);
        const double s = t * c;
        for (int k = 0; k < 4; ++k) {  // A <- A J
          const double akp = A[4 * k + p], akq = A[4 * k + q];
          A[4 * k + p] = c * akp - s * akq;
          A[4 * k + q] = s * akp + c * akq;
        }
        for (int k = 0; k < 4; ++k) {  // A <- J^T A
          const double apk = A[4 * p + k], aqk = A[4 * q + k];
          A[4 * p + k] = c * apk - s * aqk;
          A[4 * q + k] = s * apk + c * aqk;
        }
        for (int k = 0; k < 4; ++k) {  // V <- V J
          const double vkp = V[4 * k + p], vkq = V[4 * k + q];
          V[4 * k + p] = c * vkp - s * vkq;
          V[4 * k + q] = s * vkp + c * vkq;
        }
      }
    }
  }
}

// The rotation maximising tr(R^T M) for a finite M, by Horn's method.
template <typename T>
inline Mat3<T> horn_rotation(const Mat3<T>& M) {
  Mat3<double> Md;
  for (int i = 0; i < 9; ++i) Md.a[i] = static_cast<double>(M.a[i]);
  double K[16], V[16];
  horn_matrix(Md, K);
  jacobi_eigen4(K, V);
  int top = 0;  // first index among equal maxima: deterministic
  for (int i = 1; i < 4; ++i)
    if (K[5 * i] > K[5 * top]) top = i;
  double q[4], qq = 0.0;
  for (int i = 0; i < 4; ++i) {
    q[i] = V[4 * i + top];
    qq += q[i] * q[i];
  }
  const double inv_norm = 1.0 / std::sqrt(qq);
  const Mat3<double> R = quaternion_rotation(q[0] * inv_norm, q[1] * inv_norm, q[2] * inv_norm, q[3] * inv_norm);
  Mat3<T> out;
  for (int i = 0; i < 9; ++i) out.a[i] = static_cast<T>(R.a[i]);
  return out;
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
