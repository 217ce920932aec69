// The Cayley step of Zhang, Jacobson & Alexa, "Fast Updates for Least-Squares
// Rotational Alignment" (Algorithm 2), and the Cayley map back to a rotation
// (Eq. 10), written once for any lane type L (lanes.h).
//
// Convention. torchrot maximises tr(R^T M). Writing R = R0 Q, the objective is
// tr(Q^T S) with S = R0^T M, which is the paper's tr(M_p Q) for M_p = S^T. All
// formulas below are the paper's, rewritten for S:
//   m = vee(S - S^T) = (S21 - S12, S02 - S20, S10 - S01)        (Eq. 12)
//   t = tr S,   T = S + S^T - t I                               (Eq. 36)
//   (S + S^T - (t + c) I) z = -m                                (Eq. 24 / 29)
// and Q = ((1 - z.z) I + 2 z z^T + 2 [z]x) / (1 + z.z)          (Eq. 10),
// applied as R + R (Q - I) (cayley_increment, rotate_by).
// The step is also the lower block of Horn's eigenproblem K (1, z) = c (1, z)
// with K = [[t, m^T], [m, T]], so c estimates K's largest eigenvalue, i.e. the
// maximal objective.
#pragma once

#include "../fit_rotation.h"
#include "force_inline.h"
#include "lanes.h"
#include "mat3.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

// A Cayley step kept as a fraction: z = -w / d with w = adj(H) m and d = det H
// (Cramer's rule, Eqs. 31-33). Keeping d and w separate lets Eq. 10 be
// evaluated with a single division and the step size be tested without any.
template <typename V>
struct CayleyStep {
  V w[3];  // adj(H) m
  V d;     // det H
  V ww;    // w.w
  V dd;    // d^2; the paper's s = z.z = tan^2(theta / 2) is ww / dd
  V mm;    // m.m
  V hh;    // |H|_F^2

  // Is s < tol? False when H is singular or the step is not finite.
  template <typename L>
  typename L::Mask smaller_than(typename L::Scalar tol) const {
    return L::lt(ww, V(tol) * dd);
  }

  // Is H singular with the gradient m in its range, to working precision:
  // |m|^2 >= tol |H|_F^2? A step z = -H^-1 m with z.z < tol has
  // |m|^2 = |H z|^2 <= |H|_F^2 z.z < tol |H|_F^2, so a small step never meets
  // this unless Cramer's rule gave 0 / 0: H singular and the system
  // consistent, w = adj(H) m and det H both zero up to rounding, a tiny ratio
  // w.w / d^2 at a point that is not stationary (newton's H is singular
  // wherever tr(S) is an eigenvalue of S + S^T - tr(S) I).
  template <typename L>
  typename L::Mask singular(typename L::Scalar tol) const {
    return L::mask_not(L::lt(mm, V(tol) * hh));
  }
};

template <typename V>
TORCHROT_INLINE V trace(const Mat3<V>& S) {
  return S(0, 0) + S(1, 1) + S(2, 2);
}

template <typename V>
TORCHROT_INLINE void skew_vector(const Mat3<V>& S, V m[3]) {  // Eq. 12
  m[0] = S(2, 1) - S(1, 2);
  m[1] = S(0, 2) - S(2, 0);
  m[2] = S(1, 0) - S(0, 1);
}

// The estimate c of the maximal objective for `variant` (Sec. 4.2).
template <typename L>
TORCHROT_INLINE typename L::V objective_estimate(const Mat3<typename L::V>& S, Variant variant) {
  using V = typename L::V;
  const V t = trace(S);
  if (variant == Variant::kNewton) return t;  // Eq. 21: the Taylor model at 0
  V m[3];
  skew_vector(S, m);
  const V mm = dot3(m[0], m[0], m[1], m[1], m[2], m[2]);
  V g_sym = t;  // conservative: max g_S ~ tr S
  if (variant == Variant::kGershgorin) {
    // 2 lambda_2 <= max_i (2 S_ii + sum_{j != i} |S_ij + S_ji|)   (Eq. 28)
    const V s01 = L::abs(S(0, 1) + S(1, 0));
    const V s02 = L::abs(S(0, 2) + S(2, 0));
    const V s12 = L::abs(S(1, 2) + S(2, 1));
    const V two_lambda2 =
        L::max(V(2) * S(0, 0) + s01 + s02, L::max(V(2) * S(1, 1) + s01 + s12, V(2) * S(2, 2) + s02 + s12));
    g_sym = L::max(t, two_lambda2 - t);
  }
  return L::sqrt(mul_add(g_sym, g_sym, mm));  // Eqs. 26-27
}

// The symmetric system matrix H = S + S^T - (tr S + c) I of Algorithm 2.
template <typename V>
struct StepSystem {
  V h00, h11, h22, h01, h02, h12;
  TORCHROT_INLINE StepSystem(const Mat3<V>& S, V c) {
    const V shift = trace(S) + c;
    // 2 S_ii is exact: one rounding either way, one instruction fused.
    h00 = mul_add(V(2), S(0, 0), -shift);
    h11 = mul_add(V(2), S(1, 1), -shift);
    h22 = mul_add(V(2), S(2, 2), -shift);
    h01 = S(0, 1) + S(1, 0);
    h02 = S(0, 2) + S(2, 0);
    h12 = S(1, 2) + S(2, 1);
  }
  TORCHROT_INLINE V frobenius2() const {
    return mul_add(h00, h00, mul_add(h11, h11, mul_add(h22, h22, V(2) * dot3(h01, h01, h02, h02, h12, h12))));
  }
};

