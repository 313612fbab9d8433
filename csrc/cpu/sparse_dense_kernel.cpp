// Dense map of a sparse tensor and its adjoint on CPU: sparse_to_dense writes each row's C features
// into the channel planes of its site of a zero (B, C, *S) map; sparse_from_dense reads them back.
// Rows outside the grid are skipped (to_dense) or read as zeros (from_dense); sites are unique
// (SparseConvTensor's contract), so rows never race.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

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

at::Tensor sparse_to_dense_cpu(const at::Tensor& features_in, const at::Tensor& indices_in, int64_t batch_size,
                               at::IntArrayRef spatial_shape) {
  const DenseGrid g = check_to_dense_args(features_in, indices_in, batch_size, spatial_shape);
  auto f = features_in.contiguous();
  auto idx = indices_in.contiguous();
  const int64_t n = f.size(0), C = f.size(1), cols = idx.size(1);
  auto out = at::zeros(dense_sizes(g, C), f.options());
  if (n == 0 || C == 0 || out.numel() == 0) return out;
  const int32_t* ip = idx.data_ptr<int32_t>();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, f.scalar_type(), "lidarops_sparse_to_dense_cpu", [&] {
    const scalar_t* fp = f.data_ptr<scalar_t>();
    scalar_t* op = out.data_ptr<scalar_t>();
    at::parallel_for(0, n, std::max<int64_t>(1, 8192 / C), [&](int64_t s, int64_t e) {
      for (int64_t r = s; r < e; ++r) {
        const int64_t base = dense_site_offset(ip + r * cols, g, C);
        if (base < 0) continue;
        for (int64_t c = 0; c < C; ++c) op[base + c * g.cells] = fp[r * C + c];
      }
    });
  });
  return out;
}

at::Tensor sparse_from_dense_cpu(const at::Tensor& dense_in, const at::Tensor& indices_in) {
  const DenseGrid g = check_from_dense_args(dense_in, indices_in);
  auto x = dense_in.contiguous();
  auto idx = indices_in.contiguous();
  const int64_t n = idx.size(0), C = x.size(1), cols = idx.size(1);
  auto out = at::zeros({n, C}, x.options());
  if (n == 0 || C == 0 || x.numel() == 0) return out;
  const int32_t* ip = idx.data_ptr<int32_t>();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, x.scalar_type(), "lidarops_sparse_from_dense_cpu", [&] {
    const scalar_t* xp = x.data_ptr<scalar_t>();
    scalar_t* op = out.data_ptr<scalar_t>();
    at::parallel_for(0, n, std::max<int64_t>(1, 8192 / C), [&](int64_t s, int64_t e) {
      for (int64_t r = s; r < e; ++r) {
        const int64_t base = dense_site_offset(ip + r * cols, g, C);
        if (base < 0) continue;
        for (int64_t c = 0; c < C; ++c) op[r * C + c] = xp[base + c * g.cells];
      }
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("sparse_to_dense", &sparse_to_dense_cpu);
  m.impl("sparse_from_dense", &sparse_from_dense_cpu);
}

}  // namespace sparse
}  // namespace lidarops
