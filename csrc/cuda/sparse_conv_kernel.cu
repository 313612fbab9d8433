// Sparse convolution on CUDA: one fused implicit-GEMM kernel over all kernel offsets.
//
// Forward, output-stationary: out (N_out x Cout) = A (N_out x K*Cin) . W^T, where row o of A is the
// concatenation over offsets k of features[kernel_map[o, k]] (zeros where the map is -1). A block
// owns a tile of output rows x output channels and walks every offset and input-channel chunk,
// gathering the input rows straight into shared memory; offsets with no input for any row of the
// tile are skipped (a block-wide vote). No atomics, no host synchronisation: each output element is
// summed by one thread in a fixed order, so results are deterministic. Layers with too few tiles to
// fill the GPU (the deep layers of a backbone: few sites, many channels) split each tile's offsets
// over up to four blocks (offset_splits); a second kernel adds their partial sums in a fixed order.
//   - float16 / bfloat16 (sm_80+, Cin and Cout >= 16): tensor cores with float accumulation; float32
//     likewise with TF32 when torch allows TF32 matmuls (off by default). Cin a multiple of the 16-byte
//     vector and K <= 32: mma.sync fed by a cp.async pipeline, or, on Hopper (compute capability 9.0,
//     sm_90a builds) for Cout > 64, wgmma fed by the same pipeline; otherwise WMMA 16x16x16 (TF32 16x16x8).
//   - float32 otherwise (sm_80+, Cin a multiple of 4, K <= 32): SIMT (FFMA) tiles fed by cp.async
//     pipelines, or, with algo="3xtf32" (experimental), the mma.sync kernel as 3xTF32;
//   - otherwise general SIMT tiles in float (float64 in float64).
// The pipelined kernels start with the tiles of the rows with the most offsets (heavy_first_tile).
// Rows are processed in the order given by sparse_kernel_map_order (grouped by their offset masks),
// so the rows of a tile share their offsets and the skipping is effective on real data.
// Backward: the features gradient is this kernel over the transposed map (autograd in Python); the
// weight gradient is a split-K reduction over output rows into per-split partial sums (float), added
// in a fixed order: deterministic too.
// The ops' algo and splits arguments override the kernel choices (sparse.h, ConvAlgo).
#include <ATen/ATen.h>
#include <ATen/Context.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <mma.h>

#include <algorithm>
#include <cstdint>
#include <mutex>
#include <type_traits>
#include <unordered_map>

#include "lidarops/sparse.h"

