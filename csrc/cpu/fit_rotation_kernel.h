// The batched kernel, included by each kernel_*.cpp and compiled with that
// file's instruction-set flags: walks the batch in parallel, in blocks of
// L::width matrices laid out structure-of-arrays (entry k of every matrix of
// the block in one vector), and runs the per-lane state machine of
// kernel/fit_rotation_impl.h on each block. In converged mode a block takes a
// few steps per pass; lanes still running are saved and regrouped into full
// blocks for the next pass, so a slow lane costs its own steps, not its
// block's. Results do not depend on the thread count or on which block a
// matrix lands in: every lane computes the same operations on its own matrix.
#pragma once

#include <algorithm>
#include <atomic>
#include <type_traits>
#include <vector>

#include "../kernel/fit_rotation_impl.h"
#include "block_io.h"
#include "flush_to_zero.h"
#include "kernel_table.h"

namespace torchrot {
namespace cpu {
inline namespace CPU_CAPABILITY {
namespace {

// Matrices per parallel task: enough that scheduling costs little.
constexpr int64_t kGrainSize = 2048;

// Matrices fitted together, so that the lanes saved between passes stay in
// cache; and the Cayley steps of one pass in converged mode, after which
// unfinished lanes are regrouped into full blocks. Fewer steps per pass leave
// more lanes to save, restore and finish; more leave blocks stepping for a few
// lanes. 4 timed fastest of 2 to 6 on cold fits in both dtypes, also against 3
// with the lanes saved by compress instructions instead of per-lane copies
// (benchmarks/lab_notes.md: measured before the cold start's first step was
// exact, and not since).
constexpr int64_t kSubChunk = 1024;
constexpr int64_t kStepsPerPass = 4;

// Blocks whose first pass in converged mode (or with max_iter > 1) fit_range
// takes together, a Cayley step of each in turn. A block's steps are one chain
// of dependent operations (S, the estimate's square root, Cramer's rule, a
// division, the Cayley map, R Q, then the next step's S), and its whole first
// pass is over a thousand instructions: the next block's chain can start only
// once the core's out-of-order window reaches it. In turns, four blocks'
// chains are in the window together. On AVX2 (L::stream_one_step: 16
// registers, the lane state on the stack) converged fits of warm starts timed
// faster so; on AVX-512 no faster, so 1 there (benchmarks/lab_notes.md). The
// results are the same: advance stops after any step and resumes from the
// lane state alone.
template <typename L>
constexpr int kInterleavedBlocks = L::stream_one_step ? 4 : 1;

// A lane still iterating, saved between passes (its normalised A as well:
// `out` may alias M, whose block has been overwritten by then).
template <typename T>
struct SavedLane {
  int64_t index;
  T A[9], R[9];
  T iterations, attempt_steps, escapes;
  bool switched, large_step;
};

// Saves the lanes of `s` that are still running (of the first `count`),
// with their matrix indices, to `saved`.
template <typename L>
inline void save_running_lanes(const kernel::LaneState<L>& s, int count, const int64_t* index,
                               std::vector<SavedLane<typename L::Scalar>>& saved) {
  using T = typename L::Scalar;
  alignas(64) T A[9][L::width], R[9][L::width], iterations[L::width], attempt[L::width], escapes[L::width];
  for (int k = 0; k < 9; ++k) {
    L::store(s.A.a[k], A[k]);
    L::store(s.R.a[k], R[k]);
  }
  L::store(s.iterations, iterations);
  L::store(s.attempt_steps, attempt);
  L::store(s.escapes, escapes);
  for (int j = 0; j < count; ++j) {
    if (!L::lane_set(s.running, j)) continue;
    SavedLane<T> lane;
    lane.index = index[j];
    for (int k = 0; k < 9; ++k) {
      lane.A[k] = A[k][j];
      lane.R[k] = R[k][j];
    }
    lane.iterations = iterations[j];
    lane.attempt_steps = attempt[j];
    lane.escapes = escapes[j];
    lane.switched = L::lane_set(s.switched, j);
    lane.large_step = L::lane_set(s.large_step, j);
    saved.push_back(lane);
  }
}

// A block of `count` saved lanes (the other lanes idle).
template <typename L>
inline kernel::LaneState<L> restore_block(const SavedLane<typename L::Scalar>* saved, int count) {
  using T = typename L::Scalar;
  alignas(64) T A[9][L::width], R[9][L::width], iterations[L::width], attempt[L::width], escapes[L::width],
      switched[L::width], large_step[L::width], running[L::width];
  for (int j = 0; j < L::width; ++j) {
    const bool live = j < count;
    for (int k = 0; k < 9; ++k) {
      A[k][j] = live ? saved[j].A[k] : T(k % 4 == 0 ? 1 : 0);
      R[k][j] = live ? saved[j].R[k] : T(k % 4 == 0 ? 1 : 0);
    }
    iterations[j] = live ? saved[j].iterations : T(0);
    attempt[j] = live ? saved[j].attempt_steps : T(0);
    escapes[j] = live ? saved[j].escapes : T(0);
    switched[j] = live && saved[j].switched ? T(1) : T(0);
    large_step[j] = live && saved[j].large_step ? T(1) : T(0);
    running[j] = live ? T(1) : T(0);
  }
  kernel::LaneState<L> s;
  for (int k = 0; k < 9; ++k) {
    s.A.a[k] = L::load(A[k]);
    s.R.a[k] = L::load(R[k]);
  }
  const typename L::V zero(0);
  s.iterations = L::load(iterations);
  s.attempt_steps = L::load(attempt);
  s.escapes = L::load(escapes);
  s.switched = L::gt(L::load(switched), zero);
  s.large_step = L::gt(L::load(large_step), zero);
  s.running = L::gt(L::load(running), zero);
  s.fallback = s.bad_init = s.non_finite = L::all_false();
  return s;
}

template <typename L>
TORCHROT_INLINE void store_diagnostics(const kernel::LaneState<L>& s, int lane,
                                       const BatchArgs<typename L::Scalar>& args, int64_t index) {
  if (args.iterations != nullptr) args.iterations[index] = static_cast<int32_t>(L::lane(s.iterations, lane));
  if (args.status != nullptr) {
    FitStatus status = FitStatus::kCayley;
    if (L::lane_set(s.fallback, lane)) status = FitStatus::kFallback;
    if (L::lane_set(s.bad_init, lane)) status = FitStatus::kBadInit;
    if (L::lane_set(s.non_finite, lane)) status = FitStatus::kNonFinite;
    args.status[index] = static_cast<uint8_t>(status);
  }
}

// Prefetches, kPrefetchBlocks blocks ahead, the nine entries of an evenly
// spaced block (`entry(k)`: entry k's offset from `block`, which is `stride`
// from the next block): every cache line of the nine when they are one
// dense run (the paper authors' tiles at the kernel's width), else each
// entry's line, for every other block where a line holds two blocks' entry
// (each entry stream moves on by half a line a block).
template <typename L, int kWrite, typename Entry>
TORCHROT_INLINE void prefetch_even_block(const typename L::Scalar* block, int64_t first, int64_t stride, Entry entry,
                                         bool dense) {
  if (dense) {
    prefetch_contiguous_block<L, kWrite>(block);
    return;
  }
  constexpr int64_t kBlocksPerLine = std::max<int64_t>(1, 64 / (L::width * sizeof(typename L::Scalar)));
  if ((first / L::width) % kBlocksPerLine != 0) return;
  const typename L::Scalar* ahead = block + kPrefetchBlocks * stride;
  for (int k = 0; k < 9; ++k) __builtin_prefetch(ahead + entry(k), kWrite);
}

// After a one-step block (no lane left running): its bad warm starts added
// to `bad_inits`, and the iterations and status of its first `count` lanes
// stored where the caller asked for them.
template <typename L>
TORCHROT_INLINE void account_one_step_block(const kernel::LaneState<L>& s, const BatchArgs<typename L::Scalar>& args,
                                            int64_t first, int count, bool diagnostics, int64_t& bad_inits) {
  if (L::any(s.bad_init)) {
    for (int j = 0; j < count; ++j) bad_inits += L::lane_set(s.bad_init, j);
  }
  if (diagnostics) {
    for (int j = 0; j < count; ++j) store_diagnostics<L>(s, j, args, first + j);
  }
}

// Prefetches kPrefetchBlocks ahead the lines of the evenly spaced block at
// `first` of M, init and out (prefetch_even_block), which start at M, R0 and
// out and are stride[0], stride[1] and stride[2] from their next blocks.
template <typename L, typename EntriesM, typename EntriesR, typename EntriesOut>
TORCHROT_INLINE void prefetch_even_blocks(int64_t first, const typename L::Scalar* M, const typename L::Scalar* R0,
                                          const typename L::Scalar* out, const int64_t stride[3], EntriesM entries_m,
                                          EntriesR entries_r, EntriesOut entries_out, bool dense) {
  prefetch_even_block<L, 0>(M, first, stride[0], entries_m, dense);
  prefetch_even_block<L, 0>(R0, first, stride[1], entries_r, dense);
  // out's lines too where out is init: without, the tiles in place timed
  // slower on another machine (benchmarks/lab_notes.md).
  prefetch_even_block<L, 1>(out, first, stride[2], entries_out, dense);
}

// Calls block(first, M, R0, out, entries_m, entries_r, entries_out) for each
// full block [first, first + L::width) in [begin, end) of M, init and out
// evenly spaced (all_even: their EvenBlocks): the block's M, init and out
// start at M, R0 and out, their entries where the EvenEntries of
// with_even_entries put them. The layout's case is chosen once for the range
// and the blocks' addresses carried from one block to the next (both done for
// every block, they cost instructions per matrix: benchmarks/lab_notes.md),
// and each block's lines are prefetched kPrefetchBlocks ahead.
template <typename L, typename Block>
TORCHROT_INLINE void for_each_even_block(const BatchArgs<typename L::Scalar>& args, int64_t begin, int64_t end,
                                         const EvenBlocks even[3], Block block) {
  using T = typename L::Scalar;
  const int64_t stride[3] = {even[0].block * L::width, even[1].block * L::width, even[2].block * L::width};
  with_even_entries<L>(even, [&](auto entries_m, auto entries_r, auto entries_out, bool dense) TORCHROT_LAMBDA_INLINE {
    const T* M = args.M + even[0].block * begin;
    const T* R0 = args.init + even[1].block * begin;
    T* out = args.out + even[2].block * begin;
    for (int64_t first = begin; first < end; first += L::width) {
      prefetch_even_blocks<L>(first, M, R0, out, stride, entries_m, entries_r, entries_out, dense);
      block(first, M, R0, out, entries_m, entries_r, entries_out);
      M += stride[0];
      R0 += stride[1];
      out += stride[2];
    }
  });
}

// The one-step warm update of the full blocks [begin, end) of M, init and out
// evenly spaced (for_each_even_block) through
// kernel::one_step_warm_from_memory (L::stream_one_step): M and init read
// from the tensors themselves (before `out`, which may alias them, is
// written), the result written straight to out where finish has nothing to
// do, else through a buffer on the stack (q) and finish. Returns how many
// warm starts were bad.
template <typename L>
int64_t one_step_streamed_even_range(const BatchArgs<typename L::Scalar>& args, int64_t begin, int64_t end,
                                     const EvenBlocks even[3], bool diagnostics) {
  using T = typename L::Scalar;
  using V = typename L::V;
  int64_t bad_inits = 0;
  for_each_even_block<L>(args, begin, end, even,
                         [&](int64_t first, const T* M, const T* R0, T* out, auto entries_m, auto entries_r,
                             auto entries_out) TORCHROT_LAMBDA_INLINE {
                           alignas(64) T q[9 * L::width];
                           kernel::one_step_warm_from_memory<L>(
                               [&](int k) TORCHROT_LAMBDA_INLINE { return entries_m.load(M, k); },
                               [&](int k) TORCHROT_LAMBDA_INLINE { return entries_r.load(R0, k); }, q,
                               [&](int k, V x) TORCHROT_LAMBDA_INLINE { entries_out.store(x, out, k); },
                               args.options.init_known_clean, args.options.variant,
                               [&](const kernel::LaneState<L>& s, bool stored) TORCHROT_LAMBDA_INLINE {
                                 if (!stored) {
                                   const Mat3<V> R = kernel::finish<L, false>(s);
                                   for (int k = 0; k < 9; ++k) entries_out.store(R.a[k], out, k);
                                 }
                                 account_one_step_block<L>(s, args, first, L::width, diagnostics, bad_inits);
                               });
                         });
  return bad_inits;
}

// The one-step warm update of the block at `first` through
// kernel::one_step_warm_from_memory (L::stream_one_step) on the layouts that
// are not evenly spaced (one_step_streamed_even_range's), which it reads
// where it uses them: from the tensors themselves on SoA layouts that hold
// each entry of the block as one vector, else from a copy of the block on
// the stack (both read before `out`, which may alias them, is written). The
// result goes through a buffer on the stack (q) to the store, and through
// finish in blocks where finish has something to do.
template <typename L, BlockPath kPath>
TORCHROT_INLINE void one_step_block(const BatchArgs<typename L::Scalar>& args, int64_t first, int count,
                                    bool diagnostics, int64_t& bad_inits) {
  using T = typename L::Scalar;
  using V = typename L::V;
  alignas(64) T q[9 * L::width];
  const auto account = [&](const kernel::LaneState<L>& s) TORCHROT_LAMBDA_INLINE {
    account_one_step_block<L>(s, args, first, count, diagnostics, bad_inits);
  };
  const FitOptions& options = args.options;
  // The rows go to q either way; `stored`: as computed (one_step_warm_from_memory's
  // `store`), with nothing for finish to do.
  const auto store_q = [&](int k, V x) TORCHROT_LAMBDA_INLINE { L::store(x, q + k * L::width); };
  const auto done = [&](const kernel::LaneState<L>& s, bool stored) TORCHROT_LAMBDA_INLINE {
    Mat3<V> R;
    if (stored) {
      for (int k = 0; k < 9; ++k) R.a[k] = L::load(q + k * L::width);
    } else {
      R = kernel::finish<L, false>(s);
    }
    store_block<L, kPath>(R, args.out, args.out_layout, first, count);
    account(s);
  };
  if constexpr (kPath == BlockPath::kVectors) {
    // Plain vectors, not tiles half a block wide (as load_block reads them, prefetches included).
    if (2 * args.m_layout.tile != L::width && 2 * args.init_layout.tile != L::width) {
      const T* M = args.M + matrix_offset(args.m_layout, first);
      const T* R0 = args.init + matrix_offset(args.init_layout, first);
      const int64_t ahead_m = matrix_offset(args.m_layout, first + kPrefetchBlocks * L::width);
      const int64_t ahead_r = matrix_offset(args.init_layout, first + kPrefetchBlocks * L::width);
      for (int k = 0; k < 9; ++k) {
        __builtin_prefetch(args.M + ahead_m + entry_offset(args.m_layout, k));
        __builtin_prefetch(args.init + ahead_r + entry_offset(args.init_layout, k));
      }
      const auto m = [&](int k) TORCHROT_LAMBDA_INLINE { return L::load(M + entry_offset(args.m_layout, k)); };
      const auto r = [&](int k) TORCHROT_LAMBDA_INLINE { return L::load(R0 + entry_offset(args.init_layout, k)); };
      kernel::one_step_warm_from_memory<L>(m, r, q, store_q, options.init_known_clean, options.variant, done);
      return;
    }
  }
  alignas(64) T m[9 * L::width], r[9 * L::width];
  {
    const Mat3<typename L::V> M = load_block<L, kPath>(args.M, args.m_layout, first, count);
    const Mat3<typename L::V> R0 = load_block<L, kPath>(args.init, args.init_layout, first, count);
    for (int k = 0; k < 9; ++k) {
      L::store(M.a[k], m + k * L::width);
      L::store(R0.a[k], r + k * L::width);
    }
  }
  kernel::one_step_warm_from_memory<L>([&](int k) TORCHROT_LAMBDA_INLINE { return L::load(m + k * L::width); },
                                       [&](int k) TORCHROT_LAMBDA_INLINE { return L::load(r + k * L::width); }, q,
                                       store_q, options.init_known_clean, options.variant, done);
}

// The one-step warm update of the full blocks [begin, end) of M, init and
// out evenly spaced (for_each_even_block), for lanes that hold the block's
// state in registers from the loads to the stores (not L::stream_one_step):
// the loads, begin_fit, advance_one_step, finish and the stores of
// fit_range's one-step pass, in a loop of their own with each entry read and
// written at a base pointer and one stride (constant offsets on the paper
// authors' dense tiles, a block wide or half), not at offsets computed from
// the Layout for every block. Returns how many warm starts were bad.
template <typename L>
int64_t one_step_even_range(const BatchArgs<typename L::Scalar>& args, int64_t begin, int64_t end,
                            const EvenBlocks even[3], bool diagnostics) {
  using T = typename L::Scalar;
  using V = typename L::V;
  int64_t bad_inits = 0;
  for_each_even_block<L>(args, begin, end, even,
                         [&](int64_t first, const T* M_block, const T* R0_block, T* out_block, auto entries_m,
                             auto entries_r, auto entries_out) TORCHROT_LAMBDA_INLINE {
                           // Both inputs are in registers before `out` is written: out may alias them.
                           Mat3<V> M, R0;
                           for (int k = 0; k < 9; ++k) {
                             M.a[k] = entries_m.load(M_block, k);
                             R0.a[k] = entries_r.load(R0_block, k);
                           }
                           kernel::LaneState<L> s =
                               kernel::begin_fit<L>(M, &R0, args.options.init_known_clean, nullptr);
                           kernel::advance_one_step<L>(s, args.options.variant, nullptr);
                           const Mat3<V> R = kernel::finish<L, false>(s);  // one step makes no fallback lanes
                           for (int k = 0; k < 9; ++k) entries_out.store(R.a[k], out_block, k);
                           account_one_step_block<L>(s, args, first, L::width, diagnostics, bad_inits);
                         });
  return bad_inits;
}

// Fits matrices [begin, end); returns how many had a bad warm start.
// kOneStep: max_iter = 1, through kernel::advance_one_step (a code path of its
// own, so that the block's state stays in registers from the loads to the
// stores; it timed faster than advance's loop: benchmarks/lab_notes.md), on
// evenly spaced layouts through one_step_even_range, or, for warm starts with
// L::stream_one_step (AVX2), through one_step_streamed_even_range there and
// one_step_block elsewhere. Otherwise the first pass takes kInterleavedBlocks
// blocks at a time, warm starts on evenly spaced layouts read and written
// through with_even_entries.
template <typename L, BlockPath kPath, bool kOneStep, bool kCold>
int64_t fit_range(const BatchArgs<typename L::Scalar>& args, int64_t begin, int64_t end) {
  using T = typename L::Scalar;
  const bool converge = args.options.max_iter <= 0;
  const bool diagnostics = args.iterations != nullptr || args.status != nullptr;
  const int64_t first_budget = converge ? kStepsPerPass : args.options.max_iter;
  std::vector<SavedLane<T>> pending, next;
  int64_t bad_inits = 0;
  // M's, init's and out's EvenBlocks, where all three have them.
  const EvenBlocks even[3] = {even_blocks(args.m_layout, L::width),
                              kCold ? EvenBlocks{} : even_blocks(args.init_layout, L::width),
                              even_blocks(args.out_layout, L::width)};
  const bool evenly_spaced = kPath == BlockPath::kVectors && !kCold && all_even(even);
  if constexpr (kOneStep && !kCold && !L::stream_one_step && kPath == BlockPath::kVectors && L::width > 1) {
    if (evenly_spaced) return one_step_even_range<L>(args, begin, end, even, diagnostics);
  }
  if constexpr (kOneStep && !kCold && L::stream_one_step && kPath == BlockPath::kVectors) {
    if (evenly_spaced) return one_step_streamed_even_range<L>(args, begin, end, even, diagnostics);
  }
  for (int64_t sub = begin; sub < end; sub += kSubChunk) {
    const int64_t sub_end = std::min(end, sub + kSubChunk);
    pending.clear();
    const auto block_count = [&](int64_t first) TORCHROT_LAMBDA_INLINE {
      return static_cast<int>(std::min<int64_t>(L::width, sub_end - first));
    };
    // The first pass over [sub, sub_end), its blocks read by read_block(first,
    // count, M, R0) (R0 only for warm starts) and their results written by
    // write_block(R, first, count).
    const auto first_pass = [&](auto read_block, auto write_block) TORCHROT_LAMBDA_INLINE {
      // A block's result after its first pass (lanes still running get a
      // provisional one, replaced in a later pass), its bad warm starts, its
      // running lanes saved and its diagnostics.
      const auto conclude = [&](const kernel::LaneState<L>& s, int64_t first, int count) TORCHROT_LAMBDA_INLINE {
        write_block(kernel::finish<L, !kOneStep>(s), first, count);
        if (!kCold && L::any(s.bad_init)) {
          for (int j = 0; j < count; ++j) bad_inits += L::lane_set(s.bad_init, j);
        }
        if (!kOneStep && L::any(s.running)) {
          int64_t index[L::width];
          for (int j = 0; j < L::width; ++j) index[j] = first + j;
          save_running_lanes<L>(s, count, index, pending);
        }
        if (diagnostics) {
          for (int j = 0; j < count; ++j)
            if (!L::lane_set(s.running, j)) store_diagnostics<L>(s, j, args, first + j);
        }
      };
      // Both inputs are in registers before `out` is written: out may alias
      // them. Cold starts' first step takes the maximal objective as its
      // estimate (`objective`).
      const auto begin_block = [&](int64_t first, typename L::V& objective) TORCHROT_LAMBDA_INLINE {
        Mat3<typename L::V> M, R0;
        read_block(first, block_count(first), M, R0);
        return kernel::begin_fit<L>(M, kCold ? nullptr : &R0, args.options.init_known_clean,
                                    kCold ? &objective : nullptr);
      };
      if constexpr (kOneStep) {
        // Consecutive blocks, straight from and to memory.
        for (int64_t first = sub; first < sub_end; first += L::width) {
          if constexpr (!kCold && L::stream_one_step) {
            one_step_block<L, kPath>(args, first, block_count(first), diagnostics, bad_inits);
            continue;
          }
          typename L::V objective;
          kernel::LaneState<L> s = begin_block(first, objective);
          kernel::advance_one_step<L>(s, args.options.variant, kCold ? &objective : nullptr);
          conclude(s, first, block_count(first));
        }
      } else {
        // Consecutive blocks, straight from and to memory, kInterleavedBlocks
        // at a time, a step of each in turn.
        constexpr int kBlocks = kInterleavedBlocks<L>;
        for (int64_t group = sub; group < sub_end; group += kBlocks * L::width) {
          kernel::LaneState<L> states[kBlocks];
          typename L::V objectives[kBlocks];
          const int blocks = static_cast<int>(std::min<int64_t>(kBlocks, (sub_end - group + L::width - 1) / L::width));
          for (int j = 0; j < blocks; ++j) states[j] = begin_block(group + j * L::width, objectives[j]);
          if constexpr (kBlocks == 1) {
            kernel::advance<L, kCold>(states[0], args.options, first_budget, kCold ? &objectives[0] : nullptr);
          } else {
            for (int64_t step = 0; step < first_budget; ++step) {
              bool stepped = false;
              for (int j = 0; j < blocks; ++j) {
                if (!L::any(states[j].running)) continue;
                if (kCold && step == 0) {
                  kernel::advance<L, kCold>(states[j], args.options, 1, &objectives[j]);
                } else {
                  kernel::advance<L>(states[j], args.options, 1);
                }
                stepped = true;
              }
              if (!stepped) break;
            }
          }
          for (int j = 0; j < blocks; ++j) conclude(states[j], group + j * L::width, block_count(group + j * L::width));
        }
      }
    };
    // Evenly spaced warm layouts (the paper authors' tiles, SoA views): each
    // entry at a base pointer and one stride (with_even_entries), as the
    // one-step reads them, not at offsets computed from the Layouts for every
    // block (load_block and store_block: more instructions per matrix on the
    // tiles, benchmarks/lab_notes.md). The one-step has loops of its own.
    constexpr bool kEvenFirstPass = !kOneStep && !kCold && kPath == BlockPath::kVectors && L::width > 1;
    if (kEvenFirstPass && evenly_spaced) {
      if constexpr (kEvenFirstPass) {
        with_even_entries<L>(
            even, [&](auto entries_m, auto entries_r, auto entries_out, bool dense) TORCHROT_LAMBDA_INLINE {
              const int64_t stride[3] = {even[0].block * L::width, even[1].block * L::width, even[2].block * L::width};
              first_pass(
                  [&](int64_t first, int, Mat3<typename L::V>& M, Mat3<typename L::V>& R0) TORCHROT_LAMBDA_INLINE {
                    const T* M_block = args.M + even[0].block * first;
                    const T* R0_block = args.init + even[1].block * first;
                    prefetch_even_blocks<L>(first, M_block, R0_block, args.out + even[2].block * first, stride,
                                            entries_m, entries_r, entries_out, dense);
                    for (int k = 0; k < 9; ++k) {
                      M.a[k] = entries_m.load(M_block, k);
                      R0.a[k] = entries_r.load(R0_block, k);
                    }
                  },
                  [&](const Mat3<typename L::V>& R, int64_t first, int) TORCHROT_LAMBDA_INLINE {
                    T* out_block = args.out + even[2].block * first;
                    for (int k = 0; k < 9; ++k) entries_out.store(R.a[k], out_block, k);
                  });
            });
      }
    } else {
      first_pass(
          [&](int64_t first, int count, Mat3<typename L::V>& M, Mat3<typename L::V>& R0) TORCHROT_LAMBDA_INLINE {
            M = load_block<L, kPath>(args.M, args.m_layout, first, count);
            if constexpr (!kCold) R0 = load_block<L, kPath>(args.init, args.init_layout, first, count);
          },
          [&](const Mat3<typename L::V>& R, int64_t first, int count)
              TORCHROT_LAMBDA_INLINE { store_block<L, kPath>(R, args.out, args.out_layout, first, count); });
    }
    // Later passes: the unfinished lanes, regrouped into full blocks (none
    // after one step: advance_one_step leaves no lane running).
    if constexpr (kOneStep) continue;
    while (!pending.empty()) {
      next.clear();
      for (size_t i = 0; i < pending.size(); i += L::width) {
        const int count = static_cast<int>(std::min<size_t>(L::width, pending.size() - i));
        kernel::LaneState<L> s = restore_block<L>(pending.data() + i, count);
        kernel::advance<L>(s, args.options, kStepsPerPass);
        const Mat3<typename L::V> R = kernel::finish<L>(s);
        int64_t indices[L::width];
        for (int j = 0; j < count; ++j) indices[j] = pending[i + j].index;
        if (L::any(s.running)) save_running_lanes<L>(s, count, indices, next);
        alignas(64) T entries[9][L::width];
        for (int k = 0; k < 9; ++k) L::store(R.a[k], entries[k]);
        for (int j = 0; j < count; ++j) {
          const int64_t index = indices[j];
          if (L::lane_set(s.running, j)) continue;
          for (int k = 0; k < 9; ++k) {
            args.out[offset<kPath == BlockPath::kTransposed>(args.out_layout, index, k)] = entries[k][j];
          }
          if (diagnostics) store_diagnostics<L>(s, j, args, index);
        }
      }
      pending.swap(next);
    }
  }
  return bad_inits;
}

template <typename L>
int64_t fit_batch(const BatchArgs<typename L::Scalar>& args) {
  const BlockPath path =
      full_block_path(L::width, {&args.m_layout, &args.out_layout, args.init == nullptr ? nullptr : &args.init_layout});
  std::atomic<int64_t> bad_inits{0};
  // One instantiation per case, so that each loop is compiled for its own
  // (in one loop with the cold start's code, warm one-step fits executed more
  // instructions per matrix: benchmarks/lab_notes.md).
  const auto run = [&](auto one_step, auto cold) {
    parallel_blocks(args.n, L::width, kGrainSize, [&](int64_t begin, int64_t end) {
      const FlushToZero flush_to_zero;  // in the thread that runs the range
      run_block_paths<L>(path, begin, end, [&](auto block_path, int64_t b, int64_t e) {
        bad_inits += fit_range<L, block_path.value, one_step.value, cold.value>(args, b, e);
      });
    });
  };
  const bool one_step = args.options.max_iter == 1, cold = args.init == nullptr;
  if (one_step) {
    cold ? run(std::true_type{}, std::true_type{}) : run(std::true_type{}, std::false_type{});
  } else {
    cold ? run(std::false_type{}, std::true_type{}) : run(std::false_type{}, std::false_type{});
  }
  return bad_inits.load();
}

// What the check begin_fit applies finds in the warm starts, without
// fitting: fit_rotation_out validates init before it writes anything, so that
// a call that raises leaves `out` (which may be init itself) as it was; when
// every warm start is clean, its fit then skips that check
// (FitOptions::init_known_clean).
template <typename L>
WarmStartCount count_bad_warm_starts(const WarmStartArgs<typename L::Scalar>& args) {
  using T = typename L::Scalar;
  using V = typename L::V;
  const BlockPath path = full_block_path(L::width, {&args.layout});
  const EvenBlocks even = even_blocks(args.layout, L::width);
  std::atomic<int64_t> bad{0}, unclean{0};
  parallel_blocks(args.n, L::width, kGrainSize, [&](int64_t begin, int64_t end) {
    const FlushToZero flush_to_zero;  // as the fit that trusts this count computes
    int64_t local_bad = 0, local_unclean = 0;
    run_block_paths<L>(path, begin, end, [&](auto block_path, int64_t b, int64_t e) {
      // load(first, count): the warm starts of the block at `first`; one loop per way of reading them.
      const auto check_blocks = [&](auto load) TORCHROT_LAMBDA_INLINE {
        for (int64_t first = b; first < e; first += L::width) {
          const int count = static_cast<int>(std::min<int64_t>(L::width, e - first));
          const kernel::WarmStartCheck<L> check = kernel::check_warm_start<L>(load(first, count));
          const typename L::Mask clean = kernel::used_as_is<L>(check, kernel::Tolerances<T>::init_clean);
          if (!L::all(clean)) {
            for (int j = 0; j < count; ++j) {
              local_bad += L::lane_set(check.bad, j);
              local_unclean += !L::lane_set(clean, j);
            }
          }
        }
      };
      // As one_step_block and one_step_even_range read them (`entries`: EvenEntries).
      const auto load_even = [&](auto entries) TORCHROT_LAMBDA_INLINE {
        return [&, entries](int64_t first, int) TORCHROT_LAMBDA_INLINE {
          const T* block = args.init + even.block * first;
          prefetch_even_block<L, 0>(block, first, even.block * L::width, entries, even.dense());
          Mat3<V> R0;
          for (int k = 0; k < 9; ++k) R0.a[k] = entries.load(block, k);
          return R0;
        };
      };
      if (block_path.value == BlockPath::kVectors && even.entry != 0) {
        if constexpr (L::width > 1) {  // tiles half a block wide: as with_even_entries reads them
          if (even.half != 0) return check_blocks(load_even(HalfTileEntries<L>{}));
        }
        return check_blocks(load_even(EvenEntries<L, 0, 0>{even.entry}));
      }
      check_blocks([&](int64_t first, int count) TORCHROT_LAMBDA_INLINE {
        return load_block<L, block_path.value>(args.init, args.layout, first, count);
      });
    });
    bad += local_bad;
    unclean += local_unclean;
  });
  return WarmStartCount{bad.load(), unclean.load()};
}

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace cpu
}  // namespace torchrot
