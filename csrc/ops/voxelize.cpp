// Schemas of the voxelization ops. Kernels: csrc/cpu/voxelize_kernel.cpp, csrc/cuda/voxelize_kernel.cu;
// fake kernels and autograd: lidarops/ops/_voxelize_registrations.py; wrapper: lidarops/ops/voxelize.py.
//
// Voxelization is split in two shape-static ops so that nothing in them reads data back to the host
// (CUDA-graph capturable, torch.compile traceable): the assignment, whose outputs are padded to
// max_voxels, and the scatter of point features into a [num_voxels, P, C] tensor, whose size is an
// argument. The wrapper reads the count of voxels (one host sync) and scatters exactly that many.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(lidarops, m) {
  // points (N, C >= 3) float, x/y/z in columns 0..2; voxel_size (x, y, z); point_range
  // (x0, y0, z0, x1, y1, z1), upper bounds may be +inf; grid_size (x, y, z) cells. A point is in the grid
  // when lo <= p < hi and 0 <= floor((p - lo) / size) < grid_size on every axis (computation dtype).
  // Voxels are numbered in first-seen order (order of their first point); the first
  // max_points_per_voxel points of a voxel in input order fill its slots; voxels beyond max_voxels
  // and points beyond max_points_per_voxel are dropped and counted.
  // Returns
  //   coords (max_voxels, 3) int32 (z, y, x), rows >= V are -1;
  //   num_points (max_voxels,) int32, min(points in the voxel, max_points_per_voxel), 0 beyond V;
  //   point_voxel (N,) int64: the voxel of each point if that voxel was kept, else -1;
  //   point_slot (N,) int64: the point's slot in its voxel, -1 if it was not stored;
  //   stats (7,) int64: voxels kept V, voxels needed, points in the grid, points dropped by
  //     max_voxels, points dropped by max_points_per_voxel, largest points in one voxel, kept voxels
  //     holding more than max_points_per_voxel points.
  // method: 0 auto, 1 dense cell table, 2 hash table (CPU; CUDA has one sort-based path). Same result.
  m.def(
      "voxelize_assign(Tensor points, float[3] voxel_size, float[6] point_range, int[3] grid_size,"
      " int max_points_per_voxel, int max_voxels, int method=0)"
      " -> (Tensor coords, Tensor num_points, Tensor point_voxel, Tensor point_slot, Tensor stats)");
  // features (N, C) -> voxels (num_voxels, max_points_per_voxel, C), zeros where no point was stored:
  // voxels[point_voxel[i], point_slot[i]] = features[i] for point_voxel[i] in [0, num_voxels) and
  // point_slot[i] in [0, max_points_per_voxel); other entries are skipped (both devices), so a direct
  // call never writes out of bounds. (voxel, slot) pairs must be unique (as assigned; of duplicates, one
  // writer wins). Shapes, dtypes and devices: ValueError.
  m.def(
      "voxelize_scatter(Tensor features, Tensor point_voxel, Tensor point_slot, int num_voxels,"
      " int max_points_per_voxel) -> Tensor");
}
