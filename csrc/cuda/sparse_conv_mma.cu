// Sparse convolution forward on CUDA, tensor cores through mma.sync on the cp.async pipeline
// (float16, bfloat16, TF32 and the experimental 3xTF32), with its tile shapes. sparse_conv_kernel.cu
// picks it.
#include <ATen/ATen.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>

#include <cstdint>
#include <type_traits>

#include "sparse_conv_pipeline.cuh"

namespace lidarops {
namespace sparse {
namespace {

// ------------------------------------------------------------------------------------------------
// forward, tensor cores through mma.sync (sm_80+; 16-byte aligned rows, Cin a multiple of the
// 16-byte vector, K <= 32). The float32 SIMT kernel's pipeline (offset list, cp.async ring of STAGES
// buffers) feeding fragments loaded by ldmatrix and multiplied by mma.sync:
//   - A (BM gathered rows x 128 bytes of channels) and B (BN output channels x the same channels, the
//     weights as stored) sit in shared memory with the channels contiguous, 16-byte chunks swizzled
//     (MmaTile::at) so that ldmatrix and the copies are free of bank conflicts without padding: four
//     64 x 64 blocks fit in a multiprocessor; tiles of 32 or 64 rows (mma_tile_shape);
//   - one ldmatrix.x4 gives a 16 x (32 bytes) A fragment or two 8 x (32 bytes) B fragments, for 16-bit
//     types (m16n8k16) and for float32 (m16n8k8 TF32: a 32-bit element is a pair of 16-bit ones) alike;
//   - float32 is rounded to nearest TF32 (tf32_round); in the 3xTF32 mode each operand is split into a
//     TF32 "big" part and the TF32 rounding of the rest, and big*big + big*small + small*big (the small
//     products first) comes close to float32 accuracy on the tensor cores (split_tf32);
//   - a warp skips the products of each 16-row fragment none of whose rows has an input at the
//     step's offset (the tile lists the offsets any of its rows has);
//   - each thread writes its accumulator fragments to their output rows through the epilogue.
// Per output element the sum runs over offsets, then channels, in ascending order: deterministic.
// ------------------------------------------------------------------------------------------------
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
__device__ __forceinline__ void ldmatrix_x4(unsigned (&r)[4], const void* p) {
  const unsigned a = static_cast<unsigned>(__cvta_generic_to_shared(p));
  asm volatile("ldmatrix.sync.aligned.m8n8.x4.shared.b16 {%0, %1, %2, %3}, [%4];\n"
               : "=r"(r[0]), "=r"(r[1]), "=r"(r[2]), "=r"(r[3])
               : "r"(a));
}

// d += a . b for one 16 x 8 fragment (k = 16 for 16-bit types, 8 for TF32)
template <Mma M>
__device__ __forceinline__ void mma_16x8(float (&d)[4], const unsigned (&a)[4], const unsigned (&b)[2]) {
  if constexpr (M == Mma::kF16) {
    asm volatile("mma.sync.aligned.m16n8k16.row.col.f32.f16.f16.f32 {%0, %1, %2, %3}, {%4, %5, %6, %7}, {%8, %9}, "
                 "{%0, %1, %2, %3};\n"
                 : "+f"(d[0]), "+f"(d[1]), "+f"(d[2]), "+f"(d[3])
                 : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b[0]), "r"(b[1]));
  } else if constexpr (M == Mma::kBF16) {
    asm volatile("mma.sync.aligned.m16n8k16.row.col.f32.bf16.bf16.f32 {%0, %1, %2, %3}, {%4, %5, %6, %7}, {%8, %9}, "
                 "{%0, %1, %2, %3};\n"
                 : "+f"(d[0]), "+f"(d[1]), "+f"(d[2]), "+f"(d[3])
                 : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b[0]), "r"(b[1]));
  } else {
    asm volatile("mma.sync.aligned.m16n8k8.row.col.f32.tf32.tf32.f32 {%0, %1, %2, %3}, {%4, %5, %6, %7}, {%8, %9}, "
                 "{%0, %1, %2, %3};\n"
                 : "+f"(d[0]), "+f"(d[1]), "+f"(d[2]), "+f"(d[3])
                 : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b[0]), "r"(b[1]));
  }
}

