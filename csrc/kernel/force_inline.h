// TORCHROT_INLINE: `inline`, and always inlined where the compiler supports it.
//
// For the small functions every Cayley step and block runs (3x3 products, the
// step, the checks, block loads and stores, begin/finish). GCC otherwise
// decides per translation unit from size budgets, so code added anywhere in a
// kernel object could move one of them out of line, its 3x3 matrices then
// passed through memory: adding the one-step path did that to transpose_times,
// times and begin_fit and made every AVX2 fit slower (benchmarks/lab_notes.md).
#pragma once

#if defined(__GNUC__) || defined(__clang__)
#define TORCHROT_INLINE inline __attribute__((always_inline))
#define TORCHROT_LAMBDA_INLINE __attribute__((always_inline))  // after a lambda's parameters
#else
#define TORCHROT_INLINE inline
#define TORCHROT_LAMBDA_INLINE
#endif

// A compiler barrier: memory may have changed, so a load after it is not
// merged with one before (no instruction is emitted). The one-step kernel
// (kernel::one_step_warm_from_memory) uses it to read its operands again where
// it needs them instead of holding them in registers all along.
#if defined(__GNUC__) || defined(__clang__)
#define TORCHROT_MEMORY_BARRIER() asm volatile("" ::: "memory")
#else
#define TORCHROT_MEMORY_BARRIER() ((void)0)
#endif