namespace lidarops {
namespace sparse {
namespace {

LIDAROPS_HD int64_t ceil_div(int64_t a, int64_t b) { return (a + b - 1) / b; }

// Output row processed at tile position t: order[t] (rows grouped by their offset masks) or t.
__device__ __forceinline__ int64_t output_row(const int32_t* order, int64_t t, int64_t n_out) {
  if (t >= n_out) return -1;
  const int64_t o = order != nullptr ? static_cast<int64_t>(order[t]) : t;
  return o >= 0 && o < n_out ? o : -1;
}

// Offset splits (split-K over the kernel offsets) of the pipelined kernels: with gridDim.z > 1, block z
// takes its share [lo, hi) of the nk offsets its tile has and writes float partial sums, without the
// epilogue, to partial[z] (N_out x Cout); reduce_splits_kernel then adds the splits in a fixed order.
struct OffsetSplit {
  int lo, hi;
};
__device__ __forceinline__ OffsetSplit offset_split(int nk) {
  const int z = static_cast<int>(blockIdx.z), s = static_cast<int>(gridDim.z);
  return {nk * z / s, nk * (z + 1) / s};
}

// Tile of output rows a block of the pipelined kernels takes: the last first. The rows are grouped by
// their offset masks in ascending order, so the rows with every offset, whose tiles take longest, come
// last; starting those first keeps the multiprocessors busy to the end of the launch (longest job first).
__device__ __forceinline__ int64_t heavy_first_tile() { return static_cast<int64_t>(gridDim.x) - 1 - blockIdx.x; }

// ------------------------------------------------------------------------------------------------
// forward, SIMT tiles: BM output rows x BN output channels per block, BK input channels per step,
// each thread TM x TN outputs.
// ------------------------------------------------------------------------------------------------
template <typename T, int BM, int BN, int BK, int TM, int TN>
__global__ void __launch_bounds__((BM / TM) * (BN / TN))
    conv_fwd_simt_kernel(const T* __restrict__ x, const T* __restrict__ w, const int32_t* __restrict__ nbr,
                         const int32_t* __restrict__ order, T* __restrict__ out, int64_t n_out, int64_t cin,
                         int64_t cout, int64_t K, ConvEpilogue epi, int64_t n_in) {
  using A = acc_t<T>;
  constexpr int kThreads = (BM / TM) * (BN / TN);
  __shared__ A As[BK][BM + 1];  // +1: conflict-free transposed stores
  __shared__ A Bs[BK][BN + 1];
  __shared__ int32_t rows[BM];
  __shared__ int64_t orow[BM];  // output row of each tile row (through `order`), -1 past the end
  const int tid = threadIdx.x;
  const int tx = tid % (BN / TN), ty = tid / (BN / TN);
  const int64_t row0 = static_cast<int64_t>(blockIdx.x) * BM;
  const int64_t col0 = static_cast<int64_t>(blockIdx.y) * BN;
  for (int m = tid; m < BM; m += kThreads) orow[m] = output_row(order, row0 + m, n_out);
  __syncthreads();
  A acc[TM][TN];
#pragma unroll
  for (int i = 0; i < TM; ++i)
#pragma unroll
    for (int j = 0; j < TN; ++j) acc[i][j] = A(0);

  for (int64_t k = 0; k < K; ++k) {
    int mine = 0;
    for (int m = tid; m < BM; m += kThreads) {
      const int64_t o = orow[m];
      const int32_t r = o >= 0 ? map_row(nbr[o * K + k], n_in) : -1;
      rows[m] = r;
      mine |= r >= 0;
    }
    if (!__syncthreads_or(mine)) continue;  // no row of this tile has an input at offset k
    const T* wk = w + k * cin;  // W[co, k, ci] = wk[co * K * cin + ci]
    for (int64_t c0 = 0; c0 < cin; c0 += BK) {
      for (int e = tid; e < BM * BK; e += kThreads) {
        const int m = e / BK, kk = e % BK;
        const int32_t r = rows[m];
        const int64_t ci = c0 + kk;
        As[kk][m] = (r >= 0 && ci < cin) ? static_cast<A>(x[static_cast<int64_t>(r) * cin + ci]) : A(0);
      }
      for (int e = tid; e < BN * BK; e += kThreads) {
        const int n = e / BK, kk = e % BK;
        const int64_t co = col0 + n, ci = c0 + kk;
        Bs[kk][n] = (co < cout && ci < cin) ? static_cast<A>(wk[co * K * cin + ci]) : A(0);
      }
      __syncthreads();
#pragma unroll 4
      for (int kk = 0; kk < BK; ++kk) {
        A a[TM], b[TN];
#pragma unroll
        for (int i = 0; i < TM; ++i) a[i] = As[kk][ty * TM + i];
#pragma unroll
        for (int j = 0; j < TN; ++j) b[j] = Bs[kk][tx * TN + j];
#pragma unroll
        for (int i = 0; i < TM; ++i)
#pragma unroll
          for (int j = 0; j < TN; ++j) acc[i][j] += a[i] * b[j];
      }
      __syncthreads();
    }
  }
#pragma unroll
  for (int i = 0; i < TM; ++i) {
    const int64_t o = orow[ty * TM + i];
    if (o < 0) continue;
#pragma unroll
    for (int j = 0; j < TN; ++j) {
      const int64_t co = col0 + tx * TN + j;
      if (co < cout) out[o * cout + co] = static_cast<T>(epi(acc[i][j], co));
    }
  }
}

constexpr int kAsyncMaxK = 32;  // offsets a float32 tile kernel lists in one 32-bit mask

// ------------------------------------------------------------------------------------------------
// forward, float32 SIMT with asynchronous copies (sm_80+; Cin a multiple of 4, K <= 32, 16-byte
// aligned inputs): the same output-stationary product as conv_fwd_simt_kernel, built like a tuned
// SGEMM.
//   - At the start a block reads its rows' whole kernel-map slice into shared memory and lists the
//     offsets any of its rows has, so the main loop runs over (present offset, BK-channel chunk) steps
//     with no vote in between.
//   - The gathered rows and the weights go straight from global to shared memory with cp.async through
//     a ring of STAGES buffers: STAGES - 1 steps are in flight while one is multiplied. On LiDAR-sized
//     maps a block's steps form a chain of dependent gathers whose latency, not the arithmetic, sets the
//     time, so one step in flight (register prefetch) is not enough.
//   - Tiles are stored row-major, B rows with a 4-float pad (a quarter-warp's float4 reads of 8
//     consecutive B rows hit 8 different bank groups; its A reads are one broadcast row, unpadded: see
//     AsyncTile); a thread owns the rows ty + i * (BM / TM) and the columns tx + j * (BN / TN) and reads
//     float4 fragments along the channels.
//   - Per output element the sum runs over offsets, then channels, in ascending order.
// ------------------------------------------------------------------------------------------------
__device__ __forceinline__ void cp_async16(void* smem, const void* gmem, bool valid) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  const unsigned dst = static_cast<unsigned>(__cvta_generic_to_shared(smem));
  const int bytes = valid ? 16 : 0;  // 0: fill the 16 bytes with zeros, read nothing
  asm volatile("cp.async.cg.shared.global [%0], [%1], 16, %2;\n" ::"r"(dst), "l"(gmem), "r"(bytes));
#endif
}
__device__ __forceinline__ void cp_async_commit() {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  asm volatile("cp.async.commit_group;\n" ::);
#endif
}
template <int N>
__device__ __forceinline__ void cp_async_wait() {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  asm volatile("cp.async.wait_group %0;\n" ::"n"(N));
#endif
}

// A block's place in its step sequence (offset position in klist, input-channel chunk, ring slot),
// advanced one step at a time: no division by the runtime chunk count per step.
template <int STAGES>
struct StepCursor {
  int kpos, chunk, slot;
  __device__ __forceinline__ explicit StepCursor(int first) : kpos(first), chunk(0), slot(0) {}
  __device__ __forceinline__ void next(int chunks) {
    if (++chunk == chunks) {
      chunk = 0;
      ++kpos;
    }
    slot = slot + 1 == STAGES ? 0 : slot + 1;
  }
};

// The 16-byte chunks one thread of a pipelined kernel copies in every step: one chunk column of the
// gathered A rows r + u * RSTEP (u < AU) and of the weight rows (output columns) col0 + r + u * RSTEP
// (u < BU). The weight-row offsets and which columns exist are fixed for the block, so a step costs a
// map read and an address per chunk (recomputing them with divisions on every step makes the
// tensor-core kernel issue-bound).
template <typename S, int AU, int BU, int RSTEP>
struct StepCopies {
  int64_t w_row[BU];
  unsigned w_in = 0u;  // bit u: column col0 + r + u * RSTEP < Cout
  __device__ __forceinline__ StepCopies(int col0, int r, int K, int cin, int cout) {
#pragma unroll
    for (int u = 0; u < BU; ++u) {
      const int co = col0 + r + u * RSTEP;
      w_row[u] = static_cast<int64_t>(co) * K * cin;
      if (co < cout) w_in |= 1u << u;
    }
  }
  // The step at offset k, this thread's chunk starting at channel ci: A row u (input rk[u * RSTEP], -1
  // for none) to a_dst + u * a_stride, weight row u to b_dst + u * b_stride; zeros where absent.
  __device__ __forceinline__ void copy(S* a_dst, int a_stride, S* b_dst, int b_stride, const int32_t* rk,
                                       const S* x, const S* w, int k, int ci, int cin) const {
    const bool ci_in = ci < cin;  // Cin is a multiple of the vector: a chunk is all in or all out
#pragma unroll
    for (int u = 0; u < AU; ++u) {
      const int32_t r = rk[u * RSTEP];
      const bool ok = r >= 0 && ci_in;
      cp_async16(a_dst + u * a_stride, ok ? x + static_cast<int64_t>(r) * cin + ci : x, ok);
    }
    const int64_t kc = static_cast<int64_t>(k) * cin + ci;
#pragma unroll
    for (int u = 0; u < BU; ++u) {
      const bool ok = ((w_in >> u) & 1u) && ci_in;
      cp_async16(b_dst + u * b_stride, ok ? w + w_row[u] + kc : w, ok);
    }
  }
};

// The map slice of a tile of BM output rows starting at row0: orow[m] (the output row at tile row m,
// -1 past the end), rows[k * BM + m] (its input at offset k, or -1) and klist[0, nk) (the offsets any
// row of the tile has, ascending; K <= 32); with `groups`, also groups[k]: bit g set when a row of
// the 16-row group g has an input at offset k. Called by the whole block; returns nk after a barrier.
template <int BM, int kThreads>
__device__ int tile_map_slice(const int32_t* __restrict__ nbr, const int32_t* __restrict__ order, int64_t n_out,
                              int64_t n_in, int K, int64_t row0, int64_t* orow, int32_t* rows, int* klist,
                              unsigned* present, int* nk, unsigned* groups = nullptr) {
  static_assert(BM <= 16 * 32, "one bit per 16-row group");
  const int tid = threadIdx.x;
  for (int m = tid; m < BM; m += kThreads) orow[m] = output_row(order, row0 + m, n_out);
  if (tid == 0) *present = 0u;
  if (groups != nullptr && tid < kAsyncMaxK) groups[tid] = 0u;
  __syncthreads();
  for (int e = tid; e < BM * K; e += kThreads) {  // row by row: coalesced reads of the map
    const int m = e / K, k = e % K;
    const int64_t o = orow[m];
    const int32_t r = o >= 0 ? map_row(nbr[o * K + k], n_in) : -1;
    rows[k * BM + m] = r;
    if (r >= 0) {
      atomicOr(present, 1u << k);
      if (groups != nullptr) atomicOr(groups + k, 1u << (m / 16));
    }
  }
  __syncthreads();
  if (tid < 32) {
    const unsigned bits = *present;
    if ((bits >> tid) & 1u) klist[__popc(bits & ((1u << tid) - 1u))] = tid;
    if (tid == 0) *nk = __popc(bits);
  }
  __syncthreads();
  return *nk;
}

template <int BM, int BN, int TM, int TN, int BK, int STAGES>
struct AsyncTile {
  static constexpr int kThreads = (BM / TM) * (BN / TN), kStepChannels = BK;
  // A rows unpadded: the 8 threads of a quarter-warp read the same A row (a broadcast). B rows padded by
  // 16 bytes: those threads read 8 consecutive B rows, which then fall in 8 different bank groups.
  // Without A's pad four 64 x 64 blocks fit in an SM's shared memory instead of three.
  static constexpr int LDA = BK, LDB = BK + 4;
  static_assert((BN / TN) % 8 == 0, "a quarter-warp shares its A row");
  // the ring, then the map slice of K offsets (the largest K for the launch limit)
  static size_t smem(int K) { return sizeof(float) * STAGES * (BM * LDA + BN * LDB) + sizeof(int32_t) * K * BM; }
};

template <int BM, int BN, int TM, int TN, int BK, int STAGES>
__global__ void __launch_bounds__(AsyncTile<BM, BN, TM, TN, BK, STAGES>::kThreads)
    conv_fwd_f32_async_kernel(const float* __restrict__ x, const float* __restrict__ w,
                              const int32_t* __restrict__ nbr, const int32_t* __restrict__ order,
                              float* __restrict__ out, int64_t n_out, int cin, int cout, int K, ConvEpilogue epi,
                              float* __restrict__ partial, int64_t n_in) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  using Tile = AsyncTile<BM, BN, TM, TN, BK, STAGES>;
  constexpr int kThreads = Tile::kThreads, LDA = Tile::LDA, LDB = Tile::LDB;
  static_assert(BK % 4 == 0 && STAGES >= 2, "16-byte copies, at least double buffering");
  extern __shared__ __align__(16) float smem[];
  float* As = smem;                                    // [STAGES][BM][LDA]
  float* Bs = smem + STAGES * BM * LDA;                // [STAGES][BN][LDB]
  int32_t* rows = reinterpret_cast<int32_t*>(Bs + STAGES * BN * LDB);  // [K][BM]
  __shared__ int64_t orow[BM];
  __shared__ unsigned present;
  __shared__ int klist[kAsyncMaxK];
  __shared__ int nk;
  const int tid = threadIdx.x;
  const int tx = tid % (BN / TN), ty = tid / (BN / TN);
  const int col0 = static_cast<int>(blockIdx.y) * BN;
  const int chunks = (cin + BK - 1) / BK;
  const OffsetSplit split = offset_split(
      tile_map_slice<BM, kThreads>(nbr, order, n_out, n_in, K, heavy_first_tile() * BM, orow, rows, klist, &present,
                                   &nk));
  const int steps = (split.hi - split.lo) * chunks;
  // This thread's 16-byte chunks of a step: chunk c_t of the A rows r_t + u * RSTEP and of the B rows
  // (weight columns) likewise.
  constexpr int CH = BK / 4, RSTEP = kThreads / CH;
  static_assert(kThreads % CH == 0 && BM % RSTEP == 0 && BN % RSTEP == 0, "whole rows");
  const int c_t = tid % CH, r_t = tid / CH;
  const StepCopies<float, BM / RSTEP, BN / RSTEP, RSTEP> copies(col0, r_t, K, cin, cout);
  StepCursor<STAGES> in(split.lo);  // the next step to issue
  auto issue = [&]() {              // its tiles into its ring slot (nothing past the last step)
    if (in.kpos < split.hi)
      copies.copy(As + (in.slot * BM + r_t) * LDA + c_t * 4, RSTEP * LDA, Bs + (in.slot * BN + r_t) * LDB + c_t * 4,
                  RSTEP * LDB, rows + klist[in.kpos] * BM + r_t, x, w, klist[in.kpos], in.chunk * BK + c_t * 4, cin);
    in.next(chunks);
    cp_async_commit();  // an empty group past the end keeps the wait counts uniform
  };

