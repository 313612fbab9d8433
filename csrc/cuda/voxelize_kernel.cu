// Voxelization on CUDA: the same numbering as the CPU kernel (first-seen voxel order, input order
// within a voxel), deterministic, and without any host synchronisation (the outputs of
// voxelize_assign are padded to max_voxels; the wrapper reads the voxel count once, afterwards).
//
// voxelize_assign:
//   1. keys: the voxel key of every point; points outside the grid get the largest key (INT64_MAX, or with
//      32-bit keys the number of cells) so they sort last.
//   2. a stable sort of the keys: each voxel becomes a segment of its points in input order,
//      so a point's slot is its position minus the segment start, and the segment head is the
//      voxel's first point. Where the grid's cells and the points fit 32 bits (every LiDAR grid), cub's
//      radix sort of 32-bit keys over their significant bits only (a KITTI pillar grid: 18 bits, three
//      passes, against eight for ATen's sort of 64-bit keys), with 32-bit point numbers; else ATen's.
//   3. heads: flag the segment heads (in sorted order) and the first points (in input order).
//      Inclusive scans (ATen cumsum) number the segments and, over the first points in input order,
//      give each voxel its first-seen number.
//   4. starts: per segment, its start and its voxel number.
//   5. points: per sorted position, the point's voxel and slot; at each segment's last position the
//      voxel's coords and num_points, and the stats, reduced per warp then added with integer atomics
//      (order-independent, so deterministic).
// voxelize_scatter: one thread per (point, channel) copies a feature into its (voxel, slot).
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAStream.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>

#include <algorithm>

#include <cub/device/device_radix_sort.cuh>

#include "lidarops/cuda_launch.cuh"
#include "lidarops/voxelize.h"

