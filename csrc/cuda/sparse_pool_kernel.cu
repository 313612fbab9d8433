// Sparse max pooling on CUDA, same rules as the CPU kernel (csrc/cpu/sparse_pool_kernel.cpp): the
// maximum over the present inputs of each window, ties to the first offset, NaN propagates. The
// backward runs over input rows through the transposed kernel map: no atomics, deterministic.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include "lidarops/cuda_launch.cuh"
#include "lidarops/sparse.h"

namespace lidarops {
namespace sparse {
namespace {

constexpr int kThreads = 256;

inline unsigned blocks_for(int64_t n) { return gpu::stride_blocks(n, kThreads, 1048576); }

// One thread per (output row, channel), grid-stride.
template <typename T>
__global__ void max_pool_kernel(const T* __restrict__ x, const int32_t* __restrict__ nbr, T* __restrict__ out,
                                int64_t* __restrict__ arg, int64_t m, int64_t C, int64_t K, int64_t n_in) {
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < m * C;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    using A = acc_t<T>;  // compared in float: exact for half types, no ambiguous half operators
    const int64_t o = t / C, c = t % C;
    A best = A(0);
    int64_t besti = -1;
    for (int64_t k = 0; k < K; ++k) {
      const int64_t i = nbr[o * K + k];
      if (i < 0 || i >= n_in) continue;
      const A v = static_cast<A>(x[i * C + c]);
      if (besti < 0 || (!(best != best) && !(v <= best))) {
        best = v;
        besti = i;
      }
    }
    out[t] = static_cast<T>(best);
    arg[t] = besti;
  }
}

// One thread per (input row, channel): the gradients of the windows that selected this row.
template <typename T>
__global__ void max_pool_backward_kernel(const T* __restrict__ g, const int64_t* __restrict__ arg,
                                         const int32_t* __restrict__ nbr_t, T* __restrict__ gin, int64_t n_in,
                                         int64_t C, int64_t K, int64_t m) {
  using A = acc_t<T>;
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < n_in * C;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t i = t / C, c = t % C;
    A acc = A(0);
    for (int64_t k = 0; k < K; ++k) {
      const int64_t o = nbr_t[i * K + k];
      if (o < 0 || o >= m) continue;
      if (arg[o * C + c] == i) acc += static_cast<A>(g[o * C + c]);
    }
    gin[t] = static_cast<T>(acc);
  }
}

std::tuple<at::Tensor, at::Tensor> sparse_max_pool_cuda(const at::Tensor& features, const at::Tensor& nbr_in) {
  check_pool_args(features, nbr_in);
  const c10::cuda::OptionalCUDAGuard guard(features.device());
  auto x = features.contiguous();
  auto nbr = nbr_in.contiguous();
  const int64_t n_in = x.size(0), C = x.size(1), m = nbr.size(0), K = nbr.size(1);
  auto out = at::empty({m, C}, x.options());
  auto arg = at::empty({m, C}, x.options().dtype(at::kLong));
  if (m * C == 0) return {out, arg};
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, x.scalar_type(), "lidarops_sparse_max_pool_cuda", [&] {
    max_pool_kernel<scalar_t><<<blocks_for(m * C), kThreads, 0, c10::cuda::getCurrentCUDAStream()>>>(
        x.data_ptr<scalar_t>(), nbr.data_ptr<int32_t>(), out.data_ptr<scalar_t>(), arg.data_ptr<int64_t>(), m, C, K,
        n_in);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {out, arg};
}

at::Tensor sparse_max_pool_backward_cuda(const at::Tensor& grad, const at::Tensor& arg_in, const at::Tensor& nbr_t_in) {
  check_pool_backward_args(grad, arg_in, nbr_t_in);
  const c10::cuda::OptionalCUDAGuard guard(grad.device());
  auto g = grad.contiguous();
  auto arg = arg_in.contiguous();
  auto nt = nbr_t_in.contiguous();
  const int64_t m = g.size(0), C = g.size(1), n_in = nt.size(0), K = nt.size(1);
  auto gin = at::zeros({n_in, C}, g.options());
  if (n_in * C == 0 || m == 0 || K == 0) return gin;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, g.scalar_type(), "lidarops_sparse_max_pool_bw_cuda", [&] {
    max_pool_backward_kernel<scalar_t><<<blocks_for(n_in * C), kThreads, 0, c10::cuda::getCurrentCUDAStream()>>>(
        g.data_ptr<scalar_t>(), arg.data_ptr<int64_t>(), nt.data_ptr<int32_t>(), gin.data_ptr<scalar_t>(), n_in, C, K,
        m);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return gin;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("sparse_max_pool", &sparse_max_pool_cuda);
  m.impl("sparse_max_pool_backward", &sparse_max_pool_backward_cuda);
}

}  // namespace sparse
}  // namespace lidarops
