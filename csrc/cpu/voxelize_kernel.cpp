// Voxelization on CPU.
//
// voxelize_assign: the voxel key of every point in parallel, then one sequential pass over the points
// in input order that numbers the voxels as they are first seen and hands out slots (a dense cell
// table when the grid is not much larger than the cloud, e.g. every pillar grid, a hash table
// otherwise). The sequential pass is what defines the result, so it is deterministic; it does one
// table lookup per point. voxelize_scatter: independent row copies, in parallel.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/full.h>
#include <ATen/ops/zeros.h>

#include <algorithm>
#include <cstring>
#include <vector>

#include "lidarops/voxelize.h"

namespace lidarops {
namespace {

enum : int64_t { kVoxMethodAuto = 0, kVoxMethodDense = 1, kVoxMethodHash = 2 };

// Voxel key -> first-seen number: open addressing, linear probing, capacity >= 2 n.
class VoxelHashTable {
 public:
  explicit VoxelHashTable(int64_t n) {
    uint64_t cap = 16;
    while (cap < static_cast<uint64_t>(2 * n)) cap <<= 1;
    mask_ = cap - 1;
    keys_.assign(cap, kNoVoxel);
    vals_.resize(cap);
  }
  // The number stored for key; stores `fresh` if the key is new.
  int64_t find_or_insert(int64_t key, int64_t fresh) {
    uint64_t h = mix(static_cast<uint64_t>(key)) & mask_;
    while (true) {
      const int64_t k = keys_[h];
      if (k == key) return vals_[h];
      if (k == kNoVoxel) {
        keys_[h] = key;
        vals_[h] = fresh;
        return fresh;
      }
      h = (h + 1) & mask_;
    }
  }

 private:
  static uint64_t mix(uint64_t x) {  // splitmix64 finalizer: neighbouring cells spread over the table
    x ^= x >> 30;
    x *= 0xbf58476d1ce4e5b9ULL;
    x ^= x >> 27;
    x *= 0x94d049bb133111ebULL;
    return x ^ (x >> 31);
  }
  uint64_t mask_;
  std::vector<int64_t> keys_;
  std::vector<int64_t> vals_;
};

// Voxel key -> first-seen number through one int32 per grid cell.
class VoxelDenseTable {
 public:
  explicit VoxelDenseTable(int64_t cells) : cell_(cells, -1) {}
  int64_t find_or_insert(int64_t key, int64_t fresh) {
    int32_t& v = cell_[key];
    if (v < 0) v = static_cast<int32_t>(fresh);
    return v;
  }

 private:
  std::vector<int32_t> cell_;
};

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> voxelize_assign_cpu(
    const at::Tensor& points_in, at::ArrayRef<double> voxel_size, at::ArrayRef<double> point_range,
    at::IntArrayRef grid_size, int64_t max_points_per_voxel, int64_t max_voxels, int64_t method) {
  check_voxelize_assign_args(points_in, voxel_size, point_range, grid_size, max_points_per_voxel, max_voxels,
                             method);
  const int64_t cells = grid_size[0] * grid_size[1] * grid_size[2];
  TORCH_CHECK_VALUE(method != kVoxMethodDense || cells <= std::numeric_limits<int32_t>::max(),
                    "method 1 (dense table) needs a grid of fewer than 2^31 cells, got ", cells);
  auto points = points_in.contiguous();
  const int64_t N = points.size(0), C = points.size(1), P = max_points_per_voxel;
  const auto i32 = points.options().dtype(at::kInt), i64 = points.options().dtype(at::kLong);
  auto coords = at::full({max_voxels, 3}, -1, i32);
  auto num_points = at::zeros({max_voxels}, i32);
  auto point_voxel = at::empty({N}, i64);
  auto point_slot = at::empty({N}, i64);
  auto stats = at::zeros({kNumVoxelStats}, i64);

  std::vector<int64_t> keys(N);
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, points.scalar_type(), "lidarops_voxelize_assign_cpu", [&] {
    using T = acc_t<scalar_t>;
    const VoxelGrid<T> g = make_voxel_grid<T>(voxel_size, point_range, grid_size);
    check_voxel_grid_in_type(g);
    const scalar_t* p = points.data_ptr<scalar_t>();
    at::parallel_for(0, N, 4096, [&](int64_t s, int64_t e) {
      for (int64_t i = s; i < e; ++i) {
        const scalar_t* q = p + i * C;
        keys[i] = voxel_key(g, static_cast<T>(q[0]), static_cast<T>(q[1]), static_cast<T>(q[2]));
      }
    });
  });
  if (N == 0) return {coords, num_points, point_voxel, point_slot, stats};

