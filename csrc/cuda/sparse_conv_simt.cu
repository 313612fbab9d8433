// Sparse convolution forward on CUDA, SIMT tiles: the general kernel (every dtype, any Cin and K) and
// the float32 FFMA tiles fed by the cp.async pipeline (sm_80+). sparse_conv_kernel.cu picks them.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAException.h>

#include <cstdint>

#include "sparse_conv_pipeline.cuh"

namespace lidarops {
namespace sparse {
namespace {

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
    if (!__syncthreads_or(offset_rows<BM, kThreads>(nbr, orow, K, k, n_in, rows))) continue;  // no row of this tile has an input at offset k
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
  static constexpr int64_t kStaticSmem = 1024;  // orow, klist and the flags: about 1 KB (offset_splits)
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

}  // namespace

void conv_fwd_simt(const ConvLaunch& a) {
  const int64_t cout = a.w.size(0);
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, a.x.scalar_type(), "lidarops_sparse_conv_simt", [&] {
    if (cout <= 16) launch_simt<scalar_t, 128, 16, 16, 4, 2>(a.x, a.w, a.nbr, a.order, a.out, a.epi, a.stream);
    else if (cout <= 32) launch_simt<scalar_t, 64, 32, 16, 4, 2>(a.x, a.w, a.nbr, a.order, a.out, a.epi, a.stream);
    else launch_simt<scalar_t, 64, 64, 16, 4, 4>(a.x, a.w, a.nbr, a.order, a.out, a.epi, a.stream);
  });
}

void conv_fwd_ffma(const ConvLaunch& a) {
  const int64_t cout = a.w.size(0);
  auto launch = [&](auto kernel, auto tile, int bm, int bn) {
    using Tile = decltype(tile);
    launch_pipelined<float, Tile>(kernel, bm, bn, Tile::kStepChannels, 1.0, a);
  };
  // 64-row tiles, 32 channels per step, 3 stages: the best of the tiles tried (docs/notes/sparse.md)
  if (cout <= 16) launch(conv_fwd_f32_async_kernel<64, 16, 4, 2, 32, 3>, AsyncTile<64, 16, 4, 2, 32, 3>{}, 64, 16);
  else if (cout <= 32) launch(conv_fwd_f32_async_kernel<64, 32, 4, 2, 32, 3>, AsyncTile<64, 32, 4, 2, 32, 3>{}, 64, 32);
  else launch(conv_fwd_f32_async_kernel<64, 64, 4, 4, 32, 3>, AsyncTile<64, 64, 4, 4, 32, 3>{}, 64, 64);
}

}  // namespace sparse
}  // namespace lidarops
