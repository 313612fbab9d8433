// Private interface of the sparse convolution on CUDA. The forward kernels are split by family, one
// file each, and exported through the launchers below; each file keeps its kernels in an anonymous
// namespace.
//   sparse_conv_kernel.cu    the registered ops: the kernel family of a layer (overview there)
//   sparse_conv_simt.cu      SIMT tiles (every dtype) and the float32 FFMA tiles on the cp.async pipeline
//   sparse_conv_wmma.cu      tensor cores through WMMA, without the pipeline
//   sparse_conv_mma.cu       tensor cores through mma.sync on the pipeline (16-bit, TF32, 3xTF32)
//   sparse_conv_wgmma.cu     tensor cores through Hopper's wgmma on the pipeline
//   sparse_conv_pipeline.cu  the offset splits and their reduction, shared-memory limits (the device
//                            side of the pipeline and launch_pipelined: sparse_conv_pipeline.cuh)
//   sparse_conv_wgrad.cu     the weight gradient (sparse_conv_weight_grad)
#pragma once

#include <ATen/ATen.h>
#include <c10/cuda/CUDAStream.h>

#include <cstdint>

#include "lidarops/cuda_launch.cuh"
#include "lidarops/sparse.h"

namespace lidarops {
namespace sparse {

using gpu::ceil_div;
using gpu::device_props;
using gpu::DeviceProps;

inline constexpr int kAsyncMaxK = 32;  // offsets a float32 tile kernel lists in one 32-bit mask

// Operands of the tensor-core kernels: float16, bfloat16, float32 as TF32 or as 3xTF32.
enum class Mma { kF16, kBF16, kTF32, k3xTF32 };

// One forward launch: the operands, contiguous on the current device (x (N_in, Cin), w (Cout, K, Cin),
// nbr (N_out, K) int32), the row order or null, the output (N_out, Cout), every row of which the kernel
// writes, and the offset splits the op's `splits` forces on the pipelined kernels (0: offset_splits).
struct ConvLaunch {
  const at::Tensor& x;
  const at::Tensor& w;
  const at::Tensor& nbr;
  const int32_t* order;
  at::Tensor& out;
  const ConvEpilogue& epi;
  const DeviceProps& props;
  cudaStream_t stream;
  int64_t splits;
};

// SIMT tiles: every dtype, any Cin and K (float accumulation, float64 in float64).
void conv_fwd_simt(const ConvLaunch& a);
// float32 FFMA tiles on the pipeline (sm_80+; Cin a multiple of 4, K <= 32, 16-byte aligned).
void conv_fwd_ffma(const ConvLaunch& a);
// Tensor cores through WMMA (sm_80+); vec_rows: Cin a multiple of the 16-byte vector, 16-byte aligned.
void conv_fwd_wmma(const ConvLaunch& a, bool vec_rows);
// Tensor cores through mma.sync on the pipeline (sm_80+; 16-byte vector rows, K <= 32).
void conv_fwd_mma(const ConvLaunch& a, Mma mode);
// wgmma on the pipeline, 64 x `cols` tiles (an sm_90a build on compute capability 9.0; not 3xTF32).
void conv_fwd_wgmma(const ConvLaunch& a, Mma mode, int cols, ConvAlgo algo);

}  // namespace sparse
}  // namespace lidarops
