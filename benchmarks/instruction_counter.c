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
 * instruction counts once per iteration, as the trap flag traps after each. */
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/ptrace.h>
#include <sys/wait.h>
#include <unistd.h>

static void die(const char* what) {
  perror(what);
  exit(2);
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
    for (;;) {
      if (ptrace(PTRACE_SINGLESTEP, pid, 0, deliver) < 0) die("singlestep");
      deliver = 0;
      if (waitpid(pid, &status, 0) < 0) die("waitpid");
      if (!WIFSTOPPED(status)) die("the program ended inside a region");
      const int s = WSTOPSIG(status);
      if (s == SIGTRAP) {
        ++count;
      } else if (s == SIGUSR2) {
        break;
      } else {
        deliver = s;
      }
    }
    printf("%llu\n", count);
    fflush(stdout);
  }
}
