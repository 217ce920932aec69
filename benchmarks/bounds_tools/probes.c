/* Helpers that benchmarks/bounds.py loads with ctypes.
 *
 * bounds_cg_instrument / bounds_cg_zero / bounds_cg_dump: callgrind client
 * requests. Under `valgrind --tool=callgrind --instr-atstart=no` the first
 * switches instrumentation on (once: importing torch uninstrumented is ~5x
 * faster), the second zeroes the counters before a measured call, the third
 * writes the instructions counted since to a dump file named by `label`.
 * Outside valgrind they do nothing.
 *
 * bounds_multiply_chain: `iterations` x 8 dependent 64-bit integer
 * multiplications. Each waits for the previous one, and imul r64 has a
 * latency of 3 cycles on every x86-64 core of the last decade (Intel since
 * Sandy Bridge, AMD Zen), so timing it in thread CPU time gives the clock
 * frequency the kernels run at (turbo included), which the cpufreq files of
 * a virtual machine do not tell. (A chain of add-immediates would not do:
 * recent Intel cores fold those at rename, several per cycle.) */
#include <valgrind/callgrind.h>

void bounds_cg_instrument(void) { CALLGRIND_START_INSTRUMENTATION; }

void bounds_cg_zero(void) { CALLGRIND_ZERO_STATS; }

void bounds_cg_dump(const char* label) { CALLGRIND_DUMP_STATS_AT(label); }

long bounds_multiply_chain(long iterations) {
  long x = 1, factor = 3;
  for (long i = 0; i < iterations; ++i) {
    __asm__ volatile(
        "imul %1, %0\n\timul %1, %0\n\timul %1, %0\n\timul %1, %0\n\t"
        "imul %1, %0\n\timul %1, %0\n\timul %1, %0\n\timul %1, %0"
        : "+r"(x)
        : "r"(factor));
  }
  return x;
}
