// Flush-to-zero for the fitting kernels: while a FlushToZero lives, a
// floating-point result below the smallest normal number T_min (1.2e-38 in
// float32, 2.2e-308 in float64) is stored as 0 (x86-64: MXCSR's FTZ bit, set
// on construction and restored on destruction, in the thread that runs the
// block range).
//
// Why: matrices recorded from solvers (ARAP covariances with entries 1e-21 of
// the largest, warm starts with entries of 1e-33, steps of 1e-15 near
// convergence) make subnormal products inside a Cayley step, and x86 cores
// may compute each through a microcode assist: on one host that made the
// one-step update on the paper-scale ARAP recording several times slower
// (benchmarks/authors_kernel.py; on another of the same kind the assists cost
// little: benchmarks/README.md, benchmarks/lab_notes.md).
//
// Why it is safe: the fit works on M scaled to max |entry| 1 (unit_scale.h,
// computed so that no entry it keeps is flushed) and on rotations, so every
// quantity of a step is at most of order 1 and is computed to a few eps of
// that order; a flushed result changes one by less than T_min, far below its
// rounding. Two places divide by a quantity that may be tiny, and are written
// so that flushing cannot be scaled up by the division: the Cayley map
// (cayley_increment: 2 / (d^2 + w.w) multiplies a single component before
// any product of two, and can_take refuses steps with d^2 + w.w below
// T_min / eps^2) and the exact scaling (unit_scale: M * 1 would flush a
// subnormal entry that M / max keeps). Others divide by quantities of order 1
// (saddle escapes, the Horn fallback, which also skips a flushed pivot) or
// only move a bound where a flushed quantity leaves them (maximal_objective).
// Every x86 kernel (scalar included) runs in this mode, so their results
// stay bit-identical; inputs are not flushed (DAZ stays off: a subnormal
// entry of M or init is read as it is); other architectures keep the
// caller's mode (aarch64's FZ would flush inputs too).
#pragma once

#if defined(__x86_64__) || defined(_M_X64)
#include <xmmintrin.h>
#define TORCHROT_FLUSH_TO_ZERO 1
#else
#define TORCHROT_FLUSH_TO_ZERO 0
#endif

namespace torchrot {
namespace cpu {
inline namespace CPU_CAPABILITY {
namespace {

class FlushToZero {
 public:
#if TORCHROT_FLUSH_TO_ZERO
  FlushToZero() : saved_(_mm_getcsr()) { _mm_setcsr(saved_ | _MM_FLUSH_ZERO_ON); }
  ~FlushToZero() { _mm_setcsr(saved_); }
#else
  FlushToZero() = default;
#endif
  FlushToZero(const FlushToZero&) = delete;
  FlushToZero& operator=(const FlushToZero&) = delete;

 private:
#if TORCHROT_FLUSH_TO_ZERO
  unsigned int saved_;
#endif
};

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace cpu
}  // namespace torchrot
