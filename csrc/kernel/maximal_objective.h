// The maximal objective max_R tr(R^T A) over rotations, per lane: the largest
// eigenvalue lambda of Horn's K (cayley.h), i.e. sigma_1 + sigma_2 + sign(det A)
// sigma_3. With c = lambda the Cayley step (Algorithm 2) solves Horn's
// eigenproblem exactly: one step from the cold start lands on the maximum.
//
// K is traceless, and its characteristic polynomial is (Horn 1987; the
// quartic of Theobald's QCP method, 2005)
//   p(x) = x^4 - 2 |A|_F^2 x^2 - 8 det(A) x + det K,
// with det K = t det T - m^T adj(T) m for K = [[t, m^T], [m, T]] (the
// determinant of a bordered matrix). K is symmetric, so p has real roots
// only, and Laguerre's method for such polynomials,
//   x <- x - 4 p / (p' + sqrt(9 p'^2 - 12 p p'')),
// converges monotonically to lambda from any x above it, cubically (measured,
// uniform float32: 2.9 steps per lane, 3.9 per 16-lane block, against 5.6 and
// 7.5 for Newton's method), here from x0 = sqrt(3) |A|_F >= sigma_1 + sigma_2
// + sigma_3 >= lambda. Near the root it is Newton's step p / p'.
#pragma once

#include "cayley.h"
#include "force_inline.h"
#include "lanes.h"
#include "mat3.h"
#include "optimality.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

// lambda for each lane of A, from above. A lane stops once its correction
// falls below `tol` x (the next would be far below tol^2 x),
// would take x below `lower` (an objective attained, so <= lambda: only
// rounding near a double root of p, where convergence is also slow, gets
// there), or after `max_steps`. Each lane's sequence is its own, whichever
// block it is in. A = 0 gives 0; NaN entries give NaN.
template <typename L>
TORCHROT_INLINE typename L::V maximal_objective(const Mat3<typename L::V>& A, typename L::V lower,
                                                typename L::Scalar tol, int max_steps) {
  using V = typename L::V;
  using Mask = typename L::Mask;
  // K's blocks: t, m (Eq. 12) and T = A + A^T - t I (Eq. 36), which is
  // Algorithm 2's H for c = 0: its step gives det T and adj(T) m.
  const V t = trace(A);
  V m[3];
  skew_vector(A, m);
  const CayleyStep<V> system = cayley_step(A, V(0));
  const V p0 = mul_add(t, system.d, -dot3(m[0], system.w[0], m[1], system.w[1], m[2], system.w[2]));  // det K
  V norm2(0);
  for (int k = 0; k < 9; ++k) norm2 = mul_add(A.a[k], A.a[k], norm2);
  const V p2 = V(-2) * norm2;
  const V p1 = V(-8) * determinant(A);
  V x = L::sqrt(V(3) * norm2);
  Mask active = L::gt(x, V(0));
  const V two_p2 = V(2) * p2;
  for (int k = 0; k < max_steps && L::any(active); ++k) {
    const V x2 = x * x;
    const V p = mul_add(mul_add(x2 + p2, x, p1), x, p0);
    const V dp = mul_add(mul_add(V(4), x2, two_p2), x, p1);
    const V ddp = mul_add(V(12), x2, two_p2);
    // (Rounding may make the discriminant, (n - 1)^2 times a sum of squares,
    // slightly negative near a double root.)
    const V root = L::sqrt(L::max(mul_add(V(9) * dp, dp, V(-12) * (p * ddp)), V(0)));
    const V next = x - V(4) * p / (dp + root);
    const Mask move = L::mask_and(active, L::mask_and(L::lt(next, x), L::mask_not(L::lt(next, lower))));
    active = L::mask_and(move, L::gt(x - next, V(tol) * next));
    x = L::select(move, next, x);
  }
  return x;
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
