/* Exact dynamic instruction counts of a program's marked regions, by ptrace
 * single-stepping (benchmarks/instruction_counts.py builds and drives it).
 *
 * Why: perf has no hardware counters in the virtual machine the benchmarks run
 * on and valgrind cannot execute AVX-512, but the CPU's trap flag works
 * anywhere. About 1e5 instructions per second, so only small batches are
 * stepped.
 *
 * Usage: instruction_counter PROGRAM ARGS...
 * Runs PROGRAM under ptrace. When the program raises SIGUSR1 on itself, every
 * instruction its main thread executes from then on is counted (libraries,
 * not kernel-mode work such as page faults), until it raises SIGUSR2; the
 * count is then written to the tracer's standard output, one line per region.
 * Neither signal is delivered to the program. Other threads run untraced. A rep-prefixed string
 * instruction counts once per iteration, as the trap flag traps after each.
 *
 * With INSTRUCTION_COUNTER_TRACE=PREFIX in its environment (x86-64 only), the
 * instruction address at each counted stop of region K (0, 1, ...), the next
 * instruction to execute (so the region's instructions but its first, and the
 * one after its last), is also written to PREFIX.K.pcs (native 64-bit
 * integers, in order) and the
 * program's memory map at the region's end to PREFIX.K.maps
 * (benchmarks/instruction_profile.py attributes them to source functions). */
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/ptrace.h>
#include <sys/user.h>
#include <sys/wait.h>
#include <unistd.h>

static void die(const char* what) {
  perror(what);
  exit(2);
}

/* The program's current instruction address (stopped under ptrace). */
static unsigned long long instruction_address(pid_t pid) {
#if defined(__x86_64__)
  struct user_regs_struct regs;
  if (ptrace(PTRACE_GETREGS, pid, 0, &regs) < 0) die("getregs");
  return regs.rip;
#else
  (void)pid;
  fprintf(stderr, "INSTRUCTION_COUNTER_TRACE: x86-64 only\n");
  exit(2);
#endif
}

/* PREFIX.REGION.SUFFIX, opened for writing. */
static FILE* open_trace(const char* prefix, int region, const char* suffix) {
  char path[4096];
  snprintf(path, sizeof path, "%s.%d.%s", prefix, region, suffix);
  FILE* file = fopen(path, "wb");
  if (file == NULL) die(path);
  return file;
}

/* Copies /proc/PID/maps to PREFIX.REGION.maps. */
static void save_maps(pid_t pid, const char* prefix, int region) {
  char path[64], buffer[65536];
  snprintf(path, sizeof path, "/proc/%d/maps", (int)pid);
  FILE* maps = fopen(path, "r");
  if (maps == NULL) die(path);
  FILE* copy = open_trace(prefix, region, "maps");
  size_t n;
  while ((n = fread(buffer, 1, sizeof buffer, maps)) > 0) fwrite(buffer, 1, n, copy);
  fclose(maps);
  fclose(copy);
}

int main(int argc, char** argv) {
  if (argc < 2) {
    fprintf(stderr, "usage: instruction_counter PROGRAM ARGS...\n");
    return 2;
  }
  pid_t pid = fork();
  if (pid < 0) die("fork");
  if (pid == 0) {
    ptrace(PTRACE_TRACEME, 0, 0, 0);
    execvp(argv[1], argv + 1);
    _exit(127);
  }
  int status;
  if (waitpid(pid, &status, 0) < 0) die("waitpid"); /* stopped at exec */
  ptrace(PTRACE_SETOPTIONS, pid, 0, PTRACE_O_EXITKILL);
  const char* trace = getenv("INSTRUCTION_COUNTER_TRACE");
  int region = 0;
  int deliver = 0;
  for (;;) {
    if (ptrace(PTRACE_CONT, pid, 0, deliver) < 0) die("cont");
    deliver = 0;
    if (waitpid(pid, &status, 0) < 0) die("waitpid");
    if (WIFEXITED(status)) return WEXITSTATUS(status);
    if (WIFSIGNALED(status)) return 128 + WTERMSIG(status);
    const int sig = WSTOPSIG(status);
    if (sig != SIGUSR1) {
      /* SIGTRAP here is the stop after an exec (e.g. of a launcher script's
         interpreter): not the program's own. */
      deliver = sig == SIGUSR2 || sig == SIGTRAP ? 0 : sig;
      continue;
    }
    /* Step until SIGUSR2 (signals other than the trap are passed on). */
    unsigned long long count = 0;
    FILE* pcs = trace != NULL ? open_trace(trace, region, "pcs") : NULL;
    for (;;) {
      if (ptrace(PTRACE_SINGLESTEP, pid, 0, deliver) < 0) die("singlestep");
      deliver = 0;
      if (waitpid(pid, &status, 0) < 0) die("waitpid");
      if (!WIFSTOPPED(status)) die("the program ended inside a region");
      const int s = WSTOPSIG(status);
      if (s == SIGTRAP) {
        ++count;
        if (pcs != NULL) {
          const unsigned long long pc = instruction_address(pid);
          fwrite(&pc, sizeof pc, 1, pcs);
        }
      } else if (s == SIGUSR2) {
        break;
      } else {
        deliver = s;
      }
    }
    if (pcs != NULL) {
      fclose(pcs);
      save_maps(pid, trace, region);
    }
    ++region;
    printf("%llu\n", count);
    fflush(stdout);
  }
}
