// Cold start: a pre-rotation that puts the remaining rotation well inside the
// range of the Cayley map.
//
// The Cayley parameters z = tan(theta / 2) axis (Eq. 7) blow up as the remaining
// rotation approaches pi, where the iteration stalls. We therefore start from
// the best of the 24 rotations of the cube: the signed permutation matrices of
// det +1 (the identity, the quarter- and half-turns about the coordinate axes,
// the third-turns about the cube diagonals and the half-turns about the face
// diagonals). They are exact in any precision, and the objective of one,
// tr(P^T A) = sum_i s_i A(i, pi(i)), takes a few additions. For each of the 6
// permutations pi, the best signs are those of the entries A(i, pi(i)), unless
// their product has the wrong sign for det +1: then the smallest entry's sign
// flips. (Against the 12 rotations of the tetrahedral group used before, the
// 24 took fewer steps to converge, and left fewer matrices needing many:
// benchmarks/lab_notes.md.) torchrot/generic/cold_start.py's and
// torchrot/triton/cold_start.py's best_start_rotation mirror this.
#pragma once

#include "lanes.h"
#include "mat3.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

// The permutations, even ones first: row i's entry is in column kStartPerm[p][i].
constexpr int kStartPerm[6][3] = {{0, 1, 2}, {1, 2, 0}, {2, 0, 1}, {0, 2, 1}, {2, 1, 0}, {1, 0, 2}};
constexpr int kStartEvenPerms = 3;

// The best of the 24 candidates, per lane (the first of equals, in the order
// of kStartPerm), and its objective (up to rounding). The loop over the
// permutations keeps the winner's entries and columns, so the matrix is
// assembled once at the end.
template <typename L>
inline Mat3<typename L::V> best_start_rotation(const Mat3<typename L::V>& A, typename L::V& objective) {
  using V = typename L::V;
  using Mask = typename L::Mask;
  V best(0), odd_perm(0), entry[3], column[3];
#pragma GCC unroll 6
  for (int p = 0; p < 6; ++p) {
    const V x = A(0, kStartPerm[p][0]), y = A(1, kStartPerm[p][1]), z = A(2, kStartPerm[p][2]);
    const V a = L::abs(x), b = L::abs(y), c = L::abs(z);
    // The signs of x, y, z give det -1 (even permutation, product < 0; odd,
    // product > 0). A zero entry's sign is free: product 0, no flip, and
    // indeed none is needed. (A product that underflows to 0 skips a flip of
    // a negligible entry: only this estimate is off, by twice that entry.)
    const V product = (x * y) * z;
    const Mask flip = p < kStartEvenPerms ? L::lt(product, V(0)) : L::gt(product, V(0));
    const V sum = (a + b) + c;
    // (min_number: a lane with a NaN entry does not run, whatever its start.)
    const V value = L::select(flip, mul_add(V(-2), L::min_number(L::min_number(a, b), c), sum), sum);
    const Mask better = p == 0 ? L::all_true() : L::gt(value, best);
    best = L::select(better, value, best);
    odd_perm = L::select(better, V(p < kStartEvenPerms ? 0 : 1), odd_perm);
    const V xyz[3] = {x, y, z};
    for (int i = 0; i < 3; ++i) {
      entry[i] = L::select(better, xyz[i], entry[i]);
      column[i] = L::select(better, V(kStartPerm[p][i]), column[i]);
    }
  }
  // In row i, the sign of its entry, flipped in the row of the smallest entry
  // (the first of equals) where det would be -1.
  V size[3];
  Mask odd_negatives = L::gt(odd_perm, V(0));
  for (int i = 0; i < 3; ++i) {
    size[i] = L::abs(entry[i]);
    odd_negatives = L::mask_xor(odd_negatives, L::lt(entry[i], V(0)));
  }
  const Mask flip = odd_negatives;  // negatives' parity differs from the permutation's
  const Mask smallest0 = L::mask_and(L::mask_not(L::gt(size[0], size[1])), L::mask_not(L::gt(size[0], size[2])));
  const Mask smallest1 = L::mask_and(L::mask_not(smallest0), L::mask_not(L::gt(size[1], size[2])));
  const Mask smallest[3] = {smallest0, smallest1, L::mask_not(L::mask_or(smallest0, smallest1))};
  Mat3<V> R;
  for (int i = 0; i < 3; ++i) {
    const V sign = L::select(L::lt(entry[i], V(0)), V(-1), V(1));
    const V s = L::select(L::mask_and(flip, smallest[i]), V(0) - sign, sign);
    for (int j = 0; j < 3; ++j) R(i, j) = L::select(L::eq(column[i], V(j)), s, V(0));
  }
  objective = best;
  return R;
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
