// Per-query search routines shared by the CPU and CUDA kernels of knn and ball_query, and the
// argument checks of the neighborhood ops. Results are defined by exact (non-contracted) squared
// distances (common.h) and the total order (dist2, index), so every path gives identical answers.
#pragma once

#include "lidarops/common.h"
#include "lidarops/grid.h"

namespace lidarops {

// method codes of the neighborhood ops (kMethodTree: kNN on CPU only)
enum : int64_t { kMethodAuto = 0, kMethodBrute = 1, kMethodGrid = 2, kMethodTree = 3 };

// Relative slack applied to geometric lower bounds before comparing with computed distances.
template <typename T>
LIDAROPS_HD double bound_slack() { return std::is_same_v<T, double> ? 1e-13 : 1e-6; }

// k smallest (dist2, index) pairs, ascending, in caller-provided arrays pre-filled with (+inf, -1).
template <typename T>
struct KnnList {
  T* d;
  int64_t* i;
  int64_t k;
  LIDAROPS_HD T worst() const { return d[k - 1]; }
  LIDAROPS_HD void push(T dd, int64_t j) {
    if (!closer(dd, j, d[k - 1], i[k - 1])) return;
    int64_t p = k - 1;
    while (p > 0 && closer(dd, j, d[p - 1], i[p - 1])) {
      d[p] = d[p - 1];
      i[p] = i[p - 1];
      --p;
    }
    d[p] = dd;
    i[p] = j;
  }
};

// The k lowest indices (with their dist2) among the points pushed, ascending by index.
template <typename T>
struct BallList {
  T* d;
  int64_t* i;
  int64_t k;
  int64_t count = 0;
  LIDAROPS_HD void push(T dd, int64_t j) {
    if (count == k && j > i[k - 1]) return;
    int64_t p = count < k ? count : k - 1;
    if (count < k) ++count;
    while (p > 0 && j < i[p - 1]) {
      d[p] = d[p - 1];
      i[p] = i[p - 1];
      --p;
    }
    d[p] = dd;
    i[p] = j;
  }
};

template <typename T, typename S>
LIDAROPS_HD T point_sqdist(const S* pts, int64_t j, T qx, T qy, T qz) {
  return sqdist3<T>(static_cast<T>(pts[3 * j]), static_cast<T>(pts[3 * j + 1]), static_cast<T>(pts[3 * j + 2]),
                    qx, qy, qz);
}

// Lower bound on |x - q| over x in the cell slab [o + c*h, o + (c+1)*h], minus a rounding margin.
LIDAROPS_HD double slab_gap(double q, double o, double h, int64_t c, int64_t dim) {
  const double lo = o + static_cast<double>(c) * h, hi = o + static_cast<double>(c + 1) * h;
  double g = q < lo ? lo - q : (q > hi ? q - hi : 0.0);
  if (c == 0 || c == dim - 1) g = 0.0;  // edge cells also hold clamped points
  g -= grid_margin(o, h, dim, q);
  return g > 0.0 ? g : 0.0;
}

// The block of cells within Chebyshev distance r of cell c0, clamped to the grid: [lo, hi] per axis.
LIDAROPS_HD void ring_block(const int64_t* c0, int64_t r, const int64_t* dims, int64_t* lo, int64_t* hi) {
  for (int a = 0; a < 3; ++a) {
    lo[a] = c0[a] - r > 0 ? c0[a] - r : 0;
    hi[a] = c0[a] + r < dims[a] - 1 ? c0[a] + r : dims[a] - 1;
  }
}

// Narrows the cells [x0, x1] of a row to those within reach of q along x, `rest` being the squared
// distance left after the row's y and z gaps (1e300 or more, or NaN: no narrowing).
LIDAROPS_HD void clip_row_to_reach(double rest, double q, double o, double h, int64_t dim, int64_t& x0,
                                   int64_t& x1) {
  if (!(rest < 1e300)) return;
  const double reach = sqrt(rest) + grid_margin(o, h, dim, q);
  const int64_t a0 = cell_of(q - reach, o, h, dim);
  const int64_t a1 = cell_of(q + reach, o, h, dim);
  x0 = x0 > a0 ? x0 : a0;
  x1 = x1 < a1 ? x1 : a1;
}

// Lower bound on the distance from q to any point outside the block of cells [lo, hi] (per axis, a
// rounding margin off); outside = false when the block is the whole grid (no point lies outside it).
LIDAROPS_HD double outside_block_gap(const double* q, const double* o, double h, const int64_t* dims,
                                     const int64_t* lo, const int64_t* hi, bool& outside) {
  double lb = 1e308;
  outside = false;
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
  return lb;
}

// Exact kNN of one query through the grid: ring search in Chebyshev shells around the query cell,
// stopping once no unvisited point can enter the list.
template <typename T, typename S, typename List>
LIDAROPS_HD void knn_grid_search(const GridView& g, int64_t b, const S* pts, T qx, T qy, T qz, List& list) {
  const double* o = g.origin + 3 * b;
  const double h = g.cell[b];
  const int64_t* dims = g.dims + 3 * b;
  const double q[3] = {static_cast<double>(qx), static_cast<double>(qy), static_cast<double>(qz)};
  const double slack = 1.0 - bound_slack<T>();
  int64_t c0[3];
  for (int a = 0; a < 3; ++a) c0[a] = cell_of(q[a], o[a], h, dims[a]);
  auto visit = [&](int64_t i, int64_t j) { list.push(grid_point_sqdist<T>(g, b, pts, i, j, qx, qy, qz), j); };
  for (int64_t r = 0;; ++r) {
    int64_t lo[3], hi[3];
    ring_block(c0, r, dims, lo, hi);
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
        clip_row_to_reach(rest, q[0], o[0], h, dims[0], x0, x1);
        if (zs || ys) {
          if (x0 <= x1) grid_visit_row_pos(g, b, cz, cy, x0, x1, visit);
        } else {
          const int64_t xl = c0[0] - r, xh = c0[0] + r;
          if (xl >= x0 && xl <= x1) grid_visit_row_pos(g, b, cz, cy, xl, xl, visit);
          if (r > 0 && xh >= x0 && xh <= x1) grid_visit_row_pos(g, b, cz, cy, xh, xh, visit);
        }
      }
    }
    bool outside;
    const double lb = outside_block_gap(q, o, h, dims, lo, hi, outside);
    if (!outside) return;
    if (static_cast<double>(list.worst()) < lb * lb * slack) return;
  }
}

