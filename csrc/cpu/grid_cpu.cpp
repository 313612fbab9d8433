// O(N) grid construction on CPU (counting sort by cell), parallel over clouds, with the dense offsets
// table and the coordinates in cell order.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>

#include <algorithm>
#include <cmath>
#include <numeric>
#include <vector>

#include "lidarops/grid.h"

namespace lidarops {
namespace {

constexpr double kMaxCellsPerAxis = 1048576.0;

struct Box {
  double lo[3], hi[3];
};

// Bounding box of the finite coordinates (the wrappers reject NaN/inf; with their value checks off,
// non-finite points land in clamped edge cells instead of corrupting the grid).
template <typename scalar_t>
Box box_of(const scalar_t* p, int64_t n) {
  Box bx;
  for (int a = 0; a < 3; ++a) {
    bx.lo[a] = std::numeric_limits<double>::infinity();
    bx.hi[a] = -std::numeric_limits<double>::infinity();
  }
  for (int64_t i = 0; i < n; ++i)
    for (int a = 0; a < 3; ++a) {
      const double v = static_cast<double>(p[3 * i + a]);
      if (!std::isfinite(v)) continue;
      bx.lo[a] = std::min(bx.lo[a], v);
      bx.hi[a] = std::max(bx.hi[a], v);
    }
  for (int a = 0; a < 3; ++a)
    if (!(bx.lo[a] <= bx.hi[a])) bx.lo[a] = bx.hi[a] = 0.0;
  return bx;
}

// cell_for(box, n) -> wanted cell edge of one cloud
template <typename CellFor>
Grid build_cpu(const at::Tensor& points_in, const at::Tensor& lengths_in, CellFor cell_for) {
  auto points = points_in.contiguous();
  auto lengths = lengths_in.contiguous();
  const int64_t B = points.size(0), N = points.size(1);
  auto dopt = points.options().dtype(at::kDouble);
  auto lopt = points.options().dtype(at::kLong);
  Grid g{at::empty({B, 3}, dopt), at::empty({B}, dopt), at::empty({B, 3}, lopt), at::empty({B, N}, lopt),
         at::empty({B, N}, lopt), at::Tensor()};
  double* origin = g.origin.data_ptr<double>();
  double* cell = g.cell.data_ptr<double>();
  int64_t* dims = g.dims.data_ptr<int64_t>();
  const int64_t* len = lengths.data_ptr<int64_t>();
  std::vector<int64_t> keys(B * N);
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, points.scalar_type(), "lidarops_grid_cpu", [&] {
    const scalar_t* pp = points.data_ptr<scalar_t>();
    at::parallel_for(0, B, std::max<int64_t>(1, 32768 / std::max<int64_t>(N, 1)), [&](int64_t b0, int64_t b1) {
      for (int64_t b = b0; b < b1; ++b) {
        const int64_t n = len[b];
        const scalar_t* p = pp + b * N * 3;
        const Box bx = box_of(p, n);
        double ext[3], max_ext = 0;
        for (int a = 0; a < 3; ++a) {
          ext[a] = bx.hi[a] - bx.lo[a];
          max_ext = std::max(max_ext, ext[a]);
        }
        double h = std::max({cell_for(ext, max_ext, n), max_ext / (kMaxCellsPerAxis - 1.0), 1e-9});
        cell[b] = h;
        for (int a = 0; a < 3; ++a) {
          origin[3 * b + a] = bx.lo[a];
          dims[3 * b + a] = static_cast<int64_t>(std::clamp(std::floor(ext[a] / h) + 1.0, 1.0, kMaxCellsPerAxis));
        }
        const int64_t* d = dims + 3 * b;
        int64_t* kb = keys.data() + b * N;
        for (int64_t i = 0; i < n; ++i) {
          int64_t c[3];
          for (int a = 0; a < 3; ++a) {
            double f = std::floor((static_cast<double>(p[3 * i + a]) - bx.lo[a]) / h);
            f = f > 0 ? f : 0;  // also NaN -> 0
            c[a] = static_cast<int64_t>(std::min(f, static_cast<double>(d[a] - 1)));
          }
          kb[i] = (c[2] * d[1] + c[1]) * d[0] + c[0];
        }
      }
    });
  });
  int64_t max_cells = 0;
  bool dense = true;
  for (int64_t b = 0; b < B; ++b) {
    const int64_t c = dims[3 * b] * dims[3 * b + 1] * dims[3 * b + 2];
    max_cells = std::max(max_cells, c);
    dense = dense && c <= 4 * len[b] + 1024;
  }
  if (dense) g.offsets = at::empty({B, max_cells + 1}, lopt);
  const auto ct = points.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  g.sorted_points = at::zeros({B, N, 3}, points.options().dtype(ct));
  int64_t* sk = g.sorted_keys.data_ptr<int64_t>();
  int64_t* order = g.order.data_ptr<int64_t>();
  at::parallel_for(0, B, std::max<int64_t>(1, 32768 / std::max<int64_t>(N, 1)), [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      const int64_t n = len[b];
      const int64_t* kb = keys.data() + b * N;
      int64_t* skb = sk + b * N;
      int64_t* ob = order + b * N;
      std::fill(skb + n, skb + N, std::numeric_limits<int64_t>::max());
      for (int64_t i = n; i < N; ++i) ob[i] = i;
      if (dense) {  // counting sort: stable, so points of a cell stay in index order
        int64_t* off = g.offsets.data_ptr<int64_t>() + b * (max_cells + 1);
        std::fill(off, off + max_cells + 1, 0);
        for (int64_t i = 0; i < n; ++i) ++off[kb[i] + 1];
        for (int64_t c = 0; c < max_cells; ++c) off[c + 1] += off[c];
        std::vector<int64_t> cursor(off, off + max_cells);
        for (int64_t i = 0; i < n; ++i) {
          const int64_t pos = cursor[kb[i]]++;
          ob[pos] = i;
          skb[pos] = kb[i];
        }
      } else {
        std::iota(ob, ob + n, 0);
        std::stable_sort(ob, ob + n, [&](int64_t u, int64_t v) { return kb[u] < kb[v]; });
        for (int64_t i = 0; i < n; ++i) skb[i] = kb[ob[i]];
      }
    }
  });
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, points.scalar_type(), "lidarops_grid_sort_cpu", [&] {
    using T = acc_t<scalar_t>;
    const scalar_t* pp = points.data_ptr<scalar_t>();
    T* sp = g.sorted_points.data_ptr<T>();
    at::parallel_for(0, B * N, 32768, [&](int64_t s0, int64_t s1) {
      for (int64_t t = s0; t < s1; ++t) {
        const int64_t b = t / N, i = t % N;
        if (i >= len[b]) continue;
        const scalar_t* src = pp + (b * N + order[t]) * 3;
        for (int a = 0; a < 3; ++a) sp[3 * t + a] = static_cast<T>(src[a]);
      }
    });
  });
  return g;
}

}  // namespace

Grid build_knn_grid_cpu(const at::Tensor& points, const at::Tensor& lengths, int64_t k) {
  return build_cpu(points, lengths, [k](const double* ext, double max_ext, int64_t n) {
    // about k/2 points per cell at the mean density of the bounding box (flat clouds: extents floored)
    double vol = 1.0;
    for (int a = 0; a < 3; ++a) vol *= std::max(ext[a], max_ext * 1e-2 + 1e-6);
    return std::cbrt(vol * static_cast<double>(std::max<int64_t>(k, 2)) * 0.5 / static_cast<double>(std::max<int64_t>(n, 1)));
  });
}

Grid build_ball_grid_cpu(const at::Tensor& points, const at::Tensor& lengths, double radius) {
  return build_cpu(points, lengths, [radius](const double*, double, int64_t) { return radius; });
}

}  // namespace lidarops
