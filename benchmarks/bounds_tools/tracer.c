/* Exact dynamic instruction counts of one function call, by ptrace single-stepping.
 *
 * Used by benchmarks/bounds.py for the AVX-512 kernels: valgrind cannot run
 * AVX-512 code and perf has no hardware counters in the virtual machine the
 * benchmarks run on, but the CPU's trap flag works anywhere. ~1e4-1e5
 * instructions per second, so only small batches are stepped.
 *
 * Usage: TRACER_COMMAND=FILE tracer PROGRAM ARGS...
 * Runs PROGRAM under ptrace. The program arms a measurement by writing
 * "ENTRY LO HI BASE OUTFILE" (hex addresses, then a path) to FILE and raising
 * SIGUSR1 on itself (the tracer takes the signal; it is never delivered). The
 * next call of ENTRY is then stepped from its first instruction to its return,
 * counting every instruction executed by the calling thread (callees, libc and
 * the PLT included; kernel-mode work such as page faults is not an
 * instruction of the program). OUTFILE gets "total N", "outside N" (outside
 * LO <= rip < HI) and one "OFFSET COUNT" line per executed address in range,
 * OFFSET = rip - BASE (the offset objdump and addr2line use for a shared
 * library). A rep-prefixed string instruction counts once per iteration, as
 * the trap flag traps after each. */
#include <errno.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ptrace.h>
#include <sys/user.h>
#include <sys/wait.h>
#include <unistd.h>

static void die(const char* what) { perror(what); exit(2); }

int main(int argc, char** argv) {
  if (argc < 2) { fprintf(stderr, "usage: tracer PROGRAM ARGS...\n"); return 2; }
  const char* command_path = getenv("TRACER_COMMAND");
  if (!command_path) { fprintf(stderr, "TRACER_COMMAND not set\n"); return 2; }
  pid_t pid = fork();
  if (pid == 0) {
    ptrace(PTRACE_TRACEME, 0, 0, 0);
    execvp(argv[1], argv + 1);
    _exit(127);
  }
  int status;
  waitpid(pid, &status, 0);  /* stop at exec */
  ptrace(PTRACE_SETOPTIONS, pid, 0, PTRACE_O_EXITKILL);
  int deliver = 0;
  for (;;) {
    if (ptrace(PTRACE_CONT, pid, 0, deliver) < 0) die("cont");
    deliver = 0;
    if (waitpid(pid, &status, 0) < 0) die("waitpid");
    if (WIFEXITED(status)) return WEXITSTATUS(status);
    if (WIFSIGNALED(status)) return 128 + WTERMSIG(status);
    int sig = WSTOPSIG(status);
    if (sig != SIGUSR1) { deliver = sig; continue; }
    /* Arm: read the command, put an int3 on the entry. */
    unsigned long entry, lo, hi, base;
    char out_path[4096];
    FILE* cmd = fopen(command_path, "r");
    if (!cmd || fscanf(cmd, "%lx %lx %lx %lx %4095s", &entry, &lo, &hi, &base, out_path) != 5) die("command");
    fclose(cmd);
    errno = 0;
    long word = ptrace(PTRACE_PEEKTEXT, pid, entry, 0);
    if (errno) die("peek");
    if (ptrace(PTRACE_POKETEXT, pid, entry, (word & ~0xffL) | 0xcc) < 0) die("poke");
    /* Run to the breakpoint (other signals are passed on). */
    struct user_regs_struct regs;
    for (;;) {
      if (ptrace(PTRACE_CONT, pid, 0, deliver) < 0) die("cont");
      deliver = 0;
      if (waitpid(pid, &status, 0) < 0 || !WIFSTOPPED(status)) die("lost the program");
      if (WSTOPSIG(status) != SIGTRAP) { deliver = WSTOPSIG(status); continue; }
      ptrace(PTRACE_GETREGS, pid, 0, &regs);
      if (regs.rip == entry + 1) break;
    }
    ptrace(PTRACE_POKETEXT, pid, entry, word);
    regs.rip = entry;
    ptrace(PTRACE_SETREGS, pid, 0, &regs);
    errno = 0;
    unsigned long ret = (unsigned long)ptrace(PTRACE_PEEKDATA, pid, regs.rsp, 0);
    if (errno) die("peek return");
    unsigned long ret_sp = regs.rsp + 8;
    size_t span = hi - lo;
    uint64_t* hist = calloc(span, sizeof(uint64_t));
    uint64_t total = 0, outside = 0;
    for (;;) {
      if (regs.rip >= lo && regs.rip < hi) hist[regs.rip - lo]++; else outside++;
      total++;
      if (ptrace(PTRACE_SINGLESTEP, pid, 0, deliver) < 0) die("step");
      deliver = 0;
      if (waitpid(pid, &status, 0) < 0 || !WIFSTOPPED(status)) die("lost the program while stepping");
      if (WSTOPSIG(status) != SIGTRAP) deliver = WSTOPSIG(status);
      ptrace(PTRACE_GETREGS, pid, 0, &regs);
      if (regs.rip == ret && regs.rsp == ret_sp) break;
    }
    FILE* out = fopen(out_path, "w");
    if (!out) die("output");
    fprintf(out, "total %llu\noutside %llu\n", (unsigned long long)total, (unsigned long long)outside);
    for (size_t i = 0; i < span; ++i)
      if (hist[i]) fprintf(out, "%lx %llu\n", (unsigned long)(lo + i - base), (unsigned long long)hist[i]);
    fclose(out);
    free(hist);
  }
}
