// Argument checks shared by the CPU and CUDA kernels of lidarops::greedy_assign and lidarops::fill_repeats
// (csrc/ops/assign.cpp).
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

#include <cstdint>

namespace lidarops {

inline void check_greedy_assign_args(const at::Tensor& rows, const at::Tensor& cols, int64_t num_rows,
                                     int64_t num_cols, int64_t limit) {
  TORCH_CHECK_VALUE(rows.dim() == 1 && cols.dim() == 1 && rows.size(0) == cols.size(0),
                    "greedy_assign: rows and cols must be 1-D of one length, got ", rows.sizes(), " and ",
                    cols.sizes());
  TORCH_CHECK_VALUE(rows.scalar_type() == at::kLong && cols.scalar_type() == at::kLong,
                    "greedy_assign: rows and cols must be int64, got ", rows.scalar_type(), " and ",
                    cols.scalar_type());
  TORCH_CHECK_VALUE(rows.device() == cols.device(), "greedy_assign: rows is on ", rows.device(),
                    " but cols is on ", cols.device());
  TORCH_CHECK_VALUE(num_rows >= 0 && num_cols >= 0 && limit >= 0,
                    "greedy_assign: num_rows, num_cols and limit must be >= 0, got ", num_rows, ", ", num_cols,
                    ", ", limit);
}

inline void check_fill_repeats_args(const at::Tensor& points, const at::Tensor& idx) {
  TORCH_CHECK_VALUE(points.dim() == 2 && points.size(1) == 3 && points.is_contiguous() &&
                        (points.scalar_type() == at::kFloat || points.scalar_type() == at::kDouble),
                    "fill_repeats: points must be a contiguous (n, 3) float32 or float64 tensor, got ",
                    points.sizes(), " ", points.scalar_type());
  TORCH_CHECK_VALUE(idx.dim() == 1 && idx.scalar_type() == at::kLong, "fill_repeats: idx must be 1-D int64, got ",
                    idx.sizes(), " ", idx.scalar_type());
  TORCH_CHECK_VALUE(points.device() == idx.device(), "fill_repeats: points is on ", points.device(),
                    " but idx is on ", idx.device());
  TORCH_CHECK_VALUE(points.size(0) < (int64_t{1} << 31) - 1 && idx.size(0) < (int64_t{1} << 31) - 1,
                    "fill_repeats: at most 2^31 - 2 points and picks, got ", points.size(0), " and ", idx.size(0));
}

}  // namespace lidarops
