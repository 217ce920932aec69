// Flush-to-zero for the fitting kernels: while a FlushToZero lives, a
// floating-point result below the smallest normal number (1.2e-38 in float32,
// 2.2e-308 in float64) is stored as 0 (x86-64: MXCSR's FTZ bit, set on
// construction and restored on destruction, in the thread that runs the
// block range). Why: matrices recorded from solvers (ARAP covariances with
// entries 1e-21 of the largest, warm starts with entries of 1e-33) make
// subnormal products inside the Cayley step, and x86 cores compute each of
// those through a microcode assist: on the paper-scale ARAP recording the
// one-step update took 27 ns per matrix instead of 9 (float32, 1 thread,
// benchmarks/authors_kernel.py). Such values are far below eps^2 of the
// normalised matrix (the kernels scale M to max |entry| 1 first), so flushing
// them changes a result in its last bits at most, and only for inputs whose
// own entries span more than about 1e19 (float32). Inputs are not flushed (DAZ stays off): a
// subnormal entry of M or init is read as it is and scaled up to a normal
// number. Every kernel of a process (scalar and SIMD) runs in the same mode,
// so their results stay bit-identical; other architectures keep their
// default mode (aarch64's FZ would flush inputs too).
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
