// kNN on CPU: brute force for small clouds, a k-d tree (kdtree.h) for large ones, the uniform grid
// (grid.h, the structure the CUDA kernel uses) on request; parallel over all (cloud, query) pairs.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/full.h>

#include <algorithm>
#include <atomic>
#include <vector>

#include "lidarops/kdtree.h"
#include "lidarops/neighbors.h"

namespace lidarops {
namespace {

// The path taken: brute force, grid or tree.
int64_t knn_path_cpu(int64_t method, int64_t M, int64_t N) {
  if (method != kMethodAuto) return method;
  return N >= 2048 && M >= 64 ? kMethodTree : kMethodBrute;
}

std::tuple<at::Tensor, at::Tensor> knn_cpu(const at::Tensor& query_in, const at::Tensor& points_in,
                                           const at::Tensor& query_lengths, const at::Tensor& point_lengths,
                                           int64_t k, int64_t method) {
  check_pair(query_in, points_in);
  check_lengths(query_lengths, query_in, "query_lengths");
  check_lengths(point_lengths, points_in, "point_lengths");
  TORCH_CHECK_VALUE(k > 0, "k must be positive, got ", k);
  TORCH_CHECK_VALUE(method >= 0 && method <= 3, "method must be 0 (auto), 1 (brute), 2 (grid) or 3 (tree), got ", method);
  auto query = query_in.contiguous();
  auto points = points_in.contiguous();
  auto qlen = query_lengths.contiguous();
  auto plen = point_lengths.contiguous();
  const int64_t B = query.size(0), M = query.size(1), N = points.size(1);
  check_lengths_values_cpu(qlen, M, "query_lengths");
  check_lengths_values_cpu(plen, N, "point_lengths");
  auto dopt = query.options().dtype(dist_dtype(query.scalar_type()));
  auto dist = at::full({B, M, k}, std::numeric_limits<double>::infinity(), dopt);
  auto idx = at::full({B, M, k}, -1, query.options().dtype(at::kLong));
  if (B == 0 || M == 0 || N == 0) return {dist, idx};
  const int64_t path = knn_path_cpu(method, M, N);
  const bool grid = path == kMethodGrid, tree = path == kMethodTree;
  Grid g;
  GridView gv{};
  if (grid) {
    g = build_knn_grid_cpu(points, plen, k);
    gv = grid_view(g);
  }
  const int64_t* ql = qlen.data_ptr<int64_t>();
  const int64_t* pl = plen.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, query.scalar_type(), "lidarops_knn_cpu", [&] {
    using T = acc_t<scalar_t>;
    const scalar_t* qp = query.data_ptr<scalar_t>();
    const scalar_t* pp = points.data_ptr<scalar_t>();
    T* dp = dist.data_ptr<T>();
    int64_t* ip = idx.data_ptr<int64_t>();
    if (tree) {
      const std::vector<KdTree<T>> trees = build_kd_trees<T>(pp, B, N, pl);
      // Blocks of queries handed out by a shared counter, so that a thread slowed down by other
      // work on the machine (or by a denser part of the cloud) holds up no one.
      constexpr int64_t kBlock = 256;
      const int64_t total = B * M, blocks = (total + kBlock - 1) / kBlock;
      const int64_t workers =
          std::clamp<int64_t>(total * 16 * k / 32768, 1, std::max<int64_t>(1, at::get_num_threads()));
      std::atomic<int64_t> next{0};
      at::parallel_for(0, workers, 1, [&](int64_t, int64_t) {
        std::vector<KdKey<T>> buf(k + 1);
        buf[0] = KdKey<T>{};  // sentinel below the list
        KdKey<T>* keys = buf.data() + 1;
        for (int64_t blk; (blk = next.fetch_add(1, std::memory_order_relaxed)) < blocks;) {
          for (int64_t t = blk * kBlock, e = std::min(total, t + kBlock); t < e; ++t) {
            const int64_t b = t / M, m = t % M;
            if (m >= ql[b] || pl[b] == 0) continue;
            const scalar_t* q = qp + 3 * t;
            std::fill(keys, keys + k, KdKey<T>::none());
            knn_tree_search<T>(trees[b], static_cast<T>(q[0]), static_cast<T>(q[1]), static_cast<T>(q[2]), k, keys);
            T* d = dp + t * k;
            int64_t* i = ip + t * k;
            for (int64_t c = 0; c < k && !keys[c].is_none(); ++c) {
              d[c] = keys[c].dist();
              i[c] = keys[c].index();
            }
          }
        }
      });
      return;
    }
    // Grain: enough distance evaluations per task that small inputs stay on the calling thread.
    const int64_t work = grid ? 16 * k : std::max<int64_t>(N, 1);
    at::parallel_for(0, B * M, std::max<int64_t>(1, 32768 / work), [&](int64_t begin, int64_t end) {
      for (int64_t t = begin; t < end; ++t) {
        const int64_t b = t / M, m = t % M;
        if (m >= ql[b] || pl[b] == 0) continue;
        const scalar_t* q = qp + 3 * t;
        const T qx = static_cast<T>(q[0]), qy = static_cast<T>(q[1]), qz = static_cast<T>(q[2]);
        KnnList<T> list{dp + t * k, ip + t * k, k};
        const scalar_t* cloud = pp + b * N * 3;
        if (grid) knn_grid_search<T>(gv, b, cloud, qx, qy, qz, list);
        else knn_brute_search<T>(cloud, pl[b], qx, qy, qz, list);
      }
    });
  });
  return {dist, idx};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) { m.impl("knn", &knn_cpu); }

}  // namespace lidarops