  float acc[TM][TN];
#pragma unroll
  for (int i = 0; i < TM; ++i)
#pragma unroll
    for (int j = 0; j < TN; ++j) acc[i][j] = 0.f;
#pragma unroll
  for (int t = 0; t < STAGES - 1; ++t) issue();
  StepCursor<STAGES> at(split.lo);  // the step multiplied
  for (int t = 0; t < steps; ++t, at.next(chunks)) {
    cp_async_wait<STAGES - 2>();  // step t has landed (for this thread's copies) ...
    __syncthreads();              // ... and for everyone's; stage (t - 1) % STAGES is free again
    issue();                      // step t + STAGES - 1
    const float* a_t = As + at.slot * BM * LDA;
    const float* b_t = Bs + at.slot * BN * LDB;
#pragma unroll
    for (int kk = 0; kk < BK; kk += 4) {
      float4 b[TN];
#pragma unroll
      for (int j = 0; j < TN; ++j) b[j] = *reinterpret_cast<const float4*>(b_t + (tx + j * (BN / TN)) * LDB + kk);
#pragma unroll
      for (int i = 0; i < TM; ++i) {
        const float4 a = *reinterpret_cast<const float4*>(a_t + (ty + i * (BM / TM)) * LDA + kk);
#pragma unroll
        for (int j = 0; j < TN; ++j) {
          acc[i][j] = fmaf(a.x, b[j].x, acc[i][j]);
          acc[i][j] = fmaf(a.y, b[j].y, acc[i][j]);
          acc[i][j] = fmaf(a.z, b[j].z, acc[i][j]);
          acc[i][j] = fmaf(a.w, b[j].w, acc[i][j]);
        }
      }
    }
  }
  cp_async_wait<0>();
  float* part = partial != nullptr ? partial + blockIdx.z * n_out * cout : nullptr;
#pragma unroll
  for (int i = 0; i < TM; ++i) {
    const int64_t o = orow[ty + i * (BM / TM)];
    if (o < 0) continue;
#pragma unroll
    for (int j = 0; j < TN; ++j) {
      const int co = col0 + tx + j * (BN / TN);
      if (co >= cout) continue;
      if (part != nullptr) part[o * cout + co] = acc[i][j];
      else out[o * cout + co] = epi(acc[i][j], co);
    }
  }
#else
  __trap();  // launched only on sm_80+ (checked on the host)
#endif
}

// ------------------------------------------------------------------------------------------------
// forward, tensor cores: 64 x 64 tile per block of 4 warps (2 x 2, each 32 x 32 = 2 x 2 WMMA
// fragments), 32 input channels per step, float accumulation. float16 / bfloat16: 16x16x16 fragments;
// float32 when torch allows TF32 for matmuls (torch.backends.cuda.matmul.allow_tf32): 16x16x8 TF32
// fragments. kVec: Cin a multiple of the 16-byte vector and 16-byte aligned tensors, so rows are
// loaded as 16-byte vectors.
// ------------------------------------------------------------------------------------------------
template <typename T>
struct MmaTraits;
template <>
struct MmaTraits<c10::Half> {
  using S = __half;  // shared-memory element
  using F = __half;  // fragment element
  static constexpr int KS = 16, VEC = 8;
};
template <>
struct MmaTraits<c10::BFloat16> {
  using S = __nv_bfloat16;
  using F = __nv_bfloat16;
  static constexpr int KS = 16, VEC = 8;
};
template <>
struct MmaTraits<float> {
  using S = float;
  using F = nvcuda::wmma::precision::tf32;
  static constexpr int KS = 8, VEC = 4;
};

constexpr int kWmmaThreads = 128;

#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
// float32 fragments are rounded to TF32 before the MMA; other types are used as loaded.
template <typename T, typename Frag>
__device__ __forceinline__ void round_tf32(Frag& f) {
  if constexpr (std::is_same_v<T, float>) {
#pragma unroll
    for (int t = 0; t < f.num_elements; ++t) f.x[t] = nvcuda::wmma::__float_to_tf32(f.x[t]);
  }
}

// One BK-channel step of a warp's (16 FM) x (16 FN) share of the block tile, whose rows start at
// m0 and columns at n0: A row-major (As[m * lda + kk]), B column-major (Bs[n * ldb + kk]); float32
// goes through TF32 fragments.
template <typename T, int BK, int FM, int FN, typename S, typename Acc>
__device__ __forceinline__ void wmma_tile_step(const S* As, int lda, const S* Bs, int ldb, int m0, int n0,
                                               Acc (&c)[FM][FN]) {
  using namespace nvcuda;
  using FE = typename MmaTraits<T>::F;
  constexpr int KS = MmaTraits<T>::KS;
#pragma unroll
  for (int ks = 0; ks < BK / KS; ++ks) {
    wmma::fragment<wmma::matrix_a, 16, 16, KS, FE, wmma::row_major> a[FM];
    wmma::fragment<wmma::matrix_b, 16, 16, KS, FE, wmma::col_major> b[FN];
#pragma unroll
    for (int i = 0; i < FM; ++i) {
      wmma::load_matrix_sync(a[i], As + (m0 + i * 16) * lda + ks * KS, lda);
      round_tf32<T>(a[i]);
    }
#pragma unroll
    for (int j = 0; j < FN; ++j) {
      wmma::load_matrix_sync(b[j], Bs + (n0 + j * 16) * ldb + ks * KS, ldb);
      round_tf32<T>(b[j]);
    }
#pragma unroll
    for (int i = 0; i < FM; ++i)
#pragma unroll
      for (int j = 0; j < FN; ++j) wmma::mma_sync(c[i][j], a[i], b[j], c[i][j]);
  }
}
#endif

template <typename T, bool kVec>
__global__ void __launch_bounds__(kWmmaThreads)
    conv_fwd_wmma_kernel(const T* __restrict__ x, const T* __restrict__ w, const int32_t* __restrict__ nbr,
                         const int32_t* __restrict__ order, T* __restrict__ out, int64_t n_out, int64_t cin,
                         int64_t cout, int64_t K, ConvEpilogue epi, int64_t n_in) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  using namespace nvcuda;
  using S = typename MmaTraits<T>::S;
  constexpr int KS = MmaTraits<T>::KS, V = MmaTraits<T>::VEC;
  constexpr int BM = 64, BN = 64, BK = 32;
  constexpr int LDA = BK + V, LDB = BK + V;  // in elements: rows stay 16-byte aligned, as WMMA needs
  constexpr int LDC = BN + 4;                // floats: a multiple of 4
  __shared__ __align__(32) S As[BM * LDA];   // row-major A tile: As[m * LDA + kk]
  __shared__ __align__(32) S Bs[BN * LDB];   // column-major B tile (kk fastest): Bs[n * LDB + kk]
  __shared__ __align__(32) float Cs[BM * LDC];
  __shared__ int32_t rows[BM];
  __shared__ int64_t orow[BM];
  const int tid = threadIdx.x, warp = tid / 32;
  const int wm = warp / 2, wn = warp % 2;
  const int64_t row0 = static_cast<int64_t>(blockIdx.x) * BM;
  const int64_t col0 = static_cast<int64_t>(blockIdx.y) * BN;
  const S zero{};  // value-initialised: +0 (no float conversion under __CUDA_NO_HALF_CONVERSIONS__)
  for (int m = tid; m < BM; m += kWmmaThreads) orow[m] = output_row(order, row0 + m, n_out);
  __syncthreads();

  wmma::fragment<wmma::accumulator, 16, 16, KS, float> c[2][2];
#pragma unroll
  for (int i = 0; i < 2; ++i)
#pragma unroll
    for (int j = 0; j < 2; ++j) wmma::fill_fragment(c[i][j], 0.0f);

