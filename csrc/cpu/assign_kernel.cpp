// CPU kernels of lidarops::greedy_assign and lidarops::fill_repeats (schemas and contracts: csrc/ops/assign.cpp).
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/full.h>

#include <cstdint>
#include <limits>
#include <vector>

#include <torch/library.h>

#include "lidarops/assign.h"
#include "lidarops/common.h"

namespace lidarops {
namespace {

at::Tensor greedy_assign_cpu(const at::Tensor& rows_in, const at::Tensor& cols_in, int64_t num_rows,
                             int64_t num_cols, int64_t limit) {
  check_greedy_assign_args(rows_in, cols_in, num_rows, num_cols, limit);
  auto rows = rows_in.contiguous();
  auto cols = cols_in.contiguous();
  const int64_t L = rows.size(0);
  const int64_t* rp = rows.data_ptr<int64_t>();
  const int64_t* cp = cols.data_ptr<int64_t>();
  for (int64_t i = 0; i < L; ++i) {
    TORCH_CHECK_VALUE(rp[i] >= 0 && rp[i] < num_rows, "greedy_assign: rows[", i, "] = ", rp[i],
                      " is outside [0, num_rows=", num_rows, ")");
    TORCH_CHECK_VALUE(cp[i] >= 0 && cp[i] < num_cols, "greedy_assign: cols[", i, "] = ", cp[i],
                      " is outside [0, num_cols=", num_cols, ")");
  }
  auto out = at::full({num_rows}, -1, rows.options());
  int64_t* op = out.data_ptr<int64_t>();
  std::vector<char> taken(static_cast<size_t>(num_cols), 0);
  int64_t assigned = 0;
  for (int64_t i = 0; i < L && assigned < limit; ++i) {
    const int64_t r = rp[i], c = cp[i];
    if (op[r] >= 0 || taken[c]) continue;
    op[r] = c;
    taken[c] = 1;
    ++assigned;
  }
  return out;
}

template <typename T>
void fill_repeats_loop(const T* pts, int64_t n, const int64_t* ip, int64_t m, int64_t* op) {
  constexpr int32_t kFree = std::numeric_limits<int32_t>::max();
  std::vector<int32_t> holder(static_cast<size_t>(n), kFree);  // the first row holding each point
  for (int64_t r = m - 1; r >= 0; --r) holder[ip[r]] = static_cast<int32_t>(r);
  for (int64_t r = 0; r < m; ++r) {
    const int64_t i = ip[r];
    if (holder[i] == r) continue;  // its point's first row
    const double x = pts[3 * i], y = pts[3 * i + 1], z = pts[3 * i + 2];
    double best = std::numeric_limits<double>::infinity();
    int64_t at = -1;
    for (int64_t j = 0; j < n; ++j) {
      if (holder[j] != kFree) continue;
      const double d = sqdist3<double>(x, y, z, pts[3 * j], pts[3 * j + 1], pts[3 * j + 2]);
      if (d < best || at < 0) best = d, at = j;  // strictly nearer: ties keep the lower index
    }
    if (at < 0) continue;  // no free point (m > n): the repeat stays
    op[r] = at;
    holder[at] = static_cast<int32_t>(r);
  }
}

at::Tensor fill_repeats_cpu(const at::Tensor& points, const at::Tensor& idx_in) {
  check_fill_repeats_args(points, idx_in);
  auto idx = idx_in.contiguous();
  const int64_t n = points.size(0), m = idx.size(0);
  const int64_t* ip = idx.data_ptr<int64_t>();
  for (int64_t r = 0; r < m; ++r)
    TORCH_CHECK_VALUE(ip[r] >= 0 && ip[r] < n, "fill_repeats: idx[", r, "] = ", ip[r], " is outside [0, n=", n, ")");
  auto out = idx.clone();
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "fill_repeats_cpu", [&] {
    fill_repeats_loop<scalar_t>(points.data_ptr<scalar_t>(), n, ip, m, out.data_ptr<int64_t>());
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("greedy_assign", &greedy_assign_cpu);
  m.impl("fill_repeats", &fill_repeats_cpu);
}

}  // namespace lidarops
