// Helpers shared by the CUDA kernels (csrc/cuda/*.cu): launch helpers, warp shuffles, register-
// resident neighbour lists, and the uniform grid of the kNN / ball-query fast paths built on the
// device.
//
// The grid follows grid.h (same cell assignment cell_of(), same bounds slab_gap()/grid_margin(),
// same keys (cz * dims_y + cy) * dims_x + cx, sorted per cloud), but is built by a few kernels
// instead of ~30 ATen ops, holds the points in cell order next to their index (one 16- or
// 32-byte load per point, no indirection), and, when the cloud has at most `cap` cells, a table of
// the first sorted position of every cell (a row of cells costs two loads instead of two binary
// searches). Clouds with more cells use a binary search on the sorted keys, exactly like the CPU.
// The cell size does not change results: every search is exact (see grid.h / neighbors.h).
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

#include "lidarops/neighbors.h"

namespace lidarops {
namespace gpu {
// Internal linkage: each .cu file gets its own copy of these kernels and helpers.
namespace {

constexpr unsigned kFullMask = 0xffffffffu;
constexpr int64_t kInt64Max = std::numeric_limits<int64_t>::max();

// ---------------------------------------------------------------------------------------------
// host helpers
// ---------------------------------------------------------------------------------------------

struct DeviceInfo {
  int cc_major;
  int sm_count;
};

inline DeviceInfo device_info(c10::DeviceIndex dev) {
  DeviceInfo info{0, 1};
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&info.cc_major, cudaDevAttrComputeCapabilityMajor, dev));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&info.sm_count, cudaDevAttrMultiProcessorCount, dev));
  return info;
}

inline int64_t ceil_div(int64_t a, int64_t b) { return (a + b - 1) / b; }

inline int64_t pow2_ceil(int64_t v) {
  int64_t p = 1;
  while (p < v) p <<= 1;
  return p;
}

inline int64_t pow2_floor(int64_t v) {
  int64_t p = 1;
  while (p * 2 <= v) p <<= 1;
  return p;
}

// Blocks for a grid-stride loop over `total` items.
inline unsigned stride_blocks(int64_t total, int threads, int64_t max_blocks = 65536) {
  const int64_t b = ceil_div(total, threads);
  return static_cast<unsigned>(b < 1 ? 1 : (b > max_blocks ? max_blocks : b));
}

// The computation tensor of a cloud: half/bfloat16 converted to float (exact), float/double as is.
inline at::Tensor compute_tensor(const at::Tensor& t) {
  if (t.scalar_type() == at::kHalf || t.scalar_type() == at::kBFloat16) return t.to(at::kFloat).contiguous();
  return t.contiguous();
}

// Calls f(std::integral_constant<int, C>) with the smallest register capacity C >= k from `Caps`,
// or C = 0 (lists in global memory) when k exceeds them all.
template <int... Caps>
struct CapacityList {};

template <typename F>
void dispatch_capacity_impl(int64_t, F&& f, CapacityList<>) {
  f(std::integral_constant<int, 0>{});
}

template <typename F, int C0, int... Rest>
void dispatch_capacity_impl(int64_t k, F&& f, CapacityList<C0, Rest...>) {
  if (k <= C0) f(std::integral_constant<int, C0>{});
  else dispatch_capacity_impl(k, std::forward<F>(f), CapacityList<Rest...>{});
}

template <int... Caps, typename F>
void dispatch_capacity(int64_t k, F&& f) {
  dispatch_capacity_impl(k, std::forward<F>(f), CapacityList<Caps...>{});
}

// ---------------------------------------------------------------------------------------------
// device helpers
// ---------------------------------------------------------------------------------------------

template <typename T>
__device__ __forceinline__ T inf_value() {
  return std::numeric_limits<T>::infinity();
}

__device__ __forceinline__ int64_t clamp_len(int64_t v, int64_t n) { return v < 0 ? 0 : (v > n ? n : v); }

