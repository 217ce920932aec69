// Per-lane predicates of the driver: is a fixed point the maximum, and is a
// warm start a rotation (and its clean-up to the compute precision).
#pragma once

#include "../limits.h"
#include "force_inline.h"
#include "lanes.h"
#include "mat3.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

// Second-order check at a fixed point S = R^T M (S symmetric): R is the global
// maximum iff the two smallest eigenvalues of sym(S) sum to >= 0, i.e. iff
// P = tr(S) I - sym(S) is positive semidefinite (Sec. 3, analysis of g_S).
// Other fixed points are saddles or minima that a Newton-type iteration can
// reach. Tested on P + slack I; a fixed point that passes falls short of the
// maximum by at most 2 slack (plus rounding of a few eps |P|).
//
// The test eliminates on P's largest diagonal entry and checks that the 2x2
// Schur complement left is positive definite. Where two eigenvalues of P are
// tiny (three nearly equal singular values, det M < 0: a near-flat ridge of
// maximisers), Sylvester's leading minors are not usable: det P is the
// product of those two tiny eigenvalues and of one of order 1, and its
// float32 rounding (~eps |P|^3) decides its sign (a saddle 3.6e-6 short of
// the maximum passed). The pivot here is at least tr(P) / 3, so the Schur
// complement is P's restriction to its small eigenvalues, computed to
// ~eps |P|, and its 2x2 determinant has the right sign.
template <typename L>
TORCHROT_INLINE typename L::Mask is_maximum(const Mat3<typename L::V>& S, typename L::Scalar slack) {
  using V = typename L::V;
  using Mask = typename L::Mask;
  const V t = S(0, 0) + S(1, 1) + S(2, 2) + V(slack);
  const V p00 = t - S(0, 0), p11 = t - S(1, 1), p22 = t - S(2, 2);
  const V p01 = V(-0.5) * (S(0, 1) + S(1, 0));
  const V p02 = V(-0.5) * (S(0, 2) + S(2, 0));
  const V p12 = V(-0.5) * (S(1, 2) + S(2, 1));
  // Pivot i (the first of equal largest diagonal entries) and the other two
  // indices a < b: P_aa, P_bb, P_ab and the pivot's column P_ai, P_bi.
  const Mask pivot0 = L::mask_and(L::mask_not(L::lt(p00, p11)), L::mask_not(L::lt(p00, p22)));
  const Mask pivot1 = L::mask_and(L::mask_not(pivot0), L::mask_not(L::lt(p11, p22)));
  const auto pick = [&](V if0, V if1, V if2) { return L::select(pivot0, if0, L::select(pivot1, if1, if2)); };
  const V pivot = pick(p00, p11, p22);
  const V paa = pick(p11, p00, p00), pbb = pick(p22, p22, p11), pab = pick(p12, p02, p01);
  const V pai = pick(p01, p01, p02), pbi = pick(p02, p12, p12);
  // The Schur complement times the pivot (no division; the signs tested are
  // those of pivot * Q and pivot^2 det Q with pivot > 0).
  const V qaa = paa * pivot - pai * pai;
  const V qbb = pbb * pivot - pbi * pbi;
  const V qab = pab * pivot - pai * pbi;
  const V zero(0);
  return L::mask_and(L::mask_and(L::gt(pivot, zero), L::gt(qaa, zero)), L::gt(qaa * qbb - qab * qab, zero));
}

// |G - I|_F^2 for the Gram matrix G = R^T R: how far R is from orthonormal.
template <typename V>
TORCHROT_INLINE V orthonormality_deviation2(const Mat3<V>& G) {
  const V d0 = G(0, 0) - V(1), d1 = G(1, 1) - V(1), d2 = G(2, 2) - V(1);
  const V off = dot3(G(0, 1), G(0, 1), G(0, 2), G(0, 2), G(1, 2), G(1, 2));
  return mul_add(d0, d0, mul_add(d1, d1, mul_add(d2, d2, V(2) * off)));
}

