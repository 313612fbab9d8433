// The uniform grid of the kNN / ball-query fast paths, built on the device.
//
// The grid follows grid.h (same cell assignment cell_of(), same bounds slab_gap()/grid_margin(),
// same keys (cz * dims_y + cy) * dims_x + cx), but is built on the device by a counting sort (a
// setup kernel, an atomic count, one flat in-place cumsum and a scatter: no sort, no host
// synchronisation), always has a dense table of the first position of every cell (a row of cells
// costs two loads), and holds the points in cell order next to their index (one 16- or 32-byte
// load per point). The queries are put in cell order by the same counting sort, so that
// neighbouring threads search the same cells. The cell size does not change results: every search
// is exact (see grid.h / neighbors.h), so the cells may be grown to bound the table.
#pragma once

#include <ATen/ATen.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>
#include <limits>
#include <type_traits>
#include <utility>

#include "lidarops/cuda_launch.cuh"
#include "lidarops/neighbors.cuh"

namespace lidarops {
namespace gpu {
// Internal linkage: each .cu file gets its own copy of these kernels and helpers.
namespace {

// ---------------------------------------------------------------------------------------------
// uniform grid on the device
// ---------------------------------------------------------------------------------------------

enum GridMode : int { kGridKnn = 0, kGridBall = 1 };

// Per-cloud grid parameters (written by grid_setup_kernel).
struct alignas(16) DGrid {
  double o[3];    // lower corner of the bounding box of the valid points (0 for an empty cloud)
  double h;       // cell edge
  int64_t n;      // valid points: lengths[b] clamped to [0, N]
  int64_t total;  // number of cells, dims[0] * dims[1] * dims[2] <= cap
  int32_t dims[3];
  int32_t pad;
};
static_assert(sizeof(DGrid) == 64, "DGrid layout");

struct DeviceGrid {
  at::Tensor params;  // (B * 64,) uint8: one DGrid per cloud
  at::Tensor table;   // (2, B, cap + 1) int32, scanned flat: row[c] - row[0] = first position of cell c
                      // in recs ([0]) or in qorder ([1])
  at::Tensor recs;    // (B, N, 4) T: valid points in cell order: x, y, z, and the point index's bits
  at::Tensor qorder;  // (B, M) int32: query indices, valid ones in cell order, then the invalid ones
  int64_t cap;
};

// Points in cell order are stored as 4 values of T: x, y, z and the bits of the original index.
template <typename T>
__device__ __forceinline__ void load_rec(const T* recs, int64_t t, T& x, T& y, T& z, int& j);

template <>
__device__ __forceinline__ void load_rec<float>(const float* recs, int64_t t, float& x, float& y, float& z, int& j) {
  const float4 v = __ldg(reinterpret_cast<const float4*>(recs) + t);
  x = v.x;
  y = v.y;
  z = v.z;
  j = __float_as_int(v.w);
}

template <>
__device__ __forceinline__ void load_rec<double>(const double* recs, int64_t t, double& x, double& y, double& z,
                                                 int& j) {
  const double2 a = __ldg(reinterpret_cast<const double2*>(recs) + 2 * t);
  const double2 c = __ldg(reinterpret_cast<const double2*>(recs) + 2 * t + 1);
  x = a.x;
  y = a.y;
  z = c.x;
  j = static_cast<int>(__double_as_longlong(c.y));
}

template <typename T>
__device__ __forceinline__ T index_bits(int j);
template <>
__device__ __forceinline__ float index_bits<float>(int j) {
  return __int_as_float(j);
}
template <>
__device__ __forceinline__ double index_bits<double>(int j) {
  return __longlong_as_double(static_cast<long long>(j));
}

__device__ __forceinline__ int64_t cell_key(const DGrid& g, double x, double y, double z) {
  const int64_t cx = cell_of(x, g.o[0], g.h, g.dims[0]);
  const int64_t cy = cell_of(y, g.o[1], g.h, g.dims[1]);
  const int64_t cz = cell_of(z, g.o[2], g.h, g.dims[2]);
  return (cz * g.dims[1] + cy) * g.dims[0] + cx;
}

// One block per cloud: bounding box (min/max are exact in T), cell size, dims. The cell size
// follows the CPU builder (csrc/cpu/grid_cpu.cpp), then grows until the grid has at most `cap`
// cells, so that every cloud has a dense cell table. Non-finite boxes get a single cell, which is
// exact too (every point is then visited).
constexpr int kSetupThreads = 1024;

template <typename T>
__global__ void __launch_bounds__(kSetupThreads) grid_setup_kernel(const T* __restrict__ pts,
                                                                   const int64_t* __restrict__ lengths,
                                                                   int64_t N, int mode, int64_t k, double radius,
                                                                   int64_t cap, DGrid* __restrict__ grids) {
  __shared__ T red[kSetupThreads / 32][6];
  const int64_t b = blockIdx.x;
  const int64_t n = clamp_len(lengths[b], N);
  T v[6];  // lo x, y, z, then -hi x, y, z
#pragma unroll
  for (int a = 0; a < 6; ++a) v[a] = inf_value<T>();
  const T* cloud = pts + b * N * 3;
  for (int64_t i = threadIdx.x; i < n; i += blockDim.x) {
#pragma unroll
    for (int a = 0; a < 3; ++a) {
      const T c = cloud[3 * i + a];
      v[a] = v[a] < c ? v[a] : c;  // NaN coordinates are skipped (rejected upstream anyway)
      v[a + 3] = v[a + 3] < -c ? v[a + 3] : -c;
    }
  }
#pragma unroll
  for (int a = 0; a < 6; ++a)
    for (int off = 16; off > 0; off >>= 1) {
      const T o = __shfl_xor_sync(kFullMask, v[a], off);
      v[a] = v[a] < o ? v[a] : o;
    }
  const int warp = threadIdx.x >> 5, lane = threadIdx.x & 31;
  if (lane == 0)
#pragma unroll
    for (int a = 0; a < 6; ++a) red[warp][a] = v[a];
  __syncthreads();
  if (threadIdx.x != 0) return;
  for (int w = 1; w < static_cast<int>(blockDim.x >> 5); ++w)
#pragma unroll
    for (int a = 0; a < 6; ++a) v[a] = v[a] < red[w][a] ? v[a] : red[w][a];
  constexpr double kMaxCells = 1048576.0;  // 2^20 per axis, as the CPU builder
  double lo[3], ext[3], emax = 0.0;
  bool finite = true;
  for (int a = 0; a < 3; ++a) {
    lo[a] = n > 0 ? static_cast<double>(v[a]) : 0.0;
    const double hi = n > 0 ? -static_cast<double>(v[a + 3]) : 0.0;
    ext[a] = hi - lo[a];
    finite = finite && isfinite(lo[a]) && isfinite(hi) && isfinite(ext[a]);
    emax = fmax(emax, ext[a]);
  }
  double cell;
  if (mode == kGridKnn) {
    // as the CPU kNN grid: about k/2 points per cell at the mean density of the (floored) box.
    const double fl = emax * 1e-2 + 1e-6;
    const double vol = fmax(ext[0], fl) * fmax(ext[1], fl) * fmax(ext[2], fl);
    const double kk = static_cast<double>(k > 2 ? k : 2);
    cell = cbrt(vol * (kk * 0.5) / static_cast<double>(n > 1 ? n : 1));
  } else {
    cell = radius;
  }
  cell = fmax(fmax(cell, emax / (kMaxCells - 1.0)), 1e-9);
  int64_t dims[3] = {1, 1, 1};
  int64_t total = 1;
  if (finite && isfinite(cell)) {
    for (int it = 0; it < 200; ++it) {
      for (int a = 0; a < 3; ++a)
        dims[a] = static_cast<int64_t>(fmin(fmax(floor(ext[a] / cell) + 1.0, 1.0), kMaxCells));
      total = dims[0] * dims[1] * dims[2];
      if (total <= cap) break;
      cell *= fmax(1.01, cbrt(static_cast<double>(total) / static_cast<double>(cap)));
    }
  }
  if (!finite || !isfinite(cell) || total > cap) {
    for (int a = 0; a < 3; ++a) {
      lo[a] = 0.0;
      dims[a] = 1;
    }
    cell = 1.0;
    total = 1;
  }
  DGrid g;
  for (int a = 0; a < 3; ++a) {
    g.o[a] = lo[a];
    g.dims[a] = static_cast<int32_t>(dims[a]);
  }
  g.h = cell;
  g.n = n;
  g.total = total;
  g.pad = 0;
  grids[b] = g;
}

// Counting sort of the points and of the queries by cell, pass 1: each valid entry gets its cell
// key and its rank among the entries of its cell (the atomic's return value), counted in slot
// key + 1 of its table row. Items t < B * N are points, the others queries. The order inside a
// cell depends on scheduling, which no result depends on: every search is exact and ordered by
// (dist2, index) or by index.
template <typename T>
__global__ void grid_count_kernel(const T* __restrict__ pts, const int64_t* __restrict__ plen, int64_t N,
                                  const T* __restrict__ qry, const int64_t* __restrict__ qlen, int64_t M, int64_t B,
                                  const DGrid* __restrict__ grids, int64_t cap, int32_t* __restrict__ table,
                                  int2* __restrict__ key_rank) {
  const int64_t np = B * N, total = np + B * M;
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < total;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const bool is_point = t < np;
    const int64_t u = is_point ? t : t - np, L = is_point ? N : M;
    const int64_t b = u / L, i = u - b * L;
    if (i >= clamp_len(is_point ? plen[b] : qlen[b], L)) continue;
    const T* p = (is_point ? pts : qry) + 3 * u;
    // The same doubles as the CPU builder's static_cast<double>(p) and the searches' static_cast<double>(q).
    const int64_t key = cell_key(grids[b], static_cast<double>(p[0]), static_cast<double>(p[1]),
                                 static_cast<double>(p[2]));  // in [0, total) with total <= cap
    int32_t* row = table + ((is_point ? 0 : B) + b) * (cap + 1);
    key_rank[t] = make_int2(static_cast<int>(key), atomicAdd(row + key + 1, 1));
  }
}

// Pass 2, after an inclusive scan of the whole table as one flat array: each row starts with a
// zero count, so row[0] is the sum of the rows before it, and row[c] - row[0] = entries of cells
// < c = first position of cell c. Points go to recs, query indices to qorder; an invalid query m
// (m >= nq) goes to position m, which the nq valid ones leave free.
template <typename T>
__global__ void grid_scatter_kernel(const T* __restrict__ pts, const int64_t* __restrict__ plen, int64_t N,
                                    const int64_t* __restrict__ qlen, int64_t M, int64_t B, int64_t cap,
                                    const int32_t* __restrict__ table, const int2* __restrict__ key_rank,
                                    T* __restrict__ recs, int32_t* __restrict__ qorder) {
  const int64_t np = B * N, total = np + B * M;
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < total;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    if (t < np) {
      const int64_t b = t / N, i = t - b * N;
      if (i >= clamp_len(plen[b], N)) continue;
      const int2 kr = key_rank[t];
      const int32_t* row = table + b * (cap + 1);
      const int64_t pos = row[kr.x] - row[0] + kr.y;
      const T* p = pts + 3 * t;
      T* r = recs + 4 * (b * N + pos);
      r[0] = p[0];
      r[1] = p[1];
      r[2] = p[2];
      r[3] = index_bits<T>(static_cast<int>(i));
    } else {
      const int64_t u = t - np, b = u / M, m = u - b * M;
      int64_t pos = m;
      if (m < clamp_len(qlen[b], M)) {
        const int2 kr = key_rank[t];
        const int32_t* row = table + (B + b) * (cap + 1);
        pos = row[kr.x] - row[0] + kr.y;
      }
      qorder[b * M + pos] = static_cast<int32_t>(m);
    }
  }
}

// Builds the grid of the points (B, N, 3) and the cell order of the queries (B, M, 3), both of
// compute type T (float or double, contiguous). No host synchronisation.
template <typename T>
DeviceGrid build_device_grid(const at::Tensor& pts, const at::Tensor& plen, const at::Tensor& qry,
                             const at::Tensor& qlen, int mode, int64_t k, double radius, cudaStream_t stream) {
  const int64_t B = pts.size(0), N = pts.size(1), M = qry.size(1);
  TORCH_CHECK(B * (N + M) < std::numeric_limits<int32_t>::max(), "grid: at most 2^31 - 1 points and queries in a "
              "batch, got B = ", B, ", N = ", N, ", M = ", M);
  DeviceGrid g;
  // Cells per cloud: kNN grids have about 2 n / k cells (at most ~1.2 n for k >= 2, flat and line
  // clouds included); ball grids have cells of edge radius, grown when a sparse cloud would need
  // more. The table costs 8 bytes per cell and cloud.
  g.cap = (mode == kGridKnn ? 2 : 4) * N + 1024;
  g.params = at::empty({B * static_cast<int64_t>(sizeof(DGrid))}, pts.options().dtype(at::kByte));
  auto* grids = reinterpret_cast<DGrid*>(g.params.data_ptr());
  grid_setup_kernel<T><<<static_cast<unsigned>(B), kSetupThreads, 0, stream>>>(
      pts.data_ptr<T>(), plen.data_ptr<int64_t>(), N, mode, k, radius, g.cap, grids);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  g.table = at::zeros({2, B, g.cap + 1}, pts.options().dtype(at::kInt));
  auto key_rank = at::empty({B * (N + M), 2}, pts.options().dtype(at::kInt));
  const int64_t items = B * (N + M);
  grid_count_kernel<T><<<stride_blocks(items, 256, 1 << 20), 256, 0, stream>>>(
      pts.data_ptr<T>(), plen.data_ptr<int64_t>(), N, qry.data_ptr<T>(), qlen.data_ptr<int64_t>(), M, B, grids,
      g.cap, g.table.data_ptr<int32_t>(), reinterpret_cast<int2*>(key_rank.data_ptr<int32_t>()));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  // One flat scan (a single-pass device scan; a scan along the rows would be a slow per-row loop).
  // The sum of all counts is at most B * (N + M) < 2^31 (checked by the callers).
  g.table.view({-1}).cumsum_(0);
  g.recs = at::empty({B, N, 4}, pts.options());
  g.qorder = at::empty({B, M}, pts.options().dtype(at::kInt));
  grid_scatter_kernel<T><<<stride_blocks(items, 256, 1 << 20), 256, 0, stream>>>(
      pts.data_ptr<T>(), plen.data_ptr<int64_t>(), N, qlen.data_ptr<int64_t>(), M, B, g.cap,
      g.table.data_ptr<int32_t>(), reinterpret_cast<const int2*>(key_rank.data_ptr<int32_t>()), g.recs.data_ptr<T>(),
      g.qorder.data_ptr<int32_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return g;
}

// Pointers of one cloud's grid for the search routines.
template <typename T>
struct GridRef {
  DGrid g;
  const int32_t* table;  // scanned table row of the cloud: first position of cell c = table[c] - base
  int32_t base;
  const T* recs;  // points of the cloud in cell order
};

template <typename T>
__device__ __forceinline__ GridRef<T> grid_ref(const DGrid* grids, const int32_t* table, const T* recs, int64_t b,
                                               int64_t N, int64_t cap) {
  GridRef<T> r;
  r.g = grids[b];
  r.table = table + b * (cap + 1);
  r.base = r.table[0];
  r.recs = recs + b * N * 4;
  return r;
}

// Visits the points of cells [x0, x1] of row (cz, cy): f(x, y, z, index); with a group of S
// threads, thread `lane` (< S) visits every S-th point from its lane.
template <typename T, typename F, int S = 1>
__device__ __forceinline__ void grid_row(const GridRef<T>& G, int64_t cz, int64_t cy, int64_t x0, int64_t x1, F& f,
                                         int lane = 0) {
  const int64_t row = (cz * G.g.dims[1] + cy) * G.g.dims[0];
  // row + x1 + 1 <= total <= cap; both ends carry the same row base.
  const int64_t s = G.table[row + x0] - G.base, e = G.table[row + x1 + 1] - G.base;
  for (int64_t t = s + lane; t < e; t += S) {
    T x, y, z;
    int j;
    load_rec<T>(G.recs, t, x, y, z, j);
    f(x, y, z, j);
  }
}

// Smallest v over the S lanes of the calling thread's group (S a power of two <= 32, groups aligned
// in the warp, `mask` the group's lanes; every lane of the group calls it).
template <int S, typename T>
__device__ __forceinline__ T group_min(T v, unsigned mask) {
#pragma unroll
  for (int off = S >> 1; off > 0; off >>= 1) {
    const T o = __shfl_xor_sync(mask, v, off);
    v = o < v ? o : v;
  }
  return v;
}

// Exact kNN of one query: the ring search of knn_grid_search() (neighbors.h), line for line, on
// the device grid. Same bounds, same stopping rule, so the list ends with the exact C smallest.
//
// S > 1: a group of S threads (lanes `lane` of group mask `mask`) searches for one query; each
// visits every S-th point of each row into its own list, and the rows and the stopping rule use
// the smallest of the S lists' worst entries, so the lanes stay in step. That bound is valid: the
// union of the lists holds at least C points at or below any one list's worst, so the exact C-th
// of the query is at or below it. Every point among the query's C nearest is then in its lane's
// list (a lane keeps the C smallest of the points it visited), and merging the S lists (the
// caller) gives the exact answer.
template <typename T, typename List, int S = 1>
__device__ void knn_grid_search_dev(const GridRef<T>& G, T qx, T qy, T qz, List& list, int lane = 0,
                                    unsigned mask = 0xffffffffu) {
  const DGrid& g = G.g;
  const double* o = g.o;
  const double h = g.h;
  const int64_t dims[3] = {g.dims[0], g.dims[1], g.dims[2]};
  const double q[3] = {static_cast<double>(qx), static_cast<double>(qy), static_cast<double>(qz)};
  const double slack = 1.0 - bound_slack<T>();
  int64_t c0[3];
  for (int a = 0; a < 3; ++a) c0[a] = cell_of(q[a], o[a], h, dims[a]);
  // S > 1: a point farther than the group's bound (as of the row's start; bounds only fall) is
  // not among the C nearest, so it is not pushed (a lane's own list may not be full yet).
  T bound = inf_value<T>();
  auto visit = [&](T x, T y, T z, int j) {
    const T d = sqdist3<T>(x, y, z, qx, qy, qz);
    if (S == 1 || !(d > bound)) list.push(d, j);
  };
  for (int64_t r = 0;; ++r) {
    int64_t lo[3], hi[3];
    ring_block(c0, r, dims, lo, hi);
    for (int64_t cz = lo[2]; cz <= hi[2]; ++cz) {
      const bool zs = cz == c0[2] - r || cz == c0[2] + r;
      const double gz = slab_gap(q[2], o[2], h, cz, dims[2]);
      for (int64_t cy = lo[1]; cy <= hi[1]; ++cy) {
        const bool ys = cy == c0[1] - r || cy == c0[1] + r;
        const double gy = slab_gap(q[1], o[1], h, cy, dims[1]);
        bound = group_min<S>(list.worst(), mask);
        const double kth = static_cast<double>(bound);
        const double rest = kth / slack - (gz * gz + gy * gy);
        if (rest < 0.0) continue;  // every point of this row is farther than the k-th
        int64_t x0 = lo[0], x1 = hi[0];
        clip_row_to_reach(rest, q[0], o[0], h, dims[0], x0, x1);
        if (zs || ys) {
          if (x0 <= x1) grid_row<T, decltype(visit), S>(G, cz, cy, x0, x1, visit, lane);
        } else {
          const int64_t xl = c0[0] - r, xh = c0[0] + r;
          if (xl >= x0 && xl <= x1) grid_row<T, decltype(visit), S>(G, cz, cy, xl, xl, visit, lane);
          if (r > 0 && xh >= x0 && xh <= x1) grid_row<T, decltype(visit), S>(G, cz, cy, xh, xh, visit, lane);
        }
      }
    }
    bool outside;
    const double lb = outside_block_gap(q, o, h, dims, lo, hi, outside);
    if (!outside) return;
    if (static_cast<double>(group_min<S>(list.worst(), mask)) < lb * lb * slack) return;
  }
}

// Ball query of one query: every cell that can hold a point within the radius, as
// ball_grid_search() (neighbors.h).
template <typename T, typename List>
__device__ void ball_grid_search_dev(const GridRef<T>& G, T qx, T qy, T qz, T r2, double radius, List& list) {
  const DGrid& g = G.g;
  const double* o = g.o;
  const double h = g.h;
  const int64_t dims[3] = {g.dims[0], g.dims[1], g.dims[2]};
  const double q[3] = {static_cast<double>(qx), static_cast<double>(qy), static_cast<double>(qz)};
  int64_t lo[3], hi[3];
  for (int a = 0; a < 3; ++a) {
    const double reach = radius * (1.0 + 1e-6) + grid_margin(o[a], h, dims[a], q[a]);
    lo[a] = cell_of(q[a] - reach, o[a], h, dims[a]);
    hi[a] = cell_of(q[a] + reach, o[a], h, dims[a]);
  }
  auto visit = [&](T x, T y, T z, int j) {
    const T d = sqdist3<T>(x, y, z, qx, qy, qz);
    if (d < r2) list.push(d, j);
  };
  for (int64_t cz = lo[2]; cz <= hi[2]; ++cz)
    for (int64_t cy = lo[1]; cy <= hi[1]; ++cy) grid_row(G, cz, cy, lo[0], hi[0], visit);
}

}  // namespace
}  // namespace gpu
}  // namespace lidarops