// Algorithm 2 for a given c: (S + S^T - (t + c) I) z = -m by Cramer's rule
// (Eqs. 30-33), written with the symmetric adjugate of H.
template <typename V>
TORCHROT_INLINE CayleyStep<V> cayley_step(const Mat3<V>& S, V c) {
  V m[3];
  skew_vector(S, m);
  const StepSystem<V> H(S, c);
  const V h00 = H.h00, h11 = H.h11, h22 = H.h22, h01 = H.h01, h02 = H.h02, h12 = H.h12;

  const V c00 = diff_of_products(h11, h22, h12, h12);
  const V c01 = diff_of_products(h02, h12, h01, h22);
  const V c02 = diff_of_products(h01, h12, h02, h11);
  const V c11 = diff_of_products(h00, h22, h02, h02);
  const V c12 = diff_of_products(h01, h02, h00, h12);
  const V c22 = diff_of_products(h00, h11, h01, h01);

  CayleyStep<V> step;
  step.d = dot3(h00, c00, h01, c01, h02, c02);
  step.w[0] = dot3(c00, m[0], c01, m[1], c02, m[2]);
  step.w[1] = dot3(c01, m[0], c11, m[1], c12, m[2]);
  step.w[2] = dot3(c02, m[0], c12, m[1], c22, m[2]);
  step.ww = dot3(step.w[0], step.w[0], step.w[1], step.w[1], step.w[2], step.w[2]);
  step.dd = step.d * step.d;
  step.mm = dot3(m[0], m[0], m[1], m[1], m[2], m[2]);
  step.hh = H.frobenius2();
  return step;
}

// The rotation with Cayley parameters z = -w / d (Eq. 10) as Q = I + K.
// Multiplied through by d^2, Q = ((d^2 - w.w) I + 2 w w^T - 2 d [w]x) /
// (d^2 + w.w), so K = (2 w w^T - 2 (w.w) I - 2 d [w]x) / (d^2 + w.w), whose
// diagonal is -2 (w.w - w_i^2) / (d^2 + w.w): the quaternion form
// 1 - 2 (y^2 + z^2) of the rotation by the unit quaternion (d, w) / |(d, w)|.
// K is as small as the step, and so is its rounding: Q's diagonal rounded
// near 1 would add a few eps to the orthonormality error of every R it
// rotates (see rotate_by).
// Every product of two components of (d, w) is formed as u (v * 2 / (d^2 +
// w.w)): each factor is then at most about 2 / |(d, w)| and the product at
// most 2, so a product below the normal range (flushed to zero, see
// cpu/flush_to_zero.h) is an entry of K below it, not a part of one that the
// division would have scaled up (u v flushed, then times 2 / |(d, w)|^2, lost
// 1.5e-3 of an entry of K on a step with |(d, w)| ~ 1e-18: tests/test_subnormal.py).
template <typename V>
TORCHROT_INLINE Mat3<V> cayley_increment(const CayleyStep<V>& step) {
  const V x = step.w[0], y = step.w[1], w = step.w[2];
  const V two_inv = V(2) / (step.dd + step.ww);
  const V x2 = x * two_inv, y2 = y * two_inv, w2 = w * two_inv, d2 = step.d * two_inv;
  const V yy = y * y2, ww = w * w2;
  Mat3<V> K;
  K(0, 0) = -mul_add(y, y2, ww);
  K(1, 1) = -mul_add(x, x2, ww);
  K(2, 2) = -mul_add(x, x2, yy);
  const V xy = x * y2, xw = x * w2, yw = y * w2;
  // xy +- w d2, ... (one rounding each, mul_add.h)
  K(0, 1) = mul_add(w, d2, xy);
  K(1, 0) = mul_add(-w, d2, xy);
  K(0, 2) = mul_add(-y, d2, xw);
  K(2, 0) = mul_add(y, d2, xw);
  K(1, 2) = mul_add(x, d2, yw);
  K(2, 1) = mul_add(-x, d2, yw);
  return K;
}

// R Q = R + R K for Q = I + K: each entry is R's plus a small correction,
// summed at its own scale and added last, so the result is rounded about
// once per entry, whatever the step: a Cayley step adds about an eps to
// R's orthonormality error (measured: one-step results of warm starts within
// ~1 eps of their warm start's deviation), where R Q added 4-6.
// Row by row: row i of R Q is row i of R (`row`) times Q.
template <typename V>
TORCHROT_INLINE void rotate_row_by(const V row[3], const Mat3<V>& K, V out[3]) {
  for (int c = 0; c < 3; ++c) out[c] = row[c] + dot3(row[0], K(0, c), row[1], K(1, c), row[2], K(2, c));
}

template <typename V>
TORCHROT_INLINE Mat3<V> rotate_by(const Mat3<V>& R, const Mat3<V>& K) {
  Mat3<V> C;
  for (int r = 0; r < 3; ++r) rotate_row_by(&R.a[3 * r], K, &C.a[3 * r]);
  return C;
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