namespace lidarops {
namespace {

constexpr int kThreads = 256;
constexpr int64_t kSortLast = std::numeric_limits<int64_t>::max();

inline unsigned int num_blocks(int64_t n) { return gpu::stride_blocks(n, kThreads); }

// Key: int64_t (out-of-grid points INT64_MAX) or uint32_t (out-of-grid points `last`, one past the cells);
// Idx: the type of the point numbers the sort carries (int64_t or int32_t).
template <typename scalar_t, typename Key, typename Idx>
__global__ void voxel_keys_kernel(const scalar_t* __restrict__ points, int64_t N, int64_t C,
                                  VoxelGrid<acc_t<scalar_t>> g, Key last, Key* __restrict__ keys,
                                  Idx* __restrict__ rows) {
  using T = acc_t<scalar_t>;
  LIDAROPS_GRID_STRIDE(i, N) {
    const scalar_t* q = points + i * C;
    const int64_t k = voxel_key(g, static_cast<T>(q[0]), static_cast<T>(q[1]), static_cast<T>(q[2]));
    keys[i] = k == kNoVoxel ? last : static_cast<Key>(k);
    if (rows) rows[i] = static_cast<Idx>(i);
  }
}

template <typename Key, typename Idx>
__global__ void voxel_heads_kernel(const Key* __restrict__ skeys, const Idx* __restrict__ order, int64_t N, Key last,
                                   int64_t* __restrict__ head, int64_t* __restrict__ first_point) {
  LIDAROPS_GRID_STRIDE(j, N) {
    const Key k = skeys[j];
    const int64_t h = (k != last && (j == 0 || skeys[j - 1] != k)) ? 1 : 0;
    head[j] = h;
    first_point[order[j]] = h;  // order is a permutation: every point is written once
  }
}

template <typename Idx>
__global__ void voxel_starts_kernel(const int64_t* __restrict__ head, const int64_t* __restrict__ head_scan,
                                    const Idx* __restrict__ order, const int64_t* __restrict__ first_scan,
                                    int64_t N, int64_t* __restrict__ seg_start, int64_t* __restrict__ seg_voxel) {
  LIDAROPS_GRID_STRIDE(j, N) {
    if (head[j]) {
      const int64_t seg = head_scan[j] - 1;
      seg_start[seg] = j;
      seg_voxel[seg] = first_scan[order[j]] - 1;  // voxels whose first point comes earlier
    }
  }
}

__device__ __forceinline__ int64_t warp_sum(int64_t v) {
  for (int off = 16; off > 0; off >>= 1) v += __shfl_down_sync(0xffffffffu, v, off);
  return v;
}

__device__ __forceinline__ int64_t warp_max(int64_t v) {
  for (int off = 16; off > 0; off >>= 1) {
    const int64_t o = __shfl_down_sync(0xffffffffu, v, off);
    v = o > v ? o : v;
  }
  return v;
}

template <typename Key, typename Idx>
__global__ void voxel_points_kernel(const Key* __restrict__ skeys, const Idx* __restrict__ order, Key last,
                                    const int64_t* __restrict__ head_scan, const int64_t* __restrict__ seg_start,
                                    const int64_t* __restrict__ seg_voxel, int64_t N, int64_t P, int64_t max_voxels,
                                    int64_t dim_x, int64_t dim_y, int64_t dim_z, int64_t* __restrict__ point_voxel,
                                    int64_t* __restrict__ point_slot, int32_t* __restrict__ coords,
                                    int32_t* __restrict__ num_points, int64_t* __restrict__ stats) {
  const int64_t dims[3] = {dim_x, dim_y, dim_z};
  // per-thread partial stats (see VoxelStat)
  int64_t kept = 0, needed = 0, in_grid = 0, dropped_voxels = 0, dropped_points = 0, fullest = 0, overfull = 0;
  LIDAROPS_GRID_STRIDE(j, N) {
    const int64_t i = order[j];
    const Key k = skeys[j];
    if (k == last) {
      point_voxel[i] = -1;
      point_slot[i] = -1;
      continue;
    }
    const int64_t seg = head_scan[j] - 1;
    const int64_t u = seg_voxel[seg];
    const int64_t s = j - seg_start[seg];
    const bool is_kept = u < max_voxels;
    point_voxel[i] = is_kept ? u : -1;
    point_slot[i] = is_kept && s < P ? s : -1;
    if (j + 1 < N && skeys[j + 1] == k) continue;  // not the last point of its voxel
    const int64_t len = s + 1;
    ++needed;
    in_grid += len;
    fullest = len > fullest ? len : fullest;
    if (is_kept) {
      ++kept;
      int32_t zyx[3];
      voxel_key_to_zyx(static_cast<int64_t>(k), dims, zyx);
      coords[3 * u] = zyx[0];
      coords[3 * u + 1] = zyx[1];
      coords[3 * u + 2] = zyx[2];
      num_points[u] = static_cast<int32_t>(len < P ? len : P);
      if (len > P) {
        dropped_points += len - P;
        ++overfull;
      }
    } else {
      dropped_voxels += len;
    }
  }
  // Every thread of every (full) warp reaches this point: blockDim is a multiple of 32.
  kept = warp_sum(kept);
  needed = warp_sum(needed);
  in_grid = warp_sum(in_grid);
  dropped_voxels = warp_sum(dropped_voxels);
  dropped_points = warp_sum(dropped_points);
  fullest = warp_max(fullest);
  overfull = warp_sum(overfull);
  if ((threadIdx.x & 31) == 0 && needed > 0) {
    auto add = [&](int s, int64_t v) {
      if (v) atomicAdd(reinterpret_cast<unsigned long long*>(stats + s), static_cast<unsigned long long>(v));
    };
    add(kStatVoxels, kept);
    add(kStatVoxelsNeeded, needed);
    add(kStatPointsInGrid, in_grid);
    add(kStatDroppedMaxVoxels, dropped_voxels);
    add(kStatDroppedMaxPoints, dropped_points);
    atomicMax(reinterpret_cast<long long*>(stats + kStatMaxPointsInVoxel), static_cast<long long>(fullest));
    add(kStatOverfullVoxels, overfull);
  }
}

// Steps 3-5 on the sorted keys and their point numbers.
template <typename Key, typename Idx>
void assign_sorted(const Key* skeys, const Idx* order, Key last, int64_t N, int64_t P, int64_t max_voxels,
                   at::IntArrayRef grid_size, at::Tensor& point_voxel, at::Tensor& point_slot, at::Tensor& coords,
                   at::Tensor& num_points, at::Tensor& stats, cudaStream_t stream) {
  const auto i64 = point_voxel.options();
  auto head = at::empty({N}, i64);
  auto first_point = at::empty({N}, i64);
  voxel_heads_kernel<Key, Idx><<<num_blocks(N), kThreads, 0, stream>>>(skeys, order, N, last, head.data_ptr<int64_t>(),
                                                                      first_point.data_ptr<int64_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  auto head_scan = at::cumsum(head, 0);
  auto first_scan = at::cumsum(first_point, 0);
  auto seg_start = at::empty({N}, i64);  // segments <= N; only the first (voxels needed) are written
  auto seg_voxel = at::empty({N}, i64);
  voxel_starts_kernel<Idx><<<num_blocks(N), kThreads, 0, stream>>>(
      head.data_ptr<int64_t>(), head_scan.data_ptr<int64_t>(), order, first_scan.data_ptr<int64_t>(), N,
      seg_start.data_ptr<int64_t>(), seg_voxel.data_ptr<int64_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  voxel_points_kernel<Key, Idx><<<num_blocks(N), kThreads, 0, stream>>>(
      skeys, order, last, head_scan.data_ptr<int64_t>(), seg_start.data_ptr<int64_t>(), seg_voxel.data_ptr<int64_t>(),
      N, P, max_voxels, grid_size[0], grid_size[1], grid_size[2], point_voxel.data_ptr<int64_t>(),
      point_slot.data_ptr<int64_t>(), coords.data_ptr<int32_t>(), num_points.data_ptr<int32_t>(),
      stats.data_ptr<int64_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> voxelize_assign_cuda(
    const at::Tensor& points_in, at::ArrayRef<double> voxel_size, at::ArrayRef<double> point_range,
    at::IntArrayRef grid_size, int64_t max_points_per_voxel, int64_t max_voxels, int64_t method) {
  check_voxelize_assign_args(points_in, voxel_size, point_range, grid_size, max_points_per_voxel, max_voxels,
                             method);
  c10::cuda::CUDAGuard device_guard(points_in.device());
  auto points = points_in.contiguous();
  const int64_t N = points.size(0), C = points.size(1);
  const auto i32 = points.options().dtype(at::kInt), i64 = points.options().dtype(at::kLong);
  auto coords = at::full({max_voxels, 3}, -1, i32);
  auto num_points = at::zeros({max_voxels}, i32);
  auto point_voxel = at::empty({N}, i64);
  auto point_slot = at::empty({N}, i64);
  auto stats = at::zeros({kNumVoxelStats}, i64);
  const int64_t cells = grid_size[0] * grid_size[1] * grid_size[2];  // < 4.6e18: checked
  const bool narrow = cells < INT32_MAX && N < INT32_MAX;
  auto keys = at::empty({narrow ? 2 * N : N}, narrow ? i32 : i64);  // narrow: keys, then the sorted keys
  auto rows = narrow ? at::empty({2 * N}, i32) : at::Tensor();      // narrow: point numbers, then their order
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, points.scalar_type(), "lidarops_voxelize_assign_cuda", [&] {
    using T = acc_t<scalar_t>;
    const VoxelGrid<T> g = make_voxel_grid<T>(voxel_size, point_range, grid_size);
    check_voxel_grid_in_type(g);
    if (N == 0) return;
    if (narrow) {
      voxel_keys_kernel<scalar_t, uint32_t, int32_t><<<num_blocks(N), kThreads, 0, stream>>>(
          points.data_ptr<scalar_t>(), N, C, g, static_cast<uint32_t>(cells),
          reinterpret_cast<uint32_t*>(keys.data_ptr<int32_t>()), rows.data_ptr<int32_t>());
    } else {
      voxel_keys_kernel<scalar_t, int64_t, int64_t><<<num_blocks(N), kThreads, 0, stream>>>(
          points.data_ptr<scalar_t>(), N, C, g, kSortLast, keys.data_ptr<int64_t>(), nullptr);
    }
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  if (N == 0) return {coords, num_points, point_voxel, point_slot, stats};
  const int64_t P = max_points_per_voxel;
  if (narrow) {
    // the sort's bits: those of `cells`, the out-of-grid key (the largest)
    int bits = 1;
    while (bits < 32 && (static_cast<uint64_t>(cells) >> bits) != 0) ++bits;
    auto* k_in = reinterpret_cast<uint32_t*>(keys.data_ptr<int32_t>());
    int32_t* r_in = rows.data_ptr<int32_t>();
    size_t temp_bytes = 0;
    C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(nullptr, temp_bytes, k_in, k_in + N, r_in, r_in + N,
                                                   static_cast<int>(N), 0, bits, stream));
    auto temp = at::empty({static_cast<int64_t>(temp_bytes)}, points.options().dtype(at::kByte));
    C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(temp.data_ptr(), temp_bytes, k_in, k_in + N, r_in, r_in + N,
                                                   static_cast<int>(N), 0, bits, stream));
    assign_sorted<uint32_t, int32_t>(k_in + N, r_in + N, static_cast<uint32_t>(cells), N, P, max_voxels, grid_size,
                                     point_voxel, point_slot, coords, num_points, stats, stream);
  } else {
    auto [skeys, order] = keys.sort(/*stable=*/true, /*dim=*/0, /*descending=*/false);
    skeys = skeys.contiguous();
    order = order.contiguous();
    assign_sorted<int64_t, int64_t>(skeys.data_ptr<int64_t>(), order.data_ptr<int64_t>(), kSortLast, N, P, max_voxels,
                                    grid_size, point_voxel, point_slot, coords, num_points, stats, stream);
  }
  return {coords, num_points, point_voxel, point_slot, stats};
}

template <typename scalar_t>
__global__ void voxel_scatter_kernel(const scalar_t* __restrict__ features, const int64_t* __restrict__ point_voxel,
                                     const int64_t* __restrict__ point_slot, int64_t N, int64_t C, int64_t num_voxels,
                                     int64_t P, scalar_t* __restrict__ out) {
  LIDAROPS_GRID_STRIDE(t, N * C) {
    const int64_t i = t / C, c = t - i * C;
    const int64_t v = point_voxel[i], s = point_slot[i];
    if (v >= 0 && v < num_voxels && s >= 0 && s < P) out[(v * P + s) * C + c] = features[t];
  }
}

at::Tensor voxelize_scatter_cuda(const at::Tensor& features_in, const at::Tensor& point_voxel_in,
                                 const at::Tensor& point_slot_in, int64_t num_voxels, int64_t max_points_per_voxel) {
  check_voxelize_scatter_args(features_in, point_voxel_in, point_slot_in, num_voxels, max_points_per_voxel);
  c10::cuda::CUDAGuard device_guard(features_in.device());
  auto features = features_in.contiguous();
  auto point_voxel = point_voxel_in.contiguous();
  auto point_slot = point_slot_in.contiguous();
  const int64_t N = features.size(0), C = features.size(1), P = max_points_per_voxel;
  auto out = at::zeros({num_voxels, P, C}, features.options());
  if (out.numel() == 0 || N == 0) return out;
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, features.scalar_type(), "lidarops_voxelize_scatter_cuda", [&] {
    voxel_scatter_kernel<scalar_t><<<num_blocks(N * C), kThreads, 0, stream>>>(
        features.data_ptr<scalar_t>(), point_voxel.data_ptr<int64_t>(), point_slot.data_ptr<int64_t>(), N, C,
        num_voxels, P, out.data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("voxelize_assign", &voxelize_assign_cuda);
  m.impl("voxelize_scatter", &voxelize_scatter_cuda);
}

}  // namespace lidarops