template <int N>
__device__ __forceinline__ void round_tf32(unsigned (&r)[N]) {
#pragma unroll
  for (int i = 0; i < N; ++i) r[i] = tf32_round(r[i]);
}
// 3xTF32 operands: big = the float32 bits as they are (the tensor core truncates them), small = the
// exact rest x - trunc(x), rounded to nearest by adding half an ulp to its bits (the bits of an inf or
// NaN x give the rest NaN, 0x7fffffff, which that addition turns into -0: big carries the inf or NaN;
// an inf can still end as NaN, times a weight whose small part is 0). Four instructions per register,
// against seven with cvt.rna; the dropped small*small term and the truncated big leave about 3.5x the
// error of FFMA float32, with two accumulator sets (docs/notes/sparse.md).
template <int N>
__device__ __forceinline__ void split_tf32(const unsigned (&big)[N], unsigned (&small)[N]) {
#pragma unroll
  for (int i = 0; i < N; ++i) {
    const float rest = __uint_as_float(big[i]) - __uint_as_float(big[i] & 0xffffe000u);
    small[i] = (__float_as_uint(rest) + 0x1000u) & 0xffffe000u;
  }
}
#endif

template <typename T, Mma M, typename Tile>
__global__ void __launch_bounds__(Tile::kThreads)
    conv_fwd_mma_kernel(const T* __restrict__ x, const T* __restrict__ w, const int32_t* __restrict__ nbr,
                        const int32_t* __restrict__ order, T* __restrict__ out, int64_t n_out, int cin, int cout,
                        int K, ConvEpilogue epi, float* __restrict__ partial, int64_t n_in) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  using S = typename Tile::S;
  constexpr int V = Tile::V, BM = Tile::BM, BN = Tile::BN, BK = Tile::BK, KS = Tile::KS;
  constexpr int STAGES = Tile::STAGES, MF = Tile::MF, NF = Tile::NF, kThreads = Tile::kThreads, CH = BK / V;
  extern __shared__ __align__(128) unsigned char smem_raw[];
  S* ring = reinterpret_cast<S*>(smem_raw);                                             // [STAGES][BM + BN][BK]
  int32_t* rows = reinterpret_cast<int32_t*>(smem_raw + Tile::kStage * STAGES);         // [K][BM]
  __shared__ int64_t orow[BM];
  __shared__ unsigned present, groups[kAsyncMaxK];
  __shared__ int klist[kAsyncMaxK];
  __shared__ int nk;
  const int tid = threadIdx.x, warp = tid / 32, lane = tid % 32;
  const int m0 = (warp / Tile::WN) * 16 * MF, n0 = (warp % Tile::WN) * 8 * NF;
  const int col0 = static_cast<int>(blockIdx.y) * BN;
  const int chunks = (cin + BK - 1) / BK;
  const OffsetSplit split = offset_split(tile_map_slice<BM, kThreads>(
      nbr, order, n_out, n_in, K, heavy_first_tile() * BM, orow, rows, klist, &present, &nk, groups));
  const int steps = (split.hi - split.lo) * chunks;
  const S* xs = reinterpret_cast<const S*>(x);
  const S* ws = reinterpret_cast<const S*>(w);
  // This thread's 16-byte chunks of a step: chunk c_t of the rows r_t + u * RSTEP of A and of B, at the
  // same swizzled place in both (row & 7 is r_t & 7 for every u).
  constexpr int RSTEP = kThreads / CH;
  static_assert(kThreads % CH == 0 && RSTEP % 8 == 0 && BM % RSTEP == 0 && BN % RSTEP == 0, "whole rows");
  const int c_t = tid % CH, r_t = tid / CH, dst0 = Tile::at(r_t, c_t);
  const StepCopies<S, BM / RSTEP, BN / RSTEP, RSTEP> copies(col0, r_t, K, cin, cout);
  StepCursor<STAGES> in(split.lo);  // the next step to issue
  auto issue = [&]() {
    if (in.kpos < split.hi) {
      S* As = ring + in.slot * (BM + BN) * BK + dst0;  // B follows: Bs[at(n, c)] = W[col0 + n, k, c0 + c * V ...]
      copies.copy(As, RSTEP * BK, As + BM * BK, RSTEP * BK, rows + klist[in.kpos] * BM + r_t, xs, ws, klist[in.kpos],
                  in.chunk * BK + c_t * V, cin);
    }
    in.next(chunks);
    cp_async_commit();
  };

  // CHAINS accumulator sets: k-step ks adds into set ks % CHAINS, and the sets are added in a
  // fixed order at the end. 3xTF32 chains three mma.sync per fragment and k-step, so two sets shorten
  // its dependency chains and its sums (faster and more accurate); other types gain nothing from two.
  constexpr int CHAINS = M == Mma::k3xTF32 && MF * NF <= 8 ? 2 : 1;
  float acc[CHAINS][MF][NF][4];
