// Sparse convolution forward on CUDA, tensor cores through Hopper's warpgroup MMA on the cp.async
// pipeline (sm_90a builds on compute capability 9.0; float16, bfloat16, TF32). sparse_conv_kernel.cu
// picks it (wgmma_columns).
#include <ATen/ATen.h>
#include <c10/util/Exception.h>

#include <cstdint>

#include "sparse_conv_pipeline.cuh"

namespace lidarops {
namespace sparse {
namespace {

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
  static constexpr int64_t kStaticSmem = 0;  // all of it is dynamic (offset_splits)
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

template <typename T, Mma M>
void launch_wgmma(const ConvLaunch& a, int cols, ConvAlgo algo) {
  auto go = [&](auto tile) {
    using Tile = decltype(tile);
    launch_pipelined<T, Tile>(conv_fwd_wgmma_kernel<T, M, Tile>, Tile::BM, Tile::BN, Tile::BK, 0.6, a);
  };
  if constexpr (M == Mma::kTF32) {  // 16-bit types take 64 columns
    if (cols == 128) {
      // 64 x 128 tiles (TF32): three blocks with three stages fit in a multiprocessor (WgTile). Layers
      // with a full wave of those tiles or more run two per multiprocessor instead, for fewer waves with
      // less of a tail: four stages, whose shared memory (96 KB of ring) lets exactly two blocks fit, with
      // two steps' gathers and one step's wgmma in flight while the next is multiplied. Layers under a
      // wave keep three blocks, which a fourth stage would cost them. algo "wgmma_2blocks" or
      // "wgmma_3blocks" forces either, for the tests.
      bool two = ceil_div(a.nbr.size(0), 64) * ceil_div(a.w.size(0), 128) >= 3 * a.props.sms;
      if (algo == ConvAlgo::kWgmma2Blocks) two = true;
      if (algo == ConvAlgo::kWgmma3Blocks) two = false;
      return two ? go(WgTile<M, 128, 4, 2>{}) : go(WgTile<M, 128, 3>{});
    }
  }
  go(WgTile<M, 64, 4>{});
}

}  // namespace

void conv_fwd_wgmma(const ConvLaunch& a, Mma mode, int cols, ConvAlgo algo) {
  switch (mode) {
    case Mma::kF16: return launch_wgmma<c10::Half, Mma::kF16>(a, cols, algo);
    case Mma::kBF16: return launch_wgmma<c10::BFloat16, Mma::kBF16>(a, cols, algo);
    case Mma::kTF32: return launch_wgmma<float, Mma::kTF32>(a, cols, algo);
    case Mma::k3xTF32: break;
  }
  TORCH_INTERNAL_ASSERT(false, "sparse_conv: 3xTF32 runs on the mma.sync kernel");
}

}  // namespace sparse
}  // namespace lidarops
