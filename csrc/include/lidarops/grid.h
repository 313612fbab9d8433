// Uniform grid (cell lists) over a batch of ragged point clouds, used by the kNN and ball-query
// fast paths on CPU and CUDA.
//
// Each valid point gets the key of its cell, (cz * dims_y + cy) * dims_x + cx, and the keys of each
// cloud are sorted. A query
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
  // Optional (B, C + 1) int64 table, C >= every cloud's cell count: the points of cell key c of
  // cloud b are order[b, offsets[b, c] : offsets[b, c + 1]]. Undefined: use binary search.
  at::Tensor offsets;
  // Optional (B, N, 3) coordinates in sorted order, in the computation dtype (float, or double for
  // double input): the searches then read points sequentially instead of through `order`.
  at::Tensor sorted_points;
};

// CPU builders (csrc/cpu/grid_cpu.cpp), O(N) by counting sort, with the dense offsets table when the
// grid has at most about 4 cells per point. kNN cells hold about k/2 points at the mean density of the
// cloud's bounding box (extents floored at 1% of the largest); ball-query cells have edge = radius.
// The CUDA kernels build the same cells on the device (knn_grid.cuh).
Grid build_knn_grid_cpu(const at::Tensor& points, const at::Tensor& lengths, int64_t k);
Grid build_ball_grid_cpu(const at::Tensor& points, const at::Tensor& lengths, double radius);

// Raw view of a Grid for kernels.
struct GridView {
  const double* origin;
  const double* cell;
  const int64_t* dims;
  const int64_t* keys;
  const int64_t* order;
  int64_t N;
  const int64_t* offsets;  // nullptr: binary search in keys
  int64_t offsets_stride;
  const void* sorted_points;  // nullptr: read the caller's points through `order`
};

inline GridView grid_view(const Grid& g) {
  const bool dense = g.offsets.defined();
  return GridView{g.origin.data_ptr<double>(), g.cell.data_ptr<double>(), g.dims.data_ptr<int64_t>(),
                  g.sorted_keys.data_ptr<int64_t>(), g.order.data_ptr<int64_t>(), g.sorted_keys.size(1),
                  dense ? g.offsets.data_ptr<int64_t>() : nullptr, dense ? g.offsets.size(1) : 0,
                  g.sorted_points.defined() ? g.sorted_points.data_ptr() : nullptr};
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

// Visit the points of cells [x0, x1] in row (cz, cy) of cloud b: calls visit(sorted_position,
// point_index), sorted_position counting within cloud b.
template <typename Visit>
LIDAROPS_HD void grid_visit_row_pos(const GridView& g, int64_t b, int64_t cz, int64_t cy, int64_t x0, int64_t x1,
                                    Visit& visit) {
  const int64_t* dims = g.dims + 3 * b;
  const int64_t* keys = g.keys + b * g.N;
  const int64_t* order = g.order + b * g.N;
  const int64_t row = (cz * dims[1] + cy) * dims[0];
  const int64_t k0 = row + x0, k1 = row + x1;
  if (g.offsets != nullptr) {
    const int64_t* off = g.offsets + b * g.offsets_stride;
    for (int64_t i = off[k0], e = off[k1 + 1]; i < e; ++i) visit(i, order[i]);
    return;
  }
  for (int64_t i = lower_bound_i64(keys, g.N, k0); i < g.N && keys[i] <= k1; ++i) visit(i, order[i]);
}

// Same, calling visit(point_index).
template <typename Visit>
LIDAROPS_HD void grid_visit_row(const GridView& g, int64_t b, int64_t cz, int64_t cy, int64_t x0, int64_t x1,
                                Visit& visit) {
  auto by_index = [&](int64_t, int64_t j) { visit(j); };
  grid_visit_row_pos(g, b, cz, cy, x0, x1, by_index);
}

// Squared distance from (qx, qy, qz) to the point at sorted position i / index j of cloud b.
template <typename T, typename S>
LIDAROPS_HD T grid_point_sqdist(const GridView& g, int64_t b, const S* pts, int64_t i, int64_t j, T qx, T qy, T qz) {
  if (g.sorted_points != nullptr) {
    const T* p = static_cast<const T*>(g.sorted_points) + (b * g.N + i) * 3;
    return sqdist3<T>(p[0], p[1], p[2], qx, qy, qz);
  }
  return sqdist3<T>(static_cast<T>(pts[3 * j]), static_cast<T>(pts[3 * j + 1]), static_cast<T>(pts[3 * j + 2]), qx,
                    qy, qz);
}

}  // namespace lidarops
