// Moving blocks of L::width matrices between memory (any Layout) and
// structure-of-arrays registers (entry k of every matrix of the block in one
// vector): in-register transposition for full contiguous blocks, plain vector
// loads and stores for full blocks already in structure-of-arrays layout
// (matrix index stride 1, e.g. a permuted (3, 3, N) tensor, or a tile of a
// tiled one at least a block wide), runs of 32 or 16 bytes through a small
// buffer for tiles narrower than a block (the paper authors' tiles of 8
// float matrices against AVX-512's 16 lanes), a gather through that buffer
// otherwise. Shared by the batched kernels, which start their blocks at
// multiples of the width (parallel_blocks).
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <initializer_list>
#include <type_traits>

#include "../kernel/force_inline.h"
#include "../kernel/lanes.h"
#include "kernel_table.h"
#include "soa_transpose.h"

namespace torchrot {
namespace cpu {
inline namespace CPU_CAPABILITY {
namespace {

using kernel::Mat3;

// Runs f(begin, end) on [0, n) in parallel, split at multiples of `width`:
// every block of `width` matrices the kernels take from `begin` on then
// starts at a multiple of the width, so that a tiled layout's tiles line up
// with the blocks however the threads split the batch. (Results do not
// depend on the split: each lane computes on its own matrix.)
template <typename F>
void parallel_blocks(int64_t n, int64_t width, int64_t grain, const F& f) {
  const int64_t blocks = (n + width - 1) / width;
  at::parallel_for(0, blocks, std::max<int64_t>(1, grain / width), [&](int64_t first_block, int64_t end_block) {
    f(first_block * width, std::min(n, end_block * width));
  });
}

// Offset of matrix i (Layout).
inline int64_t matrix_offset(const Layout& layout, int64_t i) {
  if (layout.tile == 0) return i * layout.stride[0];
  return (i / layout.tile) * layout.tile_stride + (i % layout.tile) * layout.stride[0];
}

// Offset of entry k of matrix 0.
inline int64_t entry_offset(const Layout& layout, int k) {
  return (k / 3) * layout.stride[1] + (k % 3) * layout.stride[2];
}

// Entry (r, c) of matrix i, for any layout or for contiguous (9, 3, 1) strides.
template <bool kContiguous>
inline int64_t offset(const Layout& layout, int64_t i, int k) {
  if (kContiguous) return 9 * i + k;
  return matrix_offset(layout, i) + entry_offset(layout, k);
}

// Whether the matrix index runs with stride 1 (within tiles, if tiled): then
// entry k of consecutive matrices is consecutive values.
inline bool is_soa_batch(const Layout& layout) { return layout.stride[0] == 1; }

// Blocks ahead that the vector paths prefetch. The SoA paths prefetch each
// of their nine entry streams per tensor (M, init and out make 27 streams,
// more than the hardware prefetchers follow); the contiguous paths every
// cache line of the block's 9 W values, for machines whose hardware
// prefetchers at times leave the contiguous loops of large batches waiting on
// memory (where they keep up, the prefetch changes nothing:
// benchmarks/lab_notes.md, "Fewer instructions").
constexpr int64_t kPrefetchBlocks = 4;

// How far ahead the contiguous paths prefetch, in bytes rather than blocks:
// kPrefetchBlocks blocks of the widest vectors (64 bytes an entry: AVX-512),
// so that the blocks of fewer or narrower lanes (AVX2's 8 floats: 288 bytes)
// look as far ahead. A block dense in memory is read quicker than the nine
// entry streams of the SoA paths, and AVX2's tiles and contiguous batches
// timed faster so (benchmarks/lab_notes.md).
constexpr int64_t kPrefetchContiguousBytes = kPrefetchBlocks * 9 * 64;

template <typename L, int kWrite>
TORCHROT_INLINE void prefetch_contiguous_block(const typename L::Scalar* block) {
  constexpr int kBytes = 9 * L::width * sizeof(typename L::Scalar);
  static_assert(kBytes <= 9 * 64, "a block wider than AVX-512's: kPrefetchContiguousBytes would be under a block");
  const char* ahead = reinterpret_cast<const char*>(block) + kPrefetchContiguousBytes;
  for (int line = 0; line < kBytes; line += 64) __builtin_prefetch(ahead + line, kWrite);
}

// The two tiles of half a block each that start at `ahead`: every cache
// line of them where the tiles are dense (tile after tile, the nine entries
// of a tile one after another, as the paper authors' blocks are), else each
// entry of each tile.
template <typename L, int kWrite>
TORCHROT_INLINE void prefetch_tiles(const typename L::Scalar* data, const Layout& layout, int64_t ahead) {
  if (layout.tile_stride == 9 * layout.tile && layout.stride[1] == 3 * layout.tile && layout.stride[2] == layout.tile) {
    constexpr int kBytes = 9 * L::width * sizeof(typename L::Scalar);  // the two tiles
    const char* lines = reinterpret_cast<const char*>(data + ahead);
    for (int line = 0; line < kBytes; line += 64) __builtin_prefetch(lines + line, kWrite);
    return;
  }
  for (int k = 0; k < 9; ++k) {
    __builtin_prefetch(data + ahead + entry_offset(layout, k), kWrite);
    __builtin_prefetch(data + ahead + layout.tile_stride + entry_offset(layout, k), kWrite);
  }
}

// load_block and store_block of vector lanes through a buffer, element by
// element: for any strides and for tail blocks. Out of line, so that the
// vector paths of the callers keep their registers (inlined, they made the SoA
// one-step fit slower: benchmarks/lab_notes.md).
template <typename L, bool kContiguous>
[[gnu::noinline]] Mat3<typename L::V> gather_block(const typename L::Scalar* data, const Layout& layout, int64_t first,
                                                   int count) {
  using T = typename L::Scalar;
  alignas(64) T buf[9][L::width];
  for (int j = 0; j < L::width; ++j) {
    for (int k = 0; k < 9; ++k) {
      buf[k][j] = j < count ? data[offset<kContiguous>(layout, first + j, k)] : T(k % 4 == 0 ? 1 : 0);
    }
  }
  Mat3<typename L::V> A;
  for (int k = 0; k < 9; ++k) A.a[k] = L::load(buf[k]);
  return A;
}

template <typename L, bool kContiguous>
[[gnu::noinline]] void scatter_block(const Mat3<typename L::V>& R, typename L::Scalar* data, const Layout& layout,
                                     int64_t first, int count) {
  using T = typename L::Scalar;
  alignas(64) T buf[9][L::width];
  for (int k = 0; k < 9; ++k) L::store(R.a[k], buf[k]);
  for (int j = 0; j < count; ++j)
    for (int k = 0; k < 9; ++k) data[offset<kContiguous>(layout, first + j, k)] = buf[k][j];
}

// The offsets of the L::width / kRun runs of kRun consecutive matrices that
// make up the block of a tiled SoA layout starting at matrix `first`.
template <typename L, int kRun>
TORCHROT_INLINE void tiled_runs(const Layout& layout, int64_t first, int64_t run[L::width / kRun]) {
  int64_t tile = first / layout.tile, within = first % layout.tile;
  for (int r = 0; r < L::width / kRun; ++r) {
    run[r] = tile * layout.tile_stride + within;
    within += kRun;
    if (within == layout.tile) within = 0, ++tile;
  }
}

// A full block of a tiled SoA layout whose tiles are narrower than the block
// (or not aligned with it) but made of runs of kRun matrices that start at
// multiples of kRun: runs of half a block (the paper authors' 8 float
// matrices against AVX-512's 16 lanes) are loaded as halves of each vector
// (VectorLanes::load_halves); shorter ones are copied run by run (kRun
// values, 16 or 32 bytes: one vector move each) into a buffer and loaded
// from there (out of line, as gather_block).
template <typename L, int kRun>
[[gnu::noinline]] Mat3<typename L::V> load_tiled_runs(const typename L::Scalar* data, const Layout& layout,
                                                      int64_t first) {
  using T = typename L::Scalar;
  int64_t run[L::width / kRun];
  tiled_runs<L, kRun>(layout, first, run);
  Mat3<typename L::V> A;
  if constexpr (2 * kRun == L::width) {
    for (int k = 0; k < 9; ++k) {
      const int64_t entry = entry_offset(layout, k);
      A.a[k] = L::load_halves(data + run[0] + entry, data + run[1] + entry);
    }
  } else {
    alignas(64) T buf[9][L::width];
    for (int r = 0; r < L::width / kRun; ++r) {
      for (int k = 0; k < 9; ++k)
        std::memcpy(&buf[k][r * kRun], data + run[r] + entry_offset(layout, k), kRun * sizeof(T));
    }
    for (int k = 0; k < 9; ++k) A.a[k] = L::load(buf[k]);
  }
  return A;
}

template <typename L, int kRun>
[[gnu::noinline]] void store_tiled_runs(const Mat3<typename L::V>& R, typename L::Scalar* data, const Layout& layout,
                                        int64_t first) {
  using T = typename L::Scalar;
  int64_t run[L::width / kRun];
  tiled_runs<L, kRun>(layout, first, run);
  if constexpr (2 * kRun == L::width) {
    for (int k = 0; k < 9; ++k) {
      const int64_t entry = entry_offset(layout, k);
      L::store_halves(R.a[k], data + run[0] + entry, data + run[1] + entry);
    }
  } else {
    alignas(64) T buf[9][L::width];
    for (int k = 0; k < 9; ++k) L::store(R.a[k], buf[k]);
    for (int r = 0; r < L::width / kRun; ++r) {
      for (int k = 0; k < 9; ++k)
        std::memcpy(data + run[r] + entry_offset(layout, k), &buf[k][r * kRun], kRun * sizeof(T));
    }
  }
}

// How a full block starting at matrix `first` of an SoA layout (is_soa_batch)
// is moved: its matrices consecutive in memory (untiled, or within one tile):
// kVector, from matrix_offset(first); in runs of 32 or 16 bytes (kRuns32,
// kRuns16: a tiled layout whose tiles and `first` are multiples of them); or
// element by element (kGather).
enum class SoaMove { kVector, kRuns32, kRuns16, kGather };

template <typename L>
TORCHROT_INLINE SoaMove soa_move(const Layout& layout, int64_t first) {
  using T = typename L::Scalar;
  if (layout.tile == 0) return SoaMove::kVector;
  const int64_t within = first % layout.tile;
  if (within + L::width <= layout.tile) return SoaMove::kVector;
  constexpr int64_t run32 = 32 / sizeof(T), run16 = 16 / sizeof(T);
  if (L::width % run32 == 0 && layout.tile % run32 == 0 && within % run32 == 0) return SoaMove::kRuns32;
  if (L::width % run16 == 0 && layout.tile % run16 == 0 && within % run16 == 0) return SoaMove::kRuns16;
  return SoaMove::kGather;
}

// How a loop moves its blocks, one instantiation of the loop per path: where
// the out-of-line paths (which return a block through memory) merged with
// the vector paths in one loop, GCC stored every block the vector paths
// loaded to the stack and read it back (18 stores and 18 loads per one-step
// block), so the kernels run their full blocks on a path of their own and
// the tail block on kAny (run_block_paths).
enum class BlockPath {
  kTransposed,  // contiguous (N, 3, 3) layouts, full blocks: in-register transposition
  kVectors,     // structure of arrays (matrix stride 1), untiled or in tiles that line up with
                // the blocks (tiles_line_up), full blocks: plain vectors or vector halves
  kAny,         // any layout and count: tiled runs, gathers, tail blocks
};

// Whether the tiles of an SoA layout line up with blocks of `width`
// matrices, which start at multiples of the width (parallel_blocks): a
// whole number of blocks to a tile, or a tile to each half of a block (the
// paper authors' tiles of 8 float matrices against AVX-512's 16 lanes).
inline bool tiles_line_up(const Layout& layout, int width) {
  return layout.tile == 0 || layout.tile % width == 0 || 2 * layout.tile == width;
}

// Where the full blocks of an SoA layout and their entries lie when both
// are evenly spaced: the block of `width` matrices at `first` (a multiple of
// the width) starts at block * first, its entry k at entry * k from there,
// and, in tiles half a block wide, the second half of that entry `half`
// further on. Then the nine entries of a block are a base pointer and one
// stride, not nine offsets computed from the Layout.
struct EvenBlocks {
  int64_t block = 0, entry = 0;  // both 0: not evenly spaced
  int64_t half = 0;              // 0: each entry one vector
  // The block is one dense run of 9 * width values: entry k at k * width, or
  // its halves at k * width / 2 and 9 * width / 2 further on.
  bool dense() const { return block == 9; }
};

// Untiled structure of arrays with rows of entries evenly spaced (a permuted
// (3, 3, N) tensor: entry k at k * N), or tiles of `width` or `width / 2`
// matrices one after another, each entry of a tile one run of the tile's
// values (the paper authors' blocks: 8 float matrices, the width of AVX2's
// vectors and half of AVX-512's).
inline EvenBlocks even_blocks(const Layout& layout, int width) {
  const int64_t* s = layout.stride;
  if (s[0] != 1 || s[1] != 3 * s[2]) return {};
  if (layout.tile == 0) return {1, s[2], 0};
  if (s[2] != layout.tile || layout.tile_stride != 9 * layout.tile) return {};
  if (layout.tile == width) return {9, width, 0};
  if (2 * layout.tile == width && width > 1) return {9, layout.tile, 9 * layout.tile};
  return {};
}

// Entry k of an evenly spaced block (EvenBlocks) at `block`: at k * kEntry
// (a constant: the paper authors' dense tiles) or at k * entry (kEntry 0: a
// stride known at run time), one vector, or with kHalf two halves kHalf apart
// (tiles half a block wide).
template <typename L, int64_t kEntry, int64_t kHalf>
struct EvenEntries {
  using T = typename L::Scalar;
  using V = typename L::V;
  int64_t entry = kEntry;
  TORCHROT_INLINE int64_t offset(int k) const { return k * (kEntry != 0 ? kEntry : entry); }
  // The offset as a function of k (prefetch_even_block's `entry`).
  TORCHROT_INLINE int64_t operator()(int k) const { return offset(k); }
  TORCHROT_INLINE V load(const T* block, int k) const {
    if constexpr (kHalf != 0) {
      return L::load_halves(block + offset(k), block + offset(k) + kHalf);
    } else {
      return L::load(block + offset(k));
    }
  }
  TORCHROT_INLINE void store(V x, T* block, int k) const {
    if constexpr (kHalf != 0) {
      L::store_halves(x, block + offset(k), block + offset(k) + kHalf);
    } else {
      L::store(x, block + offset(k));
    }
  }
};

// The entries of the paper authors' dense tiles a block wide, and half a
// block wide (EvenBlocks{9, width / 2, 9 * width / 2}).
template <typename L>
using TileEntries = EvenEntries<L, L::width, 0>;
template <typename L>
using HalfTileEntries = EvenEntries<L, L::width / 2, 9 * L::width / 2>;

// Whether the full blocks of M, init and out (their EvenBlocks) are all evenly
// spaced in a way with_even_entries reads: each entry one vector in all three,
// or all three the dense tiles half a block wide.
inline bool all_even(const EvenBlocks even[3]) {
  for (int t = 0; t < 3; ++t)
    if (even[t].entry == 0) return false;
  if (even[0].half == 0 && even[1].half == 0 && even[2].half == 0) return true;
  return even[0].half != 0 && even[1].half != 0 && even[2].half != 0;  // all dense: half only comes with tiles
}

// Calls f(M's, init's and out's EvenEntries, dense) on blocks for which
// all_even holds: constant offsets where all three are dense tiles of the same
// width (dense: each block one run of 9 * L::width values), else each
// tensor's own entry stride.
template <typename L, typename F>
TORCHROT_INLINE void with_even_entries(const EvenBlocks even[3], const F& f) {
  if constexpr (L::width > 1) {
    if (even[0].dense() && even[1].dense() && even[2].dense()) {
      if (even[0].half == 0 && even[1].half == 0 && even[2].half == 0) {
        const TileEntries<L> tile;
        f(tile, tile, tile, true);
        return;
      }
      if (even[0].half != 0) {  // all three (all_even)
        const HalfTileEntries<L> half_tile;
        f(half_tile, half_tile, half_tile, true);
        return;
      }
    }
  }
  using Strided = EvenEntries<L, 0, 0>;
  f(Strided{even[0].entry}, Strided{even[1].entry}, Strided{even[2].entry}, false);
}

// Whether a layout is contiguous (N, 3, 3).
inline bool is_contiguous_batch(const Layout& layout) {
  const int64_t* s = layout.stride;
  return layout.tile == 0 && s[0] == 9 && s[1] == 3 && s[2] == 1;
}

// The path of the full blocks of width-`width` lanes of a loop over these
// layouts (nulls skipped).
inline BlockPath full_block_path(int width, std::initializer_list<const Layout*> layouts) {
  bool contiguous = true, vectors = true;
  for (const Layout* layout : layouts) {
    if (layout == nullptr) continue;
    contiguous = contiguous && is_contiguous_batch(*layout);
    vectors = vectors && is_soa_batch(*layout) && tiles_line_up(*layout, width);
  }
  return contiguous ? BlockPath::kTransposed : vectors ? BlockPath::kVectors : BlockPath::kAny;
}

// Runs f(path, b, e) on [begin, end) (begin a multiple of L::width): its full
// blocks with `path` (a std::integral_constant<BlockPath, ...>), the tail
// block with kAny.
template <typename L, typename F>
TORCHROT_INLINE void run_block_paths(BlockPath path, int64_t begin, int64_t end, const F& f) {
  using P = BlockPath;
  const int64_t full_end = path == P::kAny ? end : begin + (end - begin) / L::width * L::width;
  if (full_end > begin) {
    switch (path) {
      case P::kTransposed:
        f(std::integral_constant<P, P::kTransposed>{}, begin, full_end);
        break;
      case P::kVectors:
        f(std::integral_constant<P, P::kVectors>{}, begin, full_end);
        break;
      case P::kAny:
        f(std::integral_constant<P, P::kAny>{}, begin, full_end);
        break;
    }
  }
  if (end > full_end) f(std::integral_constant<P, P::kAny>{}, full_end, end);
}

// Gathers `count` matrices starting at `first` into SoA lanes; missing lanes
// of a tail block get the identity, a harmless input. kTransposed and
// kVectors take full blocks only.
template <typename L, BlockPath kPath>
TORCHROT_INLINE Mat3<typename L::V> load_block(const typename L::Scalar* data, const Layout& layout, int64_t first,
                                               int count) {
  constexpr bool kContiguous = kPath == BlockPath::kTransposed;
  Mat3<typename L::V> A;
  if constexpr (kernel::IsPaired<L>::value) {  // two half blocks
    using H = typename L::HalfLanes;
    const Mat3<typename H::V> lo = load_block<H, kPath>(data, layout, first, std::min(count, H::width));
    const Mat3<typename H::V> hi = load_block<H, kPath>(data, layout, first + H::width, std::max(count - H::width, 0));
    for (int k = 0; k < 9; ++k) A.a[k] = {lo.a[k], hi.a[k]};
    return A;
  } else if constexpr (L::width == 1) {  // the scalar path: one matrix, straight
    for (int k = 0; k < 9; ++k) A.a[k] = data[offset<kContiguous>(layout, first, k)];
    return A;
  } else if constexpr (kPath == BlockPath::kVectors) {
    const int64_t at = matrix_offset(layout, first), ahead = matrix_offset(layout, first + kPrefetchBlocks * L::width);
    if (2 * layout.tile == L::width) {  // each half of the block is a tile
      prefetch_tiles<L, 0>(data, layout, ahead);
      const int64_t hi = at + layout.tile_stride;
      for (int k = 0; k < 9; ++k) {
        const int64_t entry = entry_offset(layout, k);
        A.a[k] = L::load_halves(data + at + entry, data + hi + entry);
      }
      return A;
    }
    for (int k = 0; k < 9; ++k) {
      const int64_t entry = entry_offset(layout, k);
      __builtin_prefetch(data + ahead + entry);
      A.a[k] = L::load(data + at + entry);
    }
    return A;
  } else if constexpr (kPath == BlockPath::kTransposed) {
#ifdef TORCHROT_HAVE_SIMD_TRANSPOSE
    prefetch_contiguous_block<L, 0>(data + 9 * first);
    load_soa(data + 9 * first, A.a);
    return A;
#else
    return gather_block<L, true>(data, layout, first, count);
#endif
  } else {
    if (count == L::width && is_soa_batch(layout)) {  // full block, SoA
      switch (soa_move<L>(layout, first)) {
        case SoaMove::kVector:
          return load_block<L, BlockPath::kVectors>(data, layout, first, count);
        case SoaMove::kRuns32:
          if constexpr (L::width * sizeof(typename L::Scalar) > 32) {
            return load_tiled_runs<L, 32 / sizeof(typename L::Scalar)>(data, layout, first);
          }
          break;
        case SoaMove::kRuns16:
          if constexpr (L::width * sizeof(typename L::Scalar) > 16) {
            return load_tiled_runs<L, 16 / sizeof(typename L::Scalar)>(data, layout, first);
          }
          break;
        case SoaMove::kGather:
          break;
      }
    }
    return gather_block<L, false>(data, layout, first, count);
  }
}

template <typename L, BlockPath kPath>
TORCHROT_INLINE void store_block(const Mat3<typename L::V>& R, typename L::Scalar* data, const Layout& layout,
                                 int64_t first, int count) {
  constexpr bool kContiguous = kPath == BlockPath::kTransposed;
  if constexpr (kernel::IsPaired<L>::value) {
    using H = typename L::HalfLanes;
    Mat3<typename H::V> lo, hi;
    for (int k = 0; k < 9; ++k) {
      lo.a[k] = R.a[k].lo;
      hi.a[k] = R.a[k].hi;
    }
    store_block<H, kPath>(lo, data, layout, first, std::min(count, H::width));
    if (count > H::width) store_block<H, kPath>(hi, data, layout, first + H::width, count - H::width);
  } else if constexpr (L::width == 1) {
    for (int k = 0; k < 9; ++k) data[offset<kContiguous>(layout, first, k)] = R.a[k];
  } else if constexpr (kPath == BlockPath::kVectors) {
    const int64_t at = matrix_offset(layout, first), ahead = matrix_offset(layout, first + kPrefetchBlocks * L::width);
    if (2 * layout.tile == L::width) {
      prefetch_tiles<L, 1>(data, layout, ahead);
      const int64_t hi = at + layout.tile_stride;
      for (int k = 0; k < 9; ++k) {
        const int64_t entry = entry_offset(layout, k);
        L::store_halves(R.a[k], data + at + entry, data + hi + entry);
      }
      return;
    }
    for (int k = 0; k < 9; ++k) {
      const int64_t entry = entry_offset(layout, k);
      __builtin_prefetch(data + ahead + entry, 1);
      L::store(R.a[k], data + at + entry);
    }
  } else if constexpr (kPath == BlockPath::kTransposed) {
#ifdef TORCHROT_HAVE_SIMD_TRANSPOSE
    prefetch_contiguous_block<L, 1>(data + 9 * first);
    store_soa(R.a, data + 9 * first);
#else
    scatter_block<L, true>(R, data, layout, first, count);
#endif
  } else {
    if (count == L::width && is_soa_batch(layout)) {
      switch (soa_move<L>(layout, first)) {
        case SoaMove::kVector:
          return store_block<L, BlockPath::kVectors>(R, data, layout, first, count);
        case SoaMove::kRuns32:
          if constexpr (L::width * sizeof(typename L::Scalar) > 32) {
            return store_tiled_runs<L, 32 / sizeof(typename L::Scalar)>(R, data, layout, first);
          }
          break;
        case SoaMove::kRuns16:
          if constexpr (L::width * sizeof(typename L::Scalar) > 16) {
            return store_tiled_runs<L, 16 / sizeof(typename L::Scalar)>(R, data, layout, first);
          }
          break;
        case SoaMove::kGather:
          break;
      }
    }
    scatter_block<L, false>(R, data, layout, first, count);
  }
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace cpu
}  // namespace torchrot