#pragma unroll
  for (int c = 0; c < CHAINS; ++c)
#pragma unroll
    for (int i = 0; i < MF; ++i)
#pragma unroll
      for (int j = 0; j < NF; ++j)
#pragma unroll
        for (int q = 0; q < 4; ++q) acc[c][i][j][q] = 0.f;
#pragma unroll
  for (int t = 0; t < STAGES - 1; ++t) issue();
  // ldmatrix addresses of this lane at k-step ks: A row m0 + lane % 16 (+16 per fragment), chunk
  // 2 ks + lane / 16; B row n0 + lane % 8 + 8 (lane / 16) (+16 per fragment pair), chunk 2 ks + (lane / 8) % 2.
  // Fragments start at multiples of 8 rows, so every row this lane reads has row & 7 == lane & 7.
  int a_off[BK / KS], b_off[BK / KS];
#pragma unroll
  for (int ks = 0; ks < BK / KS; ++ks) {
    a_off[ks] = Tile::at(m0 + lane % 16, 2 * ks + lane / 16);
    b_off[ks] = BM * BK + Tile::at(n0 + lane % 8 + 8 * (lane / 16), 2 * ks + (lane / 8) % 2);
  }
  StepCursor<STAGES> at(split.lo);  // the step multiplied
  for (int t = 0; t < steps; ++t, at.next(chunks)) {
    cp_async_wait<STAGES - 2>();
    __syncthreads();
    issue();  // step t + STAGES - 1
    // bit i: fragment row i has inputs at this step's offset
    const unsigned live = groups[klist[at.kpos]] >> (m0 / 16);
    const S* st = ring + at.slot * (BM + BN) * BK;
#pragma unroll
    for (int ks = 0; ks < BK / KS; ++ks) {
      unsigned b[NF][2];
#pragma unroll
      for (int j = 0; j < NF / 2; ++j) {
        unsigned r[4];
        ldmatrix_x4(r, st + b_off[ks] + j * 16 * BK);
        b[2 * j][0] = r[0];
        b[2 * j][1] = r[1];
        b[2 * j + 1][0] = r[2];
        b[2 * j + 1][1] = r[3];
      }
      [[maybe_unused]] unsigned b_small[NF][2];
      if constexpr (M == Mma::k3xTF32) {
#pragma unroll
        for (int j = 0; j < NF; ++j) split_tf32(b[j], b_small[j]);
      } else if constexpr (M == Mma::kTF32) {
#pragma unroll
        for (int j = 0; j < NF; ++j) round_tf32(b[j]);
      }
#pragma unroll
      for (int i = 0; i < MF; ++i) {
        if (!((live >> i) & 1u)) continue;  // warp-uniform: no row of this fragment has the offset
        unsigned a[4];
        ldmatrix_x4(a, st + a_off[ks] + i * 16 * BK);
        if constexpr (M == Mma::k3xTF32) {
          unsigned a_small[4];
          split_tf32(a, a_small);
#pragma unroll
          for (int j = 0; j < NF; ++j) {
            mma_16x8<M>(acc[ks % CHAINS][i][j], a_small, b[j]);
            mma_16x8<M>(acc[ks % CHAINS][i][j], a, b_small[j]);
            mma_16x8<M>(acc[ks % CHAINS][i][j], a, b[j]);
          }
        } else {
          if constexpr (M == Mma::kTF32) round_tf32(a);
#pragma unroll
          for (int j = 0; j < NF; ++j) mma_16x8<M>(acc[ks % CHAINS][i][j], a, b[j]);
        }
      }
    }
  }
  cp_async_wait<0>();
