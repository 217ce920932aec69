// Kernel object: AVX2 + FMA: 8 float / 4 double matrices per block.
// Built with its own flags and CPU_CAPABILITY (setup.py); everything it
// defines lives in an anonymous namespace except the table getter below.
#include "kernel_object.h"

#if !TORCHROT_X86_64_KERNELS
#error "an x86-64 kernel object: setup.py compiles it for x86-64 targets only"
#endif

namespace torchrot {
namespace cpu {

const KernelTable& avx2_kernels() {
  static const KernelTable table = make_kernel_table<kernel::VectorLanes, kernel::PairedVectorLanes>("avx2");
  return table;
}

}  // namespace cpu
}  // namespace torchrot
