// gather (grouping) and its adjoint, scatter-add, on CPU.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>

#include <cstring>

#include "lidarops/common.h"

namespace lidarops {
namespace {

void check_gather_args(const at::Tensor& x, const at::Tensor& idx, const char* xname) {
  TORCH_CHECK_VALUE(x.dim() == 3, xname, " must be (B, N, C), got shape ", x.sizes());
  TORCH_CHECK_VALUE(idx.dim() == 2 && idx.size(0) == x.size(0), "idx must be (B, L) with B = ", x.size(0),
                    ", got shape ", idx.sizes());
  TORCH_CHECK_VALUE(idx.scalar_type() == at::kLong, "idx must be int64, got ", idx.scalar_type());
  TORCH_CHECK_VALUE(idx.device() == x.device(), "idx is on ", idx.device(), " but ", xname, " is on ", x.device());
}

void check_index_values(const at::Tensor& idx, int64_t n) {
  const int64_t* ip = idx.data_ptr<int64_t>();
  const int64_t total = idx.numel();
  int64_t bad = -1;
  for (int64_t t = 0; t < total && bad < 0; ++t)
    if (ip[t] < -1 || ip[t] >= n) bad = t;
  TORCH_CHECK_VALUE(bad < 0, "idx must lie in [-1, ", n, "), got ", bad < 0 ? 0 : ip[bad], " at flat position ", bad);
}

at::Tensor gather_cpu(const at::Tensor& x_in, const at::Tensor& idx_in) {
  check_gather_args(x_in, idx_in, "x");
  auto x = x_in.contiguous();
  auto idx = idx_in.contiguous();
  const int64_t B = x.size(0), N = x.size(1), C = x.size(2), L = idx.size(1);
  check_index_values(idx, N);
  auto out = at::empty({B, L, C}, x.options());
  if (out.numel() == 0) return out;
  const int64_t row_bytes = C * static_cast<int64_t>(x.element_size());
  const char* xp = static_cast<const char*>(x.data_ptr());
  char* op = static_cast<char*>(out.data_ptr());
  const int64_t* ip = idx.data_ptr<int64_t>();
  at::parallel_for(0, B * L, std::max<int64_t>(1, 32768 / std::max<int64_t>(row_bytes, 1)), [&](int64_t s, int64_t e) {
    for (int64_t t = s; t < e; ++t) {
      const int64_t j = ip[t];
      char* dst = op + t * row_bytes;
      if (j < 0) std::memset(dst, 0, row_bytes);
      else std::memcpy(dst, xp + ((t / L) * N + j) * row_bytes, row_bytes);
    }
  });
  return out;
}

at::Tensor gather_backward_cpu(const at::Tensor& grad_in, const at::Tensor& idx_in, int64_t n) {
  check_gather_args(grad_in, idx_in, "grad");
  TORCH_CHECK_VALUE(grad_in.size(1) == idx_in.size(1), "grad must be (B, L, C) with L = ", idx_in.size(1),
                    ", got shape ", grad_in.sizes());
  TORCH_CHECK_VALUE(n >= 0, "n must be >= 0, got ", n);
  TORCH_CHECK_VALUE(at::isFloatingType(grad_in.scalar_type()), "grad must be floating, got ", grad_in.scalar_type());
  auto grad = grad_in.contiguous();
  auto idx = idx_in.contiguous();
  const int64_t B = grad.size(0), L = grad.size(1), C = grad.size(2);
  check_index_values(idx, n);
  auto acc_dtype = grad.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  auto acc = at::zeros({B, n, C}, grad.options().dtype(acc_dtype));
  if (acc.numel() == 0 || L == 0) return acc.to(grad.scalar_type());
  const int64_t* ip = idx.data_ptr<int64_t>();
  // Parallel over (cloud, channel block): each task owns its output columns, so no races, and sums
  // are taken in index order, so results are deterministic.
  constexpr int64_t kCB = 16;
  const int64_t nblk = (C + kCB - 1) / kCB;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, grad.scalar_type(), "lidarops_gather_backward_cpu", [&] {
    using T = acc_t<scalar_t>;
    const scalar_t* gp = grad.data_ptr<scalar_t>();
    T* ap = acc.data_ptr<T>();
    at::parallel_for(0, B * nblk, std::max<int64_t>(1, 32768 / std::max<int64_t>(L * kCB, 1)), [&](int64_t s, int64_t e) {
      for (int64_t task = s; task < e; ++task) {
        const int64_t b = task / nblk, c0 = (task % nblk) * kCB, c1 = std::min(C, c0 + kCB);
        for (int64_t l = 0; l < L; ++l) {
          const int64_t j = ip[b * L + l];
          if (j < 0) continue;
          const scalar_t* g = gp + (b * L + l) * C;
          T* a = ap + (b * n + j) * C;
          for (int64_t c = c0; c < c1; ++c) a[c] += static_cast<T>(g[c]);
        }
      }
    });
  });
  return acc.scalar_type() == grad.scalar_type() ? acc : acc.to(grad.scalar_type());
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("gather", &gather_cpu);
  m.impl("gather_backward", &gather_backward_cpu);
}

}  // namespace lidarops
