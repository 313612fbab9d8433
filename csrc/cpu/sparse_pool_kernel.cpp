// Sparse max pooling on CPU: the maximum over the inputs of each output's kernel window (absent sites
// do not take part, unlike zeros). Ties go to the first kernel offset; NaN propagates. The backward
// runs over input rows through the transposed kernel map, so it needs no atomics and is deterministic.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/full.h>
#include <ATen/ops/zeros.h>

#include <cmath>

#include "lidarops/sparse.h"

namespace lidarops {
namespace sparse {
namespace {

template <typename T>
bool is_nan(T v) {
  return v != v;
}

std::tuple<at::Tensor, at::Tensor> sparse_max_pool_cpu(const at::Tensor& features_in, const at::Tensor& nbr_in) {
  check_pool_args(features_in, nbr_in);
  auto x = features_in.contiguous();
  auto nbr = nbr_in.contiguous();
  const int64_t n_in = x.size(0), C = x.size(1), m = nbr.size(0), K = nbr.size(1);
  auto out = at::zeros({m, C}, x.options());
  auto arg = at::full({m, C}, -1, x.options().dtype(at::kLong));
  if (m == 0 || C == 0 || K == 0) return {out, arg};
  const int32_t* np = nbr.data_ptr<int32_t>();
  for (int64_t t = 0; t < m * K; ++t)
    TORCH_CHECK_VALUE(np[t] >= -1 && np[t] < n_in, "kernel_map entries must lie in [-1, N_in = ", n_in, "), got ",
                      np[t], " at row ", t / K, ", offset ", t % K);
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, x.scalar_type(), "lidarops_sparse_max_pool_cpu", [&] {
    const scalar_t* xp = x.data_ptr<scalar_t>();
    scalar_t* op = out.data_ptr<scalar_t>();
    int64_t* ap = arg.data_ptr<int64_t>();
    at::parallel_for(0, m, std::max<int64_t>(1, 4096 / (K * C)), [&](int64_t s, int64_t e) {
      for (int64_t o = s; o < e; ++o) {
        scalar_t* best = op + o * C;
        int64_t* besti = ap + o * C;
        for (int64_t k = 0; k < K; ++k) {
          const int64_t i = np[o * K + k];
          if (i < 0) continue;
          const scalar_t* v = xp + i * C;
          for (int64_t c = 0; c < C; ++c) {
            if (besti[c] < 0 || (!is_nan(best[c]) && !(v[c] <= best[c]))) {
              best[c] = v[c];
              besti[c] = i;
            }
          }
        }
      }
    });
  });
  return {out, arg};
}

at::Tensor sparse_max_pool_backward_cpu(const at::Tensor& grad_in, const at::Tensor& arg_in, const at::Tensor& nbr_t_in) {
  check_pool_backward_args(grad_in, arg_in, nbr_t_in);
  auto g = grad_in.contiguous();
  auto arg = arg_in.contiguous();
  auto nt = nbr_t_in.contiguous();
  const int64_t m = g.size(0), C = g.size(1), n_in = nt.size(0), K = nt.size(1);
  const auto ct = g.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  auto acc = at::zeros({n_in, C}, g.options().dtype(ct));
  if (n_in == 0 || C == 0 || m == 0 || K == 0) return acc.to(g.scalar_type());
  const int32_t* tp = nt.data_ptr<int32_t>();
  for (int64_t t = 0; t < n_in * K; ++t)
    TORCH_CHECK_VALUE(tp[t] >= -1 && tp[t] < m, "kernel_map_t entries must lie in [-1, N_out = ", m, "), got ", tp[t]);
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, g.scalar_type(), "lidarops_sparse_max_pool_bw_cpu", [&] {
    using T = acc_t<scalar_t>;
    const scalar_t* gp = g.data_ptr<scalar_t>();
    const int64_t* ap = arg.data_ptr<int64_t>();
    T* dp = acc.data_ptr<T>();
    at::parallel_for(0, n_in, std::max<int64_t>(1, 4096 / (K * C)), [&](int64_t s, int64_t e) {
      for (int64_t i = s; i < e; ++i)
        for (int64_t k = 0; k < K; ++k) {
          const int64_t o = tp[i * K + k];
          if (o < 0) continue;
          for (int64_t c = 0; c < C; ++c)
            if (ap[o * C + c] == i) dp[i * C + c] += static_cast<T>(gp[o * C + c]);
        }
    });
  });
  return acc.to(g.scalar_type());
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("sparse_max_pool", &sparse_max_pool_cpu);
  m.impl("sparse_max_pool_backward", &sparse_max_pool_backward_cpu);
}

}  // namespace sparse
}  // namespace lidarops