template <typename T, typename S, typename List>
LIDAROPS_HD void knn_brute_search(const S* pts, int64_t n, T qx, T qy, T qz, List& list) {
  for (int64_t j = 0; j < n; ++j) list.push(point_sqdist<T>(pts, j, qx, qy, qz), j);
}

// Ball query through the grid: every cell that can hold a point within the radius.
template <typename T, typename S, typename List>
LIDAROPS_HD void ball_grid_search(const GridView& g, int64_t b, const S* pts, T qx, T qy, T qz, T r2,
                                  double radius, List& list) {
  const double* o = g.origin + 3 * b;
  const double h = g.cell[b];
  const int64_t* dims = g.dims + 3 * b;
  const double q[3] = {static_cast<double>(qx), static_cast<double>(qy), static_cast<double>(qz)};
  int64_t lo[3], hi[3];
  for (int a = 0; a < 3; ++a) {
    const double reach = radius * (1.0 + 1e-6) + grid_margin(o[a], h, dims[a], q[a]);
    lo[a] = cell_of(q[a] - reach, o[a], h, dims[a]);
    hi[a] = cell_of(q[a] + reach, o[a], h, dims[a]);
  }
  auto visit = [&](int64_t i, int64_t j) {
    const T d = grid_point_sqdist<T>(g, b, pts, i, j, qx, qy, qz);
    if (d < r2) list.push(d, j);
  };
  for (int64_t cz = lo[2]; cz <= hi[2]; ++cz)
    for (int64_t cy = lo[1]; cy <= hi[1]; ++cy) grid_visit_row_pos(g, b, cz, cy, lo[0], hi[0], visit);
}

template <typename T, typename S, typename List>
LIDAROPS_HD void ball_brute_search(const S* pts, int64_t n, T qx, T qy, T qz, T r2, List& list) {
  for (int64_t j = 0; j < n && list.count < list.k; ++j) {
    const T d = point_sqdist<T>(pts, j, qx, qy, qz);
    if (d < r2) list.push(d, j);
  }
}

// ---- argument checks shared by the CPU and CUDA kernels (shapes, dtypes, devices only: value
// checks that need the data live in the Python wrappers and the CPU kernels) ----
inline void check_cloud(const at::Tensor& t, const char* name) {
  TORCH_CHECK_VALUE(t.dim() == 3 && t.size(2) == 3, name, " must be (B, N, 3), got shape ", t.sizes());
  TORCH_CHECK_VALUE(at::isFloatingType(t.scalar_type()), name, " must be a floating tensor, got ", t.scalar_type());
}

inline void check_lengths(const at::Tensor& lengths, const at::Tensor& cloud, const char* name) {
  TORCH_CHECK_VALUE(lengths.dim() == 1 && lengths.size(0) == cloud.size(0), name, " must be (B,) with B = ",
                    cloud.size(0), ", got shape ", lengths.sizes());
  TORCH_CHECK_VALUE(lengths.scalar_type() == at::kLong, name, " must be int64, got ", lengths.scalar_type());
  TORCH_CHECK_VALUE(lengths.device() == cloud.device(), name, " is on ", lengths.device(), " but the points are on ",
                    cloud.device());
}

inline void check_pair(const at::Tensor& query, const at::Tensor& points) {
  check_cloud(query, "query");
  check_cloud(points, "points");
  TORCH_CHECK_VALUE(query.size(0) == points.size(0), "query and points must have the same batch size, got ",
                    query.size(0), " and ", points.size(0));
  TORCH_CHECK_VALUE(query.scalar_type() == points.scalar_type(), "query and points must have the same dtype, got ",
                    query.scalar_type(), " and ", points.scalar_type());
  TORCH_CHECK_VALUE(query.device() == points.device(), "query and points must be on the same device, got ",
                    query.device(), " and ", points.device());
}

// Lengths must lie in [0, n]; only callable on CPU tensors.
inline void check_lengths_values_cpu(const at::Tensor& lengths, int64_t n, const char* name) {
  const int64_t* l = lengths.data_ptr<int64_t>();
  for (int64_t b = 0; b < lengths.numel(); ++b)
    TORCH_CHECK_VALUE(l[b] >= 0 && l[b] <= n, name, "[", b, "] = ", l[b], " is outside [0, ", n, "]");
}

// dtype of the distances returned: the computation dtype (float for half/bfloat16).
inline at::ScalarType dist_dtype(at::ScalarType t) { return t == at::kDouble ? at::kDouble : at::kFloat; }

}  // namespace lidarops