// k smallest (dist2, index) pairs in registers, ascending by the total order closer(); capacity C
// compile-time so that every access uses a constant index. Padding is (+inf, -1) exactly like
// KnnList, so a point is accepted if and only if KnnList would accept it. A list of capacity C >= k
// holds the C smallest pairs; its first k are the k smallest.
template <typename T, int C>
struct RegKnnList {
  T d[C];
  int i[C];
  __device__ __forceinline__ void init() {
#pragma unroll
    for (int p = 0; p < C; ++p) {
      d[p] = inf_value<T>();
      i[p] = -1;
    }
  }
  __device__ __forceinline__ T worst() const { return d[C - 1]; }
  __device__ __forceinline__ void push(T dd, int64_t jj) {
    const int j = static_cast<int>(jj);
    if (!closer(dd, j, d[C - 1], i[C - 1])) return;
    // Replace the worst entry, then one bubbling pass restores the order (the rest is sorted).
    d[C - 1] = dd;
    i[C - 1] = j;
#pragma unroll
    for (int p = C - 1; p > 0; --p) {
      if (closer(d[p], i[p], d[p - 1], i[p - 1])) {
        const T td = d[p];
        d[p] = d[p - 1];
        d[p - 1] = td;
        const int ti = i[p];
        i[p] = i[p - 1];
        i[p - 1] = ti;
      }
    }
  }
  // Removes the first entry (used by the sub-warp merge).
  __device__ __forceinline__ void pop_front() {
#pragma unroll
    for (int p = 0; p + 1 < C; ++p) {
      d[p] = d[p + 1];
      i[p] = i[p + 1];
    }
    d[C - 1] = inf_value<T>();
    i[C - 1] = -1;
  }
};

// The C lowest indices pushed, ascending, in registers (INT_MAX = empty). Each point is pushed at
// most once, so this keeps the same set as BallList; the distances are recomputed on output with
// the same rounded formula, which gives the same bits.
template <int C>
struct RegBallList {
  int i[C];
  __device__ __forceinline__ void init() {
#pragma unroll
    for (int p = 0; p < C; ++p) i[p] = std::numeric_limits<int>::max();
  }
  template <typename T>
  __device__ __forceinline__ void push(T, int64_t jj) {
    const int j = static_cast<int>(jj);
    if (j >= i[C - 1]) return;
    i[C - 1] = j;
#pragma unroll
    for (int p = C - 1; p > 0; --p) {
      if (i[p] < i[p - 1]) {
        const int t = i[p];
        i[p] = i[p - 1];
        i[p - 1] = t;
      }
    }
  }
};

// ---------------------------------------------------------------------------------------------
// uniform grid on the device
// ---------------------------------------------------------------------------------------------

enum GridMode : int { kGridKnn = 0, kGridBall = 1 };

// Per-cloud grid parameters (written by grid_setup_kernel).
struct alignas(16) DGrid {
  double o[3];    // lower corner of the bounding box of the valid points (0 for an empty cloud)
  double h;       // cell edge
  int64_t n;      // valid points: lengths[b] clamped to [0, N]
  int64_t total;  // number of cells, dims[0] * dims[1] * dims[2]
  int32_t dims[3];
  int32_t table;  // 1: cell table present (total <= cap), 0: binary search on the sorted keys
};
static_assert(sizeof(DGrid) == 64, "DGrid layout");

