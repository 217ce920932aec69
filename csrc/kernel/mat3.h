// Fixed-size 3x3 matrix arithmetic on a generic lane type.
//
// `V` is either a scalar (float / double) or, for the vectorised kernels, an
// `at::vec::Vectorized<T>` holding one matrix entry of several matrices.  The
// code below only uses +, -, * and / so it is valid for both.  Matrices are
// row-major: entry (r, c) is `a[3 * r + c]`.
#pragma once

#include <cstdint>

#include "force_inline.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

template <typename V>
struct Mat3 {
  V a[9];
  V& operator()(int r, int c) { return a[3 * r + c]; }
  const V& operator()(int r, int c) const { return a[3 * r + c]; }
};

// Returns A^T B.
template <typename V>
TORCHROT_INLINE Mat3<V> transpose_times(const Mat3<V>& A, const Mat3<V>& B) {
  Mat3<V> C;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) {
      C(r, c) = A(0, r) * B(0, c) + A(1, r) * B(1, c) + A(2, r) * B(2, c);
    }
  }
  return C;
}

// Returns A B.
template <typename V>
TORCHROT_INLINE Mat3<V> times(const Mat3<V>& A, const Mat3<V>& B) {
  Mat3<V> C;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) {
      C(r, c) = A(r, 0) * B(0, c) + A(r, 1) * B(1, c) + A(r, 2) * B(2, c);
    }
  }
  return C;
}

// R^T R, computed once per symmetric pair.
template <typename V>
TORCHROT_INLINE Mat3<V> gram(const Mat3<V>& R) {
  Mat3<V> G;
  for (int r = 0; r < 3; ++r) {
    for (int c = r; c < 3; ++c) {
      G(r, c) = R(0, r) * R(0, c) + R(1, r) * R(1, c) + R(2, r) * R(2, c);
      G(c, r) = G(r, c);
    }
  }
  return G;
}

// One Newton-Schulz step towards the orthonormal polar factor,
// R <- R (3 I - R^T R) / 2. It squares the orthonormality error of an
// almost-rotation, so warm starts fed back call after call do not drift.
// G is R^T R (see gram).
template <typename V>
TORCHROT_INLINE Mat3<V> reorthonormalize(const Mat3<V>& R, Mat3<V> G) {
  for (int i = 0; i < 9; ++i) G.a[i] = V(i % 4 == 0 ? 1.5 : 0) - V(0.5) * G.a[i];
  return times(R, G);
}

template <typename V>
TORCHROT_INLINE Mat3<V> reorthonormalize(const Mat3<V>& R) {
  return reorthonormalize(R, gram(R));
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
