// The batched kernel, included by each kernel_*.cpp and compiled with that
// file's instruction-set flags: walks the batch in parallel, in blocks of
// L::width matrices laid out structure-of-arrays (entry k of every matrix of
// the block in one vector), and fits each block with fit_rotation_lanes.
// Results do not depend on the thread count or on where a matrix falls in a
// block: every lane computes the same operations on its own matrix.
#pragma once

#include <ATen/Parallel.h>

#include <atomic>

#include "../kernel/fit_rotation_impl.h"
#include "kernel_table.h"
#include "soa_transpose.h"

namespace torchrot {
namespace cpu {
inline namespace CPU_CAPABILITY {
namespace {


using kernel::Mat3;

// Matrices per parallel task: enough that scheduling costs little.
constexpr int64_t kGrainSize = 2048;

// Entry (r, c) of matrix i, for arbitrary or for contiguous (9, 3, 1) strides.
template <bool kContiguous>
inline int64_t offset(const int64_t stride[3], int64_t i, int k) {
  if (kContiguous) return 9 * i + k;
  return i * stride[0] + (k / 3) * stride[1] + (k % 3) * stride[2];
}

// Gathers `count` matrices starting at `first` into SoA lanes; missing lanes
// of a tail block get the identity, a harmless input.
template <typename L, bool kContiguous>
inline Mat3<typename L::V> load_block(const typename L::Scalar* data, const int64_t stride[3], int64_t first,
                                      int count) {
  using T = typename L::Scalar;
#ifdef TORCHROT_HAVE_SIMD_TRANSPOSE
  if constexpr (kContiguous && L::width > 1) {
    if (count == L::width) {  // full block: in-register transposition
      Mat3<typename L::V> A;
      load_soa<T>(data + 9 * first, A.a);
      return A;
    }
  }
#endif
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
inline void store_block(const Mat3<typename L::V>& R, typename L::Scalar* data, const int64_t stride[3],
                        int64_t first, int count) {
  using T = typename L::Scalar;
#ifdef TORCHROT_HAVE_SIMD_TRANSPOSE
  if constexpr (kContiguous && L::width > 1) {
    if (count == L::width) {
      store_soa<T>(R.a, data + 9 * first);
      return;
    }
  }
#endif
  alignas(64) T buf[9][L::width];
  for (int k = 0; k < 9; ++k) L::store(R.a[k], buf[k]);
  for (int j = 0; j < count; ++j)
    for (int k = 0; k < 9; ++k) data[offset<kContiguous>(stride, first + j, k)] = buf[k][j];
}

template <typename L>
inline void store_diagnostics(const kernel::LaneResults<L>& res, const BatchArgs<typename L::Scalar>& args,
                              int64_t first, int count) {
  for (int j = 0; j < count; ++j) {
    if (args.iterations != nullptr) args.iterations[first + j] = static_cast<int32_t>(L::lane(res.iterations, j));
    if (args.status != nullptr) {
      FitStatus s = FitStatus::kCayley;
      if (L::lane_set(res.fallback, j)) s = FitStatus::kFallback;
      if (L::lane_set(res.bad_init, j)) s = FitStatus::kBadInit;
      if (L::lane_set(res.non_finite, j)) s = FitStatus::kNonFinite;
      args.status[first + j] = static_cast<uint8_t>(s);
    }
  }
}

template <typename L>
inline int count_lanes(typename L::Mask m, int count) {
  int n = 0;
  for (int j = 0; j < count; ++j) n += L::lane_set(m, j);
  return n;
}

// Fits matrices [begin, end); returns how many had a bad warm start.
template <typename L, bool kContiguous>
int64_t fit_range(const BatchArgs<typename L::Scalar>& args, int64_t begin, int64_t end) {
  int64_t bad_inits = 0;
  for (int64_t first = begin; first < end; first += L::width) {
    const int count = static_cast<int>(std::min<int64_t>(L::width, end - first));
    // Both inputs are in registers before `out` is written: out may alias them.
    const Mat3<typename L::V> A = load_block<L, kContiguous>(args.M, args.m_stride, first, count);
    Mat3<typename L::V> R0;
    if (args.init != nullptr) R0 = load_block<L, kContiguous>(args.init, args.init_stride, first, count);
    Mat3<typename L::V> R;
    const kernel::LaneResults<L> res =
        kernel::fit_rotation_lanes<L>(A, args.init != nullptr ? &R0 : nullptr, args.options, R);
    store_block<L, kContiguous>(R, args.out, args.out_stride, first, count);
    if (args.iterations != nullptr || args.status != nullptr) store_diagnostics<L>(res, args, first, count);
    if (args.init != nullptr && L::any(res.bad_init)) bad_inits += count_lanes<L>(res.bad_init, count);
  }
  return bad_inits;
}

inline bool is_contiguous_batch(const int64_t s[3]) { return s[0] == 9 && s[1] == 3 && s[2] == 1; }

template <typename L>
int64_t fit_batch(const BatchArgs<typename L::Scalar>& args) {
  const bool contiguous = is_contiguous_batch(args.m_stride) && is_contiguous_batch(args.out_stride) &&
                          (args.init == nullptr || is_contiguous_batch(args.init_stride));
  std::atomic<int64_t> bad_inits{0};
  at::parallel_for(0, args.n, kGrainSize, [&](int64_t begin, int64_t end) {
    bad_inits += contiguous ? fit_range<L, true>(args, begin, end) : fit_range<L, false>(args, begin, end);
  });
  return bad_inits.load();
}

template <template <typename> class Lanes>
KernelTable make_kernel_table(const char* name) {
  return KernelTable{name, Lanes<float>::width, Lanes<double>::width, &fit_batch<Lanes<float>>,
                     &fit_batch<Lanes<double>>};
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace cpu
}  // namespace torchrot
