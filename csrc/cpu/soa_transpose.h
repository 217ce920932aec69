// In-register AoS <-> SoA transposition of a contiguous block of W row-major
// 3x3 matrices (9 W consecutive values), for the AVX2 and AVX-512 kernels
// (x86-64 only; every other object, NEON's included, gathers through a buffer).
// Pure data movement: the results are the same bit for bit as a gather.
//
// AVX-512: since 9 = 3 x 3 it is two stages of a stride-3 (de)interleave of
// three vectors. Because gcd(3, W) = 1 for W = 8, 16, the W values 3m + r
// (m = 0..W-1) of three consecutive vectors sit in W distinct lanes, so each
// stride-3 deinterleave is two constant blends (gather the right lane from the
// right vector) and one permute (put lane p at position m). Per block that is
// 18 permutes and 36 blends instead of 18 W scalar moves. Stage 1 splits each
// group of three vectors by column c = e mod 3; stage 2 splits each column
// stream by row r: value 3 (3 j + r) + c = 9 j + 3 r + c, which is entry
// (r, c) of matrix j. The inverse runs the stages backwards.
//
// AVX2: cross-lane permutes are slow on some AVX2 cores (vpermps is 3 uops at
// one per 4 cycles on AMD Zen 1), so a block moves through 128-bit halves
// instead: the two halves of a vector hold matrices j and j + W/2, and the
// transposes are in-lane unpacks and shuffles (float: 4 x 4 transposes of
// entries 0-3, 4-7 and 5-8, whose overlap is rewritten with the same values;
// double: pairs of entries). On Zen 1, against the stride-3 scheme, this made
// the warm-start check of contiguous data nearly as fast as plain loads of
// SoA data, and the one-step and converged fits faster in both dtypes
// (benchmarks/lab_notes.md).
#pragma once

#include <ATen/cpu/vec/vec.h>

#include <cstdint>

