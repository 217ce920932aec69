// The batched derivative kernel, included by each kernel_*.cpp and compiled
// with that file's instruction-set flags: out[i] = R[i] [u_i]x, the damped
// solution of the optimality condition's linearisation
// (kernel/rotation_gradient.h) for X[i] = dL/dR (backward) or dM (forward
// mode). One pass over the batch in SIMD blocks (paired blocks in the AVX
// objects: kernel_object.h). Compute bound, not memory bound, where the batch
// is in cache: its arithmetic takes several times as long as reading and
// writing a matrix's 144 bytes (benchmarks/lab_notes.md).
#pragma once

#include <algorithm>

#include "../kernel/rotation_gradient.h"
#include "block_io.h"
#include "kernel_table.h"

namespace torchrot {
namespace cpu {
inline namespace CPU_CAPABILITY {
namespace {

constexpr int64_t kTangentGrainSize = 4096;

template <typename L, BlockPath kPath>
void tangent_range(const TangentArgs<typename L::Scalar>& args, int64_t begin, int64_t end) {
  for (int64_t first = begin; first < end; first += L::width) {
    const int count = static_cast<int>(std::min<int64_t>(L::width, end - first));
    // All inputs are in registers before `out` is written: out may alias X.
    const Mat3<typename L::V> X = load_block<L, kPath>(args.X, args.x_layout, first, count);
    const Mat3<typename L::V> R = load_block<L, kPath>(args.R, args.r_layout, first, count);
    const Mat3<typename L::V> M = load_block<L, kPath>(args.M, args.m_layout, first, count);
    store_block<L, kPath>(kernel::rotation_tangent<L>(X, R, M, args.damping), args.out, args.out_layout, first, count);
  }
}

template <typename L>
void tangent_batch(const TangentArgs<typename L::Scalar>& args) {
  const BlockPath path = full_block_path(L::width, {&args.x_layout, &args.r_layout, &args.m_layout, &args.out_layout});
  parallel_blocks(args.n, L::width, kTangentGrainSize, [&](int64_t begin, int64_t end) {
    run_block_paths<L>(path, begin, end,
                       [&](auto block_path, int64_t b, int64_t e) { tangent_range<L, block_path.value>(args, b, e); });
  });
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace cpu
}  // namespace torchrot