  const S* xs = reinterpret_cast<const S*>(x);
  const S* ws = reinterpret_cast<const S*>(w);
  for (int64_t k = 0; k < K; ++k) {
    int mine = 0;
    for (int m = tid; m < BM; m += kWmmaThreads) {
      const int64_t o = orow[m];
      const int32_t r = o >= 0 ? map_row(nbr[o * K + k], n_in) : -1;
      rows[m] = r;
      mine |= r >= 0;
    }
    if (!__syncthreads_or(mine)) continue;
    for (int64_t c0 = 0; c0 < cin; c0 += BK) {
      // A: BM rows x BK channels, V channels (16 bytes) per item
      for (int e = tid; e < BM * (BK / V); e += kWmmaThreads) {
        const int m = e / (BK / V), v = e % (BK / V);
        const int32_t r = rows[m];
        const int64_t ci = c0 + v * V;
        S* dst = As + m * LDA + v * V;
        if (kVec && r >= 0 && ci + V <= cin) {
          *reinterpret_cast<int4*>(dst) = __ldg(reinterpret_cast<const int4*>(xs + static_cast<int64_t>(r) * cin + ci));
        } else {
#pragma unroll
          for (int t = 0; t < V; ++t)
            dst[t] = (r >= 0 && ci + t < cin) ? xs[static_cast<int64_t>(r) * cin + ci + t] : zero;
        }
      }
      // B: BN output channels x BK input channels of W[co, k, ci]
      for (int e = tid; e < BN * (BK / V); e += kWmmaThreads) {
        const int n = e / (BK / V), v = e % (BK / V);
        const int64_t co = col0 + n, ci = c0 + v * V;
        S* dst = Bs + n * LDB + v * V;
        if (co < cout) {
          const S* src = ws + (co * K + k) * cin + ci;
          if (kVec && ci + V <= cin) {
            *reinterpret_cast<int4*>(dst) = __ldg(reinterpret_cast<const int4*>(src));
          } else {
#pragma unroll
            for (int t = 0; t < V; ++t) dst[t] = ci + t < cin ? src[t] : zero;
          }
        } else {
#pragma unroll
          for (int t = 0; t < V; ++t) dst[t] = zero;
        }
      }
      __syncthreads();
      wmma_tile_step<T, BK, 2, 2>(As, LDA, Bs, LDB, wm * 32, wn * 32, c);
      __syncthreads();
    }
  }
#pragma unroll
  for (int i = 0; i < 2; ++i)
#pragma unroll
    for (int j = 0; j < 2; ++j)
      wmma::store_matrix_sync(Cs + (wm * 32 + i * 16) * LDC + wn * 32 + j * 16, c[i][j], LDC, wmma::mem_row_major);
  __syncthreads();
  for (int e = tid; e < BM * BN; e += kWmmaThreads) {
    const int m = e / BN, n = e % BN;
    const int64_t o = orow[m], co = col0 + n;
    if (o >= 0 && co < cout) out[o * cout + co] = static_cast<T>(epi(Cs[m * LDC + n], co));
  }
#else
  __trap();  // launched only on sm_80+ (checked on the host)
#endif
}

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
enum class Mma { kF16, kBF16, kTF32, k3xTF32 };

template <Mma M>
struct MmaKind {  // 16-bit types: m16n8k16
  using S = std::conditional_t<M == Mma::kF16, __half, __nv_bfloat16>;
  static constexpr int V = 8;  // elements per 16 bytes
};
template <>
struct MmaKind<Mma::kTF32> {  // float32: m16n8k8 TF32
  using S = float;
  static constexpr int V = 4;
};
template <>
struct MmaKind<Mma::k3xTF32> : MmaKind<Mma::kTF32> {};

template <Mma M, int BM_, int BN_, int WM_, int WN_, int STAGES_>
struct MmaTile {
  using S = typename MmaKind<M>::S;
  static constexpr int V = MmaKind<M>::V;
  static constexpr int BM = BM_, BN = BN_, BK = 8 * V, STAGES = STAGES_;  // a step: 128 bytes of channels
  static constexpr int WM = WM_, WN = WN_;                       // warps: WM along rows, WN along columns
  static constexpr int kThreads = 32 * WM * WN;
  static constexpr int MF = BM / (16 * WM), NF = BN / (8 * WN);  // 16 x 8 fragments per warp
  static constexpr int KS = 2 * V;                                // elements per mma k-step (32 bytes)
  static constexpr size_t kStage = sizeof(S) * (BM + BN) * BK;
  static size_t smem(int K) { return kStage * STAGES + sizeof(int32_t) * K * BM; }  // the ring, the map slice
  static_assert(MF >= 1 && NF >= 2 && NF % 2 == 0 && BK % KS == 0 && BM <= 16 * 32, "whole fragments");
  static_assert(BM % 8 == 0 && BN % 8 == 0, "swizzle: row & 7 of a tile row is that of its stage row");
  // Shared rows are 128 bytes, unpadded; the 16-byte chunk c of row r is stored at chunk c ^ (r & 7), so
  // the eight rows an ldmatrix phase reads, and the eight chunks of a row a quarter-warp copies, fall in
  // eight different bank groups.
  static __device__ __forceinline__ int at(int r, int c) { return r * BK + ((c ^ (r & 7)) * V); }
};

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

