// Dense map of a sparse tensor and its adjoint on CPU: sparse_to_dense writes each row's C features
// into the channel planes of its site of a zero (B, C, *S) map; sparse_from_dense reads them back.
// Rows outside the grid are skipped (to_dense) or read as zeros (from_dense); sites are unique
// (SparseConvTensor's contract), so rows never race.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/zeros.h>

#include <vector>

#include "lidarops/sparse.h"

namespace lidarops {
namespace sparse {
namespace {

std::vector<int64_t> dense_sizes(const DenseGrid& g, int64_t C) {
  std::vector<int64_t> sizes{g.batch, C};
  for (int d = 0; d < g.ndim; ++d) sizes.push_back(g.shape[d]);
  return sizes;
}

// kToDense: features (n, C) -> map planes; else map planes -> features
template <bool kToDense>
void transfer(const at::Tensor& src, const at::Tensor& idx, at::Tensor& dst, int64_t n, int64_t C, const DenseGrid& g) {
  const int32_t* ip = idx.data_ptr<int32_t>();
  const int64_t cols = idx.size(1);
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, src.scalar_type(), "lidarops_sparse_dense_cpu", [&] {
    const scalar_t* sp = src.data_ptr<scalar_t>();
    scalar_t* dp = dst.data_ptr<scalar_t>();
    at::parallel_for(0, n, std::max<int64_t>(1, 8192 / C), [&](int64_t s, int64_t e) {
      for (int64_t r = s; r < e; ++r) {
        const int64_t base = dense_site_offset(ip + r * cols, g, C);
        if (base < 0) continue;  // to_dense: skipped; from_dense: stays 0
        for (int64_t c = 0; c < C; ++c) {
          if (kToDense) dp[base + c * g.cells] = sp[r * C + c];
          else dp[r * C + c] = sp[base + c * g.cells];
        }
      }
    });
  });
}

at::Tensor sparse_to_dense_cpu(const at::Tensor& features_in, const at::Tensor& indices_in, int64_t batch_size,
                               at::IntArrayRef spatial_shape) {
  const DenseGrid g = check_to_dense_args(features_in, indices_in, batch_size, spatial_shape);
  auto f = features_in.contiguous();
  auto idx = indices_in.contiguous();
  const int64_t n = f.size(0), C = f.size(1);
  auto out = at::zeros(dense_sizes(g, C), f.options());
  if (n > 0 && C > 0 && out.numel() > 0) transfer<true>(f, idx, out, n, C, g);
  return out;
}

at::Tensor sparse_from_dense_cpu(const at::Tensor& dense_in, const at::Tensor& indices_in) {
  const DenseGrid g = check_from_dense_args(dense_in, indices_in);
  auto x = dense_in.contiguous();
  auto idx = indices_in.contiguous();
  const int64_t n = idx.size(0), C = x.size(1);
  auto out = at::zeros({n, C}, x.options());
  if (n > 0 && C > 0 && x.numel() > 0) transfer<false>(x, idx, out, n, C, g);
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("sparse_to_dense", &sparse_to_dense_cpu);
  m.impl("sparse_from_dense", &sparse_from_dense_cpu);
}

}  // namespace sparse
}  // namespace lidarops
