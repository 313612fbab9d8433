// CUDA helpers of the neighbourhood ops (fps, knn, ball_query): the computation dtype of a cloud,
// clamped lengths, +inf padding, and the register-resident neighbour lists of the kNN and ball-query
// kernels with the dispatch over their compile-time capacities. The CPU side is neighbors.h.
#pragma once

#include <ATen/ATen.h>
#include <cuda_runtime.h>

#include <cstdint>
#include <limits>
#include <type_traits>
#include <utility>

#include "lidarops/cuda_launch.cuh"
#include "lidarops/neighbors.h"

namespace lidarops {
namespace gpu {
// Internal linkage: each .cu file gets its own copy of these helpers.
namespace {

// ---------------------------------------------------------------------------------------------
// host helpers
// ---------------------------------------------------------------------------------------------

// The computation tensor of a cloud: half/bfloat16 converted to float (exact), float/double as is.
inline at::Tensor compute_tensor(const at::Tensor& t) {
  if (t.scalar_type() == at::kHalf || t.scalar_type() == at::kBFloat16) return t.to(at::kFloat).contiguous();
  return t.contiguous();
}

// Calls f(std::integral_constant<int, C>) with the smallest register capacity C >= k from `Caps`,
// or C = 0 (lists in global memory) when k exceeds them all.
template <int... Caps>
struct CapacityList {};

template <typename F>
void dispatch_capacity_impl(int64_t, F&& f, CapacityList<>) {
  f(std::integral_constant<int, 0>{});
}

template <typename F, int C0, int... Rest>
void dispatch_capacity_impl(int64_t k, F&& f, CapacityList<C0, Rest...>) {
  if (k <= C0) f(std::integral_constant<int, C0>{});
  else dispatch_capacity_impl(k, std::forward<F>(f), CapacityList<Rest...>{});
}

template <int... Caps, typename F>
void dispatch_capacity(int64_t k, F&& f) {
  dispatch_capacity_impl(k, std::forward<F>(f), CapacityList<Caps...>{});
}

// ---------------------------------------------------------------------------------------------
// device helpers
// ---------------------------------------------------------------------------------------------

template <typename T>
__device__ __forceinline__ T inf_value() {
  return std::numeric_limits<T>::infinity();
}

__device__ __forceinline__ int64_t clamp_len(int64_t v, int64_t n) { return v < 0 ? 0 : (v > n ? n : v); }

// k smallest (dist2, index) pairs in registers, ascending by the total order closer(); capacity C
// compile-time so that every access uses a constant index. Padding is (+inf, -1) exactly like
// KnnList, so a point is accepted if and only if KnnList would accept it. A list of capacity C >= k
// holds the C smallest pairs; its first k are the k smallest.
template <typename T, int C>
struct RegKnnList {
  T d[C];
  int i[C];
  __device__ __forceinline__ void init() {
#pragma unroll
    for (int p = 0; p < C; ++p) {
      d[p] = inf_value<T>();
      i[p] = -1;
    }
  }
  __device__ __forceinline__ T worst() const { return d[C - 1]; }
  __device__ __forceinline__ void push(T dd, int64_t jj) {
    const int j = static_cast<int>(jj);
    if (!closer(dd, j, d[C - 1], i[C - 1])) return;
    // Replace the worst entry, then one bubbling pass restores the order (the rest is sorted).
    d[C - 1] = dd;
    i[C - 1] = j;
#pragma unroll
    for (int p = C - 1; p > 0; --p) {
      if (closer(d[p], i[p], d[p - 1], i[p - 1])) {
        const T td = d[p];
        d[p] = d[p - 1];
        d[p - 1] = td;
        const int ti = i[p];
        i[p] = i[p - 1];
        i[p - 1] = ti;
      }
    }
  }
  // Removes the first entry (used by the sub-warp merge).
  __device__ __forceinline__ void pop_front() {
#pragma unroll
    for (int p = 0; p + 1 < C; ++p) {
      d[p] = d[p + 1];
      i[p] = i[p + 1];
    }
    d[C - 1] = inf_value<T>();
    i[C - 1] = -1;
  }
};

// The C lowest indices pushed, ascending, in registers (INT_MAX = empty). Each point is pushed at
// most once, so this keeps the same set as BallList; the distances are recomputed on output with
// the same rounded formula, which gives the same bits.
template <int C>
struct RegBallList {
  int i[C];
  __device__ __forceinline__ void init() {
#pragma unroll
    for (int p = 0; p < C; ++p) i[p] = std::numeric_limits<int>::max();
  }
  template <typename T>
  __device__ __forceinline__ void push(T, int64_t jj) {
    const int j = static_cast<int>(jj);
    if (j >= i[C - 1]) return;
    i[C - 1] = j;
#pragma unroll
    for (int p = C - 1; p > 0; --p) {
      if (i[p] < i[p - 1]) {
        const int t = i[p];
        i[p] = i[p - 1];
        i[p - 1] = t;
      }
    }
  }
};

}  // namespace
}  // namespace gpu
}  // namespace lidarops
