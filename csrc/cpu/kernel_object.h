// What each kernel object (kernel_*.cpp) instantiates: the fit and the
// derivative kernels for float and double over one lane type, compiled with
// that object's instruction-set flags, gathered into its KernelTable.
#pragma once

#include "fit_rotation_kernel.h"
#include "kernel_table.h"
#include "rotation_gradient_kernel.h"

namespace torchrot {
namespace cpu {
inline namespace CPU_CAPABILITY {
namespace {

// TangentLanes: the lanes of the derivative kernel, which may differ from the
// fit's (kernel::PairedVectorLanes in the AVX2 and AVX-512 objects).
template <template <typename> class Lanes, template <typename> class TangentLanes = Lanes>
KernelTable make_kernel_table(const char* name) {
  static_assert(TangentLanes<float>::fused_multiply_add == Lanes<float>::fused_multiply_add);
  return KernelTable{name,
                     Lanes<float>::width,
                     Lanes<double>::width,
                     Lanes<float>::fused_multiply_add && Lanes<double>::fused_multiply_add,
                     &fit_batch<Lanes<float>>,
                     &fit_batch<Lanes<double>>,
                     &tangent_batch<TangentLanes<float>>,
                     &tangent_batch<TangentLanes<double>>,
                     &count_bad_warm_starts<Lanes<float>>,
                     &count_bad_warm_starts<Lanes<double>>};
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace cpu
}  // namespace torchrot