// The tensor core reads a float32 operand as TF32 by dropping its low 13 bits (truncation, about 2.5x
// the error of rounding).
// Rounding to nearest is then one fused multiply-add: x + sign(x) 2^(exponent - 11), half a TF32 ulp,
// computed from x's sign and exponent bits. inf and NaN stay as they are; subnormal numbers are
// truncated (their exponent bits give 0). Two instructions per
// register instead of cvt.rna's three (a compare, an add and a mask): 4 % on the backbone's TF32 layers.
__device__ __forceinline__ unsigned tf32_round(unsigned x) {
  return __float_as_uint(__fmaf_rn(__uint_as_float(x & 0xff800000u), 0.00048828125f, __uint_as_float(x)));
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

template <typename T>
__device__ __forceinline__ void store_pair(T* p, float v0, float v1, bool both, bool pair) {
  if constexpr (std::is_same_v<T, float>) {
    if (pair) {
      *reinterpret_cast<float2*>(p) = make_float2(v0, v1);
      return;
    }
  }
  p[0] = static_cast<T>(v0);
  if (both) p[1] = static_cast<T>(v1);
}

// Writes one 16-row block of a thread's accumulators in the mma.sync / wgmma fragment layout: rows
// row0 + lane / 4 (+ 8), columns col0 + 8 j + 2 (lane % 4) (+ 1), the float sums to `part` (an offset
// split's partial sums) or, without splits, through the epilogue to `out`.
template <typename T, int NF>
__device__ __forceinline__ void store_fragments(const float (&acc)[NF][4], const int64_t* orow, int row0, int col0,
                                                int lane, int cout, T* out, float* part, const ConvEpilogue& epi) {
  const bool pair = cout % 2 == 0;
#pragma unroll
  for (int h = 0; h < 2; ++h) {
    const int64_t o = orow[row0 + lane / 4 + 8 * h];
    if (o < 0) continue;
#pragma unroll
    for (int j = 0; j < NF; ++j) {
      const int co = col0 + j * 8 + 2 * (lane % 4);
      if (co >= cout) continue;
      const float v0 = acc[j][2 * h], v1 = acc[j][2 * h + 1];
      if (part != nullptr) store_pair(part + o * cout + co, v0, v1, co + 1 < cout, pair);
      else store_pair(out + o * cout + co, epi(v0, co), co + 1 < cout ? epi(v1, co + 1) : 0.f, co + 1 < cout, pair);
    }
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

// ------------------------------------------------------------------------------------------------
// forward, Hopper warpgroup MMA (sm_90a builds on compute capability 9.0; float16, bfloat16, TF32;
// Cout > 64): the mma.sync kernel's pipeline (map slice, offset list, cp.async ring of 128-byte rows
// whose 16-byte chunks are swizzled as c ^ (row & 7), which is exactly wgmma's 128-byte swizzle layout)
// feeding wgmma.mma_async straight from shared memory:
//   - one warpgroup (4 warps) per 64-row tile of BN = 64 or 128 columns; a step is four m64nBNk8 (TF32)
//     or m64nBNk16 (16-bit) products, with no ldmatrix and no operand registers;
//   - TF32: each thread rounds the chunks it copied itself to nearest TF32 in shared memory once they
//     have landed (the tensor core would truncate them), before the barrier that publishes the step;
//   - all 64 rows are multiplied at every offset the tile has (rows without an input there are zeros);
//   - the accumulator layout per warp is mma.sync's (16 rows x 8 columns per fragment), so the epilogue,
//     the offset splits and the summation order over offsets and channels are those of conv_fwd_mma_kernel.
// ------------------------------------------------------------------------------------------------
template <int N>
struct Wgmma;  // d (64 x N, float) += A (64 x 32 bytes) . B (N x 32 bytes), both from shared memory
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
#define LIDAROPS_ACC4(j) "+f"(d[j][0]), "+f"(d[j][1]), "+f"(d[j][2]), "+f"(d[j][3])
#define LIDAROPS_WGMMA(SHAPE, REGS, DESCS, ...)                                                                   \
  if constexpr (M == Mma::kTF32)                                                                                 \
    asm volatile("wgmma.mma_async.sync.aligned." SHAPE "k8.f32.tf32.tf32 " REGS ", " DESCS ", 1, 1, 1;\n"         \
                 : __VA_ARGS__                                                                                   \
                 : "l"(a), "l"(b));                                                                              \
  else if constexpr (M == Mma::kF16)                                                                             \
    asm volatile("wgmma.mma_async.sync.aligned." SHAPE "k16.f32.f16.f16 " REGS ", " DESCS ", 1, 1, 1, 0, 0;\n"    \
                 : __VA_ARGS__                                                                                   \
                 : "l"(a), "l"(b));                                                                              \
  else                                                                                                           \
    asm volatile("wgmma.mma_async.sync.aligned." SHAPE "k16.f32.bf16.bf16 " REGS ", " DESCS ", 1, 1, 1, 0, 0;\n"  \
                 : __VA_ARGS__                                                                                   \
                 : "l"(a), "l"(b))
template <>
struct Wgmma<64> {
  template <Mma M>
  static __device__ __forceinline__ void run(float (&d)[8][4], uint64_t a, uint64_t b) {
    LIDAROPS_WGMMA("m64n64",
                   "{%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, "
                   "%16, %17, %18, %19, %20, %21, %22, %23, %24, %25, %26, %27, %28, %29, %30, %31}", "%32, %33",
                   LIDAROPS_ACC4(0), LIDAROPS_ACC4(1), LIDAROPS_ACC4(2), LIDAROPS_ACC4(3), LIDAROPS_ACC4(4),
                   LIDAROPS_ACC4(5), LIDAROPS_ACC4(6), LIDAROPS_ACC4(7));
  }
};
template <>
struct Wgmma<128> {
  template <Mma M>
  static __device__ __forceinline__ void run(float (&d)[16][4], uint64_t a, uint64_t b) {
    LIDAROPS_WGMMA("m64n128",
                   "{%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, "
                   "%16, %17, %18, %19, %20, %21, %22, %23, %24, %25, %26, %27, %28, %29, %30, %31, "
                   "%32, %33, %34, %35, %36, %37, %38, %39, %40, %41, %42, %43, %44, %45, %46, %47, "
                   "%48, %49, %50, %51, %52, %53, %54, %55, %56, %57, %58, %59, %60, %61, %62, %63}", "%64, %65",
                   LIDAROPS_ACC4(0), LIDAROPS_ACC4(1), LIDAROPS_ACC4(2), LIDAROPS_ACC4(3), LIDAROPS_ACC4(4),
                   LIDAROPS_ACC4(5), LIDAROPS_ACC4(6), LIDAROPS_ACC4(7), LIDAROPS_ACC4(8), LIDAROPS_ACC4(9),
                   LIDAROPS_ACC4(10), LIDAROPS_ACC4(11), LIDAROPS_ACC4(12), LIDAROPS_ACC4(13), LIDAROPS_ACC4(14),
                   LIDAROPS_ACC4(15));
  }
};
#undef LIDAROPS_WGMMA
#undef LIDAROPS_ACC4

// Shared-memory matrix descriptor: K-major rows of 128 bytes, 128-byte swizzle, 8-row groups 1024 bytes
// apart (the leading-dimension offset is unused in this mode: 1).
__device__ __forceinline__ uint64_t wgmma_desc(uint32_t saddr) {
  return static_cast<uint64_t>((saddr & 0x3FFFFu) >> 4) | (uint64_t(1) << 16) | (uint64_t(1024 >> 4) << 32) |
         (uint64_t(1) << 62);
}
template <int NF>
__device__ __forceinline__ void wgmma_fence_acc(float (&d)[NF][4]) {
#pragma unroll
  for (int j = 0; j < NF; ++j)
#pragma unroll
    for (int q = 0; q < 4; ++q) asm volatile("" : "+f"(d[j][q])::"memory");
}
#endif

template <Mma M, int BN_, int STAGES_, int LOOKAHEAD_ = STAGES_ - 1>
struct WgTile : MmaTile<M, 64, BN_, 4, 1, STAGES_> {
  using Base = MmaTile<M, 64, BN_, 4, 1, STAGES_>;
  // steps whose gathers are in flight while one is multiplied; STAGES - 1 - LOOKAHEAD wgmma groups stay
  // in flight across steps (the slot a step's copies overwrite is that of step t + LOOKAHEAD - STAGES)
  static constexpr int LOOKAHEAD = LOOKAHEAD_, MMA_IN_FLIGHT = STAGES_ - 1 - LOOKAHEAD_;
  static_assert(LOOKAHEAD >= 1 && MMA_IN_FLIGHT >= 0 && MMA_IN_FLIGHT <= 1, "a valid ring");
  // All of the block's shared memory is dynamic, so that it starts at the 1024-byte boundary the swizzle
  // atoms need, with nothing lost to padding: the ring, then the map slice rows [K][64], the output rows
  // orow[64], klist[32], present and nk. At 64 x 128 (TF32, 3 stages) three blocks then fit in a
  // multiprocessor instead of two.
  static constexpr size_t kAux = sizeof(int64_t) * 64 + sizeof(int) * (kAsyncMaxK + 2);
  static size_t smem(int K) { return Base::kStage * Base::STAGES + sizeof(int32_t) * K * 64 + kAux; }
};

template <typename T, Mma M, typename Tile>
__global__ void __launch_bounds__(Tile::kThreads)
    conv_fwd_wgmma_kernel(const T* __restrict__ x, const T* __restrict__ w, const int32_t* __restrict__ nbr,
                          const int32_t* __restrict__ order, T* __restrict__ out, int64_t n_out, int cin, int cout,
                          int K, ConvEpilogue epi, float* __restrict__ partial, int64_t n_in) {
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
  using S = typename Tile::S;
  constexpr int V = Tile::V, BM = Tile::BM, BN = Tile::BN, BK = Tile::BK, NF = Tile::NF;
  constexpr int STAGES = Tile::STAGES, kThreads = Tile::kThreads, CH = BK / V;
  static_assert(BM == 64 && kThreads == 128 && Tile::MF == 1 && BK * sizeof(S) == 128, "one warpgroup, 128-byte rows");
  static_assert(M != Mma::k3xTF32, "3xTF32 runs on conv_fwd_mma_kernel");
  extern __shared__ __align__(1024) unsigned char wg_smem[];  // no static shared memory: see WgTile
  const uint32_t ring_s = static_cast<uint32_t>(__cvta_generic_to_shared(wg_smem));
  if (ring_s % 1024 != 0) __trap();  // the swizzle atoms would be misread: fail loudly, never silently
  S* ring = reinterpret_cast<S*>(wg_smem);                                             // [STAGES][BM + BN][BK]
  int32_t* rows = reinterpret_cast<int32_t*>(wg_smem + Tile::kStage * STAGES);         // [K][BM]
  int64_t* orow = reinterpret_cast<int64_t*>(rows + K * BM);                           // [BM]
  int* klist = reinterpret_cast<int*>(orow + BM);                                      // [kAsyncMaxK]
  unsigned* present = reinterpret_cast<unsigned*>(klist + kAsyncMaxK);
  int* nk = klist + kAsyncMaxK + 1;
  const int tid = threadIdx.x, warp = tid / 32, lane = tid % 32;
  const int col0 = static_cast<int>(blockIdx.y) * BN;
  const int chunks = (cin + BK - 1) / BK;
  const OffsetSplit split = offset_split(tile_map_slice<BM, kThreads>(
      nbr, order, n_out, n_in, K, heavy_first_tile() * BM, orow, rows, klist, present, nk));
  const int steps = (split.hi - split.lo) * chunks;
  const S* xs = reinterpret_cast<const S*>(x);
  const S* ws = reinterpret_cast<const S*>(w);
  constexpr int RSTEP = kThreads / CH, AU = BM / RSTEP, BU = BN / RSTEP;
  static_assert(kThreads % CH == 0 && RSTEP % 8 == 0 && BM % RSTEP == 0 && BN % RSTEP == 0, "whole rows");
  const int c_t = tid % CH, r_t = tid / CH, dst0 = Tile::at(r_t, c_t);
  const StepCopies<S, AU, BU, RSTEP> copies(col0, r_t, K, cin, cout);
  StepCursor<STAGES> in(split.lo);
  auto issue = [&]() {
    if (in.kpos < split.hi) {
      S* As = ring + in.slot * (BM + BN) * BK + dst0;
      copies.copy(As, RSTEP * BK, As + BM * BK, RSTEP * BK, rows + klist[in.kpos] * BM + r_t, xs, ws, klist[in.kpos],
                  in.chunk * BK + c_t * V, cin);
    }
    in.next(chunks);
    cp_async_commit();
  };
  float acc[NF][4];
#pragma unroll
  for (int j = 0; j < NF; ++j)
#pragma unroll
    for (int q = 0; q < 4; ++q) acc[j][q] = 0.f;
  constexpr int LOOKAHEAD = Tile::LOOKAHEAD;
#pragma unroll
  for (int t = 0; t < LOOKAHEAD; ++t) issue();
  StepCursor<STAGES> at(split.lo);
  for (int t = 0; t < steps; ++t, at.next(chunks)) {
    cp_async_wait<LOOKAHEAD - 1>();
    if constexpr (M == Mma::kTF32) {  // round this thread's own chunks of the step to nearest TF32
      unsigned* st = reinterpret_cast<unsigned*>(ring + at.slot * (BM + BN) * BK + dst0);
#pragma unroll
      for (int u = 0; u < AU + BU; ++u) {
        uint4 v = *reinterpret_cast<uint4*>(st + u * RSTEP * BK);
        v.x = tf32_round(v.x);
        v.y = tf32_round(v.y);
        v.z = tf32_round(v.z);
        v.w = tf32_round(v.w);
        *reinterpret_cast<uint4*>(st + u * RSTEP * BK) = v;
      }
    }
    asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory");  // generic-proxy writes -> wgmma reads
    __syncthreads();
    issue();  // step t + LOOKAHEAD, into the slot of step t + LOOKAHEAD - STAGES (its wgmma has completed)
    const uint32_t a_s = ring_s + static_cast<uint32_t>(at.slot * (BM + BN) * BK * sizeof(S));
    const uint32_t b_s = a_s + static_cast<uint32_t>(BM * BK * sizeof(S));
    wgmma_fence_acc(acc);
    asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory");
#pragma unroll
    for (int ks = 0; ks < BK * static_cast<int>(sizeof(S)) / 32; ++ks)  // 32 bytes of channels per wgmma
      Wgmma<BN>::template run<M>(acc, wgmma_desc(a_s + 32 * ks), wgmma_desc(b_s + 32 * ks));
    asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory");
    asm volatile("wgmma.wait_group.sync.aligned %0;\n" ::"n"(Tile::MMA_IN_FLIGHT) : "memory");
    wgmma_fence_acc(acc);
  }
  asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory");
  wgmma_fence_acc(acc);
  cp_async_wait<0>();
  // warp w holds rows 16 w .. 16 w + 15 of the tile, in mma.sync's fragment layout
  float* part = partial != nullptr ? partial + blockIdx.z * n_out * cout : nullptr;
  store_fragments(acc, orow, warp * 16, col0, lane, cout, out, part, epi);
#else
  __trap();  // launched only by an sm_90a build on compute capability 9.0 (wgmma_columns)
#endif
}

// ------------------------------------------------------------------------------------------------
// weight gradient: dW[co, k, ci] = sum_o g[o, co] x[map[o, k], ci]. Block: BCO x BCI tile of one
// offset k over one split of the output rows; BR rows per step; partial sums per split.
// ------------------------------------------------------------------------------------------------
template <typename T, int BCO, int BCI, int BR, int TCO, int TCI>
__global__ void __launch_bounds__((BCO / TCO) * (BCI / TCI))
    conv_wgrad_kernel(const T* __restrict__ x, const T* __restrict__ g, const int32_t* __restrict__ nbr,
                      acc_t<T>* __restrict__ partial, int64_t n_out, int64_t cin, int64_t cout, int64_t K,
                      int64_t rows_per_split, int64_t n_in) {
  using A = acc_t<T>;
  constexpr int kThreads = (BCO / TCO) * (BCI / TCI);
  __shared__ A Gs[BR][BCO + 1];
  __shared__ A Xs[BR][BCI + 1];
  __shared__ int32_t rows[BR];
  const int tid = threadIdx.x;
  const int tci = tid % (BCI / TCI), tco = tid / (BCI / TCI);
  const int64_t tiles_ci = ceil_div(cin, BCI);
  const int64_t ci0 = (blockIdx.x % tiles_ci) * BCI, co0 = (blockIdx.x / tiles_ci) * BCO;
  const int64_t k = blockIdx.y, s = blockIdx.z;
  const int64_t r_begin = s * rows_per_split;
  const int64_t r_end = r_begin + rows_per_split < n_out ? r_begin + rows_per_split : n_out;
  A acc[TCO][TCI];
#pragma unroll
  for (int i = 0; i < TCO; ++i)
#pragma unroll
    for (int j = 0; j < TCI; ++j) acc[i][j] = A(0);
  for (int64_t r0 = r_begin; r0 < r_end; r0 += BR) {
    int mine = 0;
    for (int r = tid; r < BR; r += kThreads) {
      const int32_t v = r0 + r < r_end ? map_row(nbr[(r0 + r) * K + k], n_in) : -1;
      rows[r] = v;
      mine |= v >= 0;
    }
    if (!__syncthreads_or(mine)) continue;
    for (int e = tid; e < BR * BCO; e += kThreads) {
      const int r = e / BCO, c = e % BCO;
      const int64_t co = co0 + c;
      Gs[r][c] = (rows[r] >= 0 && co < cout) ? static_cast<A>(g[(r0 + r) * cout + co]) : A(0);
    }
    for (int e = tid; e < BR * BCI; e += kThreads) {
      const int r = e / BCI, c = e % BCI;
      const int64_t ci = ci0 + c;
      const int32_t row = rows[r];
      Xs[r][c] = (row >= 0 && ci < cin) ? static_cast<A>(x[static_cast<int64_t>(row) * cin + ci]) : A(0);
    }
    __syncthreads();
#pragma unroll 4
    for (int r = 0; r < BR; ++r) {
      A a[TCO], b[TCI];
#pragma unroll
      for (int i = 0; i < TCO; ++i) a[i] = Gs[r][tco * TCO + i];
#pragma unroll
      for (int j = 0; j < TCI; ++j) b[j] = Xs[r][tci * TCI + j];
#pragma unroll
      for (int i = 0; i < TCO; ++i)
#pragma unroll
        for (int j = 0; j < TCI; ++j) acc[i][j] += a[i] * b[j];
    }
    __syncthreads();
  }
#pragma unroll
  for (int i = 0; i < TCO; ++i) {
    const int64_t co = co0 + tco * TCO + i;
    if (co >= cout) continue;
#pragma unroll
    for (int j = 0; j < TCI; ++j) {
      const int64_t ci = ci0 + tci * TCI + j;
      if (ci < cin) partial[((s * cout + co) * K + k) * cin + ci] = acc[i][j];
    }
  }
}

// out = epi(partial[0] + ... + partial[splits - 1]), added in that order: the offset splits' sums
template <typename T>
__global__ void reduce_splits_kernel(const float* __restrict__ partial, int splits, int64_t numel, int cout,
                                     T* __restrict__ out, ConvEpilogue epi) {
  const int64_t stride = static_cast<int64_t>(gridDim.x) * blockDim.x;
  for (int64_t i = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; i < numel; i += stride) {
    float v = partial[i];
    for (int z = 1; z < splits; ++z) v += partial[z * numel + i];
    out[i] = static_cast<T>(epi(v, i % cout));
  }
}

// Compute capability major, SM count and shared memory per SM (and reserved per block) of a device,
// queried once per device.
struct DeviceProps {
  int cc_major = 0, cc_minor = 0, sms = 1, smem_per_sm = 0, smem_reserved = 0;
};

DeviceProps device_props(c10::DeviceIndex dev) {
  static std::mutex mutex;
  static std::unordered_map<int, DeviceProps> cache;
  std::lock_guard<std::mutex> lock(mutex);
  auto it = cache.find(dev);
  if (it != cache.end()) return it->second;
  DeviceProps p;
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.cc_major, cudaDevAttrComputeCapabilityMajor, dev));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.cc_minor, cudaDevAttrComputeCapabilityMinor, dev));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.sms, cudaDevAttrMultiProcessorCount, dev));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.smem_per_sm, cudaDevAttrMaxSharedMemoryPerMultiprocessor, dev));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.smem_reserved, cudaDevAttrReservedSharedMemoryPerBlock, dev));
  cache[dev] = p;
  return p;
}

