// Kernel object: the scalar path: one matrix at a time in plain C++ (the reference the SIMD kernels are tested
// against). Built with its own flags and CPU_CAPABILITY (setup.py); everything it defines lives in an anonymous
// namespace except the table getter below.
#include "kernel_object.h"

namespace torchrot {
namespace cpu {

const KernelTable& scalar_kernels() {
  static const KernelTable table = make_kernel_table<kernel::ScalarLanes>("scalar");
  return table;
}

}  // namespace cpu
}  // namespace torchrot
