// Voxel assignment shared by the CPU and CUDA voxelization kernels (and meant for streaming
// pillarization, which must put every point in the same cell as the one-shot pillarize).
//
// A point (x, y, z) belongs to the grid when, on every axis, lo <= x < hi and
// 0 <= floor((x - lo) / size) < dim, all evaluated in the computation type T (float for
// half/bfloat16/float points, double for double) with IEEE rounding after each operation: the
// convention of spconv and mmcv, with the range test made explicit so that x == hi is outside even
// when the division rounds down. NaN and infinite coordinates are outside. The voxel's linear key is
// (cz * dim_y + cy) * dim_x + cx; keys of points outside the grid are kNoVoxel.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

#include "lidarops/common.h"

namespace lidarops {

constexpr int64_t kNoVoxel = -1;
constexpr int64_t kMaxVoxelDim = int64_t(1) << 24;  // cells per axis: exact in float, coords fit int32

// Division rounded to nearest (no approximate reciprocal), identical on CPU and CUDA.
template <typename T>
LIDAROPS_HD T div_rn(T a, T b) {
#ifdef __CUDA_ARCH__
  if constexpr (std::is_same_v<T, double>) return __ddiv_rn(a, b);
  else return __fdiv_rn(a, b);
#else
  return a / b;
#endif
}

template <typename T>
LIDAROPS_HD T floor_t(T a) {
  if constexpr (std::is_same_v<T, double>) return ::floor(a);
  else return ::floorf(a);
}

// Grid parameters in the computation type; trivially copyable, passed by value to CUDA kernels.
template <typename T>
struct VoxelGrid {
  T lo[3], hi[3], size[3];  // x, y, z; hi may be +inf (only the cell test then bounds the grid)
  int64_t dims[3];          // cells along x, y, z
};

template <typename T>
VoxelGrid<T> make_voxel_grid(at::ArrayRef<double> voxel_size, at::ArrayRef<double> point_range,
                             at::IntArrayRef grid_size) {
  VoxelGrid<T> g;
  for (int a = 0; a < 3; ++a) {
    g.lo[a] = static_cast<T>(point_range[a]);
    g.hi[a] = static_cast<T>(point_range[a + 3]);
    g.size[a] = static_cast<T>(voxel_size[a]);
    g.dims[a] = grid_size[a];
  }
  return g;
}

// Cell index of coordinate x along axis a, or -1 when outside.
template <typename T>
LIDAROPS_HD int64_t voxel_cell(const VoxelGrid<T>& g, int a, T x) {
  if (!(x >= g.lo[a] && x < g.hi[a])) return -1;  // also rejects NaN
  const T c = floor_t(div_rn(sub_rn(x, g.lo[a]), g.size[a]));
  if (!(c >= T(0) && c < static_cast<T>(g.dims[a]))) return -1;
  return static_cast<int64_t>(c);
}

template <typename T>
LIDAROPS_HD int64_t voxel_key(const VoxelGrid<T>& g, T x, T y, T z) {
  const int64_t cx = voxel_cell(g, 0, x), cy = voxel_cell(g, 1, y), cz = voxel_cell(g, 2, z);
  if (cx < 0 || cy < 0 || cz < 0) return kNoVoxel;
  return (cz * g.dims[1] + cy) * g.dims[0] + cx;
}

// Key -> (z, y, x), the coords layout of spconv and OpenPCDet.
LIDAROPS_HD void voxel_key_to_zyx(int64_t key, const int64_t* dims, int32_t* zyx) {
  zyx[2] = static_cast<int32_t>(key % dims[0]);
  key /= dims[0];
  zyx[1] = static_cast<int32_t>(key % dims[1]);
  zyx[0] = static_cast<int32_t>(key / dims[1]);
}

// Layout of the stats output of voxelize_assign (int64).
enum VoxelStat : int64_t {
  kStatVoxels = 0,          // voxels kept: min(needed, max_voxels)
  kStatVoxelsNeeded,        // distinct voxels holding at least one point in the grid
  kStatPointsInGrid,        // points inside the grid
  kStatDroppedMaxVoxels,    // points of the voxels beyond max_voxels (first-seen order)
  kStatDroppedMaxPoints,    // points beyond max_points_per_voxel in the kept voxels
  kStatMaxPointsInVoxel,    // largest number of points in one voxel (kept or not)
  kStatOverfullVoxels,      // kept voxels holding more than max_points_per_voxel points
  kNumVoxelStats
};

// Argument checks shared by the CPU and CUDA kernels (shapes, dtypes and parameters; no data).
inline void check_voxelize_assign_args(const at::Tensor& points, at::ArrayRef<double> voxel_size,
                                       at::ArrayRef<double> point_range, at::IntArrayRef grid_size,
                                       int64_t max_points_per_voxel, int64_t max_voxels, int64_t method) {
  TORCH_CHECK_VALUE(points.dim() == 2 && points.size(1) >= 3, "points must be (N, C) with C >= 3, got shape ",
                    points.sizes());
  TORCH_CHECK_VALUE(at::isFloatingType(points.scalar_type()), "points must be a floating tensor, got ",
                    points.scalar_type());
  TORCH_CHECK_VALUE(voxel_size.size() == 3, "voxel_size must have 3 values (x, y, z), got ", voxel_size.size());
  TORCH_CHECK_VALUE(point_range.size() == 6, "point_range must have 6 values (x0, y0, z0, x1, y1, z1), got ",
                    point_range.size());
  TORCH_CHECK_VALUE(grid_size.size() == 3, "grid_size must have 3 values (x, y, z), got ", grid_size.size());
  double cells = 1.0;
  for (int a = 0; a < 3; ++a) {
    TORCH_CHECK_VALUE(std::isfinite(voxel_size[a]) && voxel_size[a] > 0.0, "voxel_size must be finite and positive, got ",
                      voxel_size);
    TORCH_CHECK_VALUE(std::isfinite(point_range[a]) && !std::isnan(point_range[a + 3]) &&
                          point_range[a + 3] > point_range[a],
                      "point_range must be (x0, y0, z0, x1, y1, z1) with finite lower bounds below the upper ones, got ",
                      point_range);
    TORCH_CHECK_VALUE(grid_size[a] >= 1 && grid_size[a] <= kMaxVoxelDim, "grid_size must lie in [1, 2^24] per axis, got ",
                      grid_size);
    cells *= static_cast<double>(grid_size[a]);
  }
  TORCH_CHECK_VALUE(cells < 4.6e18, "grid of ", grid_size, " cells is too large for int64 keys");
  TORCH_CHECK_VALUE(max_points_per_voxel >= 1 && max_points_per_voxel <= std::numeric_limits<int32_t>::max(),
                    "max_points_per_voxel must lie in [1, 2^31), got ", max_points_per_voxel);
  TORCH_CHECK_VALUE(max_voxels >= 1 && max_voxels <= std::numeric_limits<int32_t>::max(),
                    "max_voxels must lie in [1, 2^31), got ", max_voxels);
  TORCH_CHECK_VALUE(method >= 0 && method <= 2, "method must be 0 (auto), 1 (dense table) or 2 (hash table), got ", method);
}

template <typename T>
void check_voxel_grid_in_type(const VoxelGrid<T>& g) {
  for (int a = 0; a < 3; ++a)
    TORCH_CHECK_VALUE(std::isfinite(static_cast<double>(g.size[a])) && g.size[a] > T(0) &&
                          std::isfinite(static_cast<double>(g.lo[a])),
                      "voxel_size and point_range must stay finite and positive in the computation dtype");
}

inline void check_voxelize_scatter_args(const at::Tensor& features, const at::Tensor& point_voxel,
                                        const at::Tensor& point_slot, int64_t num_voxels,
                                        int64_t max_points_per_voxel) {
  TORCH_CHECK_VALUE(features.dim() == 2, "features must be (N, C), got shape ", features.sizes());
  TORCH_CHECK_VALUE(at::isFloatingType(features.scalar_type()), "features must be a floating tensor, got ",
                    features.scalar_type());
  const int64_t N = features.size(0);
  TORCH_CHECK_VALUE(point_voxel.dim() == 1 && point_voxel.size(0) == N && point_voxel.scalar_type() == at::kLong,
                    "point_voxel must be int64 (N,) with N = ", N, ", got shape ", point_voxel.sizes(), " dtype ",
                    point_voxel.scalar_type());
  TORCH_CHECK_VALUE(point_slot.dim() == 1 && point_slot.size(0) == N && point_slot.scalar_type() == at::kLong,
                    "point_slot must be int64 (N,) with N = ", N, ", got shape ", point_slot.sizes(), " dtype ",
                    point_slot.scalar_type());
  TORCH_CHECK_VALUE(point_voxel.device() == features.device() && point_slot.device() == features.device(),
                    "point_voxel and point_slot must be on the device of features (", features.device(), ")");
  TORCH_CHECK_VALUE(num_voxels >= 0, "num_voxels must be >= 0, got ", num_voxels);
  TORCH_CHECK_VALUE(max_points_per_voxel >= 1, "max_points_per_voxel must be >= 1, got ", max_points_per_voxel);
}

}  // namespace lidarops
