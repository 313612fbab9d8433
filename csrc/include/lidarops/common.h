// Shared helpers for lidarops kernels: argument checks and exact (non-contracted) distance arithmetic
// that gives bit-identical results on CPU and CUDA, so tie rules agree across devices.
#pragma once

// The lean ATen headers (no ATen/ATen.h, which declares every ATen op): a kernel file includes the
// <ATen/ops/*.h> of the functions it calls; the CUDA files include <ATen/ATen.h> themselves.
#include <ATen/core/Tensor.h>
#include <torch/library.h>

#ifdef __CUDACC__
#define LIDAROPS_HD __host__ __device__ __forceinline__
#else
#define LIDAROPS_HD inline
#endif

namespace lidarops {

#define LIDAROPS_CHECK_DIM(t, d, name) \
  TORCH_CHECK_VALUE((t).dim() == (d), name " must have ", d, " dimensions, got shape ", (t).sizes())

// Multiply and add with rounding after each operation (no fused multiply-add), so the CPU and
// the CUDA kernels produce the same bits for the same inputs.
template <typename T>
LIDAROPS_HD T mul_rn(T a, T b) {
#ifdef __CUDA_ARCH__
  if constexpr (std::is_same_v<T, double>) return __dmul_rn(a, b);
  else return __fmul_rn(a, b);
#else
  return a * b;
#endif
}

template <typename T>
LIDAROPS_HD T add_rn(T a, T b) {
#ifdef __CUDA_ARCH__
  if constexpr (std::is_same_v<T, double>) return __dadd_rn(a, b);
  else return __fadd_rn(a, b);
#else
  return a + b;
#endif
}

template <typename T>
LIDAROPS_HD T sub_rn(T a, T b) {
#ifdef __CUDA_ARCH__
  if constexpr (std::is_same_v<T, double>) return __dsub_rn(a, b);
  else return __fsub_rn(a, b);
#else
  return a - b;
#endif
}

// Squared Euclidean distance, evaluated as ((dx*dx + dy*dy) + dz*dz) with every step rounded.
template <typename T>
LIDAROPS_HD T sqdist3(T ax, T ay, T az, T bx, T by, T bz) {
  const T dx = sub_rn(ax, bx), dy = sub_rn(ay, by), dz = sub_rn(az, bz);
  return add_rn(add_rn(mul_rn(dx, dx), mul_rn(dy, dy)), mul_rn(dz, dz));
}

// 64-bit finaliser (MurmurHash3's fmix64, as used by splitmix64-style generators): spreads grid-regular
// keys over a hash table, and turns counters into independent random bits (lidarops/data/_raycast.py
// repeats it in NumPy for the simulator's foliage).
LIDAROPS_HD uint64_t mix64(uint64_t x) {
  x ^= x >> 33;
  x *= 0xff51afd7ed558ccdULL;
  x ^= x >> 33;
  x *= 0xc4ceb9fe1a85ec53ULL;
  x ^= x >> 33;
  return x;
}

// (distance, index) order used for every "ties to the lower index" rule.
template <typename T>
LIDAROPS_HD bool closer(T d0, int64_t i0, T d1, int64_t i1) {
  return d0 < d1 || (d0 == d1 && i0 < i1);
}

// Accumulation type: float for half/bfloat16/float, double for double.
template <typename T>
struct acc_type { using type = float; };
template <>
struct acc_type<double> { using type = double; };
template <typename T>
using acc_t = typename acc_type<T>::type;

}  // namespace lidarops
