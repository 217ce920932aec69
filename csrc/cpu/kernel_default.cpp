// Kernel object: the portable baseline, no instruction-set flags: at::vec::Vectorized's generic
// implementation on x86-64, ATen's NEON one on aarch64 (the only vector object there).
// Built with its own flags and CPU_CAPABILITY (setup.py); everything it
// defines lives in an anonymous namespace except the table getter below.
#include "kernel_object.h"

namespace torchrot {
namespace cpu {

const KernelTable& default_kernels() {
  static const KernelTable table = make_kernel_table<kernel::VectorLanes>("default");
  return table;
}

}  // namespace cpu
}  // namespace torchrot
