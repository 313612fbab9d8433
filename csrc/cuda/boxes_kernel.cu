// Rotated-box ops on CUDA: pairwise BEV overlap / IoU and 3D IoU, rotated NMS, points in boxes. The
// geometry (include/lidarops/boxes.h) is the CPU kernels' own, so both devices give the same bits.
//
// NMS: one sort of the negated scores, a bitmask kernel (bit j of row i: box j, later in score order, overlaps
// box i above the threshold; only the upper triangle is computed), and one block that walks the mask in
// blocks of 64 boxes: inside a block the kept boxes are resolved from the diagonal word by one warp, then
// the rows of the kept boxes are OR-ed into the suppression words of the later blocks. No host loop.
// nms_bev reads the number kept back; nms_bev_padded and nms_bev_checked read nothing back (the number
// of candidates and the number kept stay on the device, so the op can be captured in a CUDA graph), and
// nms_bev_checked flags bad input values beside the number kept, for a wrapper that reads both at once.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <cub/block/block_radix_sort.cuh>
#include <type_traits>

#include "lidarops/boxes.h"
#include "lidarops/cp_async.cuh"
#include "lidarops/cuda_launch.cuh"

namespace lidarops {
namespace {

using boxes::BoxGeom;
constexpr int kGeomDoubles = sizeof(BoxGeom) / sizeof(double);
static_assert(sizeof(BoxGeom) == kGeomDoubles * sizeof(double), "BoxGeom must be a plain array of doubles");


// per_frame > 0: `order` holds per_frame indices into each frame of frame_stride boxes (batched NMS).
template <typename scalar_t>
__global__ void geom_kernel(const scalar_t* __restrict__ boxes, const int64_t* __restrict__ order, int64_t n,
                            int64_t per_frame, int64_t frame_stride, BoxGeom* __restrict__ out) {
  for (int64_t i = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; i < n;
       i += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t src = order == nullptr ? i : order[i] + (per_frame > 0 ? i / per_frame * frame_stride : 0);
    out[i] = boxes::make_geom(boxes + 7 * src);
  }
}

// Geometry of boxes (in `order` when given) as an (n, kGeomDoubles) float64 tensor; per_frame, frame_stride: as
// geom_kernel's.
at::Tensor geoms_of(const at::Tensor& boxes_in, const at::Tensor& order, cudaStream_t stream, int64_t per_frame = 0,
                    int64_t frame_stride = 0) {
  auto b = boxes_in.contiguous();
  const int64_t n = order.defined() ? order.size(0) : b.size(0);
  auto out = at::empty({n, kGeomDoubles}, b.options().dtype(at::kDouble));
  if (n == 0) return out;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, b.scalar_type(), "lidarops_box_geoms_cuda", [&] {
    geom_kernel<scalar_t><<<gpu::stride_blocks(n, 128), 128, 0, stream>>>(
        b.data_ptr<scalar_t>(), order.defined() ? order.data_ptr<int64_t>() : nullptr, n, per_frame, frame_stride,
        reinterpret_cast<BoxGeom*>(out.data_ptr<double>()));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return out;
}

const BoxGeom* geom_ptr(const at::Tensor& g) { return reinterpret_cast<const BoxGeom*>(g.data_ptr<double>()); }

constexpr int kPairCols = 32, kPairRows = 8;

// Thread (y, x) of a block: pair (row tile * 8 + y, column tile * 32 + x); the tiles' boxes in shared memory.
template <typename out_t>
__global__ void __launch_bounds__(kPairCols* kPairRows)
    pairwise_kernel(const BoxGeom* __restrict__ a, int64_t N, const BoxGeom* __restrict__ b, int64_t M, int mode,
                    out_t* __restrict__ out) {
  __shared__ BoxGeom sa[kPairRows], sb[kPairCols];
  const int tx = threadIdx.x, ty = threadIdx.y, tid = ty * kPairCols + tx;
  const int64_t j0 = static_cast<int64_t>(blockIdx.x) * kPairCols, j = j0 + tx;
  if (tid < kPairCols && j0 + tid < M) sb[tid] = b[j0 + tid];
  const int64_t row_tiles = (N + kPairRows - 1) / kPairRows;
  for (int64_t tile = blockIdx.y; tile < row_tiles; tile += gridDim.y) {
    const int64_t i0 = tile * kPairRows, i = i0 + ty;
    __syncthreads();  // sb loaded; the previous tile's sa no longer read
    if (tid < kPairRows && i0 + tid < N) sa[tid] = a[i0 + tid];
    __syncthreads();
    if (i < N && j < M) out[i * M + j] = static_cast<out_t>(boxes::pair_value(sa[ty], sb[tx], mode));
  }
}

at::Tensor pairwise_cuda(const at::Tensor& a, const at::Tensor& b, int mode) {
  boxes::check_pair_args(a, b);
  c10::cuda::CUDAGuard guard(a.device());
  const int64_t N = a.size(0), M = b.size(0);
  auto out = at::empty({N, M}, a.options().dtype(a.scalar_type() == at::kDouble ? at::kDouble : at::kFloat));
  if (out.numel() == 0) return out;
  cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  auto ga = geoms_of(a, at::Tensor(), stream), gb = geoms_of(b, at::Tensor(), stream);
  TORCH_CHECK_VALUE(gpu::ceil_div(M, kPairCols) <= std::numeric_limits<int32_t>::max(), "b has too many boxes: ", M);
  const dim3 grid(static_cast<unsigned>(gpu::ceil_div(M, kPairCols)),
                  static_cast<unsigned>(std::min<int64_t>(gpu::ceil_div(N, kPairRows), 65535)));
  AT_DISPATCH_FLOATING_TYPES(out.scalar_type(), "lidarops_box_pairwise_cuda", [&] {
    pairwise_kernel<scalar_t><<<grid, dim3(kPairCols, kPairRows), 0, stream>>>(geom_ptr(ga), N, geom_ptr(gb), M,
                                                                               mode, out.data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return out;
}

at::Tensor box_overlap_bev_cuda(const at::Tensor& a, const at::Tensor& b) { return pairwise_cuda(a, b, 0); }
at::Tensor box_iou_bev_cuda(const at::Tensor& a, const at::Tensor& b) { return pairwise_cuda(a, b, 1); }
at::Tensor box_iou_3d_cuda(const at::Tensor& a, const at::Tensor& b) { return pairwise_cuda(a, b, 2); }

// Block (column word c, row words r = blockIdx.y, +gridDim.y, ...): thread t writes word c of row 64 r + t,
// for the rows r <= c (the upper triangle: only later boxes are ever suppressed). Each row first tests its
// columns' circumscribed circles (apart: no overlap) and inscribed disks (overlapping enough: suppressed);
// the pairs left undecided are queued per warp and clipped one pair per lane.
// (A thread per row would run the float64 clipping with one lane busy and the rest of the warp waiting:
// with boxes clustered on objects that made the kernel FP64-bound on idle lanes.)
// Batched (blockIdx.z = frame): each frame's n geometries, n_valid entry and n x nwords mask words follow the
// previous frame's.
__global__ void __launch_bounds__(64)
    nms_mask_kernel(const BoxGeom* __restrict__ g, const int64_t* __restrict__ group, int64_t n,
                    const int64_t* __restrict__ n_valid, int64_t nwords, double threshold,
                    uint64_t* __restrict__ mask) {
  __shared__ BoxGeom cols[64], rows[64];
  __shared__ int64_t col_group[64];
  __shared__ unsigned long long row_bits[64];
  __shared__ uint16_t queue[2][32 * 64];  // per warp: (lane of the row << 6) | column
  const int64_t frame = blockIdx.z;
  g += frame * n;
  mask += frame * n * nwords;
  if (group != nullptr) group += frame * n;
  if (n_valid != nullptr) n = std::min(n, n_valid[frame]);  // the padded variant: the grid is sized for all n
  const int64_t c = blockIdx.x, c0 = c * 64;
  if (c0 >= n) return;  // block-uniform
  const int ncols = static_cast<int>(std::min<int64_t>(64, n - c0));
  const int t = threadIdx.x, warp = t >> 5, lane = t & 31;
  if (t < ncols) {
    cols[t] = g[c0 + t];
    col_group[t] = group != nullptr ? group[c0 + t] : 0;
  }
  for (int64_t r = blockIdx.y; r <= c; r += gridDim.y) {
    const int64_t i = r * 64 + t;
    __syncthreads();  // cols loaded; the previous row word's rows and bits no longer read
    if (i < n) rows[t] = g[i];
    __syncthreads();
    uint64_t candidates = 0, surely = 0;
    if (i < n) {
      const int64_t gi = group != nullptr ? group[i] : 0;
      for (int k = r == c ? t + 1 : 0; k < ncols; ++k) {
        if (col_group[k] != gi || boxes::circles_apart(rows[t], cols[k])) continue;
        if (boxes::bev_iou_surely_above(rows[t], cols[k], threshold)) surely |= 1ull << k;
        else candidates |= 1ull << k;
      }
    }
    row_bits[t] = surely;  // its warp's lanes OR the clipped pairs in below
    // this lane's candidates go to [start, start + count) of the warp's queue
    const int count = __popcll(candidates);
    int end = count;
    for (int d = 1; d < 32; d <<= 1) {
      const int v = __shfl_up_sync(gpu::kFullMask, end, d);
      if (lane >= d) end += v;
    }
    const int total = __shfl_sync(gpu::kFullMask, end, 31);
    int pos = end - count;
    for (uint64_t bits = candidates; bits; bits &= bits - 1)
      queue[warp][pos++] = static_cast<uint16_t>((lane << 6) | (__ffsll(static_cast<long long>(bits)) - 1));
    __syncwarp();  // the queue and this warp's row_bits written
    for (int p = lane; p < total; p += 32) {
      const int q = queue[warp][p], row = warp * 32 + (q >> 6), k = q & 63;
      if (boxes::pair_value(rows[row], cols[k], 1) > threshold) atomicOr(&row_bits[row], 1ull << k);
    }
    __syncwarp();  // a warp's rows are set by its own lanes only
    if (i < n) mask[i * nwords + c] = row_bits[t];
  }
}

// The reduction: one block walks the mask 64 boxes at a time. removed[w] (shared): boxes of block w
// suppressed by the kept boxes of earlier blocks. At step c, warp 0 resolves the kept boxes of block c
// from removed[c] and the diagonal words (one iteration per kept box), then the block ORs the kept rows
// into the later words (thread t: word c + 1 + t % 64 and every 64th after it, every fourth kept row).
// The diagonal words arrive through a cp.async ring kReduceDepth - 1 blocks ahead: most steps keep no
// box and would otherwise wait for an L2 round trip each. With n_valid, only the first *n_valid boxes
// take part (the words past them were not written). Writes keep[:num_kept] = the kept boxes' indices
// (through `order`) and -1 up to max_keep. Batched (blockIdx.x = frame): each frame's mask, n_valid, n order
// entries, max_keep keep entries and num_kept follow the previous frame's.
constexpr int kReduceThreads = 256, kReduceDepth = 8;

__global__ void __launch_bounds__(kReduceThreads)
    nms_reduce_kernel(const uint64_t* __restrict__ mask, int64_t n, const int64_t* __restrict__ n_valid,
                      int64_t stride, const int64_t* __restrict__ order, int64_t max_keep,
                      int64_t* __restrict__ keep, int64_t* __restrict__ num_kept) {
  extern __shared__ uint64_t removed[];  // stride words
  __shared__ uint64_t diag[kReduceDepth][64];
  __shared__ uint64_t kept_shared;
  const int64_t frame = blockIdx.x;
  mask += frame * n * stride;
  order += frame * n;
  keep += frame * max_keep;
  num_kept += frame;
  if (n_valid != nullptr) n = std::min(n, n_valid[frame]);
  const int64_t nwords = (n + 63) / 64;
  const int t = threadIdx.x;
  for (int64_t w = t; w < nwords; w += kReduceThreads) removed[w] = 0;
  auto prefetch = [&](int64_t b) {  // the diagonal words of block b's rows
    if (b < nwords && t < 64 && b * 64 + t < n)
      gpu::cp_async8(&diag[b % kReduceDepth][t], mask + (b * 64 + t) * stride + b);
    gpu::cp_async_commit();  // a group per block, empty ones too: the wait counts stay uniform
  };
  for (int b = 0; b < kReduceDepth - 1; ++b) prefetch(b);
  int64_t count = 0;  // the same in every thread
  for (int64_t c = 0; c < nwords && count < max_keep; ++c) {
    gpu::cp_async_wait<kReduceDepth - 2>();  // this thread's copy of block c's diagonal has landed
    __syncthreads();  // everyone's has; the previous step's ORs are done and its slot is free
    prefetch(c + kReduceDepth - 1);
    const int64_t base = c * 64;
    const int nb = static_cast<int>(std::min<int64_t>(64, n - base));
    if (t < 32) {  // warp 0: the greedy pass inside block c, each lane holding two rows' diagonal words
      const int lane = t;
      const uint64_t* d = diag[c % kReduceDepth];
      const uint64_t d0 = lane < nb ? d[lane] : 0, d1 = lane + 32 < nb ? d[lane + 32] : 0;
      const uint64_t valid = nb == 64 ? ~0ull : ((1ull << nb) - 1);
      uint64_t word = removed[c], kept = 0;
      uint64_t remaining = ~word & valid;
      while (remaining) {  // warp-uniform: one iteration per kept box of the block
        const int i = __ffsll(static_cast<long long>(remaining)) - 1;
        kept |= 1ull << i;
        word |= __shfl_sync(gpu::kFullMask, i < 32 ? d0 : d1, i & 31);
        remaining = ~word & valid & (i == 63 ? 0ull : (~0ull << (i + 1)));
      }
      for (int64_t q = count + __popcll(kept); q > max_keep; --q) kept &= ~(1ull << (63 - __clzll(kept)));
      for (int p = lane; p < 64; p += 32)
        if ((kept >> p) & 1) keep[count + __popcll(kept & ((1ull << p) - 1))] = order[base + p];
      if (lane == 0) kept_shared = kept;
    }
    __syncthreads();
    const uint64_t kept = kept_shared;
    count += __popcll(kept);
    if (kept == 0 || count >= max_keep) continue;
    uint64_t mine = 0;  // this thread's share of the kept rows: every fourth, from the (t / 64)-th
    int q = 0;
    for (uint64_t bits = kept; bits; bits &= bits - 1, ++q)
      if ((q & 3) == (t >> 6)) mine |= bits & (~bits + 1);
    for (int64_t w = c + 1 + (t & 63); mine != 0 && w < nwords; w += 64) {
      uint64_t acc = 0, bits = mine;
      while (bits) {  // four independent loads in flight per round
        uint64_t v[4] = {0, 0, 0, 0};
#pragma unroll
        for (int u = 0; u < 4; ++u) {
          if (bits) {
            const int r = __ffsll(static_cast<long long>(bits)) - 1;
            bits &= bits - 1;
            v[u] = mask[(base + r) * stride + w];
          }
        }
        acc |= v[0] | v[1] | v[2] | v[3];
      }
      if (acc) atomicOr(reinterpret_cast<unsigned long long*>(&removed[w]), static_cast<unsigned long long>(acc));
    }
  }
  gpu::cp_async_wait<0>();  // no copy may land after the block has gone
  for (int64_t q = count + t; q < max_keep; q += kReduceThreads) keep[q] = -1;
  if (t == 0) *num_kept = count;
}

// key = 0 - score (float32; float64 for float64 scores): its ascending stable sort visits the boxes in
// descending score order, equal scores (-0.0 and 0.0 too) by index, NaN last. With `count`, the number
// of scores >= threshold (never NaN) is added to *count: the candidates are that many first boxes.
template <typename scalar_t, typename key_t>
__global__ void nms_key_kernel(const scalar_t* __restrict__ scores, int64_t N, double threshold,
                               key_t* __restrict__ key, unsigned long long* __restrict__ count) {
  unsigned local = 0;
  for (int64_t i = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; i < N;
       i += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const key_t v = static_cast<key_t>(scores[i]);
    key[i] = key_t(0) - v;
    local += static_cast<double>(v) >= threshold;
  }
  if (count == nullptr) return;
  local = __reduce_add_sync(gpu::kFullMask, local);
  if ((threadIdx.x & 31) == 0 && local) atomicAdd(count, static_cast<unsigned long long>(local));
}

// Up to kBlockSortItems float32-keyed boxes are ordered by one block (key, count and a stable radix sort
// in one launch): torch's sort costs several launches and allocations, the larger part of a small
// NMS call's host time.
constexpr int kBlockSortThreads = 256, kBlockSortPerThread = 16;
constexpr int64_t kBlockSortItems = kBlockSortThreads * kBlockSortPerThread;

// The float key 0 - score as an unsigned radix key whose ascending order is the key's, NaN last.
__device__ __forceinline__ uint32_t radix_key(float v) {
  const float k = 0.0f - v;  // -0.0 and 0.0 both become 0.0
  if (k != k) return 0xffffffffu;
  const uint32_t u = __float_as_uint(k);
  return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

template <typename scalar_t>
__global__ void __launch_bounds__(kBlockSortThreads)
    nms_block_order_kernel(const scalar_t* __restrict__ scores, int64_t N, double threshold,
                           int64_t* __restrict__ order, int64_t* __restrict__ count) {
  using Sort = cub::BlockRadixSort<uint32_t, kBlockSortThreads, kBlockSortPerThread, int32_t>;
  scores += blockIdx.x * N;  // batched: a block per frame of N scores
  order += blockIdx.x * N;
  if (count != nullptr) count += blockIdx.x;
  __shared__ typename Sort::TempStorage temp;
  __shared__ unsigned warp_counts[kBlockSortThreads / 32];
  uint32_t keys[kBlockSortPerThread];
  int32_t vals[kBlockSortPerThread];
  unsigned local = 0;
#pragma unroll
  for (int j = 0; j < kBlockSortPerThread; ++j) {  // blocked: thread t holds items t * 16 + j, in index order
    const int32_t i = threadIdx.x * kBlockSortPerThread + j;
    const float v = i < N ? static_cast<float>(scores[i]) : NAN;
    keys[j] = radix_key(v);  // padding sorts after every box, NaN boxes included (the sort is stable)
    vals[j] = i;
    local += i < N && static_cast<double>(v) >= threshold;
  }
  if (count != nullptr) {
    local = __reduce_add_sync(gpu::kFullMask, local);
    if ((threadIdx.x & 31) == 0) warp_counts[threadIdx.x >> 5] = local;
  }
  Sort(temp).Sort(keys, vals);
#pragma unroll
  for (int j = 0; j < kBlockSortPerThread; ++j) {
    const int64_t p = threadIdx.x * kBlockSortPerThread + j;
    if (p < N) order[p] = vals[j];
  }
  if (count != nullptr && threadIdx.x == 0) {  // the sort's barriers ordered the warp counts' writes
    unsigned total = 0;
    for (int w = 0; w < kBlockSortThreads / 32; ++w) total += warp_counts[w];
    *count = total;
  }
}

// The visiting order of the boxes: (N,) int64; with `count` (int64), the candidates counted in it.
at::Tensor nms_order(const at::Tensor& scores, double threshold, const at::Tensor& count, cudaStream_t stream) {
  const int64_t N = scores.size(0);
  if (N <= kBlockSortItems && scores.scalar_type() != at::kDouble) {
    auto s = scores.contiguous();
    auto order = at::empty({N}, s.options().dtype(at::kLong));
    if (N == 0) return order;
    AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, s.scalar_type(), "lidarops_nms_block_order_cuda", [&] {
      nms_block_order_kernel<scalar_t><<<1, kBlockSortThreads, 0, stream>>>(
          s.data_ptr<scalar_t>(), N, threshold, order.data_ptr<int64_t>(),
          count.defined() ? count.data_ptr<int64_t>() : nullptr);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
    return order;
  }
  if (count.defined()) count.zero_();
  auto key = at::empty({N}, scores.options().dtype(scores.scalar_type() == at::kDouble ? at::kDouble : at::kFloat));
  auto s = scores.contiguous();
  auto* cnt = count.defined() ? reinterpret_cast<unsigned long long*>(count.data_ptr<int64_t>()) : nullptr;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, s.scalar_type(), "lidarops_nms_key_cuda", [&] {
    if (key.scalar_type() == at::kDouble)
      nms_key_kernel<scalar_t, double><<<gpu::stride_blocks(N, 256, 1024), 256, 0, stream>>>(
          s.data_ptr<scalar_t>(), N, threshold, key.data_ptr<double>(), cnt);
    else
      nms_key_kernel<scalar_t, float><<<gpu::stride_blocks(N, 256, 1024), 256, 0, stream>>>(
          s.data_ptr<scalar_t>(), N, threshold, key.data_ptr<float>(), cnt);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return std::get<1>(key.sort(/*stable=*/true, /*dim=*/0, /*descending=*/false));
}

// NMS of the first n boxes of `order` (the first min(n, *n_valid) with n_valid): keep (max_keep,) gets
// the kept indices then -1, num_kept (int64) their number.
void nms_launch(const at::Tensor& boxes, const at::Tensor& order, const c10::optional<at::Tensor>& idxs, int64_t n,
                const int64_t* n_valid, double iou_threshold, const at::Tensor& keep, const at::Tensor& num_kept,
                cudaStream_t stream) {
  const int64_t nwords = gpu::ceil_div(n, 64);
  TORCH_CHECK_VALUE(n * nwords * 8 <= (int64_t{1} << 31), "nms_bev on CUDA keeps an n x n/64 bitmask; n = ", n,
                    " boxes would need ", n * nwords * 8, " bytes (more than 2 GiB): lower pre_max");
  auto g = geoms_of(boxes, order, stream);
  at::Tensor group;
  if (idxs.has_value() && idxs->defined()) group = idxs->index_select(0, order).contiguous();
  auto mask = at::empty({n * nwords}, boxes.options().dtype(at::kLong));
  const dim3 grid(static_cast<unsigned>(nwords), static_cast<unsigned>(std::min<int64_t>(nwords, 65535)));
  nms_mask_kernel<<<grid, 64, 0, stream>>>(geom_ptr(g), group.defined() ? group.data_ptr<int64_t>() : nullptr, n,
                                           n_valid, nwords, iou_threshold,
                                           reinterpret_cast<uint64_t*>(mask.data_ptr<int64_t>()));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  nms_reduce_kernel<<<1, kReduceThreads, nwords * sizeof(uint64_t), stream>>>(
      reinterpret_cast<const uint64_t*>(mask.data_ptr<int64_t>()), n, n_valid, nwords, order.data_ptr<int64_t>(),
      keep.size(0), keep.data_ptr<int64_t>(), num_kept.data_ptr<int64_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

at::Tensor nms_bev_cuda(const at::Tensor& boxes_in, const at::Tensor& scores, const c10::optional<at::Tensor>& idxs,
                        double iou_threshold, int64_t pre_max, int64_t post_max) {
  boxes::check_nms_args(boxes_in, scores, idxs, iou_threshold);
  const int64_t N = boxes_in.size(0);
  const int64_t n = pre_max >= 0 ? std::min(pre_max, N) : N;
  const int64_t max_keep = post_max >= 0 ? std::min(post_max, n) : n;
  c10::cuda::CUDAGuard guard(boxes_in.device());
  if (max_keep == 0) return at::empty({0}, boxes_in.options().dtype(at::kLong));
  cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  auto order = nms_order(scores, 0.0, at::Tensor(), stream).slice(0, 0, n);
  auto keep = at::empty({max_keep}, order.options());
  auto num_kept = at::empty({}, order.options());
  nms_launch(boxes_in, order, idxs, n, nullptr, iou_threshold, keep, num_kept, stream);
  return keep.slice(0, 0, num_kept.item<int64_t>());
}

// status[1] |= a box value is NaN or infinite, status[2] |= a score is, status[3] |= a finite box value is
// out of the supported values (a negative or huge size, a far centre, a huge heading:
// boxes::box_value_out_of_range), the value checks of nms_bev, read with the number kept in status[0].
// status[1:] start at 0.
template <typename box_t, typename score_t>
__global__ void nms_value_flags_kernel(const box_t* __restrict__ boxes, const score_t* __restrict__ scores,
                                       int64_t N, unsigned long long* __restrict__ status) {
  // compared in their own precision (float16/bfloat16 widen exactly): 1e300 is a finite float64
  using box_acc = std::conditional_t<std::is_same_v<box_t, double>, double, float>;
  using score_acc = std::conditional_t<std::is_same_v<score_t, double>, double, float>;
  bool bad_box = false, bad_score = false, negative = false;
  LIDAROPS_GRID_STRIDE(i, 7 * N) {
    const box_acc v = static_cast<box_acc>(boxes[i]);
    bad_box |= !isfinite(v);
    negative |= boxes::box_value_out_of_range(v, static_cast<int>(i % 7));
  }
  LIDAROPS_GRID_STRIDE(i, N) bad_score |= !isfinite(static_cast<score_acc>(scores[i]));
  bad_box = __any_sync(gpu::kFullMask, bad_box);
  bad_score = __any_sync(gpu::kFullMask, bad_score);
  negative = __any_sync(gpu::kFullMask, negative);
  if ((threadIdx.x & 31) != 0) return;
  if (bad_box) atomicOr(status + 1, 1ull);
  if (bad_score) atomicOr(status + 2, 1ull);
  if (negative) atomicOr(status + 3, 1ull);
}

// nms_bev_padded (kChecked false): (keep (K,), count ()); nms_bev_checked: (keep, status (4,)), status[0]
// the count and status[1:] the value flags of nms_value_flags_kernel.
template <bool kChecked>
std::tuple<at::Tensor, at::Tensor> nms_bev_padded_cuda(const at::Tensor& boxes_in, const at::Tensor& scores,
                                                       const c10::optional<at::Tensor>& idxs, double iou_threshold,
                                                       c10::optional<double> score_threshold, int64_t pre_max,
                                                       int64_t post_max) {
  boxes::check_nms_args(boxes_in, scores, idxs, iou_threshold);
  boxes::check_score_threshold(score_threshold);
  const int64_t N = boxes_in.size(0);
  const int64_t n = pre_max >= 0 ? std::min(pre_max, N) : N;
  const int64_t K = post_max >= 0 ? std::min(post_max, n) : n;
  c10::cuda::CUDAGuard guard(boxes_in.device());
  const auto longs = boxes_in.options().dtype(at::kLong);
  cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  auto status = kChecked ? at::empty({4}, longs) : at::empty({}, longs);
  if (kChecked || K == 0)  // the count is written by the reduction, which does not run when K is 0
    C10_CUDA_CHECK(cudaMemsetAsync(status.data_ptr<int64_t>(), 0, status.numel() * sizeof(int64_t), stream));
  if (kChecked && N > 0) {
    auto b = boxes_in.contiguous();
    auto s = scores.contiguous();
    AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, b.scalar_type(), "lidarops_nms_flags_cuda", [&] {
      using box_t = scalar_t;
      AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, s.scalar_type(), "lidarops_nms_flags_cuda", [&] {
        nms_value_flags_kernel<box_t, scalar_t><<<gpu::stride_blocks(7 * N, 256, 512), 256, 0, stream>>>(
            b.data_ptr<box_t>(), s.data_ptr<scalar_t>(), N,
            reinterpret_cast<unsigned long long*>(status.data_ptr<int64_t>()));
        C10_CUDA_KERNEL_LAUNCH_CHECK();
      });
    });
  }
  if (K == 0) return {at::empty({0}, longs), status};
  // counted on the device and never read back: the candidates are the first min(n, n_valid) of the order
  at::Tensor n_valid;
  if (score_threshold.has_value()) n_valid = at::empty({}, longs);
  auto order = nms_order(scores, score_threshold.value_or(0.0), n_valid, stream).slice(0, 0, n);
  auto keep = at::empty({K}, longs);
  nms_launch(boxes_in, order, idxs, n, n_valid.defined() ? n_valid.data_ptr<int64_t>() : nullptr, iou_threshold, keep,
             kChecked ? status.select(0, 0) : status, stream);
  return {keep, status};
}

// The batched key: key = 0 - score as nms_key_kernel's, frames of N scores; count[frame] += its scores >= threshold.
template <typename scalar_t, typename key_t>
__global__ void nms_batched_key_kernel(const scalar_t* __restrict__ scores, int64_t total, int64_t N, double threshold,
                                       key_t* __restrict__ key, unsigned long long* __restrict__ count) {
  LIDAROPS_GRID_STRIDE(i, total) {
    const key_t v = static_cast<key_t>(scores[i]);
    key[i] = key_t(0) - v;
    if (count != nullptr && static_cast<double>(v) >= threshold) atomicAdd(count + i / N, 1ull);
  }
}

// nms_bev_padded of each frame, the frames sharing every launch: their order from one block-sort launch (a
// block per frame) or one segmented sort, one mask kernel (gridDim.z = frames), one reduction launch (a block
// per frame).
std::tuple<at::Tensor, at::Tensor> nms_bev_padded_batched_cuda(const at::Tensor& boxes_in, const at::Tensor& scores_in,
                                                               double iou_threshold,
                                                               c10::optional<double> score_threshold, int64_t pre_max,
                                                               int64_t post_max) {
  boxes::check_batched_nms_args(boxes_in, scores_in, iou_threshold);
  boxes::check_score_threshold(score_threshold);
  const int64_t B = boxes_in.size(0), N = boxes_in.size(1);
  const boxes::PaddedNmsSizes sizes = boxes::padded_nms_sizes(N, pre_max, post_max);
  const int64_t n = sizes.n, K = sizes.K;
  c10::cuda::CUDAGuard guard(boxes_in.device());
  const auto longs = boxes_in.options().dtype(at::kLong);
  auto count = at::zeros({B}, longs);
  if (K == 0 || B == 0) return {at::empty({B, K}, longs), count};
  TORCH_CHECK_VALUE(B <= 65535, "nms_bev_padded_batched on CUDA takes at most 65,535 frames, got ", B);
  cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  auto s = scores_in.contiguous();
  // counted on the device and never read back: each frame's candidates are the first min(n, n_valid) of its order
  at::Tensor n_valid;
  if (score_threshold.has_value()) n_valid = at::zeros({B}, longs);
  const double threshold = score_threshold.value_or(0.0);
  at::Tensor order;
  if (N <= kBlockSortItems && s.scalar_type() != at::kDouble) {
    order = at::empty({B, N}, longs);
    AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, s.scalar_type(), "lidarops_nms_batched_order_cuda", [&] {
      nms_block_order_kernel<scalar_t><<<static_cast<unsigned>(B), kBlockSortThreads, 0, stream>>>(
          s.data_ptr<scalar_t>(), N, threshold, order.data_ptr<int64_t>(),
          n_valid.defined() ? n_valid.data_ptr<int64_t>() : nullptr);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
  } else {
    auto key = at::empty({B, N}, s.options().dtype(s.scalar_type() == at::kDouble ? at::kDouble : at::kFloat));
    auto* cnt = n_valid.defined() ? reinterpret_cast<unsigned long long*>(n_valid.data_ptr<int64_t>()) : nullptr;
    AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, s.scalar_type(), "lidarops_nms_batched_key_cuda", [&] {
      if (key.scalar_type() == at::kDouble)
        nms_batched_key_kernel<scalar_t, double><<<gpu::stride_blocks(B * N, 256, 1024), 256, 0, stream>>>(
            s.data_ptr<scalar_t>(), B * N, N, threshold, key.data_ptr<double>(), cnt);
      else
        nms_batched_key_kernel<scalar_t, float><<<gpu::stride_blocks(B * N, 256, 1024), 256, 0, stream>>>(
            s.data_ptr<scalar_t>(), B * N, N, threshold, key.data_ptr<float>(), cnt);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
    order = std::get<1>(key.sort(/*stable=*/true, /*dim=*/1, /*descending=*/false));
  }
  order = order.slice(1, 0, n).contiguous();  // (B, n): each frame's first n boxes in visiting order
  const int64_t nwords = gpu::ceil_div(n, 64);
  TORCH_CHECK_VALUE(B * n * nwords * 8 <= (int64_t{1} << 31), "nms_bev_padded_batched on CUDA keeps an n x n/64 "
                    "bitmask per frame; ", B, " frames of n = ", n, " boxes would need ", B * n * nwords * 8,
                    " bytes (more than 2 GiB): lower pre_max");
  auto g = geoms_of(boxes_in.contiguous().view({B * N, 7}), order.view({-1}), stream, n, N);
  auto mask = at::empty({B * n * nwords}, longs);
  const int64_t* nv = n_valid.defined() ? n_valid.data_ptr<int64_t>() : nullptr;
  const dim3 grid(static_cast<unsigned>(nwords), static_cast<unsigned>(std::min<int64_t>(nwords, 65535)),
                  static_cast<unsigned>(B));
  nms_mask_kernel<<<grid, 64, 0, stream>>>(geom_ptr(g), nullptr, n, nv, nwords, iou_threshold,
                                           reinterpret_cast<uint64_t*>(mask.data_ptr<int64_t>()));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  auto keep = at::empty({B, K}, longs);
  nms_reduce_kernel<<<static_cast<unsigned>(B), kReduceThreads, nwords * sizeof(uint64_t), stream>>>(
      reinterpret_cast<const uint64_t*>(mask.data_ptr<int64_t>()), n, nv, nwords, order.data_ptr<int64_t>(), K,
      keep.data_ptr<int64_t>(), count.data_ptr<int64_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {keep, count};
}

constexpr int kPointThreads = 128;

template <typename scalar_t>
__global__ void __launch_bounds__(kPointThreads)
    points_in_boxes_kernel(const scalar_t* __restrict__ points, int64_t P, int64_t C, const BoxGeom* __restrict__ g,
                           int64_t M, int64_t* __restrict__ out) {
  __shared__ BoxGeom tile[kPointThreads];
  const int64_t i = blockIdx.x * static_cast<int64_t>(kPointThreads) + threadIdx.x;
  double x = 0, y = 0, z = 0;
  if (i < P) {
    x = static_cast<double>(points[i * C]);
    y = static_cast<double>(points[i * C + 1]);
    z = static_cast<double>(points[i * C + 2]);
  }
  int64_t found = -1;
  for (int64_t j0 = 0; j0 < M; j0 += kPointThreads) {
    __syncthreads();
    if (j0 + threadIdx.x < M) tile[threadIdx.x] = g[j0 + threadIdx.x];
    __syncthreads();
    if (found >= 0 || i >= P) continue;
    const int nt = static_cast<int>(std::min<int64_t>(kPointThreads, M - j0));
    for (int t = 0; t < nt; ++t)
      if (boxes::point_in_box(x, y, z, tile[t])) {
        found = j0 + t;
        break;
      }
  }
  if (i < P) out[i] = found;
}

at::Tensor points_in_boxes_cuda(const at::Tensor& points_in, const at::Tensor& boxes_in) {
  boxes::check_points_args(points_in, boxes_in);
  c10::cuda::CUDAGuard guard(points_in.device());
  const int64_t P = points_in.size(0), M = boxes_in.size(0);
  auto out = at::full({P}, -1, points_in.options().dtype(at::kLong));
  if (P == 0 || M == 0) return out;
  cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  auto g = geoms_of(boxes_in, at::Tensor(), stream);
  auto points = points_in.contiguous();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, points.scalar_type(), "lidarops_points_in_boxes_cuda", [&] {
    points_in_boxes_kernel<scalar_t><<<static_cast<unsigned>(gpu::ceil_div(P, kPointThreads)), kPointThreads, 0,
                                       stream>>>(points.data_ptr<scalar_t>(), P, points.size(1), geom_ptr(g), M,
                                                 out.data_ptr<int64_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("box_overlap_bev", &box_overlap_bev_cuda);
  m.impl("box_iou_bev", &box_iou_bev_cuda);
  m.impl("box_iou_3d", &box_iou_3d_cuda);
  m.impl("nms_bev", &nms_bev_cuda);
  m.impl("nms_bev_padded", &nms_bev_padded_cuda<false>);
  m.impl("nms_bev_checked", &nms_bev_padded_cuda<true>);
  m.impl("nms_bev_padded_batched", &nms_bev_padded_batched_cuda);
  m.impl("points_in_boxes", &points_in_boxes_cuda);
}

}  // namespace lidarops