bool aligned16(const void* p) { return (reinterpret_cast<uintptr_t>(p) & 15) == 0; }

// Raises a kernel's dynamic shared-memory limit once per (kernel, device): a driver call per launch
// showed in the host time of small layers.
void raise_smem_limit(const void* kernel, size_t bytes, c10::DeviceIndex dev) {
  static std::mutex mutex;
  static std::unordered_map<const void*, uint64_t> done;  // kernel -> bit mask of devices
  const uint64_t bit = uint64_t(1) << (dev & 63);
  std::lock_guard<std::mutex> lock(mutex);
  uint64_t& mask = done[kernel];
  if (mask & bit) return;
  C10_CUDA_CHECK(cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, static_cast<int>(bytes)));
  mask |= bit;
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
// Columns of the wgmma tile (conv_fwd_wgmma_kernel) for a tensor-core layer, or 0 for the mma.sync
// tiles: wgmma needs an sm_90a build running on compute capability 9.0; algo "mma_sync" keeps mma.sync,
// for the tests and for comparisons. Against the mma.sync tiles:
//   - Cout <= 64: mma.sync's 32 x 64 tiles, which skip the 16-row fragments without an input at an
//     offset, stay as fast or faster;
//   - TF32: 64 x 128, each gathered row read once for 128 columns;
//   - 16-bit: 64 x 64 with four stages.
int wgmma_columns(int64_t cout, bool tf32, const DeviceProps& p, ConvAlgo algo) {
#ifdef LIDAROPS_SM90A
  if (p.cc_major != 9 || p.cc_minor != 0 || cout <= 64 || algo == ConvAlgo::kMmaSync) return 0;
  return tf32 ? 128 : 64;
#else
  return 0;
#endif
}
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

// Offset splits of a pipelined launch of `tiles` blocks (threads and dynamic shared memory each), whose
// tiles take `steps` pipeline steps (offsets x input-channel chunks) without splits. None when a tile
// has fewer than 32 steps (its kernel is short: the second launch would cost the host more than the
// splits save) or when the tiles already fill more than `split_below` of one wave; otherwise as many as
// keep the launch within 1.6 waves, at most four and 8 steps per split. split_below is 1 for the FFMA
// tiles (8 warps) and 0.6 for the tensor-core tiles (4 warps), which lose from splits once they fill
// three quarters of a wave (measurements in docs/notes/sparse.md).
// forced >= 1 (the ops' `splits`) forces that many, at most K: for the tests and for tuning.
int offset_splits(int64_t tiles, int threads, size_t smem, int64_t K, int64_t steps, double split_below,
                  const DeviceProps& p, int64_t static_smem, int64_t forced) {
  constexpr int kMaxSplits = 4;
  if (forced >= 1) return static_cast<int>(std::min<int64_t>(forced, std::max<int64_t>(K, 1)));
  if (steps < 32) return 1;
  const int64_t per_sm = std::max<int64_t>(
      1, std::min<int64_t>(2048 / threads,
                           p.smem_per_sm / (static_cast<int64_t>(smem) + static_smem + p.smem_reserved)));
  const double slots = static_cast<double>(per_sm * p.sms);
  if (static_cast<double>(tiles) > split_below * slots) return 1;
  int s = 1;
  while (s < kMaxSplits && 8 * (s + 1) <= steps && static_cast<double>(tiles * (s + 1)) <= 1.6 * slots) ++s;
  return s;
}

