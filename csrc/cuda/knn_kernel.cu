// kNN on CUDA, bit-identical to the CPU kernel: distances by sqdist3 (every operation rounded, no
// FMA) and lists ordered by closer() (dist2, then index), so the answer is defined exactly and any
// exact algorithm returns the same bits.
//
// Brute force (small clouds): the points of the cloud pass through shared memory in tiles; S
// threads per query (S a power of two <= 32, chosen to fill the GPU), thread s keeping in
// registers the C smallest of the points j = s (mod S). The S lists are then merged with sub-warp
// shuffles, k rounds each taking the smallest head by closer(). Since C >= k, the k smallest of the
// cloud are among the per-thread lists, and the merge emits them in order.
//
// Grid (large clouds): the device grid of knn_grid.cuh, one thread per query, queries taken in
// the order of their grid cell (neighbouring threads search the same cells), a register list, and
// the exact ring search of knn_grid_search() (neighbors.h).
//
// k > 64 (k > 32 for double): the lists live in the output rows (KnnList), one thread per query.
#include <ATen/Dispatch.h>

#include "lidarops/knn_grid.cuh"

namespace lidarops {
namespace {

using gpu::clamp_len;

constexpr int kBruteThreads = 256;
constexpr int kTile = 1024;  // points per shared-memory tile
constexpr int kGridThreads = 128;

// Scans the points of one cloud, tile by tile, pushing the points j = s (mod S) into `list`.
// Every thread of the block calls it (it holds the block's barriers).
template <typename T, typename List>
__device__ __forceinline__ void brute_scan(const T* __restrict__ cloud, int64_t n, bool active, int s, int S, T qx,
                                           T qy, T qz, T* sx, T* sy, T* sz, List& list) {
  for (int64_t t0 = 0; t0 < n; t0 += kTile) {
    const int tl = static_cast<int>(n - t0 < kTile ? n - t0 : kTile);
    __syncthreads();  // the previous tile is no longer read
    for (int u = threadIdx.x; u < tl; u += blockDim.x) {
      const T* p = cloud + 3 * (t0 + u);
      sx[u] = p[0];
      sy[u] = p[1];
      sz[u] = p[2];
    }
    __syncthreads();
    if (active)
      for (int u = s; u < tl; u += S) list.push(sqdist3<T>(sx[u], sy[u], sz[u], qx, qy, qz), t0 + u);
  }
}

// Grid: blockIdx.x = b * mblocks + (query block); 256 / S queries per block, S threads each.
template <typename T, int C>
__global__ void __launch_bounds__(kBruteThreads, 1)
    knn_brute_kernel(const T* __restrict__ query, const T* __restrict__ points, const int64_t* __restrict__ qlen,
                     const int64_t* __restrict__ plen, int64_t M, int64_t N, int64_t k, int S, int64_t mblocks,
                     T* __restrict__ dist, int64_t* __restrict__ idx) {
  __shared__ T sx[kTile], sy[kTile], sz[kTile];
  const int64_t b = blockIdx.x / mblocks;
  const int G = kBruteThreads / S;
  const int s = threadIdx.x & (S - 1);
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
  if constexpr (C > 0) {
    gpu::RegKnnList<T, C> list;
    list.init();
    brute_scan(cloud, n, active, s, S, qx, qy, qz, sx, sy, sz, list);
    if (S == 1 || C > 32) {  // C > 32: S == 1 (the host's choice; keeps the merge's registers out)
      if (m < M) {
#pragma unroll
        for (int r = 0; r < C; ++r) {
          if (r < k) {
            dist[row + r] = list.d[r];
            idx[row + r] = list.i[r];
          }
        }
      }
    } else if constexpr (C <= 32) {
      // Sub-warp merge; every lane of the warp takes part (the shuffles need the full mask).
      for (int64_t r = 0; r < k; ++r) {
        T md = list.d[0];
        int mi = list.i[0];
        for (int off = S >> 1; off > 0; off >>= 1) {
          const T od = __shfl_xor_sync(gpu::kFullMask, md, off);
          const int oi = __shfl_xor_sync(gpu::kFullMask, mi, off);
          if (closer(od, oi, md, mi)) {
            md = od;
            mi = oi;
          }
        }
        // Real entries are unique across the group (disjoint point sets); only padding can tie.
        if (list.d[0] == md && list.i[0] == mi) list.pop_front();
        if (s == 0 && m < M) {
          dist[row + r] = md;
          idx[row + r] = mi;
        }
      }
    }
  } else {
    // k > 64 (k > 32 for double), S == 1: the list is the output row itself.
    if (m < M)
      for (int64_t r = 0; r < k; ++r) {
        dist[row + r] = gpu::inf_value<T>();
        idx[row + r] = -1;
      }
    KnnList<T> list{dist + row, idx + row, k};
    brute_scan(cloud, n, active, 0, 1, qx, qy, qz, sx, sy, sz, list);
  }
}

// S threads per query (S a power of two <= 4; S = 1 for lists in the output rows and for C > 32),
// queries in the order of qorder (grouped by grid cell, so neighbouring groups search the same
// cells). With S > 1 each lane searches a share of every row into its register list (see
// knn_grid_search_dev) and the S lists are merged by sub-warp shuffles, as in the brute kernel.
// A group never straddles a warp and all its lanes share the query, so they exit together.
template <typename T, int C, int S>
__global__ void __launch_bounds__(kGridThreads)
    knn_grid_kernel(const T* __restrict__ query, const int64_t* __restrict__ qlen, const int32_t* __restrict__ qorder,
                    int64_t B, int64_t M, const gpu::DGrid* __restrict__ grids, const int32_t* __restrict__ table,
                    const T* __restrict__ recs, int64_t N, int64_t cap, int64_t k, T* __restrict__ dist,
                    int64_t* __restrict__ idx) {
  static_assert(S == 1 || (C > 0 && C <= 32), "S > 1 needs register lists of at most 32 entries");
  const int64_t t = (blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x) / S;
  if (t >= B * M) return;
  const int lane = static_cast<int>(threadIdx.x & (S - 1));
  const unsigned mask = S == 32 ? gpu::kFullMask : ((1u << S) - 1u) << (threadIdx.x & 31 & ~(S - 1));
  const int64_t b = t / M;
  const int64_t m = qorder[t];  // a permutation of [0, M) per cloud
  const int64_t row = (b * M + m) * k;
  const gpu::GridRef<T> G = gpu::grid_ref(grids, table, recs, b, N, cap);
  if (m >= clamp_len(qlen[b], M) || G.g.n == 0) {
    for (int64_t r = lane; r < k; r += S) {
      dist[row + r] = gpu::inf_value<T>();
      idx[row + r] = -1;
    }
    return;
  }
  const T* q = query + 3 * (b * M + m);
  const T qx = q[0], qy = q[1], qz = q[2];
  if constexpr (C > 0) {
    gpu::RegKnnList<T, C> list;
    list.init();
    gpu::knn_grid_search_dev<T, decltype(list), S>(G, qx, qy, qz, list, lane, mask);
    if constexpr (S == 1) {
#pragma unroll
      for (int r = 0; r < C; ++r) {
        if (r < k) {
          dist[row + r] = list.d[r];
          idx[row + r] = list.i[r];
        }
      }
    } else {
      for (int64_t r = 0; r < k; ++r) {
        T md = list.d[0];
        int mi = list.i[0];
#pragma unroll
        for (int off = S >> 1; off > 0; off >>= 1) {
          const T od = __shfl_xor_sync(mask, md, off);
          const int oi = __shfl_xor_sync(mask, mi, off);
          if (closer(od, oi, md, mi)) {
            md = od;
            mi = oi;
          }
        }
        // Real entries are unique across the group (disjoint point sets); only padding can tie.
        if (list.d[0] == md && list.i[0] == mi) list.pop_front();
        if (lane == 0) {
          dist[row + r] = md;
          idx[row + r] = mi;
        }
      }
    }
  } else {
    for (int64_t r = 0; r < k; ++r) {
      dist[row + r] = gpu::inf_value<T>();
      idx[row + r] = -1;
    }
    KnnList<T> list{dist + row, idx + row, k};
    gpu::knn_grid_search_dev(G, qx, qy, qz, list);
  }
}

bool use_grid_cuda(int64_t method, int64_t B, int64_t M, int64_t N) {
  if (method != kMethodAuto) return method == kMethodGrid;
  // Brute force costs B*M*N distances; the grid costs a few launches and a counting sort, which pays
  // from about 2^24 distances on (tuning in docs/notes/ops.md).
  return N >= 2048 && static_cast<double>(B) * static_cast<double>(M) * static_cast<double>(N) >= 16777216.0;
}

std::tuple<at::Tensor, at::Tensor> knn_cuda(const at::Tensor& query_in, const at::Tensor& points_in,
                                            const at::Tensor& query_lengths, const at::Tensor& point_lengths,
                                            int64_t k, int64_t method) {
  check_pair(query_in, points_in);
  check_lengths(query_lengths, query_in, "query_lengths");
  check_lengths(point_lengths, points_in, "point_lengths");
  TORCH_CHECK_VALUE(k > 0, "k must be positive, got ", k);
  TORCH_CHECK_VALUE(method >= 0 && method <= 2, "method must be 0 (auto), 1 (brute) or 2 (grid), got ", method);
  c10::cuda::CUDAGuard device_guard(query_in.device());
  const int64_t B = query_in.size(0), M = query_in.size(1), N = points_in.size(1);
  TORCH_CHECK_VALUE(N < std::numeric_limits<int32_t>::max(), "points: at most 2^31 - 2 points per cloud on CUDA, got ", N);
  auto dopt = query_in.options().dtype(dist_dtype(query_in.scalar_type()));
  auto iopt = query_in.options().dtype(at::kLong);
  if (B == 0 || M == 0 || N == 0)
    return {at::full({B, M, k}, std::numeric_limits<double>::infinity(), dopt), at::full({B, M, k}, -1, iopt)};
  // Every entry is written by the kernels (padding included).
  auto dist = at::empty({B, M, k}, dopt);
  auto idx = at::empty({B, M, k}, iopt);
  // half/bfloat16 -> float is exact, and is what the CPU kernel computes with.
  auto query = gpu::compute_tensor(query_in);
  auto points = gpu::compute_tensor(points_in);
  auto qlen = query_lengths.contiguous();
  auto plen = point_lengths.contiguous();
  const bool grid = use_grid_cuda(method, B, M, N);
  const auto info = gpu::device_props(query_in.device().index());
  cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, query_in.scalar_type(), "lidarops_knn_cuda", [&] {
    using T = acc_t<scalar_t>;
    const T* qp = query.data_ptr<T>();
    const T* pp = points.data_ptr<T>();
    T* dp = dist.data_ptr<T>();
    int64_t* ip = idx.data_ptr<int64_t>();
    // Register lists up to 64 entries (32 for double, whose lists would spill), else output rows.
    auto by_capacity = [&](auto&& launch) {
      if constexpr (std::is_same_v<T, double>) gpu::dispatch_capacity<1, 2, 4, 8, 16, 32>(k, launch);
      else gpu::dispatch_capacity<1, 2, 4, 8, 16, 32, 64>(k, launch);
    };
    if (grid) {
      const gpu::DeviceGrid g =
          gpu::build_device_grid<T>(points, plen, query, qlen, gpu::kGridKnn, k, 0.0, stream);
      const auto* grids = reinterpret_cast<const gpu::DGrid*>(g.params.data_ptr());
      by_capacity([&](auto cap_c) {
        constexpr int C = decltype(cap_c)::value;
        // Threads per query: up to 4 while the queries alone give fewer than 256 threads per SM; once
        // the queries fill the GPU, more than one thread per query is slower (docs/notes/ops.md).
        int S = 1;
        const int64_t want = static_cast<int64_t>(info.sms) * 256;
        if (C > 0 && C <= 32)
          while (S < 4 && B * M * S < want) S <<= 1;
        const unsigned blocks = static_cast<unsigned>(gpu::ceil_div(B * M * S, kGridThreads));
        auto launch = [&](auto s_c) {
          constexpr int SS = decltype(s_c)::value;
          if constexpr (SS == 1 || (C > 0 && C <= 32))
            knn_grid_kernel<T, C, SS><<<blocks, kGridThreads, 0, stream>>>(
                qp, qlen.data_ptr<int64_t>(), g.qorder.data_ptr<int32_t>(), B, M, grids,
                g.table.data_ptr<int32_t>(), g.recs.data_ptr<T>(), N, g.cap, k, dp, ip);
        };
        switch (S) {
          case 4: launch(std::integral_constant<int, 4>{}); break;
          case 2: launch(std::integral_constant<int, 2>{}); break;
          default: launch(std::integral_constant<int, 1>{});
        }
        C10_CUDA_KERNEL_LAUNCH_CHECK();
      });
    } else {
      by_capacity([&](auto cap_c) {
        constexpr int C = decltype(cap_c)::value;
        // Threads per query: fill the GPU, but give each thread at least 128 points; one thread
        // per query for lists in the output rows (C = 0) and for C > 32 (no merge).
        int S = 1;
        const int64_t want = static_cast<int64_t>(info.sms) * 2048;
        if (C > 0 && C <= 32)
          while (S < 32 && B * M * S < want && static_cast<int64_t>(S) * 128 <= N) S <<= 1;
        const int64_t mblocks = gpu::ceil_div(M, kBruteThreads / S);
        knn_brute_kernel<T, C><<<static_cast<unsigned>(B * mblocks), kBruteThreads, 0, stream>>>(
            qp, pp, qlen.data_ptr<int64_t>(), plen.data_ptr<int64_t>(), M, N, k, S, mblocks, dp, ip);
        C10_CUDA_KERNEL_LAUNCH_CHECK();
      });
    }
  });
  return {dist, idx};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) { m.impl("knn", &knn_cuda); }

}  // namespace lidarops
