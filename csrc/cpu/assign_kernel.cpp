// CPU kernel of lidarops::greedy_assign (schema and contract: csrc/ops/assign.cpp).
#include <ATen/core/Tensor.h>
#include <ATen/ops/full.h>

#include <cstdint>
#include <vector>

#include <torch/library.h>

#include "lidarops/assign.h"

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

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) { m.impl("greedy_assign", &greedy_assign_cpu); }

}  // namespace lidarops
