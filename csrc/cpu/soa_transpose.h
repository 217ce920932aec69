// In-register AoS <-> SoA transposition of a contiguous block of W row-major
// 3x3 matrices (9 W consecutive values), for the AVX2 and AVX-512 kernels
// (x86-64 only; every other object, NEON's included, gathers through a buffer).
//
// Since 9 = 3 x 3 it is two stages of a stride-3 (de)interleave of three
// vectors. Because gcd(3, W) = 1 for W = 4, 8, 16, the W values 3m + r
// (m = 0..W-1) of three consecutive vectors sit in W distinct lanes, so each
// stride-3 deinterleave is two constant blends (gather the right lane from the
// right vector) and one permute (put lane p at position m). Per block that is
// 18 permutes and 36 blends instead of 18 W scalar moves.
//
// Stage 1 splits each group of three vectors by column c = e mod 3; stage 2
// splits each column stream by row r: value 3 (3 j + r) + c = 9 j + 3 r + c,
// which is entry (r, c) of matrix j. The inverse runs the stages backwards.
#pragma once

#include <ATen/cpu/vec/vec.h>

#include <cstdint>
#include <type_traits>

namespace torchrot {
namespace cpu {
inline namespace CPU_CAPABILITY {
namespace {

#if defined(CPU_CAPABILITY_AVX512) || defined(CPU_CAPABILITY_AVX2)
#define TORCHROT_HAVE_SIMD_TRANSPOSE 1

// Constant lane tables of a stride-3 (de)interleave of three W-wide vectors
// (values 0..3W-1, vector g holding gW..gW+W-1), in the integer width `Int`
// of the permute indices (`Int` pairs for AVX2 double, see Shuffle<double>).
//   deinterleave, output r:  B = in[0] | in[1] on mask pick[r][0] | in[2] on
//     mask pick[r][1]; out[r] = permute(B, gather[r])  (lane m = value 3m + r)
//   interleave, output g:  P_r = permute(in[r], scatter[r]);
//     out[g] = P_0 | P_1 on place[g][0] | P_2 on place[g][1]
template <int W, typename Int, int kIndexRepeat = 1>
struct Stride3Tables {
  alignas(64) Int gather[3][W * kIndexRepeat] = {};
  alignas(64) Int scatter[3][W * kIndexRepeat] = {};
  alignas(64) Int pick_lanes[3][2][W] = {};   // -1 where selected (blendv masks)
  alignas(64) Int place_lanes[3][2][W] = {};
  uint32_t pick[3][2] = {};                   // bit masks (AVX-512 blends)
  uint32_t place[3][2] = {};

  constexpr Stride3Tables() {
    for (int r = 0; r < 3; ++r) {
      for (int m = 0; m < W; ++m) {
        const int p = (3 * m + r) % W;
        for (int k = 0; k < kIndexRepeat; ++k) {
          gather[r][m * kIndexRepeat + k] = static_cast<Int>(p * kIndexRepeat + k);
          scatter[r][p * kIndexRepeat + k] = static_cast<Int>(m * kIndexRepeat + k);
        }
      }
      for (int p = 0; p < W; ++p) {
        for (int g = 1; g < 3; ++g) {
          if ((g * W + p) % 3 == r) {  // deinterleave: lane p of output r is in vector g
            pick[r][g - 1] |= 1u << p;
            pick_lanes[r][g - 1][p] = -1;
          }
        }
      }
    }
    for (int g = 0; g < 3; ++g) {
      for (int p = 0; p < W; ++p) {
        const int r = (g * W + p) % 3;  // interleave: lane p of vector g comes from output r
        if (r > 0) {
          place[g][r - 1] |= 1u << p;
          place_lanes[g][r - 1][p] = -1;
        }
      }
    }
  }
};

// The ISA-specific primitives: constant-mask blend and constant permute.
template <typename T>
struct Shuffle;

#if defined(CPU_CAPABILITY_AVX512)
template <>
struct Shuffle<float> {
  using R = __m512;
  static constexpr int W = 16;
  static constexpr Stride3Tables<W, int32_t> tables{};
  static R permute(R a, const int32_t* idx) { return _mm512_permutexvar_ps(_mm512_load_si512(idx), a); }
  static R blend(R a, R b, uint32_t mask, const int32_t*) {
    return _mm512_mask_blend_ps(static_cast<__mmask16>(mask), a, b);
  }
};
template <>
struct Shuffle<double> {
  using R = __m512d;
  static constexpr int W = 8;
  static constexpr Stride3Tables<W, int64_t> tables{};
  static R permute(R a, const int64_t* idx) { return _mm512_permutexvar_pd(_mm512_load_si512(idx), a); }
  static R blend(R a, R b, uint32_t mask, const int64_t*) {
    return _mm512_mask_blend_pd(static_cast<__mmask8>(mask), a, b);
  }
};
#else  // AVX2
template <>
struct Shuffle<float> {
  using R = __m256;
  static constexpr int W = 8;
  static constexpr Stride3Tables<W, int32_t> tables{};
  static R permute(R a, const int32_t* idx) {
    return _mm256_permutevar8x32_ps(a, _mm256_load_si256(reinterpret_cast<const __m256i*>(idx)));
  }
  static R blend(R a, R b, uint32_t, const int32_t* lanes) {
    return _mm256_blendv_ps(a, b, _mm256_castsi256_ps(_mm256_load_si256(reinterpret_cast<const __m256i*>(lanes))));
  }
};
template <>
struct Shuffle<double> {  // permutes 64-bit lanes as pairs of 32-bit lanes
  using R = __m256d;
  static constexpr int W = 4;
  static constexpr Stride3Tables<W, int32_t, 2> tables{};
  static constexpr Stride3Tables<W, int64_t> masks{};
  static R permute(R a, const int32_t* idx) {
    const __m256i index = _mm256_load_si256(reinterpret_cast<const __m256i*>(idx));
    return _mm256_castps_pd(_mm256_permutevar8x32_ps(_mm256_castpd_ps(a), index));
  }
  static R blend(R a, R b, uint32_t, const int64_t* lanes) {
    return _mm256_blendv_pd(a, b, _mm256_castsi256_pd(_mm256_load_si256(reinterpret_cast<const __m256i*>(lanes))));
  }
};
#endif

template <typename S>
constexpr const auto& mask_tables() {
  if constexpr (std::is_same_v<typename S::R, __m256d>) {
    return S::masks;
  } else {
    return S::tables;
  }
}

// out[r] lane m = value 3m + r of the three vectors in[0..2].
template <typename T>
inline void deinterleave3(const typename Shuffle<T>::R in[3], typename Shuffle<T>::R out[3]) {
  using S = Shuffle<T>;
  constexpr const auto& tab = S::tables;
  constexpr const auto& mask = mask_tables<S>();
  for (int r = 0; r < 3; ++r) {
    typename S::R b = S::blend(in[0], in[1], mask.pick[r][0], mask.pick_lanes[r][0]);
    b = S::blend(b, in[2], mask.pick[r][1], mask.pick_lanes[r][1]);
    out[r] = S::permute(b, tab.gather[r]);
  }
}

// Inverse of deinterleave3.
template <typename T>
inline void interleave3(const typename Shuffle<T>::R in[3], typename Shuffle<T>::R out[3]) {
  using S = Shuffle<T>;
  constexpr const auto& tab = S::tables;
  constexpr const auto& mask = mask_tables<S>();
  typename S::R placed[3];
  for (int r = 0; r < 3; ++r) placed[r] = S::permute(in[r], tab.scatter[r]);
  for (int g = 0; g < 3; ++g) {
    typename S::R v = S::blend(placed[0], placed[1], mask.place[g][0], mask.place_lanes[g][0]);
    out[g] = S::blend(v, placed[2], mask.place[g][1], mask.place_lanes[g][1]);
  }
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

#endif  // CPU_CAPABILITY_AVX512 || CPU_CAPABILITY_AVX2

}  // namespace
}  // namespace CPU_CAPABILITY
}  // namespace cpu
}  // namespace torchrot
