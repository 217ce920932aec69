// The derivative of the fitted rotation, from the optimality condition.
//
// Derivation (see also docs in torchrot/_autograd.py). The maximiser R of
// tr(R^T M) makes S = R^T M symmetric (paper, Sec. 3: the gradient of the
// objective on SO(3) is the skew part of S), with tr(S) I - S positive
// semi-definite at the maximum. Perturb M -> M + dM and R -> R (I + [w]x),
// [w]x the cross-product matrix of w. To first order
//     d(R^T M) = -[w]x S + R^T dM,
// and its skew part must vanish. For symmetric S,
//     [w]x S + S [w]x = [(tr(S) I - S) w]x,
// so, with A = tr(S) I - S and vex([a]x) = a,
//     A w = vex(E - E^T),   E = R^T dM,          dR = R [w]x.        (G1)
// A's eigenvalues are sigma_i + sigma_j (the signed singular values of M):
// it is singular exactly where R is not unique (rank-deficient M, rotations
// by pi). The map dM -> dR is self-adjoint under <X, Y> = tr(X^T Y): for a
// loss gradient G = dL/dR, dL = <G, R [w]x> = g . w with g = vex(R^T G -
// G^T R), and since A is symmetric, dL/dM = R [u]x with A u = g.       (G2)
// So one routine gives both the backward (G2, input G) and the forward-mode
// tangent (G1, input dM).
//
// Damping. A is replaced by its Tikhonov-regularised inverse,
//     u = (A^2 + lambda^2 I)^-1 A g = Re (A + i lambda I)^-1 g,   lambda = eps |M|_F,
// which equals A^-1 g up to a relative (lambda / (sigma_i + sigma_j))^2
// (below rounding where the system is well conditioned) and is bounded by
// |g| / (2 lambda) where A is (nearly) singular, with no branch. The solve
// runs on S / |M|_F, so nothing over- or underflows for any finite M; the
// result is divided by |M|_F (the derivative of R scales as 1 / |M|).
#pragma once

#include <cmath>
#include <limits>

#include "force_inline.h"
#include "lanes.h"
#include "mat3.h"
#include "unit_scale.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

template <typename V>
struct Vec3 {
  V x, y, z;
};

// vex(B - B^T) for B = R^T X: the axial vector of twice B's skew part.
template <typename V>
inline Vec3<V> skew_axial(const Mat3<V>& R, const Mat3<V>& X) {
  const Mat3<V> B = transpose_times(R, X);
  return {B(2, 1) - B(1, 2), B(0, 2) - B(2, 0), B(1, 0) - B(0, 1)};
}

// R [u]x, [u]x = [[0, -z, y], [z, 0, -x], [-y, x, 0]].
template <typename V>
inline Mat3<V> times_cross(const Mat3<V>& R, const Vec3<V>& u) {
  Mat3<V> out;
  for (int r = 0; r < 3; ++r) {
    out(r, 0) = diff_of_products(R(r, 1), u.z, R(r, 2), u.y);
    out(r, 1) = diff_of_products(R(r, 2), u.x, R(r, 0), u.z);
    out(r, 2) = diff_of_products(R(r, 0), u.y, R(r, 1), u.x);
  }
  return out;
}

