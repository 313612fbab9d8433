// Dense map of a sparse tensor and its adjoint on CUDA. A block moves a tile of 32 rows x 32 channels
// through shared memory: it reads the features row by row (32 consecutive channels per warp) and writes
// the map channel by channel (32 consecutive rows per warp). Rows come in linear site order from every
// lidarops layer, so consecutive rows mostly sit at consecutive sites and the writes coalesce (a plain
// index_put_ writes one scattered element per channel plane per thread, about twice as slow).
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <vector>

#include "lidarops/cuda_launch.cuh"
#include "lidarops/sparse.h"

namespace lidarops {
namespace sparse {
namespace {

constexpr int kTile = 32, kRowsPerPass = 8;  // blocks of 32 x 8 threads

using gpu::ceil_div;

// kToDense: features (n, C) -> map; else map -> features (rows outside the grid get zeros)
template <typename T, bool kToDense>
__global__ void __launch_bounds__(kTile* kRowsPerPass)
    dense_transfer_kernel(const T* __restrict__ src, const int32_t* __restrict__ idx, T* __restrict__ dst, int64_t n,
                          int64_t C, int cols, DenseGrid g) {
  __shared__ T tile[kTile][kTile + 1];  // [row][channel]
  __shared__ int64_t base[kTile];
  const int tx = threadIdx.x, ty = threadIdx.y;
  const int64_t r0 = static_cast<int64_t>(blockIdx.x) * kTile, c0 = static_cast<int64_t>(blockIdx.y) * kTile;
  if (ty == 0) base[tx] = r0 + tx < n ? dense_site_offset(idx + (r0 + tx) * cols, g, C) : -1;
  if (kToDense) {
    for (int i = ty; i < kTile; i += kRowsPerPass)
      if (r0 + i < n && c0 + tx < C) tile[i][tx] = src[(r0 + i) * C + c0 + tx];
    __syncthreads();
    for (int i = ty; i < kTile; i += kRowsPerPass)
      if (c0 + i < C && base[tx] >= 0) dst[base[tx] + (c0 + i) * g.cells] = tile[tx][i];
  } else {
    __syncthreads();
    for (int i = ty; i < kTile; i += kRowsPerPass)
      if (c0 + i < C && r0 + tx < n) tile[tx][i] = base[tx] >= 0 ? src[base[tx] + (c0 + i) * g.cells] : T(0);
    __syncthreads();
    for (int i = ty; i < kTile; i += kRowsPerPass)
      if (r0 + i < n && c0 + tx < C) dst[(r0 + i) * C + c0 + tx] = tile[i][tx];
  }
}

template <bool kToDense>
void launch_transfer(const at::Tensor& src, const at::Tensor& idx, at::Tensor& dst, int64_t n, int64_t C,
                     const DenseGrid& g) {
  TORCH_CHECK_VALUE(ceil_div(n, kTile) < (int64_t(1) << 31) && ceil_div(C, kTile) < 65536,
                    "sparse_to_dense: too many rows or channels for one launch (", n, " x ", C, ")");
  const dim3 grid(static_cast<unsigned>(ceil_div(n, kTile)), static_cast<unsigned>(ceil_div(C, kTile)));
  const dim3 block(kTile, kRowsPerPass);
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, src.scalar_type(), "lidarops_sparse_dense_transfer", [&] {
    dense_transfer_kernel<scalar_t, kToDense><<<grid, block, 0, c10::cuda::getCurrentCUDAStream()>>>(
        src.data_ptr<scalar_t>(), idx.data_ptr<int32_t>(), dst.data_ptr<scalar_t>(), n, C,
        static_cast<int>(idx.size(1)), g);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

at::Tensor sparse_to_dense_cuda(const at::Tensor& features_in, const at::Tensor& indices_in, int64_t batch_size,
                                at::IntArrayRef spatial_shape) {
  const DenseGrid g = check_to_dense_args(features_in, indices_in, batch_size, spatial_shape);
  const c10::cuda::OptionalCUDAGuard guard(features_in.device());
  auto f = features_in.contiguous();
  auto idx = indices_in.contiguous();
  const int64_t n = f.size(0), C = f.size(1);
  std::vector<int64_t> sizes{g.batch, C};
  for (int d = 0; d < g.ndim; ++d) sizes.push_back(g.shape[d]);
  auto out = at::zeros(sizes, f.options());
  if (n > 0 && C > 0 && out.numel() > 0) launch_transfer<true>(f, idx, out, n, C, g);
  return out;
}

at::Tensor sparse_from_dense_cuda(const at::Tensor& dense_in, const at::Tensor& indices_in) {
  const DenseGrid g = check_from_dense_args(dense_in, indices_in);
  const c10::cuda::OptionalCUDAGuard guard(dense_in.device());
  auto x = dense_in.contiguous();
  auto idx = indices_in.contiguous();
  const int64_t n = idx.size(0), C = x.size(1);
  if (x.numel() == 0) return at::zeros({n, C}, x.options());
  auto out = at::empty({n, C}, x.options());
  if (n > 0 && C > 0) launch_transfer<false>(x, idx, out, n, C, g);
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("sparse_to_dense", &sparse_to_dense_cuda);
  m.impl("sparse_from_dense", &sparse_from_dense_cuda);
}

}  // namespace sparse
}  // namespace lidarops