struct DeviceGrid {
  at::Tensor params;  // (B * 64,) uint8: one DGrid per cloud
  at::Tensor keys;    // (B, N) int64: sorted cell keys; the first n are valid, then INT64_MAX
  at::Tensor table;   // (B, cap + 1) int32: first sorted position of each cell (when table = 1)
  at::Tensor recs;    // (B, N, 4) T: points in cell order: x, y, z, and the point index's bits
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

// One block per cloud: bounding box (in double, exact), cell size, dims. Same formulas as
// knn_cell_size() and build_grid() (grid.cpp); non-finite boxes fall back to a single cell,
// which is exact too (every point is then visited).
constexpr int kSetupThreads = 512;

template <typename T>
__global__ void __launch_bounds__(kSetupThreads) grid_setup_kernel(const T* __restrict__ pts,
                                                                   const int64_t* __restrict__ lengths,
                                                                   int64_t N, int mode, int64_t k, double radius,
                                                                   int64_t cap, DGrid* __restrict__ grids) {
  __shared__ double red[kSetupThreads / 32][6];
  const int64_t b = blockIdx.x;
  const int64_t n = clamp_len(lengths[b], N);
  double v[6];  // lo x, y, z, then -hi x, y, z
#pragma unroll
  for (int a = 0; a < 6; ++a) v[a] = inf_value<double>();
  const T* cloud = pts + b * N * 3;
  for (int64_t i = threadIdx.x; i < n; i += blockDim.x) {
#pragma unroll
    for (int a = 0; a < 3; ++a) {
      const double c = static_cast<double>(cloud[3 * i + a]);
      v[a] = fmin(v[a], c);
      v[a + 3] = fmin(v[a + 3], -c);
    }
  }
#pragma unroll
  for (int a = 0; a < 6; ++a)
    for (int off = 16; off > 0; off >>= 1) v[a] = fmin(v[a], __shfl_xor_sync(kFullMask, v[a], off));
  const int warp = threadIdx.x >> 5, lane = threadIdx.x & 31;
  if (lane == 0)
#pragma unroll
    for (int a = 0; a < 6; ++a) red[warp][a] = v[a];
  __syncthreads();
  if (threadIdx.x != 0) return;
  for (int w = 1; w < static_cast<int>(blockDim.x >> 5); ++w)
#pragma unroll
    for (int a = 0; a < 6; ++a) v[a] = fmin(v[a], red[w][a]);
  constexpr double kMaxCells = 1048576.0;  // 2^20 per axis, as build_grid
  double lo[3], ext[3], emax = 0.0;
  bool finite = true;
  for (int a = 0; a < 3; ++a) {
    lo[a] = n > 0 ? v[a] : 0.0;
    const double hi = n > 0 ? -v[a + 3] : 0.0;
    ext[a] = hi - lo[a];
    finite = finite && isfinite(lo[a]) && isfinite(hi) && isfinite(ext[a]);
    emax = fmax(emax, ext[a]);
  }
  double cell;
  if (mode == kGridKnn) {
    // knn_cell_size(): about k/2 points per cell at the mean density of the (floored) box.
    const double fl = emax * 1e-2 + 1e-6;
    const double vol = fmax(ext[0], fl) * fmax(ext[1], fl) * fmax(ext[2], fl);
    const double kk = static_cast<double>(k > 2 ? k : 2);
    cell = cbrt(vol * (kk * 0.5) / static_cast<double>(n > 1 ? n : 1));
  } else {
    cell = radius;
  }
  cell = fmax(fmax(cell, emax / (kMaxCells - 1.0)), 1e-9);
  DGrid g;
  int64_t dims[3];
  if (!finite || !isfinite(cell)) {
    for (int a = 0; a < 3; ++a) {
      lo[a] = 0.0;
      dims[a] = 1;
    }
    cell = 1.0;
  } else {
    for (int a = 0; a < 3; ++a) dims[a] = static_cast<int64_t>(fmin(fmax(floor(ext[a] / cell) + 1.0, 1.0), kMaxCells));
  }
  for (int a = 0; a < 3; ++a) {
    g.o[a] = lo[a];
    g.dims[a] = static_cast<int32_t>(dims[a]);
  }
  g.h = cell;
  g.n = n;
  g.total = dims[0] * dims[1] * dims[2];
  g.table = g.total <= cap ? 1 : 0;
  grids[b] = g;
}

// Cell keys of the valid entries of a (B, L, 3) cloud in the grid of the points; INT64_MAX after.
template <typename T>
__global__ void grid_keys_kernel(const T* __restrict__ pts, const int64_t* __restrict__ lengths, int64_t B,
                                 int64_t L, const DGrid* __restrict__ grids, int64_t* __restrict__ keys) {
  const int64_t total = B * L;
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < total;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t b = t / L, i = t - b * L;
    if (i >= clamp_len(lengths[b], L)) {
      keys[t] = kInt64Max;
      continue;
    }
    const T* p = pts + 3 * t;
    // Same value as build_grid's points.to(kDouble) and the searches' static_cast<double>(q).
    keys[t] = cell_key(grids[b], static_cast<double>(p[0]), static_cast<double>(p[1]), static_cast<double>(p[2]));
  }
}

// Points in cell order (recs) and, for clouds with at most cap cells, the cell table.
template <typename T>
__global__ void grid_fill_kernel(const T* __restrict__ pts, const int64_t* __restrict__ keys,
                                 const int64_t* __restrict__ order, const DGrid* __restrict__ grids, int64_t B,
                                 int64_t N, int64_t cap, int32_t* __restrict__ table, T* __restrict__ recs) {
  const int64_t n_recs = B * N, n_table = B * (cap + 1);
  const int64_t total = n_recs > n_table ? n_recs : n_table;
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < total;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    if (t < n_recs) {
      const int64_t b = t / N, i = t - b * N;
      if (i < grids[b].n) {
        const int64_t j = order[t];  // in [0, n): the sort moved the INT64_MAX keys behind
        const T* p = pts + (b * N + j) * 3;
        T* r = recs + 4 * t;
        r[0] = p[0];
        r[1] = p[1];
        r[2] = p[2];
        r[3] = index_bits<T>(static_cast<int>(j));
      }
    }
    if (t < n_table) {
      const int64_t b = t / (cap + 1), c = t - b * (cap + 1);
      const DGrid& g = grids[b];
      if (g.table && c <= g.total) table[t] = static_cast<int32_t>(lower_bound_i64(keys + b * N, g.n, c));
    }
  }
}

