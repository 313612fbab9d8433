// cp.async (sm_80+): asynchronous copies from global to shared memory, grouped and waited for in order.
// Below sm_80 the copies are plain loads and stores, so a kernel written for the ring stays correct.
#pragma once

#include <cstdint>

namespace lidarops {
namespace gpu {

// 16 bytes, 16-byte aligned; valid = false fills them with zeros and reads nothing.
__device__ __forceinline__ void cp_async16(void* smem, const void* gmem, bool valid) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  const unsigned dst = static_cast<unsigned>(__cvta_generic_to_shared(smem));
  const int bytes = valid ? 16 : 0;
  asm volatile("cp.async.cg.shared.global [%0], [%1], 16, %2;\n" ::"r"(dst), "l"(gmem), "r"(bytes));
#else
  struct alignas(16) V { uint64_t a, b; };
  *static_cast<V*>(smem) = valid ? *static_cast<const V*>(gmem) : V{0, 0};
#endif
}

// 8 bytes, 8-byte aligned.
__device__ __forceinline__ void cp_async8(void* smem, const void* gmem) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  const unsigned dst = static_cast<unsigned>(__cvta_generic_to_shared(smem));
  asm volatile("cp.async.ca.shared.global [%0], [%1], 8;\n" ::"r"(dst), "l"(gmem));
#else
  *static_cast<uint64_t*>(smem) = *static_cast<const uint64_t*>(gmem);
#endif
}

__device__ __forceinline__ void cp_async_commit() {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  asm volatile("cp.async.commit_group;\n" ::);
#endif
}

// Wait until at most N of this thread's committed groups are still in flight (a barrier then makes
// every thread's copies visible to the block).
template <int N>
__device__ __forceinline__ void cp_async_wait() {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  asm volatile("cp.async.wait_group %0;\n" ::"n"(N));
#endif
}

}  // namespace gpu
}  // namespace lidarops
