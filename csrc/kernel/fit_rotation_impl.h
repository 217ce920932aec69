// Algorithm 1 as a per-lane state machine, for a block of L::width matrices
// (one per lane): begin (normalise, start), advance (Cayley steps, each lane
// until its own convergence, with the maximum check, saddle escapes and the
// iteration cap), finish (final clean-up, fallback, NaN). A lane's state can
// be saved and resumed in another block, so the batched kernel can regroup
// slow lanes densely instead of stepping whole blocks for one straggler; the
// operations a lane executes do not depend on its block, so results are
// identical however lanes are grouped, and identical to the scalar path.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>
#include <type_traits>

#include "../limits.h"
#include "cayley.h"
#include "cold_start.h"
#include "force_inline.h"
#include "horn_fallback.h"
#include "lanes.h"
#include "maximal_objective.h"
#include "optimality.h"
#include "saddle_escape.h"
#include "unit_scale.h"

namespace torchrot {
namespace kernel {
inline namespace CPU_CAPABILITY {
namespace {

template <typename T>
struct Tolerances {
  static constexpr T eps = std::numeric_limits<T>::epsilon();
  // Converged once an (almost) undamped step has s = tan^2(theta / 2) < eps:
  // Newton converges quadratically there, so the applied step leaves an
  // error of order eps. A damped step (c > tr S) can be tiny far from the
  // optimum, so it counts only if its damping c - tr S is at most
  // sqrt(eps) |tr S|, which moves it from the Newton step by at most
  // sqrt(eps) |z| <= eps. (The conservative estimate is within ~eps |tr S|
  // of tr S there, far from that bound; Gershgorin's slack is not.)
  static constexpr T converged = eps;
  static constexpr T undamped = T(sizeof(T) == 4 ? limits::kUndampedFloat : limits::kUndampedDouble);  // sqrt(eps)
  // Laguerre's method for the maximal objective (maximal_objective.h) stops
  // a lane once its correction is below sqrt(eps) x (the next would be below
  // eps x), or after this many steps (slow, linear convergence only near a
  // double root: three nearly equal singular values with det < 0, or rank 1).
  static constexpr T objective_tolerance = undamped;
  static constexpr int objective_steps = limits::kObjectiveLaguerreSteps;
  // In converged mode the Gershgorin variant switches to the conservative
  // estimate after its first two steps (per start or escape) or after a step
  // below ~1 degree. Gershgorin's bound (Eq. 28) is meant for the large first
  // steps; it stays above tr S at the optimum by its slack, which makes
  // convergence linear, and so slow on anisotropic M that a quarter of the
  // warm data ran out of steps (measured). The conservative estimate exceeds
  // tr S only by ~m.m / (2 tr S), which vanishes quadratically at the
  // optimum, while it still damps steps that are not small (Sec. 4.2).
  static constexpr T estimate_switch = T(limits::kEstimateSwitch);
  static constexpr int gershgorin_steps = limits::kGershgorinSteps;
  // Slack of the second-order check: the objective may fall short of the
  // maximum by at most 2 * slack * max |M_ij|.
  static constexpr T max_check_slack = T(limits::kMaxCheckSlackEps) * eps;
  // Cayley steps allowed in converged mode per start or saddle escape.
  static constexpr int converged_cap = limits::kConvergedCap;
  // Saddle escapes allowed in converged mode before the fallback decides.
  static constexpr int max_escapes = limits::kMaxEscapes;
  // Most steps a lane can take in converged mode.
  static constexpr int converged_budget = (max_escapes + 1) * converged_cap;
  // Warm starts (limits.h) are used as they are below init_clean (and
  // accepted at all below limits::kInitTolerance, see check_warm_start).
  static constexpr T init_clean = T(limits::kInitCleanEps) * eps;
  // A result is cleaned up where a step was at least this large
  // (tan^2(theta / 2)) or it took more than steps_without_clean_up (finish).
  static constexpr T large_step = T(limits::kLargeStep);
  static constexpr int steps_without_clean_up = limits::kStepsWithoutCleanUp;
};

template <typename L>
struct LaneState {
  using V = typename L::V;
  using Mask = typename L::Mask;
  Mat3<V> A;        // M scaled to max |entry| 1
  Mat3<V> R;        // the current rotation
  V iterations;     // Cayley steps taken
  V attempt_steps;  // steps since the start or the last saddle escape
  V escapes;        // saddle escapes taken
  Mask switched;    // converged mode: Gershgorin switched to the conservative estimate
  Mask running;     // still iterating
  Mask fallback;    // converged mode: needs the Horn/Jacobi fallback
  Mask bad_init;    // the warm start was finite but not a rotation
  Mask non_finite;  // M or init held NaN/Inf
  Mask large_step;  // took a large step or a saddle escape: finish cleans it up
};

// Normalises M and picks the start: init (brought to the compute precision,
// see clean_warm_start) or the cold start. `init` may be null; lanes whose M
// or init are unusable, and M = 0 (every rotation is optimal: the start is
// kept), do not run. A warm start that is not a rotation is flagged whatever M
// holds (the operator rejects the call). `init_known_clean`: the caller has
// made this check (FitOptions::init_known_clean), init is used as it is.
// Cold starts also return the maximal objective in `objective` (not null
// then), the estimate c of their first step (advance, advance_one_step).
template <typename L>
TORCHROT_INLINE LaneState<L> begin_fit(const Mat3<typename L::V>& M, const Mat3<typename L::V>* init,
                                       bool init_known_clean, typename L::V* objective) {
  using T = typename L::Scalar;
  using Tol = Tolerances<T>;
  using V = typename L::V;
  using Mask = typename L::Mask;
  LaneState<L> s;
  s.iterations = s.attempt_steps = s.escapes = V(0);
  s.switched = s.fallback = s.bad_init = s.large_step = L::all_false();

  const V max_abs = max_abs_entry<L>(M);  // NaN if any entry is NaN
  Mask finite = L::is_finite(max_abs);

  const Mask zero = L::eq(max_abs, V(0));
  s.A = unit_scale<L>(M, max_abs).A;  // max |entry| 1: the maximiser is unchanged

  if (init != nullptr && init_known_clean) {
    s.R = *init;
  } else if (init != nullptr) {
    const WarmStartCheck<L> check = check_warm_start<L>(*init);
    finite = L::mask_and(finite, check.finite);
    s.bad_init = check.bad;
    s.R = clean_warm_start<L>(*init, check, Tol::init_clean);
  } else {
    // The first step from the cube start takes c = lambda itself, so it
    // solves Horn's eigenproblem: measured, uniform float32 lanes then need 2
    // steps (the second confirms), not 3.18 with the estimate.
    V start_objective;
    s.R = best_start_rotation<L>(s.A, start_objective);
    *objective = maximal_objective<L>(s.A, start_objective, Tol::objective_tolerance, Tol::objective_steps);
    // Gershgorin's bound (Eq. 28) is for the large first steps, which this one
    // replaces: converged mode goes on with the conservative estimate.
    s.switched = L::all_true();
  }
  s.non_finite = L::mask_not(finite);
  s.running = L::mask_and(L::mask_and(finite, L::mask_not(zero)), L::mask_not(s.bad_init));
  return s;
}

// Whether a lane can take `step`. A singular H (or a non-finite step) takes
// no step; nor does a step whose d^2 + w.w is below T_min / eps^2 (T_min: the
// smallest normal number). A square of a component below sqrt(T_min) is
// flushed to zero (cpu/flush_to_zero.h), so above that floor what is lost is
// below eps^2 of d^2 + w.w and Q stays orthogonal; below it, d and w have
// lost their precision anyway: since |S| >= 1 after normalisation, H is
// singular to working precision there (a flat objective).
template <typename L>
TORCHROT_INLINE typename L::Mask can_take(const CayleyStep<typename L::V>& step) {
  using T = typename L::Scalar;
  using V = typename L::V;
  constexpr T eps = std::numeric_limits<T>::epsilon();
  const V norm2 = step.dd + step.ww;
  return L::mask_and(L::mask_and(L::gt(step.dd, V(0)), L::is_finite(norm2)),
                     L::gt(norm2, V(std::numeric_limits<T>::min() / (eps * eps))));
}

// take_step's bookkeeping of `step`, taken by the lanes `stepping`.
template <typename L>
TORCHROT_INLINE void count_step(LaneState<L>& s, const CayleyStep<typename L::V>& step, typename L::Mask stepping) {
  using V = typename L::V;
  using T = typename L::Scalar;
  const typename L::Mask large = L::mask_not(step.template smaller_than<L>(Tolerances<T>::large_step));
  s.large_step = L::mask_or(s.large_step, L::mask_and(stepping, large));
  const V taken = L::select(stepping, V(1), V(0));
  s.iterations = s.iterations + taken;
  s.attempt_steps = s.attempt_steps + taken;
}

// Applies `step` to the running lanes that can take it (`valid`, see
// can_take), counts it (iterations, attempt_steps) and notes a large one
// (LaneState::large_step); returns those lanes.
// advance and advance_one_step both step through it, so their steps are the
// same bit for bit.
template <typename L>
TORCHROT_INLINE typename L::Mask take_step(LaneState<L>& s, const CayleyStep<typename L::V>& step,
                                           typename L::Mask valid) {
  const typename L::Mask stepping = L::mask_and(s.running, valid);
  s.R = select<L>(stepping, rotate_by(s.R, cayley_increment(step)), s.R);
  count_step<L>(s, step, stepping);
  return stepping;
}

// Takes up to `budget` Cayley steps on the running lanes, the first with c =
// *first_estimate with kFirstEstimate (a cold start's maximal objective: a
// function of its own, so that warm fits run the same code as before, with no
// more instructions per matrix). One function per lane type: GCC's clone
// specialised to one call site (IPA constant propagation) and its inlining
// choices around it ran the AVX2 fits slower (benchmarks/lab_notes.md).
template <typename L, bool kFirstEstimate = false>
[[gnu::noinline, gnu::noclone]] inline void advance(LaneState<L>& s, const FitOptions& options, int64_t budget,
                                                    const typename L::V* first_estimate = nullptr) {
  using T = typename L::Scalar;
  using V = typename L::V;
  using Mask = typename L::Mask;
  using Tol = Tolerances<T>;
  const bool converge = options.max_iter <= 0;
  // Per-lane step cap; larger counts than 2^24 are left to `budget`.
  const V cap(static_cast<T>(converge ? Tol::converged_cap : std::min<int64_t>(options.max_iter, 1 << 24)));
  const V one(1), zero(0);
  for (int64_t b = 0; b < budget && L::any(s.running); ++b) {
    const Mat3<V> S = transpose_times(s.R, s.A);
    const V t = trace(S);
    V c;
    if (kFirstEstimate && b == 0) {
      c = *first_estimate;
    } else {
      c = objective_estimate<L>(S, options.variant);
      if (converge && options.variant == Variant::kGershgorin) {
        c = L::select(s.switched, objective_estimate<L>(S, Variant::kConservative), c);
      }
    }
    const CayleyStep<V> step = cayley_step(S, c);
    const Mask valid = can_take<L>(step);
    Mask stalled = L::mask_and(s.running, L::mask_not(valid));
    const Mask stepping = take_step<L>(s, step, valid);
    // An undamped step below eps: converged.
    const Mask undamped = L::mask_not(L::gt(c - t, V(Tol::undamped) * L::abs(t)));
    Mask finished = L::mask_and(stepping, L::mask_and(undamped, step.template smaller_than<L>(Tol::converged)));

    if (converge) {
      if (options.variant == Variant::kGershgorin) {  // the only variant that reads `switched`
        const Mask switch_now = L::mask_or(step.template smaller_than<L>(Tol::estimate_switch),
                                           L::mask_not(L::lt(s.attempt_steps, V(Tol::gershgorin_steps))));
        s.switched = L::mask_or(s.switched, L::mask_and(stepping, switch_now));
      }
      if (L::any(finished)) {
        // Unless the step is small only because H is singular
        // (CayleyStep::singular): that lane is stalled like one that cannot
        // step at all. (With a step limit, stalled and finished lanes both
        // stop: no check needed.)
        const Mask singular = L::mask_and(finished, step.template singular<L>(Tol::converged));
        stalled = L::mask_or(stalled, singular);
        finished = L::mask_and(finished, L::mask_not(singular));
        // The maximum, or a saddle (S of this last tiny step is symmetric
        // up to it)? Saddles are escaped by a half-turn and iterate again.
        const Mask at_maximum = L::mask_and(finished, is_maximum<L>(S, Tol::max_check_slack));
        const Mask saddle = L::mask_and(finished, L::mask_not(at_maximum));
        const Mask escape = L::mask_and(saddle, L::lt(s.escapes, V(Tol::max_escapes)));
        s.fallback = L::mask_or(s.fallback, L::mask_and(saddle, L::mask_not(escape)));
        if (L::any(escape)) {
          s.R = select<L>(escape, times(s.R, saddle_escape_rotation<L>(transpose_times(s.R, s.A))), s.R);
          s.large_step = L::mask_or(s.large_step, escape);
          s.escapes = s.escapes + L::select(escape, one, zero);
          s.attempt_steps = L::select(escape, zero, s.attempt_steps);
          s.switched = L::mask_and(s.switched, L::mask_not(escape));
          finished = L::mask_and(finished, L::mask_not(escape));
        }
      }
      // Not converged within the cap, or stalled: the fallback decides.
      const Mask exhausted =
          L::mask_and(L::mask_and(stepping, L::mask_not(finished)), L::mask_not(L::lt(s.attempt_steps, cap)));
      s.fallback = L::mask_or(s.fallback, L::mask_or(exhausted, stalled));
      finished = L::mask_or(finished, L::mask_or(exhausted, stalled));
    } else {
      finished = L::mask_or(finished, L::mask_or(stalled, L::mask_not(L::lt(s.attempt_steps, cap))));
    }
    s.running = L::mask_and(s.running, L::mask_not(finished));
  }
}

// advance(s, options, 1, estimate) for max_iter = 1 (the paper's one-step warm start):
// the same operations on the running lanes, so the same results bit for bit,
// without the bookkeeping of the convergence decision. Inline, so that the
// block's state stays in registers from begin_fit to finish.
template <typename L>
TORCHROT_INLINE void advance_one_step(LaneState<L>& s, Variant variant, const typename L::V* estimate = nullptr) {
  using V = typename L::V;
  const Mat3<V> S = transpose_times(s.R, s.A);
  const CayleyStep<V> step = cayley_step(S, estimate != nullptr ? *estimate : objective_estimate<L>(S, variant));
  take_step<L>(s, step, can_take<L>(step));
  s.running = L::all_false();
}

// begin_fit and advance_one_step for a warm start (the paper's one-step
// update), with M and init read from memory where they are used instead of
// held in registers: m(k) and r(k) load entry k (row-major) of the block's M
// and init (memory that nothing writes while this runs), and the result is
// written to q (entry k at q + k * L::width). The same operations as those two, so the
// same results bit for bit; then calls done(state), in each of its two paths,
// so that the state is built after the reads (passed out by reference or
// returned, GCC kept the whole state in memory or copied it).
//
// Why: the step (Algorithm 2, then R + R K for the Cayley map of Eq. 10)
// needs R0 at its end and M's entries only to form S = R0^T A, yet from the
// loads on both stayed in registers, 18 vectors besides the step's own; with
// 16 registers (L::stream_one_step) GCC spilled values of every stage. Here M
// is read once for its largest entry, S is built up over the rows of R0 and A
// = M / max (transpose_times_by_rows: one row of each at a time besides S's
// nine partial sums), and R0 is read again for the update, a row at a time
// (with the 9 entries of K = Q - I) into q. Blocks with lanes that begin_fit treats
// apart (a largest entry outside the normal range, M = 0 included, or a warm
// start to clean up; rare) take the general path.
// `store`: store(k, v) writes entry k of the block's result where it goes
// (memory that aliases M or init exactly, if at all: each row of R0 is read
// before that row is written; q itself, where the caller moves the result on
// from there). Where every lane takes the step and finish would change
// nothing (none took a large step), the rows go there instead of to q, and
// done(state, true) is called with state.R unset; else done(state, false).
template <typename L, typename LoadM, typename LoadR, typename Store, typename Done>
TORCHROT_INLINE void one_step_warm_from_memory(LoadM m, LoadR r, typename L::Scalar* q, Store store,
                                               bool init_known_clean, Variant variant, Done done) {
  using T = typename L::Scalar;
  using V = typename L::V;
  using Mask = typename L::Mask;
  using Tol = Tolerances<T>;
  const auto load = [](auto entry) {
    Mat3<V> X;
    for (int k = 0; k < 9; ++k) X.a[k] = entry(k);
    return X;
  };
  const V max_abs = max_abs_entry<L>(load(m));
  Mask finite = L::is_finite(max_abs);
  // unit_scale's lanes apart (zero included), and clean_warm_start's.
  const OutsideNormalRange<L> range = outside_normal_range<L>(max_abs);
  Mask apart = L::mask_or(range.below_normal, range.above_reciprocal);
  Mask bad_init = L::all_false();
  if (!init_known_clean) {
    const WarmStartCheck<L> check = check_warm_start<L>(load(r));
    finite = L::mask_and(finite, check.finite);
    bad_init = check.bad;
    apart = L::mask_or(apart, needs_cleaning<L>(check, Tol::init_clean));
  }
  if (L::any(apart)) {
    const Mat3<typename L::V> R0 = load(r);
    LaneState<L> s = begin_fit<L>(load(m), &R0, init_known_clean, nullptr);
    advance_one_step<L>(s, variant);
    done(s, false);
    return;
  }
  const V inv = V(1) / max_abs;  // unit_scale without lanes apart
  TORCHROT_MEMORY_BARRIER();     // M and R0 are read again below, row by row
  const Mat3<V> S = transpose_times_by_rows<V>([&](int k, V a[3], V b[3]) {
    for (int c = 0; c < 3; ++c) {
      a[c] = r(3 * k + c);        // R0(k, c): row k of R0
      b[c] = m(3 * k + c) * inv;  // A(k, c)
    }
  });
  const CayleyStep<V> step = cayley_step(S, objective_estimate<L>(S, variant));
  // take_step, with R0 read again for the update and R0 Q written over it row
  // by row (a row of R0 and of the result at a time besides Q - I).
  const Mask running = L::mask_and(finite, L::mask_not(bad_init));
  const Mask stepping = L::mask_and(running, can_take<L>(step));
  const Mat3<V> K = cayley_increment(step);
  // Every lane takes the step, and finish would change nothing (it cleans up
  // large steps, NaNs the lanes not running): the rows are written as
  // rotated, with no select.
  const bool as_computed = L::all(stepping) && !L::any(L::mask_not(step.template smaller_than<L>(Tol::large_step)));
  // kSelect: the lanes not stepping keep their row of R0.
  const auto write_rows = [&](auto write, auto kSelect) TORCHROT_LAMBDA_INLINE {
    for (int i = 0; i < 3; ++i) {
      V row[3], rotated[3];
      for (int c = 0; c < 3; ++c) row[c] = r(3 * i + c);
      rotate_row_by(row, K, rotated);
      for (int c = 0; c < 3; ++c) write(3 * i + c, kSelect ? L::select(stepping, rotated[c], row[c]) : rotated[c]);
    }
  };
  TORCHROT_MEMORY_BARRIER();
  if (as_computed) {
    write_rows(store, std::false_type{});
  } else {
    write_rows([&](int k, V x) TORCHROT_LAMBDA_INLINE { L::store(x, q + k * L::width); }, std::true_type{});
  }
  TORCHROT_MEMORY_BARRIER();
  // begin_fit's state for these lanes (no M = 0: those are apart), set after
  // the barriers (which would otherwise keep it in memory), after the step.
  // s.A, read only by fallback lanes, which one step never makes, is left
  // unset.
  LaneState<L> s;
  s.escapes = V(0);
  s.switched = s.fallback = s.running = L::all_false();
  if (as_computed) {
    // Every lane ran and took a step that was not large: count_step's
    // counts, known here (no mask to read, no bad warm start to count).
    s.iterations = s.attempt_steps = V(1);
    s.large_step = s.bad_init = s.non_finite = L::all_false();
    done(s, true);
    return;
  }
  for (int k = 0; k < 9; ++k) s.R.a[k] = L::load(q + k * L::width);
  s.iterations = s.attempt_steps = V(0);
  s.large_step = L::all_false();
  s.bad_init = bad_init;
  s.non_finite = L::mask_not(finite);
  count_step<L>(s, step, stepping);
  done(s, false);
}

// The fallback lanes of R, solved exactly (rare: out of line).
template <typename L>
[[gnu::noinline]] void solve_fallback_lanes(const LaneState<L>& s, Mat3<typename L::V>& R) {
  for (int i = 0; i < L::width; ++i) {
    if (L::lane_set(s.fallback, i)) insert_lane<L>(R, i, horn_rotation(extract_lane<L>(s.A, i)));
  }
}

// The result of every lane that is not running. One Newton-Schulz step
// squares the orthonormality error that the product of Cayley factors
// accumulates (each step's rounding adds to it), on the lanes that need it:
// those that took a large step or a saddle escape, or more than
// Tolerances::steps_without_clean_up steps. A small step adds at most ~1.4
// eps to its warm start's deviation, which is below Tolerances::init_clean
// (begin_fit cleans it up to there otherwise), so the results of one or two
// of them (the one-step update, converged fits from warm starts) are
// rotations at working precision as they are; one fed back after its
// deviation drifted past that threshold is cleaned before its next step
// (limits::kInitCleanEps; tests/test_warm_start_precision.py chains 1,000
// one-step updates). Fallback lanes are solved exactly, unusable lanes are NaN.
// kFallback: whether s may hold fallback lanes (a one-step fit's cannot: only
// converged mode makes them); without, s is not passed out of line, which
// kept the whole state in memory.
template <typename L, bool kFallback = true>
TORCHROT_INLINE Mat3<typename L::V> finish(const LaneState<L>& s) {
  using T = typename L::Scalar;
  using V = typename L::V;
  const typename L::Mask clean_up =
      L::mask_or(s.large_step, L::mask_not(L::lt(s.iterations, V(T(Tolerances<T>::steps_without_clean_up + 1)))));
  Mat3<V> R = s.R;
  if (L::all(clean_up)) {
    R = reorthonormalize(R);
  } else if (L::any(clean_up)) {
    R = select<L>(clean_up, reorthonormalize(R), R);
  }
  if constexpr (kFallback) {
    if (L::any(s.fallback)) solve_fallback_lanes<L>(s, R);
  }
  const typename L::Mask nan_lanes = L::mask_or(s.non_finite, s.bad_init);
  if (L::any(nan_lanes)) {
    const V nan(std::numeric_limits<T>::quiet_NaN());
    for (int k = 0; k < 9; ++k) R.a[k] = L::select(nan_lanes, nan, R.a[k]);
  }
  return R;
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace kernel
}  // namespace torchrot
