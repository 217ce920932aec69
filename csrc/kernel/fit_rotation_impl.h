// Algorithm 1 for one matrix: cold or warm start, Cayley steps until the
// matrix's own convergence, a check that the fixed point is the maximum, and
// the guaranteed fallback.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

#include "cayley.h"
#include "cold_start.h"
#include "horn_fallback.h"
#include "saddle_escape.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {

struct FitResult {
  int32_t iterations = 0;
  FitStatus status = FitStatus::kCayley;
};

template <typename T>
struct Tolerances {
  static constexpr T eps = std::numeric_limits<T>::epsilon();
  // Converged once a step's s = tan^2(theta / 2) < eps: Newton converges
  // quadratically there, so the applied step leaves an error of order eps.
  static constexpr T converged = eps;
  // Below ~1 degree every variant switches to the Newton estimate c = tr S
  // (converged mode only). The conservative and Gershgorin estimates exceed
  // tr S at the optimum by up to their Gershgorin slack (Eq. 28), which turns
  // quadratic convergence into linear convergence; Newton has no such slack
  // and, this close to a maximum, no risk of overshooting (Sec. 4.2).
  static constexpr T newton_switch = T(1e-4);
  // Slack of the second-order check: the objective may fall short of the
  // maximum by at most 2 * slack * |M|_max.
  static constexpr T max_check_slack = T(4) * eps;
  // Warm starts must be rotations to this orthonormality error.
  static constexpr T init_orthonormality = sizeof(T) == 4 ? T(1e-4) : T(1e-7);
  // Cayley steps allowed in converged mode (per start or saddle escape)
  // before the fallback takes over.
  static constexpr int converged_cap = 12;
  // Saddle escapes allowed in converged mode.
  static constexpr int max_escapes = 2;
};

template <typename T>
inline Mat3<T> nan_matrix() {
  Mat3<T> R;
  for (int i = 0; i < 9; ++i) R.a[i] = std::numeric_limits<T>::quiet_NaN();
  return R;
}

// Largest |entry|, NaN if any entry is NaN.
template <typename T>
inline T max_abs_entry(const Mat3<T>& M) {
  T result = T(0);
  for (int i = 0; i < 9; ++i) {
    const T a = std::fabs(M.a[i]);
    if (!(a <= result)) result = a;  // also picks up NaN
  }
  return result;
}

template <typename T>
inline bool all_finite(const Mat3<T>& M) {
  for (int i = 0; i < 9; ++i)
    if (!std::isfinite(M.a[i])) return false;
  return true;
}

// Is R a proper rotation up to `tol` (max |R^T R - I| <= tol, det R > 0)?
template <typename T>
inline bool is_rotation(const Mat3<T>& R, T tol) {
  const Mat3<T> G = transpose_times(R, R);
  for (int i = 0; i < 9; ++i) {
    if (!(std::fabs(G.a[i] - T(i % 4 == 0 ? 1 : 0)) <= tol)) return false;
  }
  const T det = R(0, 0) * (R(1, 1) * R(2, 2) - R(1, 2) * R(2, 1)) -
                R(0, 1) * (R(1, 0) * R(2, 2) - R(1, 2) * R(2, 0)) +
                R(0, 2) * (R(1, 0) * R(2, 1) - R(1, 1) * R(2, 0));
  return det > T(0);
}

// Second-order check at a fixed point S = R^T M (S symmetric): R is the global
// maximum iff the two smallest eigenvalues of sym(S) sum to >= 0, i.e. iff
// tr(S) I - sym(S) is positive semidefinite (Sec. 3, analysis of g_S). Other
// fixed points are saddles or minima reached by a Newton-type iteration.
// Checked by Sylvester's criterion on tr(S) I - sym(S) + slack I.
template <typename T>
inline bool is_maximum(const Mat3<T>& S, T slack) {
  const T t = S(0, 0) + S(1, 1) + S(2, 2) + slack;
  const T p00 = t - S(0, 0), p11 = t - S(1, 1), p22 = t - S(2, 2);
  const T p01 = T(-0.5) * (S(0, 1) + S(1, 0));
  const T p02 = T(-0.5) * (S(0, 2) + S(2, 0));
  const T p12 = T(-0.5) * (S(1, 2) + S(2, 1));
  const T minor2 = p00 * p11 - p01 * p01;
  const T det = p00 * (p11 * p22 - p12 * p12) - p01 * (p01 * p22 - p12 * p02) +
                p02 * (p01 * p12 - p11 * p02);
  return p00 > T(0) && minor2 > T(0) && det > T(0);
}

