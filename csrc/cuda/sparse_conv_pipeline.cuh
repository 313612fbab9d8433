// Device code the pipelined forward kernels share (the float32 FFMA tiles, mma.sync, wgmma; WMMA and
// the SIMT tiles use output_row): the tile's rows and offset splits, the cp.async ring and its copies,
// the map slice of a tile, the tensor-core tile layout and fragment stores; and launch_pipelined, the
// launcher of every pipelined kernel, with its host helpers in sparse_conv_pipeline.cu.
#pragma once

#include <c10/cuda/CUDAException.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>

#include <cstddef>
#include <cstdint>
#include <type_traits>

#include "lidarops/cp_async.cuh"
#include "sparse_conv.cuh"

namespace lidarops {
namespace sparse {

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
// the cp.async pipeline (sm_80+): 16-byte copies from global to shared memory through a ring of
// STAGES buffers, STAGES - 1 steps in flight (sparse_conv_simt.cu describes it)
// ------------------------------------------------------------------------------------------------
using gpu::cp_async16;
using gpu::cp_async_commit;
using gpu::cp_async_wait;

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

// The inputs of the tile's output rows orow[0, BM) at kernel offset k, into rows[0, BM) (-1: none);
// whether this thread found one (the block ORs it with __syncthreads_or to skip an empty offset).
template <int BM, int kThreads>
__device__ __forceinline__ int offset_rows(const int32_t* nbr, const int64_t* orow, int64_t K, int64_t k,
                                           int64_t n_in, int32_t* rows) {
  int mine = 0;
  for (int m = threadIdx.x; m < BM; m += kThreads) {
    const int64_t o = orow[m];
    const int32_t r = o >= 0 ? map_row(nbr[o * K + k], n_in) : -1;
    rows[m] = r;
    mine |= r >= 0;
  }
  return mine;
}

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

// ------------------------------------------------------------------------------------------------
// tensor-core tiles of the mma.sync and wgmma kernels (sparse_conv_mma.cu describes them)
// ------------------------------------------------------------------------------------------------
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
  static constexpr int64_t kStaticSmem = 1024;  // orow, klist and the flags: about 1 KB (offset_splits)
  static_assert(MF >= 1 && NF >= 2 && NF % 2 == 0 && BK % KS == 0 && BM <= 16 * 32, "whole fragments");
  static_assert(BM % 8 == 0 && BN % 8 == 0, "swizzle: row & 7 of a tile row is that of its stage row");
  // Shared rows are 128 bytes, unpadded; the 16-byte chunk c of row r is stored at chunk c ^ (r & 7), so
  // the eight rows an ldmatrix phase reads, and the eight chunks of a row a quarter-warp copies, fall in
  // eight different bank groups.
  static __device__ __forceinline__ int at(int r, int c) { return r * BK + ((c ^ (r & 7)) * V); }
};

#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
// The tensor core reads a float32 operand as TF32 by dropping its low 13 bits (truncation, about 2.5x
// the error of rounding).
// Rounding to nearest is then one fused multiply-add: x + sign(x) 2^(exponent - 11), half a TF32 ulp,
// computed from x's sign and exponent bits. inf and NaN stay as they are; subnormal numbers are
// truncated (their exponent bits give 0). Two instructions per
// register instead of cvt.rna's three (a compare, an add and a mask): 4 % on the backbone's TF32 layers.
__device__ __forceinline__ unsigned tf32_round(unsigned x) {
  return __float_as_uint(__fmaf_rn(__uint_as_float(x & 0xff800000u), 0.00048828125f, __uint_as_float(x)));
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

// Offset splits of a pipelined launch (sparse_conv_pipeline.cu); `forced` >= 1 forces that many.
int offset_splits(int64_t tiles, int threads, size_t smem, int64_t K, int64_t steps, double split_below,
                  const DeviceProps& p, int64_t static_smem, int64_t forced);
// out = epi(partial[0] + ... + partial[splits - 1]), added in that order (float, float16, bfloat16).
template <typename T>
void reduce_offset_splits(const at::Tensor& partial, int splits, int cout, at::Tensor& out, const ConvEpilogue& epi,
                          const DeviceProps& props, cudaStream_t stream);

// Launches a pipelined forward kernel (the FFMA tiles or the tensor-core kernel: the same parameters) on
// tiles of bm x bn, step_channels input channels per step, with the offset splits offset_splits picks:
// one launch writing `out`, or the float partial sums of every split and reduce_offset_splits.
template <typename T, typename Tile, typename Kernel>
void launch_pipelined(Kernel kernel, int bm, int bn, int step_channels, double split_below, const ConvLaunch& a) {
  const at::Tensor &x = a.x, &w = a.w, &nbr = a.nbr;
  const int32_t* order = a.order;
  at::Tensor& out = a.out;
  const ConvEpilogue& epi = a.epi;
  const DeviceProps& props = a.props;
  cudaStream_t stream = a.stream;
  const int64_t n_out = nbr.size(0), K = nbr.size(1), cin = x.size(1), cout = w.size(0);
  gpu::raise_smem_limit(reinterpret_cast<const void*>(kernel), Tile::smem(kAsyncMaxK), x.get_device());
  const int64_t row_tiles = ceil_div(n_out, bm), col_tiles = ceil_div(cout, bn);
  const size_t smem = Tile::smem(static_cast<int>(K));
  const int64_t steps = K * ceil_div(cin, step_channels);  // of a tile, without splits
  const int splits = offset_splits(row_tiles * col_tiles, Tile::kThreads, smem, K, steps, split_below, props,
                                   Tile::kStaticSmem, a.splits);
  at::Tensor partial;
  if (splits > 1) partial = at::empty({splits, out.numel()}, out.options().dtype(at::kFloat));
  const dim3 grid(static_cast<unsigned>(row_tiles), static_cast<unsigned>(col_tiles), static_cast<unsigned>(splits));
  kernel<<<grid, Tile::kThreads, smem, stream>>>(x.data_ptr<T>(), w.data_ptr<T>(), nbr.data_ptr<int32_t>(), order,
                                                 out.data_ptr<T>(), n_out, static_cast<int>(cin),
                                                 static_cast<int>(cout), static_cast<int>(K), epi,
                                                 splits > 1 ? partial.data_ptr<float>() : nullptr, x.size(0));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (splits == 1) return;
  reduce_offset_splits<T>(partial, splits, static_cast<int>(cout), out, epi, props, stream);
}

}  // namespace sparse
}  // namespace lidarops