#pragma unroll
  for (int c = 1; c < CHAINS; ++c)
#pragma unroll
    for (int i = 0; i < MF; ++i)
#pragma unroll
      for (int j = 0; j < NF; ++j)
#pragma unroll
        for (int q = 0; q < 4; ++q) acc[0][i][j][q] += acc[c][i][j][q];
  float* part = partial != nullptr ? partial + blockIdx.z * n_out * cout : nullptr;
#pragma unroll
  for (int i = 0; i < MF; ++i) store_fragments(acc[0][i], orow, m0 + i * 16, col0 + n0, lane, cout, out, part, epi);
#else
  __trap();  // launched only on sm_80+ (checked on the host)
#endif
}

// Tile of the tensor-core kernel (measurements in docs/notes/sparse.md):
//   - 32 x 64 tiles (4 warps of 16 x 32) beat 64 x 64 on most layers with Cout > 32: twice the
//     blocks, each with half the rows waiting on gathers, hide the gathers' latency better;
//   - 64 x 64 stays ahead when a layer already has about seven 64 x 64 tiles per multiprocessor;
//   - with Cout <= 32, or too few rows for two 32 x 64 tiles per multiprocessor, 64-row tiles with
//     fewer columns (tile_columns). Larger tiles (128 x 64, 128 x 128, 64 x 128), 2 or 4 stages and 8 warps
//     per block were slower on the benchmark layers.
struct MmaShape {
  int rows, cols;
};

// Output columns per 64-row tile: 64, or fewer when Cout is small, or when the layer has fewer than two
// 64 x 64 tiles per multiprocessor (the deep layers of a backbone: few sites, many channels), to fill
// the GPU; aiming for four tiles per multiprocessor was slower, and the FFMA tiles gain nothing.
int tile_columns(int64_t n_out, int64_t cout, int sms) {
  int bn = cout <= 16 ? 16 : cout <= 32 ? 32 : 64;
  const int64_t want = 2 * static_cast<int64_t>(sms);
  while (bn > 16 && ceil_div(n_out, 64) * ceil_div(cout, bn) < want) bn /= 2;
  return bn;
}
MmaShape mma_tile_shape(int64_t n_out, int64_t cout, int sms) {
  const int64_t col_tiles = ceil_div(cout, 64);
  if (cout > 32 && ceil_div(n_out, 64) * col_tiles < 7 * static_cast<int64_t>(sms) &&
      ceil_div(n_out, 32) * col_tiles >= 2 * static_cast<int64_t>(sms))
    return {32, 64};
  return {64, tile_columns(n_out, cout, sms)};
}

template <typename T, Mma M>
void launch_mma(const ConvLaunch& a) {
  auto go = [&](auto tile) {
    using Tile = decltype(tile);
    launch_pipelined<T, Tile>(conv_fwd_mma_kernel<T, M, Tile>, Tile::BM, Tile::BN, Tile::BK, 0.6, a);
  };
  const MmaShape shape = mma_tile_shape(a.nbr.size(0), a.w.size(0), a.props.sms);
  if (shape.rows == 32) go(MmaTile<M, 32, 64, 2, 2, 3>{});
  else if (shape.cols <= 16) go(MmaTile<M, 64, 16, 4, 1, 3>{});
  else if (shape.cols <= 32) go(MmaTile<M, 64, 32, 4, 1, 3>{});
  else go(MmaTile<M, 64, 64, 2, 2, 3>{});
}

}  // namespace

void conv_fwd_mma(const ConvLaunch& a, Mma mode) {
  switch (mode) {
    case Mma::kF16: return launch_mma<c10::Half, Mma::kF16>(a);
    case Mma::kBF16: return launch_mma<c10::BFloat16, Mma::kBF16>(a);
    case Mma::kTF32: return launch_mma<float, Mma::kTF32>(a);
    case Mma::k3xTF32: return launch_mma<float, Mma::k3xTF32>(a);
  }
}

}  // namespace sparse
}  // namespace lidarops
