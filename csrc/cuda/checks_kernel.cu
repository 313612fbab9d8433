// value_flags on CUDA: one grid-stride kernel per tensor, all writing into one int32 flag array
// (zeroed by a memset). A block that finds a bad value stores 1 into its tensor's flag; several
// blocks may store the same 1, which is benign. No host synchronisation here: the wrapper reads
// all the flags with one copy.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include "lidarops/checks.h"
#include "lidarops/cuda_launch.cuh"

namespace lidarops {
namespace {

constexpr int kThreads = 256;

template <typename T>
__global__ void __launch_bounds__(kThreads) nonfinite_kernel(const T* __restrict__ p, int64_t n, int32_t* flag) {
  bool bad = false;
  for (int64_t i = blockIdx.x * static_cast<int64_t>(kThreads) + threadIdx.x; i < n;
       i += static_cast<int64_t>(gridDim.x) * kThreads)
    bad |= !isfinite(static_cast<float>(p[i]));
  if (__syncthreads_or(bad) && threadIdx.x == 0) *flag = 1;
}

template <>
__global__ void __launch_bounds__(kThreads) nonfinite_kernel<double>(const double* __restrict__ p, int64_t n,
                                                                     int32_t* flag) {
  bool bad = false;
  for (int64_t i = blockIdx.x * static_cast<int64_t>(kThreads) + threadIdx.x; i < n;
       i += static_cast<int64_t>(gridDim.x) * kThreads)
    bad |= !isfinite(p[i]);
  if (__syncthreads_or(bad) && threadIdx.x == 0) *flag = 1;
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    outside_kernel(const T* __restrict__ p, int64_t n, int64_t lo, int64_t hi, int32_t* flag) {
  bool bad = false;
  for (int64_t i = blockIdx.x * static_cast<int64_t>(kThreads) + threadIdx.x; i < n;
       i += static_cast<int64_t>(gridDim.x) * kThreads) {
    const int64_t v = static_cast<int64_t>(p[i]);
    bad |= v < lo || v > hi;
  }
  if (__syncthreads_or(bad) && threadIdx.x == 0) *flag = 1;
}

int blocks_for(int64_t n, int sm_count) {
  return static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(gpu::ceil_div(n, kThreads * 4), sm_count * 4)));
}

at::Tensor value_flags_cuda(at::TensorList finite, at::TensorList ranged, at::IntArrayRef lo, at::IntArrayRef hi) {
  const c10::Device device = check_value_flags_args(finite, ranged, lo, hi, c10::Device(c10::kCUDA));
  const c10::cuda::CUDAGuard guard(device);
  auto flags = at::zeros({static_cast<int64_t>(finite.size() + ranged.size())}, at::dtype(at::kInt).device(device));
  if (flags.numel() == 0) return flags;
  const int sms = gpu::device_props(device.index()).sms;
  auto stream = at::cuda::getCurrentCUDAStream();
  int32_t* f = flags.data_ptr<int32_t>();
  for (size_t i = 0; i < finite.size(); ++i) {
    if (finite[i].numel() == 0) continue;
    auto t = finite[i].contiguous();
    AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, t.scalar_type(), "value_flags_finite", [&] {
      nonfinite_kernel<scalar_t><<<blocks_for(t.numel(), sms), kThreads, 0, stream>>>(t.data_ptr<scalar_t>(),
                                                                                      t.numel(), f + i);
    });
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  for (size_t j = 0; j < ranged.size(); ++j) {
    if (ranged[j].numel() == 0) continue;
    auto t = ranged[j].contiguous();
    AT_DISPATCH_INTEGRAL_TYPES(t.scalar_type(), "value_flags_range", [&] {
      outside_kernel<scalar_t><<<blocks_for(t.numel(), sms), kThreads, 0, stream>>>(
          t.data_ptr<scalar_t>(), t.numel(), lo[j], hi[j], f + finite.size() + j);
    });
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  return flags;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) { m.impl("value_flags", &value_flags_cuda); }

}  // namespace lidarops