// Builds the grid of a (B, N, 3) cloud of compute type T (float or double, contiguous).
template <typename T>
DeviceGrid build_device_grid(const at::Tensor& pts, const at::Tensor& lengths, int mode, int64_t k, double radius,
                             cudaStream_t stream) {
  const int64_t B = pts.size(0), N = pts.size(1);
  DeviceGrid g;
  g.cap = 4 * N + 64;
  g.params = at::empty({B * static_cast<int64_t>(sizeof(DGrid))}, pts.options().dtype(at::kByte));
  auto* grids = reinterpret_cast<DGrid*>(g.params.data_ptr());
  grid_setup_kernel<T><<<static_cast<unsigned>(B), kSetupThreads, 0, stream>>>(
      pts.data_ptr<T>(), lengths.data_ptr<int64_t>(), N, mode, k, radius, g.cap, grids);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  auto keys = at::empty({B, N}, pts.options().dtype(at::kLong));
  grid_keys_kernel<T><<<stride_blocks(B * N, 256), 256, 0, stream>>>(pts.data_ptr<T>(), lengths.data_ptr<int64_t>(),
                                                                      B, N, grids, keys.data_ptr<int64_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  auto sorted = keys.sort(/*stable=*/true, /*dim=*/1, /*descending=*/false);
  g.keys = std::get<0>(sorted).contiguous();
  auto order = std::get<1>(sorted).contiguous();
  g.table = at::empty({B, g.cap + 1}, pts.options().dtype(at::kInt));
  g.recs = at::empty({B, N, 4}, pts.options());
  const int64_t work = std::max(B * N, B * (g.cap + 1));
  grid_fill_kernel<T><<<stride_blocks(work, 256), 256, 0, stream>>>(
      pts.data_ptr<T>(), g.keys.data_ptr<int64_t>(), order.data_ptr<int64_t>(), grids, B, N, g.cap,
      g.table.data_ptr<int32_t>(), g.recs.data_ptr<T>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return g;
}

// Order in which to process the queries: sorted by the cell of the point grid they fall in, so
// that neighbouring threads search the same cells (coherent loads, little divergence). Invalid
// queries (m >= query_lengths[b]) come last. Returns (B, M) int64 query indices.
template <typename T>
at::Tensor query_order(const at::Tensor& query, const at::Tensor& qlen, const DeviceGrid& g, cudaStream_t stream) {
  const int64_t B = query.size(0), M = query.size(1);
  auto keys = at::empty({B, M}, query.options().dtype(at::kLong));
  grid_keys_kernel<T><<<stride_blocks(B * M, 256), 256, 0, stream>>>(
      query.data_ptr<T>(), qlen.data_ptr<int64_t>(), B, M, reinterpret_cast<const DGrid*>(g.params.data_ptr()),
      keys.data_ptr<int64_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return std::get<1>(keys.sort(/*stable=*/true, /*dim=*/1, /*descending=*/false)).contiguous();
}

// Pointers of one cloud's grid for the search routines.
template <typename T>
struct GridRef {
  DGrid g;
  const int64_t* keys;   // sorted keys of the cloud
  const int32_t* table;  // cell table of the cloud
  const T* recs;         // points in cell order
};

template <typename T>
__device__ __forceinline__ GridRef<T> grid_ref(const DGrid* grids, const int64_t* keys, const int32_t* table,
                                               const T* recs, int64_t b, int64_t N, int64_t cap) {
  GridRef<T> r;
  r.g = grids[b];
  r.keys = keys + b * N;
  r.table = table + b * (cap + 1);
  r.recs = recs + b * N * 4;
  return r;
}

// Visits the points of cells [x0, x1] of row (cz, cy): f(x, y, z, index).
template <typename T, typename F>
__device__ __forceinline__ void grid_row(const GridRef<T>& G, int64_t cz, int64_t cy, int64_t x0, int64_t x1, F& f) {
  const int64_t row = (cz * G.g.dims[1] + cy) * G.g.dims[0];
  const int64_t k0 = row + x0, k1 = row + x1;  // k1 + 1 <= total: inside the table
  int64_t s, e;
  if (G.g.table) {
    s = G.table[k0];
    e = G.table[k1 + 1];
  } else {
    s = lower_bound_i64(G.keys, G.g.n, k0);
    e = s + lower_bound_i64(G.keys + s, G.g.n - s, k1 + 1);
  }
  for (int64_t t = s; t < e; ++t) {
    T x, y, z;
    int j;
    load_rec<T>(G.recs, t, x, y, z, j);
    f(x, y, z, j);
  }
}

// Exact kNN of one query: the ring search of knn_grid_search() (neighbors.h), line for line, on
// the device grid. Same bounds, same stopping rule, so the list ends with the exact C smallest.
template <typename T, typename List>
__device__ void knn_grid_search_dev(const GridRef<T>& G, T qx, T qy, T qz, List& list) {
  const DGrid& g = G.g;
  const double* o = g.o;
  const double h = g.h;
  const int64_t dims[3] = {g.dims[0], g.dims[1], g.dims[2]};
  const double q[3] = {static_cast<double>(qx), static_cast<double>(qy), static_cast<double>(qz)};
  const double slack = 1.0 - bound_slack<T>();
  int64_t c0[3];
  for (int a = 0; a < 3; ++a) c0[a] = cell_of(q[a], o[a], h, dims[a]);
  auto visit = [&](T x, T y, T z, int j) { list.push(sqdist3<T>(x, y, z, qx, qy, qz), j); };
  for (int64_t r = 0;; ++r) {
    int64_t lo[3], hi[3];
    for (int a = 0; a < 3; ++a) {
      lo[a] = c0[a] - r > 0 ? c0[a] - r : 0;
      hi[a] = c0[a] + r < dims[a] - 1 ? c0[a] + r : dims[a] - 1;
    }
    for (int64_t cz = lo[2]; cz <= hi[2]; ++cz) {
      const bool zs = cz == c0[2] - r || cz == c0[2] + r;
      const double gz = slab_gap(q[2], o[2], h, cz, dims[2]);
      for (int64_t cy = lo[1]; cy <= hi[1]; ++cy) {
        const bool ys = cy == c0[1] - r || cy == c0[1] + r;
        const double gy = slab_gap(q[1], o[1], h, cy, dims[1]);
        const double kth = static_cast<double>(list.worst());
        const double rest = kth / slack - (gz * gz + gy * gy);
        if (rest < 0.0) continue;  // every point of this row is farther than the k-th
        int64_t x0 = lo[0], x1 = hi[0];
        if (rest < 1e300) {  // restrict the row to cells within reach
          const double reach = sqrt(rest) + grid_margin(o[0], h, dims[0], q[0]);
          const int64_t a0 = cell_of(q[0] - reach, o[0], h, dims[0]);
          const int64_t a1 = cell_of(q[0] + reach, o[0], h, dims[0]);
          x0 = x0 > a0 ? x0 : a0;
          x1 = x1 < a1 ? x1 : a1;
        }
        if (zs || ys) {
          if (x0 <= x1) grid_row(G, cz, cy, x0, x1, visit);
        } else {
          const int64_t xl = c0[0] - r, xh = c0[0] + r;
          if (xl >= x0 && xl <= x1) grid_row(G, cz, cy, xl, xl, visit);
          if (r > 0 && xh >= x0 && xh <= x1) grid_row(G, cz, cy, xh, xh, visit);
        }
      }
    }
    // Lower bound on the distance to any point outside the visited block of cells.
    double lb = 1e308;
    bool outside = false;
    for (int a = 0; a < 3; ++a) {
      const double m = grid_margin(o[a], h, dims[a], q[a]);
      if (lo[a] > 0) {
        outside = true;
        const double gap = q[a] - (o[a] + static_cast<double>(lo[a]) * h) - m;
        lb = fmin(lb, gap > 0.0 ? gap : 0.0);
      }
      if (hi[a] < dims[a] - 1) {
        outside = true;
        const double gap = (o[a] + static_cast<double>(hi[a] + 1) * h) - q[a] - m;
        lb = fmin(lb, gap > 0.0 ? gap : 0.0);
      }
    }
    if (!outside) return;
    if (static_cast<double>(list.worst()) < lb * lb * slack) return;
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
