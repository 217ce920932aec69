// Transparent huge pages for the kernels' fresh outputs.
//
// A result the operator allocates is written once, densely, by the kernel right
// after: on 4 KiB pages, its first touch takes one page fault per 4 KiB, which
// for a large result can cost more than a copy_ of M, and made a one-step
// update with a new output markedly slower than with out=
// (benchmarks/lab_notes.md). Asking the kernel for transparent huge pages on
// the part of the buffer that spans whole 2 MiB pages takes one fault per 2 MiB
// instead; the same advice as PyTorch's opt-in THP_MEM_ALLOC_ENABLE, which
// gives it to every large allocation. Here it is given only to buffers the
// kernel is about to fill, so no huge page is left partly unused. It changes no
// value: where the system does not take the advice (THP disabled, other
// kernels, other allocators' memory) nothing changes at all.
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace torchrot {
namespace cpu {

// The transparent huge page size on x86-64 and on aarch64 with 4 KiB pages.
constexpr uintptr_t kHugePageBytes = uintptr_t{2} << 20;

// Advises huge pages for the whole 2 MiB pages inside `fresh`'s storage, if
// it is a CPU tensor of at least two of them (so that it contains one), and
// returns it. Best effort: a failing madvise is ignored.
inline at::Tensor advise_huge_pages(at::Tensor fresh) {
#if defined(__linux__) && defined(MADV_HUGEPAGE)
  if (!fresh.is_cpu() || fresh.storage().nbytes() < 2 * kHugePageBytes) return fresh;
  const auto begin = reinterpret_cast<uintptr_t>(fresh.storage().data());
  const uintptr_t end = begin + fresh.storage().nbytes();
  const uintptr_t first = (begin + kHugePageBytes - 1) & ~(kHugePageBytes - 1);
  const uintptr_t last = end & ~(kHugePageBytes - 1);
  if (last > first) (void)madvise(reinterpret_cast<void*>(first), last - first, MADV_HUGEPAGE);
#endif
  return fresh;
}

}  // namespace cpu
}  // namespace torchrot
