// Sparse convolution on CUDA: one fused implicit-GEMM kernel over all kernel offsets.
//
// Forward, output-stationary: out (N_out x Cout) = A (N_out x K*Cin) . W^T, where row o of A is the
// concatenation over offsets k of features[kernel_map[o, k]] (zeros where the map is -1). A block
// owns a tile of output rows x output channels and walks every offset and input-channel chunk,
// gathering the input rows straight into shared memory; offsets with no input for any row of the
// tile are skipped (a block-wide vote). One launch per layer, no atomics, no host synchronisation:
// each output element is summed by one thread in a fixed order, so results are deterministic.
//   - float16 / bfloat16 (sm_80+, Cin and Cout >= 16): tensor cores (WMMA 16x16x16, float accumulation);
//     float32 likewise with TF32 fragments when torch allows TF32 matmuls (off by default); fed by
//     cp.async pipelines when Cin is a multiple of the 16-byte vector and K <= 32.
//   - float32 otherwise (sm_80+, Cin a multiple of 4, K <= 32): SIMT tiles fed by cp.async pipelines;
//   - otherwise general SIMT tiles in float (float64 in float64).
// Rows are processed in the order given by sparse_kernel_map_order (grouped by their offset masks),
// so the rows of a tile share their offsets and the skipping is effective on real data.
// Backward: the features gradient is this kernel over the transposed map (autograd in Python); the
// weight gradient is a split-K reduction over output rows into per-split partial sums (float), added
// in a fixed order: deterministic too.
#include <ATen/Context.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <mma.h>

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

