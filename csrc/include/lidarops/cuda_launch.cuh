// Launch helpers every CUDA file shares: grid sizes, the full warp mask, the grid-stride loop and the
// properties of a device (compute capability, multiprocessors, shared memory), queried once per device.
#pragma once

#include <c10/core/Device.h>
#include <c10/cuda/CUDAException.h>
#include <cuda_runtime.h>

#include <cstdint>
#include <mutex>
#include <unordered_map>

#include "lidarops/common.h"

namespace lidarops {
namespace gpu {

inline constexpr unsigned kFullMask = 0xffffffffu;

LIDAROPS_HD int64_t ceil_div(int64_t a, int64_t b) { return (a + b - 1) / b; }

inline int64_t pow2_ceil(int64_t v) {
  int64_t p = 1;
  while (p < v) p <<= 1;
  return p;
}

inline int64_t pow2_floor(int64_t v) {
  int64_t p = 1;
  while (p * 2 <= v) p <<= 1;
  return p;
}

// Blocks for a grid-stride loop over `total` items: at least one, at most max_blocks.
inline unsigned stride_blocks(int64_t total, int threads, int64_t max_blocks = 65536) {
  const int64_t b = ceil_div(total, threads);
  return static_cast<unsigned>(b < 1 ? 1 : (b > max_blocks ? max_blocks : b));
}

#define LIDAROPS_GRID_STRIDE(i, n) \
  for (int64_t i = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; i < (n); \
       i += static_cast<int64_t>(blockDim.x) * gridDim.x)

// Compute capability, multiprocessor count and shared memory per multiprocessor (and reserved per
// block) of a device. Cached: the attribute queries showed in the host time of small launches.
struct DeviceProps {
  int cc_major = 0, cc_minor = 0, sms = 1, smem_per_sm = 0, smem_reserved = 0;
};

inline DeviceProps device_props(c10::DeviceIndex dev) {
  static std::mutex mutex;
  static std::unordered_map<int, DeviceProps> cache;
  std::lock_guard<std::mutex> lock(mutex);
  auto it = cache.find(dev);
  if (it != cache.end()) return it->second;
  DeviceProps p;
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.cc_major, cudaDevAttrComputeCapabilityMajor, dev));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.cc_minor, cudaDevAttrComputeCapabilityMinor, dev));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.sms, cudaDevAttrMultiProcessorCount, dev));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.smem_per_sm, cudaDevAttrMaxSharedMemoryPerMultiprocessor, dev));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&p.smem_reserved, cudaDevAttrReservedSharedMemoryPerBlock, dev));
  cache[dev] = p;
  return p;
}

// Raises a kernel's dynamic shared-memory limit once per (kernel, device): a driver call per launch
// showed in the host time of small layers.
inline void raise_smem_limit(const void* kernel, size_t bytes, c10::DeviceIndex dev) {
  static std::mutex mutex;
  static std::unordered_map<const void*, uint64_t> done;  // kernel -> bit mask of devices
  const uint64_t bit = uint64_t(1) << (dev & 63);
  std::lock_guard<std::mutex> lock(mutex);
  uint64_t& mask = done[kernel];
  if (mask & bit) return;
  C10_CUDA_CHECK(cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, static_cast<int>(bytes)));
  mask |= bit;
}

}  // namespace gpu
}  // namespace lidarops
