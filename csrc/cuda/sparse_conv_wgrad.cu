// Sparse convolution on CUDA, the weight gradient (sparse_conv_weight_grad): a split-K reduction over
// the output rows into per-split partial sums (float), added in a fixed order: deterministic.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <algorithm>
#include <cstdint>

#include "sparse_conv.cuh"

namespace lidarops {
namespace sparse {
namespace {

// ------------------------------------------------------------------------------------------------
// weight gradient: dW[co, k, ci] = sum_o g[o, co] x[map[o, k], ci]. Block: BCO x BCI tile of one
// offset k over one split of the output rows; BR rows per step; partial sums per split.
// ------------------------------------------------------------------------------------------------
template <typename T, int BCO, int BCI, int BR, int TCO, int TCI>
__global__ void __launch_bounds__((BCO / TCO) * (BCI / TCI))
    conv_wgrad_kernel(const T* __restrict__ x, const T* __restrict__ g, const int32_t* __restrict__ nbr,
                      acc_t<T>* __restrict__ partial, int64_t n_out, int64_t cin, int64_t cout, int64_t K,
                      int64_t rows_per_split, int64_t n_in) {
  using A = acc_t<T>;
  constexpr int kThreads = (BCO / TCO) * (BCI / TCI);
  __shared__ A Gs[BR][BCO + 1];
  __shared__ A Xs[BR][BCI + 1];
  __shared__ int32_t rows[BR];
  const int tid = threadIdx.x;
  const int tci = tid % (BCI / TCI), tco = tid / (BCI / TCI);
  const int64_t tiles_ci = ceil_div(cin, BCI);
  const int64_t ci0 = (blockIdx.x % tiles_ci) * BCI, co0 = (blockIdx.x / tiles_ci) * BCO;
  const int64_t k = blockIdx.y, s = blockIdx.z;
  const int64_t r_begin = s * rows_per_split;
  const int64_t r_end = r_begin + rows_per_split < n_out ? r_begin + rows_per_split : n_out;
  A acc[TCO][TCI];
#pragma unroll
  for (int i = 0; i < TCO; ++i)
#pragma unroll
    for (int j = 0; j < TCI; ++j) acc[i][j] = A(0);
  for (int64_t r0 = r_begin; r0 < r_end; r0 += BR) {
    int mine = 0;
    for (int r = tid; r < BR; r += kThreads) {
      const int32_t v = r0 + r < r_end ? map_row(nbr[(r0 + r) * K + k], n_in) : -1;
      rows[r] = v;
      mine |= v >= 0;
    }
    if (!__syncthreads_or(mine)) continue;
    for (int e = tid; e < BR * BCO; e += kThreads) {
      const int r = e / BCO, c = e % BCO;
      const int64_t co = co0 + c;
      Gs[r][c] = (rows[r] >= 0 && co < cout) ? static_cast<A>(g[(r0 + r) * cout + co]) : A(0);
    }
    for (int e = tid; e < BR * BCI; e += kThreads) {
      const int r = e / BCI, c = e % BCI;
      const int64_t ci = ci0 + c;
      const int32_t row = rows[r];
      Xs[r][c] = (row >= 0 && ci < cin) ? static_cast<A>(x[static_cast<int64_t>(row) * cin + ci]) : A(0);
    }
    __syncthreads();
#pragma unroll 4
    for (int r = 0; r < BR; ++r) {
      A a[TCO], b[TCI];
#pragma unroll
      for (int i = 0; i < TCO; ++i) a[i] = Gs[r][tco * TCO + i];
#pragma unroll
      for (int j = 0; j < TCI; ++j) b[j] = Xs[r][tci * TCI + j];
#pragma unroll
      for (int i = 0; i < TCO; ++i)
#pragma unroll
        for (int j = 0; j < TCI; ++j) acc[i][j] += a[i] * b[j];
    }
    __syncthreads();
  }
#pragma unroll
  for (int i = 0; i < TCO; ++i) {
    const int64_t co = co0 + tco * TCO + i;
    if (co >= cout) continue;
#pragma unroll
    for (int j = 0; j < TCI; ++j) {
      const int64_t ci = ci0 + tci * TCI + j;
      if (ci < cin) partial[((s * cout + co) * K + k) * cin + ci] = acc[i][j];
    }
  }
}

at::Tensor sparse_conv_weight_grad_cuda(const at::Tensor& features, const at::Tensor& grad_in, const at::Tensor& nbr_in) {
  check_weight_grad_args(features, grad_in, nbr_in);
  const c10::cuda::OptionalCUDAGuard guard(features.device());
  auto x = features.contiguous();
  auto g = grad_in.contiguous();
  auto nbr = nbr_in.contiguous();
  const int64_t n_in = x.size(0), cin = x.size(1), cout = g.size(1), K = nbr.size(1), n_out = nbr.size(0);
  const auto dtype = x.scalar_type();
  const auto ct = dtype == at::kDouble ? at::kDouble : at::kFloat;
  if (n_out == 0 || n_in == 0 || cin == 0 || cout == 0 || K == 0)
    return at::zeros({cout, K, cin}, x.options());
  constexpr int BCO = 32, BCI = 32, BR = 32, TCO = 2, TCI = 2;
  const int64_t tiles = ceil_div(cout, BCO) * ceil_div(cin, BCI);
  TORCH_CHECK_VALUE(tiles < (int64_t(1) << 31) && K < 65536, "sparse_conv_weight_grad: too many channels or offsets");
  const int64_t sms = device_props(x.get_device()).sms;
  // enough row splits to fill the GPU about four times over, each of at least 256 rows
  const int64_t splits = std::max<int64_t>(
      1, std::min<int64_t>({ceil_div(4 * sms, tiles * K), ceil_div(n_out, 256), int64_t(65535)}));
  const int64_t rows_per_split = ceil_div(n_out, splits);
  auto partial = at::empty({splits, cout, K, cin}, x.options().dtype(ct));
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  const dim3 grid(static_cast<unsigned>(tiles), static_cast<unsigned>(K), static_cast<unsigned>(splits));
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, dtype, "lidarops_sparse_conv_wgrad", [&] {
    conv_wgrad_kernel<scalar_t, BCO, BCI, BR, TCO, TCI><<<grid, (BCO / TCO) * (BCI / TCI), 0, stream>>>(
        x.data_ptr<scalar_t>(), g.data_ptr<scalar_t>(), nbr.data_ptr<int32_t>(), partial.data_ptr<acc_t<scalar_t>>(),
        n_out, cin, cout, K, rows_per_split, n_in);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  auto dw = splits == 1 ? partial.select(0, 0) : partial.sum(0);
  return dw.to(dtype).contiguous();
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) { m.impl("sparse_conv_weight_grad", &sparse_conv_weight_grad_cuda); }

}  // namespace sparse
}  // namespace lidarops