// The rotational tangent of (G1)/(G2): R [u]x with u the damped solution of
// A u = vex(R^T X - X^T R), A = tr(S) I - sym(S), S = R^T M, for X = G (the
// backward) or X = dM (the forward-mode derivative). `damping` is eps.
template <typename L>
TORCHROT_INLINE Mat3<typename L::V> rotation_tangent(const Mat3<typename L::V>& X, const Mat3<typename L::V>& R,
                                                     const Mat3<typename L::V>& M, typename L::Scalar damping) {
  using T = typename L::Scalar;
  using V = typename L::V;
  // |M|_F without overflow or underflow: scale by the largest entry first
  // (exactly, as begin_fit does).
  const V max_abs = max_abs_entry<L>(M);  // NaN if any entry is NaN
  const auto zero = L::eq(max_abs, V(0));
  const UnitScale<V> unit = unit_scale<L>(M, max_abs);
  const Mat3<V>& A = unit.A;  // M / max |M_ij|
  const V lift = unit.lift, inv_max = unit.inv;
  V frob2(0);
  for (int k = 0; k < 9; ++k) frob2 = mul_add(A.a[k], A.a[k], frob2);
  const V frob = L::select(zero, V(1), L::sqrt(frob2));  // |A|_F in [1, 3]
  // S = R^T M / |M|_F, symmetrised; K = tr(S) I - S.
  const Mat3<V> S = transpose_times(R, A);
  const V inv_frob = V(1) / frob;
  const V trace = (S(0, 0) + S(1, 1) + S(2, 2)) * inv_frob;
  const V half_inv = V(T(0.5)) * inv_frob;
  const V k00 = trace - S(0, 0) * inv_frob, k11 = trace - S(1, 1) * inv_frob, k22 = trace - S(2, 2) * inv_frob;
  const V k01 = -(S(0, 1) + S(1, 0)) * half_inv;
  const V k02 = -(S(0, 2) + S(2, 0)) * half_inv;
  const V k12 = -(S(1, 2) + S(2, 1)) * half_inv;
  // An X with entries above 2^(max_exponent / 2) is scaled down by that
  // power of two (exact) so that g and the products below cannot overflow;
  // the result is scaled back, saturating. Rare, so only blocks with such a
  // lane multiply (by 1 elsewhere: the same values).
  constexpr int kHalfRange = std::numeric_limits<T>::max_exponent / 2;
  auto x_huge = L::all_false();
  for (int k = 0; k < 9; ++k) x_huge = L::mask_or(x_huge, L::gt(L::abs(X.a[k]), V(std::ldexp(T(1), kHalfRange))));
  const bool scaled = L::any(x_huge);
  Mat3<V> Xs = X;
  if (scaled) {
    for (int k = 0; k < 9; ++k) Xs.a[k] = X.a[k] * L::select(x_huge, V(std::ldexp(T(1), -kHalfRange)), V(1));
  }
  const Vec3<V> g = skew_axial(R, Xs);
  // u = (K^2 + lambda^2 I)^-1 K g = Re (K + i lambda I)^-1 g, evaluated in
  // the second form: forming K^2 would square K's condition number (float32
  // gradients on condition-1e3 data lost 3 digits that way, measured). For
  // 3x3, with c2 = tr adj K (characteristic polynomial of K),
  //   adj(K + i lambda I) = (adj K - lambda^2 I) + i lambda (tr(K) I - K),
  //   det(K + i lambda I) = (det K - lambda^2 tr K) + i lambda (c2 - lambda^2) = a + i b,
  // so u = (a (adj K - lambda^2) g + b lambda (tr(K) g - K g)) / (a^2 + b^2).
  const V c00 = diff_of_products(k11, k22, k12, k12), c01 = diff_of_products(k02, k12, k01, k22);
  const V c02 = diff_of_products(k01, k12, k02, k11), c11 = diff_of_products(k00, k22, k02, k02);
  const V c12 = diff_of_products(k01, k02, k00, k12), c22 = diff_of_products(k00, k11, k01, k01);
  const V det_k = dot3(k00, c00, k01, c01, k02, c02);
  const V trace_k = k00 + k11 + k22;
  const V lambda(damping), lambda2(damping * damping);
  const V a = det_k - lambda2 * trace_k;
  const V b = lambda * (c00 + c11 + c22 - lambda2);
  const Vec3<V> adj_g{dot3(c00, g.x, c01, g.y, c02, g.z), dot3(c01, g.x, c11, g.y, c12, g.z),
                      dot3(c02, g.x, c12, g.y, c22, g.z)};
  const Vec3<V> shift_g{mul_add(trace_k, g.x, -dot3(k00, g.x, k01, g.y, k02, g.z)),
                        mul_add(trace_k, g.y, -dot3(k01, g.x, k11, g.y, k12, g.z)),
                        mul_add(trace_k, g.z, -dot3(k02, g.x, k12, g.y, k22, g.z))};
  // Divide by a^2 + b^2 after scaling a, b by 1 / max(|a|, |b|): no underflow
  // of the squares. With lambda = 0 and K singular in floating point (or
  // max(|a|, |b|) below the smallest normal number, where 1 / it overflows)
  // the undetermined tangent is dropped; u is clamped to +-T_max, so that
  // R [u]x cannot form inf - inf.
  const V ab_max = L::max(L::abs(a), L::abs(b));
  const auto solvable = L::gt(ab_max, V(std::numeric_limits<T>::min()));
  const V inv_ab_max = L::select(solvable, V(1) / ab_max, V(0));
  const V as = a * inv_ab_max, bs = b * inv_ab_max;
  const V norm2 = L::select(solvable, mul_add(as, as, bs * bs), V(1));  // in [1, 2]; 1 where dropped (as = bs = 0)
  const V weight_adj = as * inv_ab_max / norm2;                         // a / (a^2 + b^2)
  const V weight_shift = bs * inv_ab_max / norm2 * lambda;
  const V huge(std::numeric_limits<T>::max());
  auto saturate = [&huge](V x) { return L::clamp(x, V(0) - huge, huge); };
  // Each term saturates on its own: a sum of two overflows is +-inf, never NaN.
  auto solve = [&](V adj, V gi, V shift) {
    return saturate(saturate(weight_adj * (adj - lambda2 * gi)) + saturate(weight_shift * shift));
  };
  const Vec3<V> u{solve(adj_g.x, g.x, shift_g.x), solve(adj_g.y, g.y, shift_g.y), solve(adj_g.z, g.z, shift_g.z)};
  // Undo the scaling by 1 / |M|_F = inv_frob / max |M_ij|. Below |M|_F ~
  // 1 / T_max (subnormal M) the exact derivative exceeds T's range: it
  // saturates at +-T_max (never inf, never 0 * inf = NaN).
  // (Saturating after the product with inv_frob: |A|_F may round below 1, and
  // T_max * inv_frob then overflowed to inf, and 0 * inf gave NaN.)
  const V scale = L::clamp(lift * inv_max * inv_frob, V(0), huge);
  Mat3<V> tangent = times_cross(R, u);
  for (int k = 0; k < 9; ++k) tangent.a[k] = saturate(tangent.a[k] * scale);
  if (scaled) {
    const V x_up = L::select(x_huge, V(std::ldexp(T(1), kHalfRange)), V(1));
    for (int k = 0; k < 9; ++k) tangent.a[k] = saturate(tangent.a[k] * x_up);
  }
  return tangent;
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
