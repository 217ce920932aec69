// Algorithm 1 for a block of L::width matrices (one per lane): cold or warm
// start, Cayley steps until each lane's own convergence, a check that each
// fixed point is the maximum, saddle escapes, and the guaranteed fallback.
// Lanes that converge early are frozen (never re-stepped into noise); lanes
// that need the fallback take it alone, after the block's vector work.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

#include "cayley.h"
#include "cold_start.h"
#include "horn_fallback.h"
#include "lanes.h"
#include "optimality.h"
#include "saddle_escape.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

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
  // maximum by at most 2 * slack * max |M_ij|.
  static constexpr T max_check_slack = T(4) * eps;
  // Warm starts must be rotations to this orthonormality error.
  static constexpr T init_orthonormality = sizeof(T) == 4 ? T(1e-4) : T(1e-7);
  // Cayley steps allowed in converged mode per start or saddle escape.
  static constexpr int converged_cap = 12;
  // Saddle escapes allowed in converged mode before the fallback decides.
  static constexpr int max_escapes = 2;
};

// Per-lane outcome of fit_rotation_lanes.
template <typename L>
struct LaneResults {
  typename L::V iterations;    // Cayley steps taken (as floating values)
  typename L::Mask fallback;   // solved by the Horn/Jacobi fallback
  typename L::Mask bad_init;   // the warm start was finite but not a rotation
  typename L::Mask non_finite; // M or init held NaN/Inf
};

template <typename L>
struct IterationEnd {
  typename L::Mask converged;
  Mat3<typename L::V> last_S;  // S = R^T A of each lane's last step
};

// Algorithm 1's loop: up to `cap` Cayley steps R <- R Q(z) on the `active`
// lanes. A lane stops when its step is below the convergence tolerance or its
// H is singular (then no step is taken).
template <typename L>
inline IterationEnd<L> run_cayley_steps(const Mat3<typename L::V>& A, int64_t cap, Variant variant,
                                        bool switch_to_newton, typename L::Mask active,
                                        Mat3<typename L::V>& R, typename L::V& iterations) {
  using V = typename L::V;
  using Mask = typename L::Mask;
  using Tol = Tolerances<typename L::Scalar>;
  IterationEnd<L> end;
  end.converged = L::all_false();
  for (int k = 0; k < 9; ++k) end.last_S.a[k] = V(0);
  Mask done = L::mask_not(active);
  Mask newton = L::all_false();
  for (int64_t it = 0; it < cap && !L::all(done); ++it) {
    const Mat3<V> S = transpose_times(R, A);
    V c = objective_estimate<L>(S, variant);
    if (switch_to_newton && variant != Variant::kNewton) c = L::select(newton, trace(S), c);
    const CayleyStep<V> step = cayley_step(S, c);
    const Mask finite = L::is_finite(step.zz);
    const Mask stepping = L::mask_and(L::mask_not(done), finite);
    done = L::mask_or(done, L::mask_not(finite));
    R = select<L>(stepping, times(R, cayley_rotation(step)), R);
    end.last_S = select<L>(stepping, S, end.last_S);
    iterations = iterations + L::select(stepping, V(1), V(0));
    if (switch_to_newton) {
      newton = L::mask_or(newton, L::mask_and(stepping, L::lt(step.zz, V(Tol::newton_switch))));
    }
    const Mask now_converged = L::mask_and(stepping, L::lt(step.zz, V(Tol::converged)));
    end.converged = L::mask_or(end.converged, now_converged);
    done = L::mask_or(done, now_converged);
  }
  return end;
}

// Fits R maximising tr(R^T M) for each lane. `init` may be null.
template <typename L>
inline LaneResults<L> fit_rotation_lanes(const Mat3<typename L::V>& M, const Mat3<typename L::V>* init,
                                         const FitOptions& options, Mat3<typename L::V>& R) {
  using T = typename L::Scalar;
  using V = typename L::V;
  using Mask = typename L::Mask;
  using Tol = Tolerances<T>;
  LaneResults<L> res;
  res.iterations = V(0);
  res.fallback = L::all_false();
  res.bad_init = L::all_false();

  Mask finite = L::all_true();
  V max_abs(0);
  for (int k = 0; k < 9; ++k) {
    finite = L::mask_and(finite, L::is_finite(M.a[k]));
    max_abs = L::max(max_abs, L::abs(M.a[k]));
    if (init != nullptr) finite = L::mask_and(finite, L::is_finite(init->a[k]));
  }
  res.non_finite = L::mask_not(finite);

  // Scale to max |entry| = 1: the maximiser is unchanged and no product in a
  // step can over- or underflow. 1 / subnormal may overflow, so those lanes
  // are first lifted by 2^digits (exact). M = 0 stays 0.
  const V lift = L::select(L::lt(max_abs, V(std::numeric_limits<T>::min())),
                           V(std::ldexp(T(1), std::numeric_limits<T>::digits)), V(1));
  const Mask zero = L::eq(max_abs, V(0));
  const V inv = L::select(zero, V(0), V(1) / (max_abs * lift));
  Mat3<V> A;
  for (int k = 0; k < 9; ++k) A.a[k] = (M.a[k] * lift) * inv;

  // M = 0: every rotation is optimal; such lanes keep the start (init or I).
  Mask active = L::mask_and(finite, L::mask_not(zero));
  if (init != nullptr) {
    res.bad_init = L::mask_and(finite, L::mask_not(is_rotation<L>(*init, Tol::init_orthonormality)));
    active = L::mask_and(active, L::mask_not(res.bad_init));
    // Warm starts fed back call after call would drift from orthonormal.
    R = reorthonormalize(*init);
  } else {
    R = best_start_rotation<L>(A);
  }

  if (options.max_iter > 0) {
    run_cayley_steps<L>(A, options.max_iter, options.variant, /*switch_to_newton=*/false, active, R,
                        res.iterations);
  } else {
    Mask accepted = L::all_false();
    Mask pending = active;
    for (int attempt = 0; attempt <= Tol::max_escapes && L::any(pending); ++attempt) {
      const IterationEnd<L> end = run_cayley_steps<L>(A, Tol::converged_cap, options.variant,
                                                      /*switch_to_newton=*/true, pending, R, res.iterations);
      const Mask at_maximum = L::mask_and(end.converged, is_maximum<L>(end.last_S, Tol::max_check_slack));
      accepted = L::mask_or(accepted, at_maximum);
      // Converged to a saddle: escape by a half-turn and iterate again.
      pending = L::mask_and(end.converged, L::mask_not(at_maximum));
      if (attempt < Tol::max_escapes && L::any(pending)) {
        R = select<L>(pending, times(R, saddle_escape_rotation<L>(transpose_times(R, A))), R);
      }
    }
    // Products of Cayley factors accumulate rounding; one Newton-Schulz step
    // brings R back to orthonormal at the dtype's precision.
    R = select<L>(accepted, reorthonormalize(R), R);
    res.fallback = L::mask_and(active, L::mask_not(accepted));
    if (L::any(res.fallback)) {
      for (int i = 0; i < L::width; ++i) {
        if (L::lane_set(res.fallback, i)) insert_lane<L>(R, i, horn_rotation(extract_lane<L>(A, i)));
      }
    }
  }
  const Mask nan_lanes = L::mask_or(res.non_finite, res.bad_init);
  if (L::any(nan_lanes)) {
    const V nan(std::numeric_limits<T>::quiet_NaN());
    for (int k = 0; k < 9; ++k) R.a[k] = L::select(nan_lanes, nan, R.a[k]);
  }
  return res;
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