// Static shared memory of a pipelined kernel, for offset_splits: about 1 KB (the output rows and the
// offset lists) for the FFMA and mma.sync kernels, none for the wgmma kernel (WgTile).
template <typename Tile>
constexpr int64_t static_smem(const Tile*) {
  return 1024;
}
template <Mma M, int BN, int STAGES, int LOOKAHEAD>
constexpr int64_t static_smem(const WgTile<M, BN, STAGES, LOOKAHEAD>*) {
  return 0;
}

// Launches a pipelined forward kernel (the FFMA tiles or the tensor-core kernel: the same parameters) on
// tiles of bm x bn, step_channels input channels per step, with the offset splits offset_splits picks:
// one launch writing `out`, or the float partial sums of every split and reduce_splits_kernel;
// forced_splits >= 1 forces the splits.
template <typename T, typename Tile, typename Kernel>
void launch_pipelined(Kernel kernel, int bm, int bn, int step_channels, double split_below, const at::Tensor& x,
                      const at::Tensor& w, const at::Tensor& nbr, const int32_t* order, at::Tensor& out,
                      const ConvEpilogue& epi, const DeviceProps& props, cudaStream_t stream, int64_t forced_splits) {
  const int64_t n_out = nbr.size(0), K = nbr.size(1), cin = x.size(1), cout = w.size(0);
  raise_smem_limit(reinterpret_cast<const void*>(kernel), Tile::smem(kAsyncMaxK), x.get_device());
  const int64_t row_tiles = ceil_div(n_out, bm), col_tiles = ceil_div(cout, bn);
  const size_t smem = Tile::smem(static_cast<int>(K));
  const int64_t steps = K * ceil_div(cin, step_channels);  // of a tile, without splits
  const int splits = offset_splits(row_tiles * col_tiles, Tile::kThreads, smem, K, steps, split_below, props,
                                   static_smem(static_cast<const Tile*>(nullptr)), forced_splits);
  at::Tensor partial;
  if (splits > 1) partial = at::empty({splits, out.numel()}, out.options().dtype(at::kFloat));
  const dim3 grid(static_cast<unsigned>(row_tiles), static_cast<unsigned>(col_tiles), static_cast<unsigned>(splits));
  kernel<<<grid, Tile::kThreads, smem, stream>>>(x.data_ptr<T>(), w.data_ptr<T>(), nbr.data_ptr<int32_t>(), order,
                                                 out.data_ptr<T>(), n_out, static_cast<int>(cin),
                                                 static_cast<int>(cout), static_cast<int>(K), epi,
                                                 splits > 1 ? partial.data_ptr<float>() : nullptr, x.size(0));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (splits == 1) return;
  const int64_t numel = out.numel();
  const int64_t blocks = std::min<int64_t>(ceil_div(numel, 256), 8 * static_cast<int64_t>(props.sms));
  reduce_splits_kernel<T><<<static_cast<unsigned>(blocks), 256, 0, stream>>>(
      partial.data_ptr<float>(), splits, numel, static_cast<int>(cout), out.data_ptr<T>(), epi);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

template <typename T, int BM, int BN, int BK, int TM, int TN>
void launch_simt(const at::Tensor& x, const at::Tensor& w, const at::Tensor& nbr, const int32_t* order, at::Tensor& out,
                 const ConvEpilogue& epi, cudaStream_t stream) {
  const int64_t n_out = nbr.size(0), K = nbr.size(1), cin = x.size(1), cout = w.size(0);
  const dim3 grid(static_cast<unsigned>(ceil_div(n_out, BM)), static_cast<unsigned>(ceil_div(cout, BN)));
  conv_fwd_simt_kernel<T, BM, BN, BK, TM, TN><<<grid, (BM / TM) * (BN / TN), 0, stream>>>(
      x.data_ptr<T>(), w.data_ptr<T>(), nbr.data_ptr<int32_t>(), order, out.data_ptr<T>(), n_out, cin, cout, K, epi,
      x.size(0));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

__global__ void row_mask_kernel(const int32_t* __restrict__ nbr, int64_t m, int64_t K, int64_t* __restrict__ masks) {
  const int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x;
  if (t < m) masks[t] = row_mask(nbr + t * K, K);
}

at::Tensor sparse_kernel_map_order_cuda(const at::Tensor& nbr_in) {
  TORCH_CHECK_VALUE(nbr_in.dim() == 2 && nbr_in.scalar_type() == at::kInt, "kernel_map must be (N_out, K) int32, got shape ",
                    nbr_in.sizes(), " and dtype ", nbr_in.scalar_type());
  const c10::cuda::OptionalCUDAGuard guard(nbr_in.device());
  auto nbr = nbr_in.contiguous();
  const int64_t m = nbr.size(0), K = nbr.size(1);
  auto masks = at::empty({m}, nbr.options().dtype(at::kLong));
  if (m > 0) {
    row_mask_kernel<<<static_cast<unsigned>(ceil_div(m, 256)), 256, 0, c10::cuda::getCurrentCUDAStream()>>>(
        nbr.data_ptr<int32_t>(), m, K, masks.data_ptr<int64_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  return std::get<1>(masks.sort(/*stable=*/true, /*dim=*/0, /*descending=*/false)).to(at::kInt);
}

// Output rows with no input: every one is epi(0) (at::empty otherwise, so each kernel writes every row).
at::Tensor conv_without_inputs(at::Tensor& out, const ConvEpilogue& epi, const at::Tensor& scale,
                               const at::Tensor& shift) {
  if (!scale.defined() && !shift.defined()) return out.zero_();
  auto row = shift.defined() ? shift.clone() : at::zeros({out.size(1)}, out.options().dtype(at::kFloat));
  if (epi.relu) row.clamp_min_(0);  // scale * 0 = 0
  return out.copy_(row.unsqueeze(0).expand_as(out));
}

at::Tensor sparse_conv_cuda_impl(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& nbr_in,
                                 const c10::optional<at::Tensor>& order_in, const at::Tensor& scale,
                                 const at::Tensor& shift, bool relu, ConvAlgo algo, int64_t splits) {
  const c10::cuda::OptionalCUDAGuard guard(features.device());
  const ConvEpilogue epi = make_epilogue(scale, shift, relu);
  auto x = features.contiguous();
  auto w = weight.contiguous();
  auto nbr = nbr_in.contiguous();
  at::Tensor order_t;
  if (order_in.has_value() && order_in->defined()) order_t = order_in->contiguous();
  const int32_t* order = order_t.defined() ? order_t.data_ptr<int32_t>() : nullptr;
  const int64_t n_in = x.size(0), cin = x.size(1), cout = w.size(0), K = w.size(1), n_out = nbr.size(0);
  TORCH_CHECK_VALUE(ceil_div(n_out, 64) < (int64_t(1) << 31) && ceil_div(cout, 16) < 65536,
                    "sparse_conv: too many output rows or channels for one launch (", n_out, " x ", cout, ")");
  auto out = at::empty({n_out, cout}, x.options());
  if (n_out == 0 || cout == 0) return out;
  if (n_in == 0 || cin == 0 || K == 0) return conv_without_inputs(out, epi, scale, shift);
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  const auto dtype = x.scalar_type();
  const bool half_type = dtype == at::kHalf || dtype == at::kBFloat16;
  // float32 follows torch.backends.cuda.matmul.allow_tf32 (off by default: float32 accuracy)
  const bool tf32 = dtype == at::kFloat && at::globalContext().allowTF32CuBLAS();
  const bool x3 = dtype == at::kFloat && !tf32 && algo == ConvAlgo::k3xTF32;
  const DeviceProps props = device_props(x.get_device());
  const bool sm80 = props.cc_major >= 8;
  const bool tensor_cores = (half_type || tf32 || x3) && cin >= 16 && cout >= 16 && sm80;
  // rows of 16-byte vectors (8 halves or 4 floats), 16-byte aligned: the cp.async pipelines
  const bool vec_rows = cin % (half_type ? 8 : 4) == 0 && aligned16(x.data_ptr()) && aligned16(w.data_ptr());
  const bool pipelined = vec_rows && K <= kAsyncMaxK;
  if (tensor_cores && pipelined) {
    auto launch = [&](auto tag, auto mode) {
      using scalar_t = decltype(tag);
      constexpr Mma M = decltype(mode)::value;
      auto go = [&](auto tile) {
        using Tile = decltype(tile);
        launch_pipelined<scalar_t, Tile>(conv_fwd_mma_kernel<scalar_t, M, Tile>, Tile::BM, Tile::BN, Tile::BK, 0.6, x,
                                         w, nbr, order, out, epi, props, stream, splits);
      };
      const MmaShape shape = mma_tile_shape(n_out, cout, props.sms);
      if constexpr (M != Mma::k3xTF32) {
        // 64 x 128 tiles (TF32): three blocks with three stages fit in a multiprocessor (WgTile). Layers
        // with a full wave of those tiles or more run two per multiprocessor instead, for fewer waves with
        // less of a tail: four stages, whose shared memory (96 KB of ring) lets exactly two blocks fit, with
        // two steps' gathers and one step's wgmma in flight while the next is multiplied. Layers under a
        // wave keep three blocks, which a fourth stage would cost them. algo "wgmma_2blocks" or
        // "wgmma_3blocks" forces either, for the tests.
        auto go_wg = [&](auto tile) {
          using Tile = decltype(tile);
          launch_pipelined<scalar_t, Tile>(conv_fwd_wgmma_kernel<scalar_t, M, Tile>, Tile::BM, Tile::BN, Tile::BK, 0.6,
                                           x, w, nbr, order, out, epi, props, stream, splits);
        };
        const int wg = wgmma_columns(cout, M == Mma::kTF32, props, algo);
        if constexpr (M == Mma::kTF32) {  // 16-bit types take 64 columns
          if (wg == 128) {
            bool two = ceil_div(n_out, 64) * ceil_div(cout, 128) >= 3 * props.sms;
            if (algo == ConvAlgo::kWgmma2Blocks) two = true;
            if (algo == ConvAlgo::kWgmma3Blocks) two = false;
            return two ? go_wg(WgTile<M, 128, 4, 2>{}) : go_wg(WgTile<M, 128, 3>{});
          }
        }
        if (wg == 64) return go_wg(WgTile<M, 64, 4>{});
      }
      if (shape.rows == 32) go(MmaTile<M, 32, 64, 2, 2, 3>{});
      else if (shape.cols <= 16) go(MmaTile<M, 64, 16, 4, 1, 3>{});
      else if (shape.cols <= 32) go(MmaTile<M, 64, 32, 4, 1, 3>{});
      else go(MmaTile<M, 64, 64, 2, 2, 3>{});
    };
    if (dtype == at::kHalf) launch(c10::Half{}, std::integral_constant<Mma, Mma::kF16>{});
    else if (dtype == at::kBFloat16) launch(c10::BFloat16{}, std::integral_constant<Mma, Mma::kBF16>{});
    else if (x3) launch(float{}, std::integral_constant<Mma, Mma::k3xTF32>{});
    else launch(float{}, std::integral_constant<Mma, Mma::kTF32>{});
    return out;
  }
  if (tensor_cores && !x3) {  // the plain WMMA kernel: rows not 16-byte vectors, or K > 32
    const dim3 grid(static_cast<unsigned>(ceil_div(n_out, 64)), static_cast<unsigned>(ceil_div(cout, 64)));
    auto launch = [&](auto tag) {
      using scalar_t = decltype(tag);
      auto kernel = vec_rows ? conv_fwd_wmma_kernel<scalar_t, true> : conv_fwd_wmma_kernel<scalar_t, false>;
      kernel<<<grid, kWmmaThreads, 0, stream>>>(x.data_ptr<scalar_t>(), w.data_ptr<scalar_t>(), nbr.data_ptr<int32_t>(),
                                                order, out.data_ptr<scalar_t>(), n_out, cin, cout, K, epi, n_in);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    };
    if (dtype == at::kHalf) launch(c10::Half{});
    else if (dtype == at::kBFloat16) launch(c10::BFloat16{});
    else launch(float{});
    return out;
  }
  if (dtype == at::kFloat && pipelined && sm80) {
    auto launch = [&](auto kernel, auto tile, int bm, int bn) {
      using Tile = decltype(tile);
      launch_pipelined<float, Tile>(kernel, bm, bn, Tile::kStepChannels, 1.0, x, w, nbr, order, out, epi, props,
                                    stream, splits);
    };
    // 64-row tiles, 32 channels per step, 3 stages: the best of the tiles tried (docs/notes/sparse.md)
    if (cout <= 16) launch(conv_fwd_f32_async_kernel<64, 16, 4, 2, 32, 3>, AsyncTile<64, 16, 4, 2, 32, 3>{}, 64, 16);
    else if (cout <= 32) launch(conv_fwd_f32_async_kernel<64, 32, 4, 2, 32, 3>, AsyncTile<64, 32, 4, 2, 32, 3>{}, 64, 32);
    else launch(conv_fwd_f32_async_kernel<64, 64, 4, 4, 32, 3>, AsyncTile<64, 64, 4, 4, 32, 3>{}, 64, 64);
    return out;
  }
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, dtype, "lidarops_sparse_conv_simt", [&] {
    if (cout <= 16) launch_simt<scalar_t, 128, 16, 16, 4, 2>(x, w, nbr, order, out, epi, stream);
    else if (cout <= 32) launch_simt<scalar_t, 64, 32, 16, 4, 2>(x, w, nbr, order, out, epi, stream);
    else launch_simt<scalar_t, 64, 64, 16, 4, 4>(x, w, nbr, order, out, epi, stream);
  });
  return out;
}

at::Tensor sparse_conv_cuda(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& nbr,
                            const c10::optional<at::Tensor>& order, c10::string_view algo, int64_t splits) {
  check_conv_args(features, weight, nbr);
  check_order(order, nbr);
  const ConvAlgo choice = check_conv_algo(algo, splits);
  return sparse_conv_cuda_impl(features, weight, nbr, order, at::Tensor(), at::Tensor(), false, choice, splits);
}

at::Tensor sparse_conv_affine_cuda(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& nbr,
                                   const c10::optional<at::Tensor>& order, const c10::optional<at::Tensor>& scale,
                                   const c10::optional<at::Tensor>& shift, bool relu, c10::string_view algo,
                                   int64_t splits) {
  check_conv_args(features, weight, nbr);
  check_order(order, nbr);
  const auto scale_c = epilogue_operand(scale, "scale", weight.size(0), features);  // checked in this order
  const auto shift_c = epilogue_operand(shift, "shift", weight.size(0), features);
  const ConvAlgo choice = check_conv_algo(algo, splits);
  return sparse_conv_cuda_impl(features, weight, nbr, order, scale_c, shift_c, relu, choice, splits);
}

at::Tensor sparse_conv_weight_grad_cuda(const at::Tensor& features, const at::Tensor& grad_in, const at::Tensor& nbr_in) {
  check_weight_grad_args(features, grad_in, nbr_in);
  const c10::cuda::OptionalCUDAGuard guard(features.device());
  auto x = features.contiguous();
  auto g = grad_in.contiguous();
  auto nbr = nbr_in.contiguous();
  const int64_t n_in = x.size(0), cin = x.size(1), cout = g.size(1), K = nbr.size(1), n_out = nbr.size(0);
  const auto dtype = x.scalar_type();
  const auto ct = dtype == at::kDouble ? at::kDouble : at::kFloat;
  if (n_out == 0 || n_in == 0 || cin == 0 || cout == 0 || K == 0)
    return at::zeros({cout, K, cin}, x.options());
  constexpr int BCO = 32, BCI = 32, BR = 32, TCO = 2, TCI = 2;
  const int64_t tiles = ceil_div(cout, BCO) * ceil_div(cin, BCI);
  TORCH_CHECK_VALUE(tiles < (int64_t(1) << 31) && K < 65536, "sparse_conv_weight_grad: too many channels or offsets");
  const int64_t sms = device_props(x.get_device()).sms;
  // enough row splits to fill the GPU about four times over, each of at least 256 rows
  const int64_t splits = std::max<int64_t>(
      1, std::min<int64_t>({ceil_div(4 * sms, tiles * K), ceil_div(n_out, 256), int64_t(65535)}));
  const int64_t rows_per_split = ceil_div(n_out, splits);
  auto partial = at::empty({splits, cout, K, cin}, x.options().dtype(ct));
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  const dim3 grid(static_cast<unsigned>(tiles), static_cast<unsigned>(K), static_cast<unsigned>(splits));
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, dtype, "lidarops_sparse_conv_wgrad", [&] {
    conv_wgrad_kernel<scalar_t, BCO, BCI, BR, TCO, TCI><<<grid, (BCO / TCO) * (BCI / TCI), 0, stream>>>(
        x.data_ptr<scalar_t>(), g.data_ptr<scalar_t>(), nbr.data_ptr<int32_t>(), partial.data_ptr<acc_t<scalar_t>>(),
        n_out, cin, cout, K, rows_per_split, n_in);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  auto dw = splits == 1 ? partial.select(0, 0) : partial.sum(0);
  return dw.to(dtype).contiguous();
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("sparse_kernel_map_order", &sparse_kernel_map_order_cuda);
  m.impl("sparse_conv", &sparse_conv_cuda);
  m.impl("sparse_conv_affine", &sparse_conv_affine_cuda);
  m.impl("sparse_conv_weight_grad", &sparse_conv_weight_grad_cuda);
}

}  // namespace sparse
}  // namespace lidarops
