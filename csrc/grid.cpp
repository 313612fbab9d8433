#include "lidarops/grid.h"

namespace lidarops {

namespace {
constexpr double kMaxCellsPerAxis = 1048576.0;  // 2^20: keys stay below 2^60

// Per-cloud bounding box of the valid points; (0, 0) for empty clouds.
// Box of the finite coordinates of the valid points; (0, 0) on axes with none (the wrappers reject
// NaN/inf; with their value checks off, non-finite points land in clamped edge cells).
std::pair<at::Tensor, at::Tensor> bounding_box(const at::Tensor& p, const at::Tensor& valid) {
  const double inf = std::numeric_limits<double>::infinity();
  auto v = valid.unsqueeze(-1) & at::isfinite(p);
  auto lo = at::where(v, p, inf).amin(1);
  auto hi = at::where(v, p, -inf).amax(1);
  auto ok = lo <= hi;
  return {at::where(ok, lo, 0.0), at::where(ok, hi, 0.0)};
}

at::Tensor valid_mask(const at::Tensor& points, const at::Tensor& lengths) {
  auto ar = at::arange(points.size(1), lengths.options());
  return ar.unsqueeze(0) < lengths.unsqueeze(1);
}
}  // namespace

at::Tensor knn_cell_size(const at::Tensor& points, const at::Tensor& lengths, int64_t k) {
  auto p = points.to(at::kDouble);
  auto [lo, hi] = bounding_box(p, valid_mask(points, lengths));
  auto ext = hi - lo;
  // Flat or line-like clouds (LiDAR ground, a wall) have near-zero volume: floor each extent.
  auto floor_ext = ext.amax(1, true) * 1e-2 + 1e-6;
  auto vol = at::maximum(ext, floor_ext).prod(1);
  auto n = lengths.to(at::kDouble).clamp_min(1.0);
  return at::pow(vol * (static_cast<double>(std::max<int64_t>(k, 2)) * 0.5) / n, 1.0 / 3.0);
}

Grid build_grid(const at::Tensor& points, const at::Tensor& lengths, const at::Tensor& cell_size) {
  const int64_t N = points.size(1);
  auto p = points.to(at::kDouble);
  auto valid = valid_mask(points, lengths);
  auto [lo, hi] = bounding_box(p, valid);
  auto ext = hi - lo;
  auto cell = at::maximum(cell_size.to(at::kDouble), ext.amax(1) / (kMaxCellsPerAxis - 1.0)).clamp_min(1e-9);
  auto dims = (at::floor(ext / cell.unsqueeze(1)) + 1.0).clamp(1.0, kMaxCellsPerAxis).to(at::kLong);
  auto c = at::floor((p - lo.unsqueeze(1)) / cell.view({-1, 1, 1})).nan_to_num(0.0).clamp_min(0.0);
  c = at::minimum(c, (dims - 1).unsqueeze(1).to(at::kDouble)).to(at::kLong);
  auto dx = dims.select(1, 0).unsqueeze(1), dy = dims.select(1, 1).unsqueeze(1);
  auto key = (c.select(2, 2) * dy + c.select(2, 1)) * dx + c.select(2, 0);
  key = at::where(valid, key, std::numeric_limits<int64_t>::max());
  auto [sorted, order] = key.sort(/*stable=*/true, /*dim=*/1, /*descending=*/false);
  const auto ct = points.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  auto sorted_points = points.to(ct).gather(1, order.unsqueeze(-1).expand({points.size(0), N, 3})).contiguous();
  return Grid{lo.contiguous(), cell.contiguous(), dims.contiguous(), sorted.contiguous(), order.contiguous(),
              at::Tensor(), sorted_points};
}

}  // namespace lidarops
