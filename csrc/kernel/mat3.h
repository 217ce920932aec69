// Fixed-size 3x3 matrix arithmetic on a generic lane type.
//
// `V` is either a scalar (float / double) or, for the vectorised kernels, an
// `at::vec::Vectorized<T>` holding one matrix entry of several matrices.  The
// code below only uses +, -, *, / and mul_add (mul_add.h) so it is valid for
// both.  Matrices are row-major: entry (r, c) is `a[3 * r + c]`.  Sums of three
// products (dot3) and differences of two (diff_of_products) are evaluated in
// one order everywhere, so every kernel object rounds alike.
#pragma once

#include <cstdint>

#include "force_inline.h"
#include "mul_add.h"

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

// a0 b0 + a1 b1 + a2 b2, the kernel's one evaluation order for it.
template <typename V>
TORCHROT_INLINE V dot3(const V& a0, const V& b0, const V& a1, const V& b1, const V& a2, const V& b2) {
  return mul_add(a0, b0, mul_add(a1, b1, a2 * b2));
}

// a b - c d, the kernel's one evaluation order for it (cofactors, cross
// products): only c d is rounded before the fused step.
template <typename V>
TORCHROT_INLINE V diff_of_products(const V& a, const V& b, const V& c, const V& d) {
  return mul_add(a, b, -(c * d));
}

// Returns A^T B.
template <typename V>
TORCHROT_INLINE Mat3<V> transpose_times(const Mat3<V>& A, const Mat3<V>& B) {
  Mat3<V> C;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) {
      C(r, c) = dot3(A(0, r), B(0, c), A(1, r), B(1, c), A(2, r), B(2, c));
    }
  }
  return C;
}

// A^T B built up over the rows k of A and B, from the last to the first,
// row(k, a, b) giving row k of A in a and of B in b: the same roundings as
// transpose_times (dot3 adds the k = 2 product first), in an order that needs
// only one row of each operand at a time besides the nine partial sums, so
// that the rows can be read from memory (or formed) where they are used.
template <typename V, typename Rows>
TORCHROT_INLINE Mat3<V> transpose_times_by_rows(Rows row) {
  Mat3<V> C;
  for (int k = 2; k >= 0; --k) {
    V a[3], b[3];
    row(k, a, b);
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) C(r, c) = k == 2 ? a[r] * b[c] : mul_add(a[r], b[c], C(r, c));
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
      C(r, c) = dot3(A(r, 0), B(0, c), A(r, 1), B(1, c), A(r, 2), B(2, c));
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
      G(r, c) = dot3(R(0, r), R(0, c), R(1, r), R(1, c), R(2, r), R(2, c));
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
  for (int i = 0; i < 9; ++i) G.a[i] = mul_add(V(-0.5), G.a[i], V(i % 4 == 0 ? 1.5 : 0));
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
