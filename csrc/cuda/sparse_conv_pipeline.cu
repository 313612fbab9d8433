// The host side of the cp.async pipeline of sparse_conv_pipeline.cuh: how many offset splits a launch
// takes and the kernel that adds their partial sums.
#include <ATen/ATen.h>
#include <c10/cuda/CUDAException.h>

#include <algorithm>
#include <cstdint>

#include "sparse_conv_pipeline.cuh"

namespace lidarops {
namespace sparse {
namespace {

// out = epi(partial[0] + ... + partial[splits - 1]), added in that order: the offset splits' sums
template <typename T>
__global__ void reduce_splits_kernel(const float* __restrict__ partial, int splits, int64_t numel, int cout,
                                     T* __restrict__ out, ConvEpilogue epi) {
  const int64_t stride = static_cast<int64_t>(gridDim.x) * blockDim.x;
  for (int64_t i = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; i < numel; i += stride) {
    float v = partial[i];
    for (int z = 1; z < splits; ++z) v += partial[z * numel + i];
    out[i] = static_cast<T>(epi(v, i % cout));
  }
}

}  // namespace

template <typename T>
void reduce_offset_splits(const at::Tensor& partial, int splits, int cout, at::Tensor& out, const ConvEpilogue& epi,
                          const DeviceProps& props, cudaStream_t stream) {
  const int64_t numel = out.numel();
  const int64_t blocks = std::min<int64_t>(ceil_div(numel, 256), 8 * static_cast<int64_t>(props.sms));
  reduce_splits_kernel<T><<<static_cast<unsigned>(blocks), 256, 0, stream>>>(partial.data_ptr<float>(), splits, numel,
                                                                              cout, out.data_ptr<T>(), epi);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}
template void reduce_offset_splits<float>(const at::Tensor&, int, int, at::Tensor&, const ConvEpilogue&,
                                          const DeviceProps&, cudaStream_t);
template void reduce_offset_splits<c10::Half>(const at::Tensor&, int, int, at::Tensor&, const ConvEpilogue&,
                                              const DeviceProps&, cudaStream_t);
template void reduce_offset_splits<c10::BFloat16>(const at::Tensor&, int, int, at::Tensor&, const ConvEpilogue&,
                                                  const DeviceProps&, cudaStream_t);

// Offset splits of a pipelined launch of `tiles` blocks (threads and dynamic shared memory each), whose
// tiles take `steps` pipeline steps (offsets x input-channel chunks) without splits. None when a tile
// has fewer than 32 steps (its kernel is short: the second launch would cost the host more than the
// splits save) or when the tiles already fill more than `split_below` of one wave; otherwise as many as
// keep the launch within 1.6 waves, at most four and 8 steps per split. split_below is 1 for the FFMA
// tiles (8 warps) and 0.6 for the tensor-core tiles (4 warps), which lose from splits once they fill
// three quarters of a wave (measurements in docs/notes/sparse.md).
// forced >= 1 (the ops' `splits`) forces that many, at most K: for the tests and for tuning.
int offset_splits(int64_t tiles, int threads, size_t smem, int64_t K, int64_t steps, double split_below,
                  const DeviceProps& p, int64_t static_smem, int64_t forced) {
  constexpr int kMaxSplits = 4;
  if (forced >= 1) return static_cast<int>(std::min<int64_t>(forced, std::max<int64_t>(K, 1)));
  if (steps < 32) return 1;
  const int64_t per_sm = std::max<int64_t>(
      1, std::min<int64_t>(2048 / threads,
                           p.smem_per_sm / (static_cast<int64_t>(smem) + static_smem + p.smem_reserved)));
  const double slots = static_cast<double>(per_sm * p.sms);
  if (static_cast<double>(tiles) > split_below * slots) return 1;
  int s = 1;
  while (s < kMaxSplits && 8 * (s + 1) <= steps && static_cast<double>(tiles * (s + 1)) <= 1.6 * slots) ++s;
  return s;
}

}  // namespace sparse
}  // namespace lidarops
