// Ball query on CPU: the first k points in index order with dist2 < radius^2. Brute force (which
// stops after k hits) for small clouds, the uniform grid with cell = radius for large ones.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/full.h>

#include "lidarops/neighbors.h"

namespace lidarops {
namespace {

bool use_grid_cpu(int64_t method, int64_t M, int64_t N) {
  if (method != kMethodAuto) return method == kMethodGrid;
  return N >= 4096 && M >= 64;
}

std::tuple<at::Tensor, at::Tensor> ball_query_cpu(const at::Tensor& query_in, const at::Tensor& points_in,
                                                  const at::Tensor& query_lengths,
                                                  const at::Tensor& point_lengths, int64_t k, double radius,
                                                  int64_t method) {
  check_pair(query_in, points_in);
  check_lengths(query_lengths, query_in, "query_lengths");
  check_lengths(point_lengths, points_in, "point_lengths");
  TORCH_CHECK_VALUE(k > 0, "k must be positive, got ", k);
  TORCH_CHECK_VALUE(radius >= 0 && std::isfinite(radius), "radius must be finite and >= 0, got ", radius);
  TORCH_CHECK_VALUE(method >= 0 && method <= 2, "method must be 0 (auto), 1 (brute) or 2 (grid), got ", method);
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
  if (B == 0 || M == 0 || N == 0 || radius == 0) return {dist, idx};
  const bool grid = use_grid_cpu(method, M, N);
  Grid g;
  GridView gv{};
  if (grid) {
    g = build_ball_grid_cpu(points, plen, radius);
    gv = grid_view(g);
  }
  const int64_t* ql = qlen.data_ptr<int64_t>();
  const int64_t* pl = plen.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, query.scalar_type(), "lidarops_ball_query_cpu", [&] {
    using T = acc_t<scalar_t>;
    const T r2 = static_cast<T>(radius) * static_cast<T>(radius);
    const scalar_t* qp = query.data_ptr<scalar_t>();
    const scalar_t* pp = points.data_ptr<scalar_t>();
    T* dp = dist.data_ptr<T>();
    int64_t* ip = idx.data_ptr<int64_t>();
    const int64_t work = grid ? 16 * k : std::max<int64_t>(N, 1);
    at::parallel_for(0, B * M, std::max<int64_t>(1, 32768 / work), [&](int64_t begin, int64_t end) {
      for (int64_t t = begin; t < end; ++t) {
        const int64_t b = t / M, m = t % M;
        if (m >= ql[b] || pl[b] == 0) continue;
        const scalar_t* q = qp + 3 * t;
        const T qx = static_cast<T>(q[0]), qy = static_cast<T>(q[1]), qz = static_cast<T>(q[2]);
        BallList<T> list{dp + t * k, ip + t * k, k};
        const scalar_t* cloud = pp + b * N * 3;
        if (grid) ball_grid_search<T>(gv, b, cloud, qx, qy, qz, r2, radius, list);
        else ball_brute_search<T>(cloud, pl[b], qx, qy, qz, r2, list);
      }
    });
  });
  return {dist, idx};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) { m.impl("ball_query", &ball_query_cpu); }

}  // namespace lidarops