namespace torchrot {
namespace cpu {
inline namespace CPU_CAPABILITY {
namespace {

#if defined(CPU_CAPABILITY_AVX512) || defined(CPU_CAPABILITY_AVX2)
#define TORCHROT_HAVE_SIMD_TRANSPOSE 1
#endif

#if defined(CPU_CAPABILITY_AVX512)

// Constant lane tables of a stride-3 (de)interleave of three W-wide vectors
// (values 0..3W-1, vector g holding gW..gW+W-1), in the integer type `Int`
// of the permute indices.
//   deinterleave, output r:  B = in[0] | in[1] on mask pick[r][0] | in[2] on
//     mask pick[r][1]; out[r] = permute(B, gather[r])  (lane m = value 3m + r)
//   interleave, output g:  P_r = permute(in[r], scatter[r]);
//     out[g] = P_0 | P_1 on place[g][0] | P_2 on place[g][1]
template <int W, typename Int>
struct Stride3Tables {
  alignas(64) Int gather[3][W] = {};
  alignas(64) Int scatter[3][W] = {};
  uint32_t pick[3][2] = {};  // blend bit masks
  uint32_t place[3][2] = {};

  constexpr Stride3Tables() {
    for (int r = 0; r < 3; ++r) {
      for (int m = 0; m < W; ++m) {
        const int p = (3 * m + r) % W;
        gather[r][m] = static_cast<Int>(p);
        scatter[r][p] = static_cast<Int>(m);
      }
      for (int p = 0; p < W; ++p) {
        for (int g = 1; g < 3; ++g) {
          if ((g * W + p) % 3 == r) pick[r][g - 1] |= 1u << p;  // deinterleave: lane p of output r is in vector g
        }
      }
    }
    for (int g = 0; g < 3; ++g) {
      for (int p = 0; p < W; ++p) {
        const int r = (g * W + p) % 3;  // interleave: lane p of vector g comes from output r
        if (r > 0) place[g][r - 1] |= 1u << p;
      }
    }
  }
};

// The ISA-specific primitives: constant-mask blend and constant permute.
template <typename T>
struct Shuffle;

template <>
struct Shuffle<float> {
  using R = __m512;
  static constexpr int W = 16;
  static constexpr Stride3Tables<W, int32_t> tables{};
  static R permute(R a, const int32_t* idx) { return _mm512_permutexvar_ps(_mm512_load_si512(idx), a); }
  static R blend(R a, R b, uint32_t mask) { return _mm512_mask_blend_ps(static_cast<__mmask16>(mask), a, b); }
};
template <>
struct Shuffle<double> {
  using R = __m512d;
  static constexpr int W = 8;
  static constexpr Stride3Tables<W, int64_t> tables{};
  static R permute(R a, const int64_t* idx) { return _mm512_permutexvar_pd(_mm512_load_si512(idx), a); }
  static R blend(R a, R b, uint32_t mask) { return _mm512_mask_blend_pd(static_cast<__mmask8>(mask), a, b); }
};

// out[r] lane m = value 3m + r of the three vectors in[0..2].
template <typename T>
inline void deinterleave3(const typename Shuffle<T>::R in[3], typename Shuffle<T>::R out[3]) {
  using S = Shuffle<T>;
  constexpr const auto& tab = S::tables;
  for (int r = 0; r < 3; ++r) {
    const typename S::R b = S::blend(S::blend(in[0], in[1], tab.pick[r][0]), in[2], tab.pick[r][1]);
    out[r] = S::permute(b, tab.gather[r]);
  }
}

// Inverse of deinterleave3.
template <typename T>
inline void interleave3(const typename Shuffle<T>::R in[3], typename Shuffle<T>::R out[3]) {
  using S = Shuffle<T>;
  constexpr const auto& tab = S::tables;
  typename S::R placed[3];
  for (int r = 0; r < 3; ++r) placed[r] = S::permute(in[r], tab.scatter[r]);
  for (int g = 0; g < 3; ++g)
    out[g] = S::blend(S::blend(placed[0], placed[1], tab.place[g][0]), placed[2], tab.place[g][1]);
}

// Loads W contiguous matrices: soa[k] lane j = entry k of matrix j.
template <typename T>
inline void load_soa(const T* data, at::vec::Vectorized<T> soa[9]) {
  using S = Shuffle<T>;
  typename S::R v[9], u[3][3], w[3];
  for (int i = 0; i < 9; ++i) v[i] = at::vec::Vectorized<T>::loadu(data + i * S::W);
  for (int q = 0; q < 3; ++q) deinterleave3<T>(v + 3 * q, u[q]);  // u[q][c]
  for (int c = 0; c < 3; ++c) {
    const typename S::R column[3] = {u[0][c], u[1][c], u[2][c]};
    deinterleave3<T>(column, w);  // w[r]
    for (int r = 0; r < 3; ++r) soa[3 * r + c] = w[r];
  }
}

// Inverse of load_soa.
template <typename T>
inline void store_soa(const at::vec::Vectorized<T> soa[9], T* data) {
  using S = Shuffle<T>;
  typename S::R u[3][3], v[3];
  for (int c = 0; c < 3; ++c) {
    const typename S::R rows[3] = {soa[c], soa[3 + c], soa[6 + c]};
    typename S::R column[3];
    interleave3<T>(rows, column);
    for (int q = 0; q < 3; ++q) u[q][c] = column[q];
  }
  for (int q = 0; q < 3; ++q) {
    interleave3<T>(u[q], v);
    for (int g = 0; g < 3; ++g) at::vec::Vectorized<T>(v[g]).store(data + (3 * q + g) * S::W);
  }
}

#elif defined(CPU_CAPABILITY_AVX2)

// The 128 bits at `lo` and at `hi` as the two halves of one vector.
inline __m256 load_halves(const float* lo, const float* hi) {
  return _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(lo)), _mm_loadu_ps(hi), 1);
}
inline __m256d load_halves(const double* lo, const double* hi) {
  return _mm256_insertf128_pd(_mm256_castpd128_pd256(_mm_loadu_pd(lo)), _mm_loadu_pd(hi), 1);
}
inline void store_halves(__m256 v, float* lo, float* hi) {
  _mm_storeu_ps(lo, _mm256_castps256_ps128(v));
  _mm_storeu_ps(hi, _mm256_extractf128_ps(v, 1));
}
inline void store_halves(__m256d v, double* lo, double* hi) {
  _mm_storeu_pd(lo, _mm256_castpd256_pd128(v));
  _mm_storeu_pd(hi, _mm256_extractf128_pd(v, 1));
}

// Transposes the 4 x 4 matrix in each 128-bit half: out[k] lane i = in[i]
// lane k, within the lower and within the upper four lanes.
inline void transpose_halves(const __m256 in[4], __m256 out[4]) {
  const __m256 t0 = _mm256_unpacklo_ps(in[0], in[1]);           // a0 b0 a1 b1
  const __m256 t1 = _mm256_unpackhi_ps(in[0], in[1]);           // a2 b2 a3 b3
  const __m256 t2 = _mm256_unpacklo_ps(in[2], in[3]);           // c0 d0 c1 d1
  const __m256 t3 = _mm256_unpackhi_ps(in[2], in[3]);           // c2 d2 c3 d3
  out[0] = _mm256_shuffle_ps(t0, t2, _MM_SHUFFLE(1, 0, 1, 0));  // a0 b0 c0 d0
  out[1] = _mm256_shuffle_ps(t0, t2, _MM_SHUFFLE(3, 2, 3, 2));
  out[2] = _mm256_shuffle_ps(t1, t3, _MM_SHUFFLE(1, 0, 1, 0));
  out[3] = _mm256_shuffle_ps(t1, t3, _MM_SHUFFLE(3, 2, 3, 2));
}

// float, W = 8: lane i (i < 4) holds matrix i and lane 4 + i matrix 4 + i, so
// loading entries e..e+3 of matrices i and 4 + i into vector i (i < 4) and
// transposing the halves gives entries e..e+3 as vectors. Entry groups
// 0-3, 4-7 and 5-8 stay inside each matrix (no access past the block).
constexpr int kFloatEntryGroups[3] = {0, 4, 5};

inline void load_soa(const float* data, at::vec::Vectorized<float> soa[9]) {
  for (const int e : kFloatEntryGroups) {
    __m256 rows[4], entries[4];
    for (int i = 0; i < 4; ++i) rows[i] = load_halves(data + 9 * i + e, data + 9 * (i + 4) + e);
    transpose_halves(rows, entries);
    for (int k = 0; k < 4; ++k) soa[e + k] = entries[k];  // group 5-8 rewrites 5-7 with the same values
  }
}

// Inverse of load_soa; group 5-8 rewrites entries 5-7 with the values group
// 4-7 wrote.
inline void store_soa(const at::vec::Vectorized<float> soa[9], float* data) {
  for (const int e : kFloatEntryGroups) {
    const __m256 entries[4] = {soa[e], soa[e + 1], soa[e + 2], soa[e + 3]};
    __m256 rows[4];
    transpose_halves(entries, rows);
    for (int i = 0; i < 4; ++i) store_halves(rows[i], data + 9 * i + e, data + 9 * (i + 4) + e);
  }
}

// double, W = 4: the pair of entries e, e + 1 of matrices 0 and 2 in one
// vector, of matrices 1 and 3 in another; one unpack of the two gives entry e
// and one gives entry e + 1. Pairs 0, 2, 4, 6 and 7 cover the nine entries.
constexpr int kDoubleEntryPairs[5] = {0, 2, 4, 6, 7};

inline void load_soa(const double* data, at::vec::Vectorized<double> soa[9]) {
  for (const int e : kDoubleEntryPairs) {
    const __m256d even = load_halves(data + e, data + 18 + e);     // matrices 0, 2
    const __m256d odd = load_halves(data + 9 + e, data + 27 + e);  // matrices 1, 3
    soa[e] = _mm256_unpacklo_pd(even, odd);
    soa[e + 1] = _mm256_unpackhi_pd(even, odd);
  }
}

inline void store_soa(const at::vec::Vectorized<double> soa[9], double* data) {
  for (const int e : kDoubleEntryPairs) {
    store_halves(_mm256_unpacklo_pd(soa[e], soa[e + 1]), data + e, data + 18 + e);
    store_halves(_mm256_unpackhi_pd(soa[e], soa[e + 1]), data + 9 + e, data + 27 + e);
  }
}

#endif  // CPU_CAPABILITY_AVX512 / CPU_CAPABILITY_AVX2

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace cpu
}  // namespace torchrot