// ------------------------------------------------------------------------------------------------
// forward, SIMT tiles: BM output rows x BN output channels per block, BK input channels per step,
// each thread TM x TN outputs.
// ------------------------------------------------------------------------------------------------
template <typename T, int BM, int BN, int BK, int TM, int TN>
__global__ void __launch_bounds__((BM / TM) * (BN / TN))
    conv_fwd_simt_kernel(const T* __restrict__ x, const T* __restrict__ w, const int32_t* __restrict__ nbr,
                         const int32_t* __restrict__ order, T* __restrict__ out, int64_t n_out, int64_t cin,
                         int64_t cout, int64_t K, ConvEpilogue epi) {
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
      const int32_t r = o >= 0 ? nbr[o * K + k] : -1;
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
//     maps a block's steps form a chain of dependent gathers whose latency, not the arithmetic, set the
//     time (H200, session 5: a register-prefetched version with one step in flight was 1.2-1.4x slower).
//   - Tiles are stored row-major with a 4-float pad (rows 16-byte aligned; a quarter-warp's float4 reads
//     of 8 consecutive rows hit 8 different bank groups); a thread owns the rows ty + i * (BM / TM) and
//     the columns tx + j * (BN / TN) and reads float4 fragments along the channels.
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

// The map slice of a tile of BM output rows starting at row0: orow[m] (the output row at tile row m,
// -1 past the end), rows[k * BM + m] (its input at offset k, or -1) and klist[0, nk) (the offsets any
// row of the tile has, ascending; K <= 32). Called by the whole block; returns nk after a barrier.
template <int BM, int kThreads>
__device__ int tile_map_slice(const int32_t* __restrict__ nbr, const int32_t* __restrict__ order, int64_t n_out,
                              int K, int64_t row0, int64_t* orow, int32_t* rows, int* klist, unsigned* present,
                              int* nk) {
  const int tid = threadIdx.x;
  for (int m = tid; m < BM; m += kThreads) orow[m] = output_row(order, row0 + m, n_out);
  if (tid == 0) *present = 0u;
  __syncthreads();
  for (int e = tid; e < BM * K; e += kThreads) {  // row by row: coalesced reads of the map
    const int m = e / K, k = e % K;
    const int64_t o = orow[m];
    const int32_t r = o >= 0 ? nbr[o * K + k] : -1;
    rows[k * BM + m] = r;
    if (r >= 0) atomicOr(present, 1u << k);
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
  static constexpr int kThreads = (BM / TM) * (BN / TN);
  static constexpr int LD = BK + 4;
  static constexpr size_t kSmem = sizeof(float) * STAGES * (BM + BN) * LD + sizeof(int32_t) * kAsyncMaxK * BM;
};

template <int BM, int BN, int TM, int TN, int BK, int STAGES>
__global__ void __launch_bounds__(AsyncTile<BM, BN, TM, TN, BK, STAGES>::kThreads)
    conv_fwd_f32_async_kernel(const float* __restrict__ x, const float* __restrict__ w,
                              const int32_t* __restrict__ nbr, const int32_t* __restrict__ order,
                              float* __restrict__ out, int64_t n_out, int cin, int cout, int K, ConvEpilogue epi) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  using Tile = AsyncTile<BM, BN, TM, TN, BK, STAGES>;
  constexpr int kThreads = Tile::kThreads, LD = Tile::LD;
  static_assert(BK % 4 == 0 && STAGES >= 2, "16-byte copies, at least double buffering");
  extern __shared__ __align__(16) float smem[];
  float* As = smem;                                   // [STAGES][BM][LD]
  float* Bs = smem + STAGES * BM * LD;                // [STAGES][BN][LD]
  int32_t* rows = reinterpret_cast<int32_t*>(Bs + STAGES * BN * LD);  // [kAsyncMaxK][BM]
  __shared__ int64_t orow[BM];
  __shared__ unsigned present;
  __shared__ int klist[kAsyncMaxK];
  __shared__ int nk;
  const int tid = threadIdx.x;
  const int tx = tid % (BN / TN), ty = tid / (BN / TN);
  const int col0 = static_cast<int>(blockIdx.y) * BN;
  const int chunks = (cin + BK - 1) / BK;
  const int steps = tile_map_slice<BM, kThreads>(nbr, order, n_out, K, static_cast<int64_t>(blockIdx.x) * BM, orow, rows,
                                                 klist, &present, &nk) * chunks;
  auto issue = [&](int t) {  // step t's tiles into stage t % STAGES (nothing past the last step)
    if (t < steps) {
      const int k = klist[t / chunks], c0 = (t % chunks) * BK, st = t % STAGES;
      for (int e = tid; e < BM * (BK / 4); e += kThreads) {
        const int m = e / (BK / 4), ci = c0 + (e % (BK / 4)) * 4;
        const int32_t r = rows[k * BM + m];
        const bool ok = r >= 0 && ci < cin;
        cp_async16(As + (st * BM + m) * LD + (ci - c0), ok ? x + static_cast<int64_t>(r) * cin + ci : x, ok);
      }
      for (int e = tid; e < BN * (BK / 4); e += kThreads) {
        const int n = e / (BK / 4), ci = c0 + (e % (BK / 4)) * 4, co = col0 + n;
        const bool ok = co < cout && ci < cin;
        cp_async16(Bs + (st * BN + n) * LD + (ci - c0), ok ? w + (static_cast<int64_t>(co) * K + k) * cin + ci : w, ok);
      }
    }
    cp_async_commit();  // an empty group past the end keeps the wait counts uniform
  };

  float acc[TM][TN];
#pragma unroll
  for (int i = 0; i < TM; ++i)
#pragma unroll
    for (int j = 0; j < TN; ++j) acc[i][j] = 0.f;
#pragma unroll
  for (int t = 0; t < STAGES - 1; ++t) issue(t);
  for (int t = 0; t < steps; ++t) {
    cp_async_wait<STAGES - 2>();  // step t has landed (for this thread's copies) ...
    __syncthreads();              // ... and for everyone's; stage (t - 1) % STAGES is free again
    issue(t + STAGES - 1);
    const float* a_t = As + (t % STAGES) * BM * LD;
    const float* b_t = Bs + (t % STAGES) * BN * LD;
#pragma unroll
    for (int kk = 0; kk < BK; kk += 4) {
      float4 a[TM], b[TN];
#pragma unroll
      for (int i = 0; i < TM; ++i) a[i] = *reinterpret_cast<const float4*>(a_t + (ty + i * (BM / TM)) * LD + kk);
#pragma unroll
      for (int j = 0; j < TN; ++j) b[j] = *reinterpret_cast<const float4*>(b_t + (tx + j * (BN / TN)) * LD + kk);
#pragma unroll
      for (int i = 0; i < TM; ++i)
#pragma unroll
        for (int j = 0; j < TN; ++j) {
          acc[i][j] = fmaf(a[i].x, b[j].x, acc[i][j]);
          acc[i][j] = fmaf(a[i].y, b[j].y, acc[i][j]);
          acc[i][j] = fmaf(a[i].z, b[j].z, acc[i][j]);
          acc[i][j] = fmaf(a[i].w, b[j].w, acc[i][j]);
        }
    }
  }
  cp_async_wait<0>();
#pragma unroll
  for (int i = 0; i < TM; ++i) {
    const int64_t o = orow[ty + i * (BM / TM)];
    if (o < 0) continue;
#pragma unroll
    for (int j = 0; j < TN; ++j) {
      const int co = col0 + tx + j * (BN / TN);
      if (co < cout) out[o * cout + co] = epi(acc[i][j], co);
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
                         int64_t cout, int64_t K, ConvEpilogue epi) {
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
      const int32_t r = o >= 0 ? nbr[o * K + k] : -1;
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
// forward, tensor cores fed by cp.async (16-byte aligned rows, Cin a multiple of the 16-byte vector,
// K <= 32): conv_fwd_wmma_kernel's 64 x 64 tile and fragments, with the float32 SIMT kernel's offset
// list and a ring of STAGES shared buffers, so the gathers of the next steps are in flight while
// one step is multiplied. The float accumulator tile for the coalesced store reuses the ring.
// ------------------------------------------------------------------------------------------------
template <typename T, int BM_ = 64, int BN_ = 64, int FM_ = 2, int FN_ = 2>
struct WmmaAsyncTile {
  using S = typename MmaTraits<T>::S;
  static constexpr int V = MmaTraits<T>::VEC;
  static constexpr int BM = BM_, BN = BN_, BK = 32, STAGES = 3;
  static constexpr int FM = FM_, FN = FN_;                      // 16 x 16 fragments per warp
  static constexpr int WARPS_N = BN / (16 * FN);                 // warps along the columns
  static constexpr int kThreads = 32 * (BM / (16 * FM)) * WARPS_N;
  static constexpr int LD = BK + V;  // elements: rows 16-byte aligned, 16-row blocks 32-byte aligned (WMMA)
  static constexpr int LDC = BN + 4;
  static constexpr size_t kStage = sizeof(S) * (BM + BN) * LD;
  static constexpr size_t kRing = kStage * STAGES;
  static constexpr size_t kC = sizeof(float) * BM * LDC;
  static constexpr size_t kRows = sizeof(int32_t) * kAsyncMaxK * BM;
  static constexpr size_t kSmem = (kRing > kC ? kRing : kC) + kRows;
  static_assert(BM % (16 * FM) == 0 && BN % (16 * FN) == 0, "whole warp tiles");
};

template <typename T, typename Tile>
__global__ void __launch_bounds__(Tile::kThreads)
    conv_fwd_wmma_async_kernel(const T* __restrict__ x, const T* __restrict__ w, const int32_t* __restrict__ nbr,
                               const int32_t* __restrict__ order, T* __restrict__ out, int64_t n_out, int cin,
                               int cout, int K, ConvEpilogue epi) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  using namespace nvcuda;
  using S = typename Tile::S;
  constexpr int KS = MmaTraits<T>::KS, V = Tile::V, BM = Tile::BM, BN = Tile::BN, BK = Tile::BK;
  constexpr int STAGES = Tile::STAGES, LD = Tile::LD, LDC = Tile::LDC, FM = Tile::FM, FN = Tile::FN;
  constexpr int kThreads = Tile::kThreads;
  extern __shared__ __align__(128) unsigned char smem_raw[];
  S* ring = reinterpret_cast<S*>(smem_raw);
  float* Cs = reinterpret_cast<float*>(smem_raw);  // after the main loop only
  int32_t* rows = reinterpret_cast<int32_t*>(smem_raw + (Tile::kSmem - Tile::kRows));  // [kAsyncMaxK][BM]
  __shared__ int64_t orow[BM];
  __shared__ unsigned present;
  __shared__ int klist[kAsyncMaxK];
  __shared__ int nk;
  const int tid = threadIdx.x, warp = tid / 32;
  const int m0 = (warp / Tile::WARPS_N) * 16 * FM, n0 = (warp % Tile::WARPS_N) * 16 * FN;
  const int col0 = static_cast<int>(blockIdx.y) * BN;
  const int chunks = (cin + BK - 1) / BK;
  const int steps = tile_map_slice<BM, kThreads>(nbr, order, n_out, K, static_cast<int64_t>(blockIdx.x) * BM, orow,
                                                 rows, klist, &present, &nk) * chunks;
  const S* xs = reinterpret_cast<const S*>(x);
  const S* ws = reinterpret_cast<const S*>(w);
  auto issue = [&](int t) {
    if (t < steps) {
      const int k = klist[t / chunks], c0 = (t % chunks) * BK;
      S* As = ring + (t % STAGES) * (BM + BN) * LD;
      S* Bs = As + BM * LD;  // column-major B: Bs[n * LD + kk] = W[col0 + n, k, c0 + kk]
      for (int e = tid; e < BM * (BK / V); e += kThreads) {
        const int m = e / (BK / V), ci = c0 + (e % (BK / V)) * V;
        const int32_t r = rows[k * BM + m];
        const bool ok = r >= 0 && ci < cin;  // Cin is a multiple of V: a vector is all in or all out
        cp_async16(As + m * LD + (ci - c0), ok ? xs + static_cast<int64_t>(r) * cin + ci : xs, ok);
      }
      for (int e = tid; e < BN * (BK / V); e += kThreads) {
        const int n = e / (BK / V), ci = c0 + (e % (BK / V)) * V, co = col0 + n;
        const bool ok = co < cout && ci < cin;
        cp_async16(Bs + n * LD + (ci - c0), ok ? ws + (static_cast<int64_t>(co) * K + k) * cin + ci : ws, ok);
      }
    }
    cp_async_commit();
  };

  wmma::fragment<wmma::accumulator, 16, 16, KS, float> c[FM][FN];
#pragma unroll
  for (int i = 0; i < FM; ++i)
#pragma unroll
    for (int j = 0; j < FN; ++j) wmma::fill_fragment(c[i][j], 0.0f);
#pragma unroll
  for (int t = 0; t < STAGES - 1; ++t) issue(t);
  for (int t = 0; t < steps; ++t) {
    cp_async_wait<STAGES - 2>();
    __syncthreads();
    issue(t + STAGES - 1);
    const S* As = ring + (t % STAGES) * (BM + BN) * LD;
    wmma_tile_step<T, BK, FM, FN>(As, LD, As + BM * LD, LD, m0, n0, c);
  }
  cp_async_wait<0>();
  __syncthreads();  // every warp is done with the ring before Cs overwrites it
#pragma unroll
  for (int i = 0; i < FM; ++i)
#pragma unroll
    for (int j = 0; j < FN; ++j)
      wmma::store_matrix_sync(Cs + (m0 + i * 16) * LDC + n0 + j * 16, c[i][j], LDC, wmma::mem_row_major);
  __syncthreads();
  for (int e = tid; e < BM * BN; e += kThreads) {
    const int m = e / BN, n = e % BN;
    const int64_t o = orow[m];
    const int co = col0 + n;
    if (o >= 0 && co < cout) out[o * cout + co] = static_cast<T>(epi(Cs[m * LDC + n], co));
  }
#else
  __trap();  // launched only on sm_80+ (checked on the host)
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
                      int64_t rows_per_split) {
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
      const int32_t v = r0 + r < r_end ? nbr[(r0 + r) * K + k] : -1;
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

// Compute capability major and SM count of a device, queried once per device.
struct DeviceProps {
  int cc_major = 0, sms = 1;
};

DeviceProps device_props(c10::DeviceIndex dev) {
  static std::mutex mutex;
  static std::unordered_map<int, DeviceProps> cache;
  std::lock_guard<std::mutex> lock(mutex);
  auto it = cache.find(dev);
  if (it != cache.end()) return it->second;
  DeviceProps p;
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.cc_major, cudaDevAttrComputeCapabilityMajor, dev));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.sms, cudaDevAttrMultiProcessorCount, dev));
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

template <typename T, int BM, int BN, int BK, int TM, int TN>
void launch_simt(const at::Tensor& x, const at::Tensor& w, const at::Tensor& nbr, const int32_t* order, at::Tensor& out,
                 const ConvEpilogue& epi, cudaStream_t stream) {
  const int64_t n_out = nbr.size(0), K = nbr.size(1), cin = x.size(1), cout = w.size(0);
  const dim3 grid(static_cast<unsigned>(ceil_div(n_out, BM)), static_cast<unsigned>(ceil_div(cout, BN)));
  conv_fwd_simt_kernel<T, BM, BN, BK, TM, TN><<<grid, (BM / TM) * (BN / TN), 0, stream>>>(
      x.data_ptr<T>(), w.data_ptr<T>(), nbr.data_ptr<int32_t>(), order, out.data_ptr<T>(), n_out, cin, cout, K, epi);
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
                                 const at::Tensor& shift, bool relu) {
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
  // float32 follows torch.backends.cuda.matmul.allow_tf32 (off by default: exact float32)
  const bool tf32 = dtype == at::kFloat && at::globalContext().allowTF32CuBLAS();
  if ((half_type || tf32) && cin >= 16 && cout >= 16 &&
      device_props(x.get_device()).cc_major >= 8) {
    const int64_t vec = half_type ? 8 : 4;
    const bool use_vec = cin % vec == 0 && aligned16(x.data_ptr()) && aligned16(w.data_ptr());
    const dim3 grid(static_cast<unsigned>(ceil_div(n_out, 64)), static_cast<unsigned>(ceil_div(cout, 64)));
    auto launch = [&](auto tag) {
      using scalar_t = decltype(tag);
      if (use_vec && K <= kAsyncMaxK) {  // the pipelined kernel
        // 64 x 64 tiles: 128 x 64, 64 x 128 and 128 x 128 were slower on the H100 (docs/sparse.md)
        using Tile = WmmaAsyncTile<scalar_t>;
        auto kernel = conv_fwd_wmma_async_kernel<scalar_t, Tile>;
        raise_smem_limit(reinterpret_cast<const void*>(kernel), Tile::kSmem, x.get_device());
        kernel<<<grid, Tile::kThreads, Tile::kSmem, stream>>>(x.data_ptr<scalar_t>(), w.data_ptr<scalar_t>(),
                                                              nbr.data_ptr<int32_t>(), order, out.data_ptr<scalar_t>(), n_out,
                                                              static_cast<int>(cin), static_cast<int>(cout),
                                                              static_cast<int>(K), epi);
        C10_CUDA_KERNEL_LAUNCH_CHECK();
        return;
      }
      auto kernel = use_vec ? conv_fwd_wmma_kernel<scalar_t, true> : conv_fwd_wmma_kernel<scalar_t, false>;
      kernel<<<grid, kWmmaThreads, 0, stream>>>(x.data_ptr<scalar_t>(), w.data_ptr<scalar_t>(), nbr.data_ptr<int32_t>(),
                                                order, out.data_ptr<scalar_t>(), n_out, cin, cout, K, epi);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    };
    if (dtype == at::kHalf) launch(c10::Half{});
    else if (dtype == at::kBFloat16) launch(c10::BFloat16{});
    else launch(float{});
    return out;
  }
  if (dtype == at::kFloat && cin % 4 == 0 && K <= kAsyncMaxK && device_props(x.get_device()).cc_major >= 8 &&
      aligned16(x.data_ptr()) && aligned16(w.data_ptr())) {
    auto launch = [&](auto kernel, auto tile, int bm, int bn) {
      using Tile = decltype(tile);
      raise_smem_limit(reinterpret_cast<const void*>(kernel), Tile::kSmem, x.get_device());
      const dim3 grid(static_cast<unsigned>(ceil_div(n_out, bm)), static_cast<unsigned>(ceil_div(cout, bn)));
      kernel<<<grid, Tile::kThreads, Tile::kSmem, stream>>>(x.data_ptr<float>(), w.data_ptr<float>(), nbr.data_ptr<int32_t>(),
                                                            order, out.data_ptr<float>(), n_out, static_cast<int>(cin),
                                                            static_cast<int>(cout), static_cast<int>(K), epi);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    };
    // 64-row tiles, 32 channels per step, 3 stages: the best of the tiles tried on the H200 (docs/sparse.md)
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
                            const c10::optional<at::Tensor>& order) {
  check_conv_args(features, weight, nbr);
  check_order(order, nbr);
  return sparse_conv_cuda_impl(features, weight, nbr, order, at::Tensor(), at::Tensor(), false);
}

at::Tensor sparse_conv_affine_cuda(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& nbr,
                                   const c10::optional<at::Tensor>& order, const c10::optional<at::Tensor>& scale,
                                   const c10::optional<at::Tensor>& shift, bool relu) {
  check_conv_args(features, weight, nbr);
  check_order(order, nbr);
  const auto scale_c = epilogue_operand(scale, "scale", weight.size(0), features);  // checked in this order
  const auto shift_c = epilogue_operand(shift, "shift", weight.size(0), features);
  return sparse_conv_cuda_impl(features, weight, nbr, order, scale_c, shift_c, relu);
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
        n_out, cin, cout, K, rows_per_split);
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
