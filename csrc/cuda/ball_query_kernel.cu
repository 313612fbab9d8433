// Ball query on CUDA, bit-identical to the CPU kernel: the first k points in index order with
// sqdist3(point, query) < r2, where r2 = T(radius) * T(radius) is computed on the host in the
// compute type T, as on CPU.
//
// Brute force (small clouds): the points pass through shared memory in tiles; S threads per query
// (S a power of two <= 32) test S consecutive indices at a time, and a warp ballot gives each hit
// its rank among the group's hits, so the hits are written straight to the output in index order;
// a group stops once it has k hits (the block once all its groups have).
//
// Grid (large clouds): the device grid of knn_grid.cuh (cells of edge `radius`), one thread per
// query, queries in grid-cell order, the cells of ball_grid_search(), and a register list of the C
// lowest indices (k <= 128) or BallList in the output row (k > 128). Distances of the register
// list are recomputed on output with the same formula, hence the same bits.
#include <ATen/Dispatch.h>

#include "lidarops/knn_grid.cuh"

namespace lidarops {
namespace {

using gpu::clamp_len;
using gpu::kFullMask;

constexpr int kBruteThreads = 256;
constexpr int kTile = 1024;
constexpr int kGridThreads = 128;

// Grid: blockIdx.x = b * mblocks + (query block); 256 / S queries per block, S threads each.
template <typename T>
__global__ void __launch_bounds__(kBruteThreads)
    ball_brute_kernel(const T* __restrict__ query, const T* __restrict__ points, const int64_t* __restrict__ qlen,
                      const int64_t* __restrict__ plen, int64_t M, int64_t N, int64_t k, T r2, int S,
                      int64_t mblocks, T* __restrict__ dist, int64_t* __restrict__ idx) {
  __shared__ T sx[kTile], sy[kTile], sz[kTile];
  const int64_t b = blockIdx.x / mblocks;
  const int G = kBruteThreads / S;
  const int lane = threadIdx.x & 31;
  const int s = threadIdx.x & (S - 1);
  const int group_base = lane & ~(S - 1);                   // first lane of the group in the warp
  const unsigned group_mask = S == 32 ? kFullMask : ((1u << S) - 1u);
  const unsigned lower_mask = (1u << s) - 1u;               // lanes of the group before this one
  const int64_t m = (blockIdx.x - b * mblocks) * G + threadIdx.x / S;
  const int64_t nq = clamp_len(qlen[b], M), n = clamp_len(plen[b], N);
  const bool active = m < nq;
  T qx = T(0), qy = T(0), qz = T(0);
  if (active) {
    const T* q = query + 3 * (b * M + m);
    qx = q[0];
    qy = q[1];
    qz = q[2];
  }
  const int64_t row = (b * M + m) * k;  // dereferenced only when m < M
  const T* cloud = points + b * N * 3;
  int64_t count = 0;    // hits so far; the same in every lane of the group
  bool done = !active;  // likewise
  for (int64_t t0 = 0; t0 < n; t0 += kTile) {
    const int tl = static_cast<int>(n - t0 < kTile ? n - t0 : kTile);
    __syncthreads();
    for (int u = threadIdx.x; u < tl; u += kBruteThreads) {
      const T* p = cloud + 3 * (t0 + u);
      sx[u] = p[0];
      sy[u] = p[1];
      sz[u] = p[2];
    }
    __syncthreads();
    if (!__all_sync(kFullMask, done)) {  // warp-uniform: the ballots below see every lane
      for (int u0 = 0; u0 < tl; u0 += S) {
        const int u = u0 + s;
        T d = T(0);
        bool hit = false;
        if (!done && u < tl) {
          d = sqdist3<T>(sx[u], sy[u], sz[u], qx, qy, qz);
          hit = d < r2;
        }
        const unsigned bits = (__ballot_sync(kFullMask, hit) >> group_base) & group_mask;
        if (hit) {
          const int64_t pos = count + __popc(bits & lower_mask);
          if (pos < k) {
            dist[row + pos] = d;
            idx[row + pos] = t0 + u;
          }
        }
        count += __popc(bits);
        done = done || count >= k;
      }
    }
    if (__syncthreads_and(done)) break;
  }
  if (m < M)
    for (int64_t p = (count < k ? count : k) + s; p < k; p += S) {
      dist[row + p] = gpu::inf_value<T>();
      idx[row + p] = -1;
    }
}

// One thread per query, in the order of qorder (queries grouped by grid cell).
template <typename T, int C>
__global__ void __launch_bounds__(kGridThreads, 1)
    ball_grid_kernel(const T* __restrict__ query, const T* __restrict__ points, const int64_t* __restrict__ qlen,
                     const int32_t* __restrict__ qorder, int64_t B, int64_t M, const gpu::DGrid* __restrict__ grids,
                     const int32_t* __restrict__ table, const T* __restrict__ recs, int64_t N, int64_t cap,
                     int64_t k, T r2, double radius, T* __restrict__ dist, int64_t* __restrict__ idx) {
  const int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x;
  if (t >= B * M) return;
  const int64_t b = t / M;
  const int64_t m = qorder[t];  // a permutation of [0, M) per cloud
  const int64_t row = (b * M + m) * k;
  const gpu::GridRef<T> G = gpu::grid_ref(grids, table, recs, b, N, cap);
  if (m >= clamp_len(qlen[b], M) || G.g.n == 0) {
    for (int64_t r = 0; r < k; ++r) {
      dist[row + r] = gpu::inf_value<T>();
      idx[row + r] = -1;
    }
    return;
  }
  const T* q = query + 3 * (b * M + m);
  const T qx = q[0], qy = q[1], qz = q[2];
  if constexpr (C > 0) {
    gpu::RegBallList<C> list;
    list.init();
    gpu::ball_grid_search_dev(G, qx, qy, qz, r2, radius, list);
    const T* cloud = points + b * N * 3;
#pragma unroll
    for (int r = 0; r < C; ++r) {
      if (r < k) {
        const int j = list.i[r];
        if (j == std::numeric_limits<int>::max()) {
          dist[row + r] = gpu::inf_value<T>();
          idx[row + r] = -1;
        } else {
          dist[row + r] = point_sqdist<T>(cloud, j, qx, qy, qz);
          idx[row + r] = j;
        }
      }
    }
  } else {
    for (int64_t r = 0; r < k; ++r) {
      dist[row + r] = gpu::inf_value<T>();
      idx[row + r] = -1;
    }
    BallList<T> list{dist + row, idx + row, k};
    gpu::ball_grid_search_dev(G, qx, qy, qz, r2, radius, list);
  }
}

bool use_grid_cuda(int64_t method, int64_t B, int64_t M, int64_t N) {
  if (method != kMethodAuto) return method == kMethodGrid;
  return N >= 2048 && static_cast<double>(B) * static_cast<double>(M) * static_cast<double>(N) >= 67108864.0;
}

std::tuple<at::Tensor, at::Tensor> ball_query_cuda(const at::Tensor& query_in, const at::Tensor& points_in,
                                                   const at::Tensor& query_lengths,
                                                   const at::Tensor& point_lengths, int64_t k, double radius,
                                                   int64_t method) {
  check_pair(query_in, points_in);
  check_lengths(query_lengths, query_in, "query_lengths");
  check_lengths(point_lengths, points_in, "point_lengths");
  TORCH_CHECK_VALUE(k > 0, "k must be positive, got ", k);
  TORCH_CHECK_VALUE(radius >= 0 && std::isfinite(radius), "radius must be finite and >= 0, got ", radius);
  TORCH_CHECK_VALUE(method >= 0 && method <= 2, "method must be 0 (auto), 1 (brute) or 2 (grid), got ", method);
  c10::cuda::CUDAGuard device_guard(query_in.device());
  const int64_t B = query_in.size(0), M = query_in.size(1), N = points_in.size(1);
  TORCH_CHECK_VALUE(N < std::numeric_limits<int32_t>::max(), "points: at most 2^31 - 2 points per cloud on CUDA, got ", N);
  auto dopt = query_in.options().dtype(dist_dtype(query_in.scalar_type()));
  auto iopt = query_in.options().dtype(at::kLong);
  if (B == 0 || M == 0 || N == 0 || radius == 0)
    return {at::full({B, M, k}, std::numeric_limits<double>::infinity(), dopt), at::full({B, M, k}, -1, iopt)};
  auto dist = at::empty({B, M, k}, dopt);  // every entry is written by the kernels
  auto idx = at::empty({B, M, k}, iopt);
  auto query = gpu::compute_tensor(query_in);  // half/bfloat16 -> float, exact
  auto points = gpu::compute_tensor(points_in);
  auto qlen = query_lengths.contiguous();
  auto plen = point_lengths.contiguous();
  const bool grid = use_grid_cuda(method, B, M, N);
  const auto info = gpu::device_props(query_in.device().index());
  cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, query_in.scalar_type(), "lidarops_ball_query_cuda", [&] {
    using T = acc_t<scalar_t>;
    const T r2 = static_cast<T>(radius) * static_cast<T>(radius);  // as the CPU kernel
    const T* qp = query.data_ptr<T>();
    const T* pp = points.data_ptr<T>();
    T* dp = dist.data_ptr<T>();
    int64_t* ip = idx.data_ptr<int64_t>();
    if (grid) {
      const gpu::DeviceGrid g =
          gpu::build_device_grid<T>(points, plen, query, qlen, gpu::kGridBall, k, radius, stream);
      const auto* grids = reinterpret_cast<const gpu::DGrid*>(g.params.data_ptr());
      const unsigned blocks = static_cast<unsigned>(gpu::ceil_div(B * M, kGridThreads));
      gpu::dispatch_capacity<8, 16, 32, 64, 128>(k, [&](auto cap_c) {
        constexpr int C = decltype(cap_c)::value;
        ball_grid_kernel<T, C><<<blocks, kGridThreads, 0, stream>>>(
            qp, pp, qlen.data_ptr<int64_t>(), g.qorder.data_ptr<int32_t>(), B, M, grids,
            g.table.data_ptr<int32_t>(), g.recs.data_ptr<T>(), N, g.cap, k, r2, radius, dp, ip);
        C10_CUDA_KERNEL_LAUNCH_CHECK();
      });
    } else {
      // Threads per query: fill the GPU, but give each thread at least 128 points.
      int S = 1;
      const int64_t want = static_cast<int64_t>(info.sms) * 2048;
      while (S < 32 && B * M * S < want && static_cast<int64_t>(S) * 128 <= N) S <<= 1;
      const int64_t mblocks = gpu::ceil_div(M, kBruteThreads / S);
      ball_brute_kernel<T><<<static_cast<unsigned>(B * mblocks), kBruteThreads, 0, stream>>>(
          qp, pp, qlen.data_ptr<int64_t>(), plen.data_ptr<int64_t>(), M, N, k, r2, S, mblocks, dp, ip);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
  });
  return {dist, idx};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) { m.impl("ball_query", &ball_query_cuda); }

}  // namespace lidarops
