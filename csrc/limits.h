// Every limit, default and tolerance of torchrot, defined once. The kernels
// (kernel/fit_rotation_impl.h), the operator checks and schemas
// (ops/checks.cpp, ops/schemas.h) read them here; Python reads them through
// torchrot._C.constants() (module.cpp), so the fake kernels, the argument
// checks and the pure-PyTorch path (torchrot/_constants.py,
// torchrot/reference.py) cannot drift from the kernel.
// Nothing here depends on the instruction set.
#pragma once

#include <cstdint>

// Default damping of the derivative, as a literal so that the operator
// schemas (ops/schemas.h) can spell it: lambda = gradient_eps |M|_F (see
// kernel/rotation_gradient.h).
#define TORCHROT_DEFAULT_GRADIENT_EPS 1e-6

namespace torchrot {
namespace limits {

constexpr double kDefaultGradientEps = TORCHROT_DEFAULT_GRADIENT_EPS;

// Largest damping accepted: beyond it the derivative is ~0 anyway, and the
// kernel's eps^4 terms would overflow float (NaN gradients from 1e10 on).
constexpr double kMaxGradientEps = 1e3;

// Largest step count accepted: more steps never help (max_iter=None converges
// with a guaranteed fallback), and on flat problems (rank-1 M) a lane can step
// without converging until its cap, which made huge values hang.
constexpr int64_t kMaxIter = 1000;

// A warm start is accepted when |R^T R - I|_F < kInitTolerance and det R > 0,
// whatever the compute dtype: a rotation rounded to bfloat16 (unit roundoff
// u = 2^-8) deviates by at most ~2 sqrt(3) u = 1.4e-2 (measured on 1e6 random
// rotations: 9.3e-3; float16: 1.1e-3, float32: 1.4e-7), so rotations from any
// floating dtype are accepted, cast up or down; a matrix further off is not a
// rotation at any precision torch offers.
constexpr double kInitTolerance = 5e-2;

// Below this deviation (in units of the compute dtype's eps) a warm start is
// used as it is; above it (a rotation of lower precision: fitted in float32
// and fed to a float64 fit, rounded to float16 or bfloat16, or a result fed
// back whose deviation has drifted) it first takes Newton-Schulz steps until
// below it (at most kInitCleanSteps, each taking a deviation d to ~(3/4)
// d^2: 5e-2 -> 1.9e-3 -> 2.7e-6 -> 5.5e-12 -> 2e-23). It must be at the
// compute precision: Cayley factors are orthogonal, so the iteration keeps
// R's deviation, and its fixed point makes R^T M symmetric for that R, which
// moves the converged rotation by about the deviation times M's conditioning
// (float32 rotations used as float64 warm starts below a former threshold of
// 1e-7 gave errors up to 1.5e-6, against 2e-13 from a cold start). And it
// bounds the drift of results fed back one step at a time, which are not
// cleaned up themselves (kLargeStep): each such step adds at most
// ~1.4 eps (measured, float32), so a chain of them stays within 5 + 1.4 eps
// of orthonormality (plus an eps between the computed and the true
// deviation), below the 1e-6 = 8.4 eps of float32's accuracy criterion.
// 5 eps is above the computed deviation of a cleaned-up rotation (at most
// 3.3 eps, measured on 20,000 fits per dtype).
constexpr double kInitCleanEps = 5;
// A result is cleaned up with a Newton-Schulz step only where it took a
// large step, tan^2(theta / 2) >= kLargeStep (theta ~ 28 degrees; a saddle
// escape counts as one), or more than kStepsWithoutCleanUp steps: there Q's
// rounding adds up to ~8 eps to R's deviation (measured), below it at most
// ~1.4 (float32; ~2.3 float64) a step, which the next call's warm-start
// threshold (kInitCleanEps) absorbs when the result is fed back. So the
// one-step update and converged fits from warm starts, which take one or two
// small steps, skip it.
constexpr double kLargeStep = 0.0625;
constexpr int kStepsWithoutCleanUp = 2;
constexpr int kInitCleanSteps = 4;

// A tiny step is the last only if undamped: its damping c - tr S is at most
// this times |tr S| (sqrt(eps) of the compute dtype, see kernel::Tolerances).
constexpr double kUndampedFloat = 3.4526698e-4;
constexpr double kUndampedDouble = 1.4901161193847656e-8;

// Laguerre steps at most for the maximal objective that a cold start's first
// Cayley step takes as its estimate (kernel/maximal_objective.h). Measured
// per lane: uniform and Gaussian M need 2-6 (float32) and 3-7 (float64);
// only near a double root, where convergence is linear, do more run.
constexpr int kObjectiveLaguerreSteps = 16;

// Converged mode (max_iter=None), see kernel::Tolerances: Cayley steps per
// start or saddle escape before the fallback decides, saddle escapes allowed,
// steps the Gershgorin estimate (Eq. 28) is used for before the conservative
// one takes over, the step size (tan^2(theta/2)) below which it takes over
// early, and the slack of the second-order maximum check in units of eps.
constexpr int kConvergedCap = 12;
constexpr int kMaxEscapes = 2;
constexpr int kGershgorinSteps = 2;
constexpr double kEstimateSwitch = 1e-4;
constexpr double kMaxCheckSlackEps = 4;

}  // namespace limits
}  // namespace torchrot
