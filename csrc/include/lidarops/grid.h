// Uniform grid (cell lists) over a batch of ragged point clouds, used by the kNN and ball-query
// fast paths on CPU and CUDA.
//
// The grid is built with ATen ops (so one builder serves every device): each valid point gets the
// key of its cell, (cz * dims_y + cy) * dims_x + cx, and the keys of each cloud are sorted. A query
// finds the points of a cell by binary search in its cloud's sorted keys; the points of one grid row
// (fixed cz, cy, consecutive cx) are contiguous, so a row costs one search.
//
// Exactness: the search visits cells until no unvisited point can beat the current answer. The
// bounds it uses are computed in double with a safety margin, so rounding in the cell assignment
// can only make it visit more cells, never fewer; results are identical to brute force.
#pragma once

#include <cstdint>
#include <limits>

#include "lidarops/common.h"

namespace lidarops {

struct Grid {
  at::Tensor origin;       // (B, 3) double: lower corner of each cloud's bounding box
  at::Tensor cell;         // (B,) double: cell edge length
  at::Tensor dims;         // (B, 3) int64: cells along x, y, z
  at::Tensor sorted_keys;  // (B, N) int64: cell keys of the valid points, ascending, then INT64_MAX
  at::Tensor order;        // (B, N) int64: point index of each sorted key
};

// cell_size: (B,) double tensor, wanted cell edge per cloud (clamped so each axis has <= 2^20 cells).
Grid build_grid(const at::Tensor& points, const at::Tensor& lengths, const at::Tensor& cell_size);

// Cell edge for kNN: about k/2 points per cell at the cloud's mean density over its bounding box.
at::Tensor knn_cell_size(const at::Tensor& points, const at::Tensor& lengths, int64_t k);

// Raw view of a Grid for kernels.
struct GridView {
  const double* origin;
  const double* cell;
  const int64_t* dims;
  const int64_t* keys;
  const int64_t* order;
  int64_t N;
};

inline GridView grid_view(const Grid& g) {
  return GridView{g.origin.data_ptr<double>(), g.cell.data_ptr<double>(), g.dims.data_ptr<int64_t>(),
                  g.sorted_keys.data_ptr<int64_t>(), g.order.data_ptr<int64_t>(), g.sorted_keys.size(1)};
}

LIDAROPS_HD int64_t lower_bound_i64(const int64_t* a, int64_t n, int64_t key) {
  int64_t lo = 0, hi = n;
  while (lo < hi) {
    const int64_t mid = (lo + hi) >> 1;
    if (a[mid] < key) lo = mid + 1;
    else hi = mid;
  }
  return lo;
}

LIDAROPS_HD int64_t clamp_i64(int64_t v, int64_t lo, int64_t hi) { return v < lo ? lo : (v > hi ? hi : v); }

LIDAROPS_HD int64_t cell_of(double x, double origin, double cell, int64_t dim) {
  const double c = floor((x - origin) / cell);
  if (!(c > 0)) return 0;  // also maps NaN to 0 (inputs are validated upstream)
  if (c >= static_cast<double>(dim - 1)) return dim - 1;
  return static_cast<int64_t>(c);
}

// Margin, in metres, on geometric bounds: covers the rounding of the cell assignment.
LIDAROPS_HD double grid_margin(double origin, double cell, int64_t dim, double q) {
  return 1e-9 * (fabs(origin) + cell * static_cast<double>(dim) + fabs(q)) + 1e-12;
}

// Visit the points of cells [x0, x1] in row (cz, cy) of cloud b: calls visit(point_index).
template <typename Visit>
LIDAROPS_HD void grid_visit_row(const GridView& g, int64_t b, int64_t cz, int64_t cy, int64_t x0, int64_t x1,
                                Visit& visit) {
  const int64_t* dims = g.dims + 3 * b;
  const int64_t* keys = g.keys + b * g.N;
  const int64_t* order = g.order + b * g.N;
  const int64_t row = (cz * dims[1] + cy) * dims[0];
  const int64_t k0 = row + x0, k1 = row + x1;
  for (int64_t i = lower_bound_i64(keys, g.N, k0); i < g.N && keys[i] <= k1; ++i) visit(order[i]);
}

}  // namespace lidarops
