// Streaming pillarization (lidarops.stream): helpers shared by the CPU and CUDA kernels of
// pillar_decorate, pillar_stream_gather and pillar_stream_push (schemas in csrc/ops/pillar_stream.cpp).
//
// State of a stream (all tensors on the stream's device; M = max_pillars, N = max_points_per_pillar):
//   pool_xyzi (M, N, 4) float32, pool_t (M, N) float64: slot s holds one pillar's points as a circular
//     queue, kept sorted by t (ties in arrival order) from head[s] for count[s] points;
//   head, count (M,) int32; slot_cell (M,) int32: the pillar's linear key y * W + x, -1 when free;
//   cell_slot (H * W,) int32: the slot of each pillar, -1 when it is empty;
//   free_slots (M,) int32, num_free (1,) int32: a stack of the free slots (free_slots[0:num_free]);
//   log_cell (L,) int32, log_t (L,) float64: a ring of one (pillar key, t) entry per point in the
//     window, written in runs (one run per push, sorted by t); run r occupies the absolute positions
//     [start_r, end_r) (position p is stored at p % L). The runs' bounds live on the host.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

#include "lidarops/voxelize.h"

namespace lidarops {

// Layout of the stats output of pillar_stream_push (int64).
enum PillarStreamStat : int64_t {
  kPsPointsIn = 0,      // points that entered the window (inside the grid, t > cutoff)
  kPsPointsOut,         // points that left the window (expired)
  kPsPointsOutside,     // pushed points outside the grid (never enter)
  kPsPointsLate,        // pushed points inside the grid with t <= cutoff (never enter)
  kPsOverflow,          // bits kPsOverflow*: a capacity would be exceeded; bits kPsBad*: the state is corrupt
  kPsMaxPointsNeeded,   // most points one touched pillar would hold after the push
  kPsPillarsNeeded,     // active pillars after the push (as if there were no capacity limit)
  kPsNewPillars,        // pillars that were empty and gain points
  kPsEmptied,           // pillars that lose all their points (and gain none)
  kPsTouchedSlots,      // scratch: active pillars that lose points
  kPsSegments,          // scratch: pillars that gain points
  kPsDroppedPoints,     // drop mode: entering points of admitted pillars beyond their queue's room
  kPsDroppedPillars,    // drop mode: entering points of new pillars that found no free slot
  kNumPillarStreamStats
};
enum : int64_t { kPsOverflowPoints = 1, kPsOverflowPillars = 2 };

// State invariants of pillar_stream_push. The state lives on the device, so its values are not read
// on the host: every value the kernels index with is checked where it is read (in the plan, before
// anything is written), an out-of-range value is never used as an index, and the push reports it in
// stats[kPsOverflow] with one of these bits and changes nothing (as for an overflow):
enum : int64_t {
  kPsBadRuns = 4,        // a run [start, end) with start < 0, end < start or end - start > L
  kPsBadLog = 8,         // an expiring log entry names a cell outside [0, H W) or an empty pillar; or, read from
                         // the op's scalars, log_head outside [0, 2^62) or a NaN cutoff
  kPsBadCellSlot = 16,   // cell_slot holds a value outside [-1, M), or cell_slot[c] = s but slot_cell[s] != c
  kPsBadQueue = 32,      // head outside [0, N), count outside [0, N], or more of a queue's points expire
                         // than it holds
  kPsBadNumFree = 64,    // num_free outside [0, M], or the slots freed by the push would overflow the stack
  kPsBadFreeSlots = 128  // a slot the push would pop from free_slots is outside [0, M) or in use
};
constexpr int64_t kPsCorrupt =
    kPsBadRuns | kPsBadLog | kPsBadCellSlot | kPsBadQueue | kPsBadNumFree | kPsBadFreeSlots;
// log_head + (entries of one push) must not overflow int64 (the positions are taken modulo L)
constexpr int64_t kPsMaxLogHead = int64_t(1) << 62;

// A queue (slot) that the kernels may index: 0 <= head < N and 0 <= count <= N.
LIDAROPS_HD bool ps_queue_ok(int32_t head, int32_t count, int64_t N) {
  return head >= 0 && head < N && count >= 0 && count <= N;
}

// The decorated features of one point of a pillar (the PointPillars decoration): x, y, z, intensity,
// offsets to the mean of the pillar's points, offsets x, y to the pillar centre. Computed in double
// with every operation rounded (no contraction), so CPU and CUDA give the same bits; each output is
// rounded once to the output type.
template <typename scalar_t>
LIDAROPS_HD void decorate_point(const scalar_t* p, const double* mean, double cx, double cy, scalar_t* f) {
  const double x = static_cast<double>(p[0]), y = static_cast<double>(p[1]), z = static_cast<double>(p[2]);
  f[0] = p[0];
  f[1] = p[1];
  f[2] = p[2];
  f[3] = p[3];
  f[4] = static_cast<scalar_t>(sub_rn(x, mean[0]));
  f[5] = static_cast<scalar_t>(sub_rn(y, mean[1]));
  f[6] = static_cast<scalar_t>(sub_rn(z, mean[2]));
  f[7] = static_cast<scalar_t>(sub_rn(x, cx));
  f[8] = static_cast<scalar_t>(sub_rn(y, cy));
}

// Pillar centre along one axis: lo + (i + 0.5) * size, rounded after each operation.
LIDAROPS_HD double pillar_centre(double lo, double size, int32_t i) {
  return add_rn(lo, mul_rn(add_rn(static_cast<double>(i), 0.5), size));
}

// Mean of the first n points (4 values each) of a pillar, summed in slot order in double.
template <typename scalar_t>
LIDAROPS_HD void pillar_mean(const scalar_t* pts, int64_t n, double* mean) {
  double s[3] = {0.0, 0.0, 0.0};
  for (int64_t k = 0; k < n; ++k)
    for (int a = 0; a < 3; ++a) s[a] = add_rn(s[a], static_cast<double>(pts[4 * k + a]));
  const double dn = static_cast<double>(n > 0 ? n : 1);
  for (int a = 0; a < 3; ++a) mean[a] = div_rn(s[a], dn);
}

inline void check_pillar_decorate_args(const at::Tensor& raw, const at::Tensor& num_points, const at::Tensor& coords,
                                       at::ArrayRef<double> pillar_size, at::ArrayRef<double> origin) {
  TORCH_CHECK_VALUE(raw.dim() == 3 && raw.size(2) == 4, "raw must be (P, N, 4), got shape ", raw.sizes());
  TORCH_CHECK_VALUE(raw.scalar_type() == at::kFloat || raw.scalar_type() == at::kDouble,
              "raw must be float32 or float64, got ", raw.scalar_type());
  const int64_t P = raw.size(0);
  TORCH_CHECK_VALUE(num_points.dim() == 1 && num_points.size(0) == P && num_points.scalar_type() == at::kInt,
              "num_points must be int32 (P,) with P = ", P, ", got shape ", num_points.sizes(), " dtype ",
              num_points.scalar_type());
  TORCH_CHECK_VALUE(coords.dim() == 2 && coords.size(0) == P && coords.size(1) == 3 && coords.scalar_type() == at::kInt,
              "coords must be int32 (P, 3) with P = ", P, ", got shape ", coords.sizes(), " dtype ",
              coords.scalar_type());
  TORCH_CHECK_VALUE(num_points.device() == raw.device() && coords.device() == raw.device(),
              "num_points and coords must be on the device of raw (", raw.device(), ")");
  TORCH_CHECK_VALUE(pillar_size.size() == 2 && origin.size() == 2, "pillar_size and origin must have 2 values (x, y)");
}

inline void check_pillar_gather_args(const at::Tensor& pool_xyzi, const at::Tensor& head, const at::Tensor& count,
                                     const at::Tensor& cell_slot, const at::Tensor& cells) {
  TORCH_CHECK_VALUE(pool_xyzi.dim() == 3 && pool_xyzi.size(2) == 4 && pool_xyzi.scalar_type() == at::kFloat,
                    "pool_xyzi must be float32 (M, N, 4), got shape ", pool_xyzi.sizes(), " dtype ",
                    pool_xyzi.scalar_type());
  const int64_t M = pool_xyzi.size(0);
  for (const auto* t : {&head, &count})
    TORCH_CHECK_VALUE(t->dim() == 1 && t->size(0) == M && t->scalar_type() == at::kInt,
                "head and count must be int32 (M,) with M = ", M, ", got shape ", t->sizes(), " dtype ",
                t->scalar_type());
  TORCH_CHECK_VALUE(pool_xyzi.size(0) < std::numeric_limits<int32_t>::max() &&
                        pool_xyzi.size(1) < std::numeric_limits<int32_t>::max(),
                    "pool_xyzi must have M, N < 2^31, got ", pool_xyzi.sizes());
  TORCH_CHECK_VALUE(cell_slot.dim() == 1 && cell_slot.scalar_type() == at::kInt,
                    "cell_slot must be int32 (H * W,), got shape ", cell_slot.sizes(), " dtype ", cell_slot.scalar_type());
  TORCH_CHECK_VALUE(cells.dim() == 1 && cells.scalar_type() == at::kLong, "cells must be int64 (P,), got shape ",
                    cells.sizes(), " dtype ", cells.scalar_type());
  for (const auto* t : {&head, &count, &cell_slot, &cells})
    TORCH_CHECK_VALUE(t->device() == pool_xyzi.device(), "every tensor must be on the device of pool_xyzi (",
                      pool_xyzi.device(), "), got ", t->device());
  TORCH_CHECK_VALUE(head.is_contiguous() && count.is_contiguous() && cell_slot.is_contiguous() &&
                        pool_xyzi.is_contiguous(),
                    "the stream state (pool_xyzi, head, count, cell_slot) must be contiguous");
}

struct PillarStreamArgs {
  int64_t M, N, L, H, W;
};

inline PillarStreamArgs check_pillar_stream_push_args(
    const at::Tensor& pool_xyzi, const at::Tensor& pool_t, const at::Tensor& head, const at::Tensor& count,
    const at::Tensor& slot_cell, const at::Tensor& cell_slot, const at::Tensor& free_slots, const at::Tensor& num_free,
    const at::Tensor& log_cell, const at::Tensor& log_t, const at::Tensor& points, const at::Tensor& t,
    const at::Tensor& runs, int64_t log_head, double cutoff, at::ArrayRef<double> point_range,
    at::ArrayRef<double> pillar_size, at::IntArrayRef grid_hw) {
  TORCH_CHECK_VALUE(pool_xyzi.dim() == 3 && pool_xyzi.size(2) == 4 && pool_xyzi.scalar_type() == at::kFloat,
              "pool_xyzi must be float32 (M, N, 4), got shape ", pool_xyzi.sizes(), " dtype ", pool_xyzi.scalar_type());
  PillarStreamArgs a;
  a.M = pool_xyzi.size(0);
  a.N = pool_xyzi.size(1);
  TORCH_CHECK_VALUE(a.M >= 1 && a.N >= 1 && a.M < std::numeric_limits<int32_t>::max() &&
                  a.N < std::numeric_limits<int32_t>::max(),
              "pool_xyzi must have 1 <= M, N < 2^31, got ", pool_xyzi.sizes());
  TORCH_CHECK_VALUE(pool_t.dim() == 2 && pool_t.size(0) == a.M && pool_t.size(1) == a.N && pool_t.scalar_type() == at::kDouble,
              "pool_t must be float64 (M, N), got shape ", pool_t.sizes(), " dtype ", pool_t.scalar_type());
  for (const auto* s : {&head, &count, &slot_cell, &free_slots})
    TORCH_CHECK_VALUE(s->dim() == 1 && s->size(0) == a.M && s->scalar_type() == at::kInt,
                "head, count, slot_cell and free_slots must be int32 (M,) with M = ", a.M, ", got shape ", s->sizes(),
                " dtype ", s->scalar_type());
  TORCH_CHECK_VALUE(grid_hw.size() == 2 && grid_hw[0] >= 1 && grid_hw[1] >= 1 && grid_hw[0] <= kMaxVoxelDim &&
                  grid_hw[1] <= kMaxVoxelDim && grid_hw[0] * grid_hw[1] < std::numeric_limits<int32_t>::max(),
              "grid_hw must be (H, W) with H * W < 2^31, got ", grid_hw);
  a.H = grid_hw[0];
  a.W = grid_hw[1];
  TORCH_CHECK_VALUE(cell_slot.dim() == 1 && cell_slot.size(0) == a.H * a.W && cell_slot.scalar_type() == at::kInt,
              "cell_slot must be int32 (H * W,) = (", a.H * a.W, ",), got shape ", cell_slot.sizes(), " dtype ",
              cell_slot.scalar_type());
  TORCH_CHECK_VALUE(num_free.dim() == 1 && num_free.size(0) == 1 && num_free.scalar_type() == at::kInt,
              "num_free must be int32 (1,), got shape ", num_free.sizes(), " dtype ", num_free.scalar_type());
  TORCH_CHECK_VALUE(log_cell.dim() == 1 && log_cell.scalar_type() == at::kInt && log_t.dim() == 1 &&
                  log_t.scalar_type() == at::kDouble && log_t.size(0) == log_cell.size(0) && log_cell.size(0) >= 1,
              "log_cell (L,) int32 and log_t (L,) float64 must have one length L >= 1, got shapes ", log_cell.sizes(),
              " and ", log_t.sizes());
  a.L = log_cell.size(0);
  TORCH_CHECK_VALUE(points.dim() == 2 && points.size(1) == 4 && points.scalar_type() == at::kFloat,
              "points must be float32 (n, 4), got shape ", points.sizes(), " dtype ", points.scalar_type());
  TORCH_CHECK_VALUE(t.dim() == 1 && t.size(0) == points.size(0) && t.scalar_type() == at::kDouble,
              "t must be float64 (n,) with n = ", points.size(0), ", got shape ", t.sizes(), " dtype ",
              t.scalar_type());
  TORCH_CHECK_VALUE(points.size(0) <= a.L, "a push of ", points.size(0), " points needs a log of at least that length, got ",
              a.L);
  TORCH_CHECK_VALUE(runs.dim() == 2 && runs.size(1) == 2 && runs.scalar_type() == at::kLong,
              "runs must be int64 (R, 2), got shape ", runs.sizes(), " dtype ", runs.scalar_type());
  const at::Tensor* all[] = {&pool_xyzi, &pool_t, &head, &count, &slot_cell, &cell_slot, &free_slots,
                             &num_free, &log_cell, &log_t, &points, &t, &runs};
  const char* names[] = {"pool_xyzi", "pool_t", "head", "count", "slot_cell", "cell_slot", "free_slots",
                         "num_free", "log_cell", "log_t", "points", "t", "runs"};
  for (int i = 0; i < 13; ++i) {
    TORCH_CHECK_VALUE(all[i]->device() == pool_xyzi.device(), names[i], " is on ", all[i]->device(),
                      " but pool_xyzi (the stream state) is on ", pool_xyzi.device());
    // the state is written in place through raw pointers: a strided view would be written wrongly
    TORCH_CHECK_VALUE(i >= 10 || all[i]->is_contiguous(), names[i], " (stream state) must be contiguous");
  }
  TORCH_CHECK_VALUE(log_head >= 0 && log_head < kPsMaxLogHead, "log_head must be in [0, 2^62), got ", log_head);
  TORCH_CHECK_VALUE(!std::isnan(cutoff), "cutoff must not be NaN");
  TORCH_CHECK_VALUE(point_range.size() == 6 && pillar_size.size() == 2, "point_range must have 6 values and pillar_size 2");
  return a;
}

// scalars of pillar_stream_push: int64 (2,) on the state's device (log_head, the bits of cutoff).
inline void check_pillar_stream_scalars(const at::Tensor& scalars, const at::Tensor& pool_xyzi) {
  TORCH_CHECK_VALUE(scalars.dim() == 1 && scalars.size(0) == 2 && scalars.scalar_type() == at::kLong,
                    "scalars must be int64 (2,): log_head and the bits of cutoff (float64), got shape ",
                    scalars.sizes(), " dtype ", scalars.scalar_type());
  TORCH_CHECK_VALUE(scalars.device() == pool_xyzi.device(), "scalars is on ", scalars.device(),
                    " but pool_xyzi (the stream state) is on ", pool_xyzi.device());
}

// The voxel grid of a pillar grid: one cell along z (as pillarize's call of voxelize_assign).
inline VoxelGrid<float> pillar_voxel_grid(at::ArrayRef<double> point_range, at::ArrayRef<double> pillar_size,
                                          const PillarStreamArgs& a) {
  const double vs[3] = {pillar_size[0], pillar_size[1], point_range[5] - point_range[2]};
  const int64_t gs[3] = {a.W, a.H, 1};
  auto g = make_voxel_grid<float>(at::ArrayRef<double>(vs, 3), point_range, at::IntArrayRef(gs, 3));
  check_voxel_grid_in_type(g);
  return g;
}

}  // namespace lidarops