  // Sequential first-seen pass: voxel u is the u-th distinct voxel in input order; a point takes the
  // next slot of its voxel.
  std::vector<int64_t> count, first_key;
  int64_t* pv = point_voxel.data_ptr<int64_t>();
  int64_t* ps = point_slot.data_ptr<int64_t>();
  auto first_seen_pass = [&](auto& table) {
    for (int64_t i = 0; i < N; ++i) {
      const int64_t k = keys[i];
      if (k == kNoVoxel) {
        pv[i] = -1;
        ps[i] = -1;
        continue;
      }
      const int64_t fresh = static_cast<int64_t>(count.size());
      const int64_t u = table.find_or_insert(k, fresh);
      if (u == fresh) {
        count.push_back(0);
        first_key.push_back(k);
      }
      const int64_t s = count[u]++;
      const bool kept = u < max_voxels;
      pv[i] = kept ? u : -1;
      ps[i] = kept && s < P ? s : -1;
    }
  };
  const bool dense = method == kVoxMethodDense ||
                     (method == kVoxMethodAuto && cells <= 8 * N + 65536 && N <= std::numeric_limits<int32_t>::max());
  if (dense) {
    VoxelDenseTable table(cells);
    first_seen_pass(table);
  } else {
    VoxelHashTable table(N);
    first_seen_pass(table);
  }

  const int64_t U = static_cast<int64_t>(count.size()), V = std::min(U, max_voxels);
  int32_t* cp = coords.data_ptr<int32_t>();
  int32_t* np = num_points.data_ptr<int32_t>();
  int64_t in_grid = 0, dropped_voxels = 0, dropped_points = 0, fullest = 0, overfull = 0;
  for (int64_t u = 0; u < U; ++u) {
    const int64_t c = count[u];
    in_grid += c;
    fullest = std::max(fullest, c);
    if (u < V) {
      voxel_key_to_zyx(first_key[u], grid_size.data(), cp + 3 * u);
      np[u] = static_cast<int32_t>(std::min(c, P));
      if (c > P) {
        dropped_points += c - P;
        ++overfull;
      }
    } else {
      dropped_voxels += c;
    }
  }
  int64_t* st = stats.data_ptr<int64_t>();
  st[kStatVoxels] = V;
  st[kStatVoxelsNeeded] = U;
  st[kStatPointsInGrid] = in_grid;
  st[kStatDroppedMaxVoxels] = dropped_voxels;
  st[kStatDroppedMaxPoints] = dropped_points;
  st[kStatMaxPointsInVoxel] = fullest;
  st[kStatOverfullVoxels] = overfull;
  return {coords, num_points, point_voxel, point_slot, stats};
}

at::Tensor voxelize_scatter_cpu(const at::Tensor& features_in, const at::Tensor& point_voxel_in,
                                const at::Tensor& point_slot_in, int64_t num_voxels, int64_t max_points_per_voxel) {
  check_voxelize_scatter_args(features_in, point_voxel_in, point_slot_in, num_voxels, max_points_per_voxel);
  auto features = features_in.contiguous();
  auto point_voxel = point_voxel_in.contiguous();
  auto point_slot = point_slot_in.contiguous();
  const int64_t N = features.size(0), C = features.size(1), P = max_points_per_voxel;
  auto out = at::zeros({num_voxels, P, C}, features.options());
  if (out.numel() == 0 || N == 0) return out;
  const int64_t row_bytes = C * static_cast<int64_t>(features.element_size());
  const char* fp = static_cast<const char*>(features.data_ptr());
  char* op = static_cast<char*>(out.data_ptr());
  const int64_t* pv = point_voxel.data_ptr<int64_t>();
  const int64_t* ps = point_slot.data_ptr<int64_t>();
  at::parallel_for(0, N, 4096, [&](int64_t s, int64_t e) {
    for (int64_t i = s; i < e; ++i) {
      const int64_t v = pv[i], k = ps[i];
      if (v >= 0 && v < num_voxels && k >= 0 && k < P) std::memcpy(op + (v * P + k) * row_bytes, fp + i * row_bytes, row_bytes);
    }
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("voxelize_assign", &voxelize_assign_cpu);
  m.impl("voxelize_scatter", &voxelize_scatter_cpu);
}

}  // namespace lidarops
