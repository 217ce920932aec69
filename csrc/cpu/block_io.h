// Moving blocks of L::width matrices between memory (any element strides)
// and structure-of-arrays registers (entry k of every matrix of the block in
// one vector): in-register transposition for full contiguous blocks, plain
// vector loads and stores for full blocks already in structure-of-arrays
// layout (matrix index stride 1, e.g. a permuted (3, 3, N) tensor), a gather
// through a small buffer otherwise. Shared by the batched kernels.
#pragma once

#include <algorithm>
#include <cstdint>

#include "../kernel/force_inline.h"
#include "../kernel/lanes.h"
#include "soa_transpose.h"

namespace torchrot {
namespace cpu {
inline namespace CPU_CAPABILITY {
namespace {

using kernel::Mat3;

// Entry (r, c) of matrix i, for arbitrary or for contiguous (9, 3, 1) strides.
template <bool kContiguous>
inline int64_t offset(const int64_t stride[3], int64_t i, int k) {
  if (kContiguous) return 9 * i + k;
  return i * stride[0] + (k / 3) * stride[1] + (k % 3) * stride[2];
}

// Whether a full block at these strides is in structure-of-arrays layout:
// entry k of W consecutive matrices is W consecutive values.
inline bool is_soa_batch(const int64_t stride[3]) { return stride[0] == 1; }

// Blocks ahead that the SoA paths prefetch each of their nine entry streams
// per tensor: M, init and out make 27 streams, more than the hardware
// prefetchers follow.
constexpr int64_t kSoaPrefetchBlocks = 4;

// Offset of entry k of matrix 0 (the start of entry k's values in SoA layout).
inline int64_t entry_offset(const int64_t stride[3], int k) { return (k / 3) * stride[1] + (k % 3) * stride[2]; }

// load_block and store_block of vector lanes through a buffer, element by
// element: for any strides and for tail blocks. Out of line, so that the
// vector paths of the callers keep their registers (measured: inlined, they
// made the SoA one-step fit 10% slower).
template <typename L, bool kContiguous>
[[gnu::noinline]] Mat3<typename L::V> gather_block(const typename L::Scalar* data, const int64_t stride[3],
                                                  int64_t first, int count) {
  using T = typename L::Scalar;
  alignas(64) T buf[9][L::width];
  for (int j = 0; j < L::width; ++j) {
    for (int k = 0; k < 9; ++k) {
      buf[k][j] = j < count ? data[offset<kContiguous>(stride, first + j, k)] : T(k % 4 == 0 ? 1 : 0);
    }
  }
  Mat3<typename L::V> A;
  for (int k = 0; k < 9; ++k) A.a[k] = L::load(buf[k]);
  return A;
}

template <typename L, bool kContiguous>
[[gnu::noinline]] void scatter_block(const Mat3<typename L::V>& R, typename L::Scalar* data, const int64_t stride[3],
                                     int64_t first, int count) {
  using T = typename L::Scalar;
  alignas(64) T buf[9][L::width];
  for (int k = 0; k < 9; ++k) L::store(R.a[k], buf[k]);
  for (int j = 0; j < count; ++j)
    for (int k = 0; k < 9; ++k) data[offset<kContiguous>(stride, first + j, k)] = buf[k][j];
}

// Gathers `count` matrices starting at `first` into SoA lanes; missing lanes
// of a tail block get the identity, a harmless input.
template <typename L, bool kContiguous>
TORCHROT_INLINE Mat3<typename L::V> load_block(const typename L::Scalar* data, const int64_t stride[3],
                                               int64_t first, int count) {
  Mat3<typename L::V> A;
  if constexpr (kernel::IsPaired<L>::value) {  // two half blocks
    using H = typename L::HalfLanes;
    const Mat3<typename H::V> lo = load_block<H, kContiguous>(data, stride, first, std::min(count, H::width));
    const Mat3<typename H::V> hi =
        load_block<H, kContiguous>(data, stride, first + H::width, std::max(count - H::width, 0));
    for (int k = 0; k < 9; ++k) A.a[k] = {lo.a[k], hi.a[k]};
    return A;
  } else if constexpr (L::width == 1) {  // the scalar path: one matrix, straight
    for (int k = 0; k < 9; ++k) A.a[k] = data[offset<kContiguous>(stride, first, k)];
    return A;
  } else {
    if constexpr (!kContiguous) {
      if (count == L::width && is_soa_batch(stride)) {  // full block, SoA: plain vectors
        for (int k = 0; k < 9; ++k) {
          const typename L::Scalar* entry = data + first + entry_offset(stride, k);
          __builtin_prefetch(entry + kSoaPrefetchBlocks * L::width);
          A.a[k] = L::load(entry);
        }
        return A;
      }
    }
#ifdef TORCHROT_HAVE_SIMD_TRANSPOSE
    if constexpr (kContiguous) {
      if (count == L::width) {  // full contiguous block: in-register transposition
        load_soa(data + 9 * first, A.a);
        return A;
      }
    }
#endif
    return gather_block<L, kContiguous>(data, stride, first, count);
  }
}

template <typename L, bool kContiguous>
TORCHROT_INLINE void store_block(const Mat3<typename L::V>& R, typename L::Scalar* data, const int64_t stride[3],
                                 int64_t first, int count) {
  if constexpr (kernel::IsPaired<L>::value) {
    using H = typename L::HalfLanes;
    Mat3<typename H::V> lo, hi;
    for (int k = 0; k < 9; ++k) {
      lo.a[k] = R.a[k].lo;
      hi.a[k] = R.a[k].hi;
    }
    store_block<H, kContiguous>(lo, data, stride, first, std::min(count, H::width));
    if (count > H::width) store_block<H, kContiguous>(hi, data, stride, first + H::width, count - H::width);
  } else if constexpr (L::width == 1) {
    for (int k = 0; k < 9; ++k) data[offset<kContiguous>(stride, first, k)] = R.a[k];
  } else {
#ifdef TORCHROT_HAVE_SIMD_TRANSPOSE
    if constexpr (kContiguous) {
      if (count == L::width) {
        store_soa(R.a, data + 9 * first);
        return;
      }
    }
#endif
    if constexpr (!kContiguous) {
      if (count == L::width && is_soa_batch(stride)) {
        for (int k = 0; k < 9; ++k) {
          typename L::Scalar* entry = data + first + entry_offset(stride, k);
          __builtin_prefetch(entry + kSoaPrefetchBlocks * L::width, 1);
          L::store(R.a[k], entry);
        }
        return;
      }
    }
    scatter_block<L, kContiguous>(R, data, stride, first, count);
  }
}

inline bool is_contiguous_batch(const int64_t s[3]) { return s[0] == 9 && s[1] == 3 && s[2] == 1; }

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace cpu
}  // namespace torchrot