// Scales M so that its largest |entry| is 1: the objective's maximiser does
// not change, and no product in the step over- or underflows for entries
// anywhere between the smallest subnormal and the largest finite value.
template <typename T>
inline Mat3<T> normalized(const Mat3<T>& M, T max_abs) {
  T pre = T(1);
  if (max_abs < std::numeric_limits<T>::min()) {
    // 1 / subnormal may overflow: lift by 2^digits first (exact).
    pre = std::ldexp(T(1), std::numeric_limits<T>::digits);
    max_abs *= pre;
  }
  const T inv = T(1) / max_abs;
  Mat3<T> A;
  for (int i = 0; i < 9; ++i) A.a[i] = (M.a[i] * pre) * inv;
  return A;
}

template <typename T>
struct IterationEnd {
  bool converged = false;
  Mat3<T> last_S;  // S = R^T A of the last step taken
};

// Algorithm 1's loop: up to `cap` Cayley steps R <- R Q(z), stopping when a
// step is below the convergence tolerance or H is singular (no step taken).
template <typename T>
inline IterationEnd<T> run_cayley_steps(const Mat3<T>& A, int64_t cap, Variant variant,
                                        bool switch_to_newton, Mat3<T>& R, FitResult& result) {
  using Tol = Tolerances<T>;
  IterationEnd<T> end;
  for (int64_t it = 0; it < cap; ++it) {
    end.last_S = transpose_times(R, A);
    const CayleyStep<T> step = cayley_step(end.last_S, variant);
    if (!std::isfinite(step.zz)) break;
    R = times(R, cayley_rotation(step));
    ++result.iterations;
    if (switch_to_newton && step.zz < Tol::newton_switch) variant = Variant::kNewton;
    if (step.zz < Tol::converged) {
      end.converged = true;
      break;
    }
  }
  return end;
}

// Fits the rotation maximising tr(R^T M) for one matrix. `init` may be null.
template <typename T>
inline FitResult fit_rotation_one(const Mat3<T>& M, const Mat3<T>* init,
                                  const FitOptions& options, Mat3<T>& R) {
  using Tol = Tolerances<T>;
  FitResult result;
  const T max_abs = max_abs_entry(M);
  if (!std::isfinite(max_abs) || (init != nullptr && !all_finite(*init))) {
    R = nan_matrix<T>();
    result.status = FitStatus::kNonFinite;
    return result;
  }
  if (init != nullptr && !is_rotation(*init, Tol::init_orthonormality)) {
    R = nan_matrix<T>();
    result.status = FitStatus::kBadInit;
    return result;
  }
  if (max_abs == T(0)) {
    // Every rotation attains the maximum 0: keep the warm start, else I.
    R = init != nullptr ? reorthonormalize(*init) : identity3<T>();
    return result;
  }
  const Mat3<T> A = normalized(M, max_abs);
  const bool converge = options.max_iter <= 0;
  R = init != nullptr ? reorthonormalize(*init)
                      : start_candidate_rotation<T>(best_start_candidate(A));

  if (!converge) {
    run_cayley_steps(A, options.max_iter, options.variant, /*switch_to_newton=*/false, R, result);
    return result;
  }
  // Converged mode. A fixed point that fails the second-order check is a
  // saddle: escape it by a half-turn (saddle_escape.h) and iterate again, at
  // most Tolerances::max_escapes times; whatever has not reached a verified maximum by
  // then goes to the fallback.
  for (int attempt = 0; attempt <= Tol::max_escapes; ++attempt) {
    const IterationEnd<T> end =
        run_cayley_steps(A, Tol::converged_cap, options.variant, /*switch_to_newton=*/true, R, result);
    if (end.converged && is_maximum(end.last_S, Tol::max_check_slack)) {
      // Products of Cayley factors accumulate rounding; one Newton-Schulz
      // step brings R back to orthonormal at the dtype's precision.
      R = reorthonormalize(R);
      return result;
    }
    if (!end.converged) break;
    R = times(R, saddle_escape_rotation(transpose_times(R, A)));
  }
  R = horn_rotation(A);
  result.status = FitStatus::kFallback;
  return result;
}

}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