template <typename V>
TORCHROT_INLINE V determinant(const Mat3<V>& R) {
  // Expansion along the first row.
  const V c0 = diff_of_products(R(1, 1), R(2, 2), R(1, 2), R(2, 1));
  const V c1 = diff_of_products(R(1, 2), R(2, 0), R(1, 0), R(2, 2));
  const V c2 = diff_of_products(R(1, 0), R(2, 1), R(1, 1), R(2, 0));
  return dot3(R(0, 0), c0, R(0, 1), c1, R(0, 2), c2);
}

// A warm start R0, checked: `finite` where all its entries are finite, `bad`
// where it is finite but not a rotation (|R0^T R0 - I|_F >=
// limits::kInitTolerance or det R0 <= 0), and its squared deviation for the
// clean-up. (Not its Gram matrix, which only the rare clean-up needs: kept
// here, GCC stored its six vectors to the stack, dead stores that the
// validation pass of out= calls executed: benchmarks/lab_notes.md, "Fewer
// instructions".)
template <typename L>
struct WarmStartCheck {
  typename L::Mask finite, bad;
  typename L::V deviation2;
};

template <typename L>
TORCHROT_INLINE WarmStartCheck<L> check_warm_start(const Mat3<typename L::V>& R) {
  using V = typename L::V;
  using T = typename L::Scalar;
  WarmStartCheck<L> check;
  const Mat3<V> G = gram(R);
  check.deviation2 = orthonormality_deviation2(G);
  // The Gram diagonal is finite iff every entry of R is.
  check.finite = L::is_finite(G(0, 0) + G(1, 1) + G(2, 2));
  constexpr T tol = T(limits::kInitTolerance);
  const typename L::Mask rotation = L::mask_and(L::lt(check.deviation2, V(tol * tol)), L::gt(determinant(R), V(0)));
  check.bad = L::mask_and(check.finite, L::mask_not(rotation));
  return check;
}

// The lanes whose warm start is used at all: finite rotations.
template <typename L>
TORCHROT_INLINE typename L::Mask is_usable(const WarmStartCheck<L>& check) {
  return L::mask_and(check.finite, L::mask_not(check.bad));
}

// The lanes whose warm start clean_warm_start returns as it is: usable and
// deviating less than `clean`. (The operator's validation pass counts the
// others, see FitOptions::init_known_clean.)
template <typename L>
TORCHROT_INLINE typename L::Mask used_as_is(const WarmStartCheck<L>& check, typename L::Scalar clean) {
  using V = typename L::V;
  return L::mask_and(is_usable<L>(check), L::lt(check.deviation2, V(clean * clean)));
}

// The lanes that clean_warm_start changes: usable, deviating at least `clean`.
template <typename L>
TORCHROT_INLINE typename L::Mask needs_cleaning(const WarmStartCheck<L>& check, typename L::Scalar clean) {
  using V = typename L::V;
  return L::mask_and(is_usable<L>(check), L::mask_not(L::lt(check.deviation2, V(clean * clean))));
}

// The warm start at the compute dtype's precision: lanes whose deviation is at
// or above `clean` (a rotation of lower precision, e.g. fitted in float32 and
// fed to a float64 fit) take Newton-Schulz steps until it is below (each
// takes a deviation d to ~(3/4) d^2; limits::kInitCleanSteps suffice from the
// acceptance tolerance). Other lanes are returned unchanged, so the result of
// a lane does not depend on its block.
template <typename L>
inline Mat3<typename L::V> clean_warm_start(const Mat3<typename L::V>& R0, const WarmStartCheck<L>& check,
                                            typename L::Scalar clean) {
  using V = typename L::V;
  const V clean2(clean * clean);
  typename L::Mask rough = needs_cleaning<L>(check, clean);
  if (!L::any(rough)) return R0;
  Mat3<V> R = R0;
  Mat3<V> G = gram(R0);  // as check_warm_start computed it
  for (int k = 0; k < limits::kInitCleanSteps && L::any(rough); ++k) {
    R = select<L>(rough, reorthonormalize(R, G), R);
    G = gram(R);
    rough = L::mask_and(rough, L::mask_not(L::lt(orthonormality_deviation2(G), clean2)));
  }
  return R;
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
