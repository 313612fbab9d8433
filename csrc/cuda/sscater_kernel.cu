// SSCATeR delta convolution on CUDA, same contract as the CPU kernels (csrc/cpu/sscater_kernel.cpp).
// The scatter runs one cuBLAS GEMM for all taps, then one thread per (changed site, tap, channel) adds
// its product into the accumulator with atomicAdd: several changed inputs can reach one output site.
// The order of those additions is not fixed, so results agree with the CPU to rounding, not bit for bit.
// The GEMM covers every tap of every changed row (one cuBLAS call; on the GPU the products for taps
// that land on inactive sites cost less than splitting the GEMM per tap); the scatter skips them.
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include "lidarops/sscater.h"

namespace lidarops {
namespace sscater {
namespace {

constexpr int kThreads = 256;

inline unsigned blocks_for(int64_t n) {
  const int64_t b = (n + kThreads - 1) / kThreads;
  return static_cast<unsigned>(b < 1 ? 1 : (b > 65535 * 16 ? 65535 * 16 : b));
}

// One thread per (changed site, tap): the reached output site, -1 outside the grid.
__global__ void targets_kernel(const int32_t* __restrict__ sites, const bool* __restrict__ active,
                               int64_t* __restrict__ target, int64_t n, int64_t kh, int64_t kw, int64_t Ho, int64_t Wo,
                               int64_t stride, int64_t padding, bool transposed) {
  const int64_t K = kh * kw;
  for (int64_t r = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; r < n * K;
       r += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t k = r % K, i = r / K;
    const int64_t oy = reach(sites[2 * i], k / kw, stride, padding, Ho, transposed);
    const int64_t ox = oy < 0 ? -1 : reach(sites[2 * i + 1], k % kw, stride, padding, Wo, transposed);
    int64_t o = ox < 0 ? -1 : oy * Wo + ox;
    if (o >= 0 && active != nullptr && !active[o]) o = -1;
    target[r] = o;
  }
}

// One thread per (changed site, tap, channel).
template <typename T>
__global__ void scatter_kernel(T* __restrict__ acc, const int64_t* __restrict__ target, const T* __restrict__ prod,
                               int64_t rows, int64_t C) {
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < rows * C;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t o = target[t / C];
    if (o >= 0) atomicAdd(acc + o * C + t % C, prod[t]);
  }
}

template <typename T>
__global__ void finalize_kernel(const T* __restrict__ acc, T* __restrict__ out, const bool* __restrict__ active,
                                const int32_t* __restrict__ sites, const T* __restrict__ scale,
                                const T* __restrict__ shift, bool* __restrict__ changed, T* __restrict__ delta,
                                int64_t m, int64_t C, int64_t Ho, int64_t Wo, int64_t sy, int64_t sx, int64_t sc) {
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < m * C;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t i = t / C, c = t % C;
    const int64_t y = sites[2 * i], x = sites[2 * i + 1];
    if (y < 0 || y >= Ho || x < 0 || x >= Wo) continue;  // the wrapper validates; never write out of bounds
    T v = active[y * Wo + x] ? acc[(y * Wo + x) * C + c] * scale[c] + shift[c] : T(0);
    v = v > T(0) ? v : T(0);
    T* o = out + y * sy + x * sx + c * sc;
    const T old = *o;
    delta[t] = v - old;
    if (v != old) changed[i] = true;  // every writer stores the same value
    *o = v;
  }
}

at::Tensor scatter_cuda(at::Tensor& acc, const at::Tensor& sites_in, const at::Tensor& delta_in,
                        const at::Tensor& weight_in, int64_t stride, int64_t padding, bool transposed,
                        const c10::optional<at::Tensor>& out_active) {
  check_scatter_args(acc, sites_in, delta_in, weight_in, stride, padding);
  check_out_active(out_active, acc);
  const int64_t n = sites_in.size(0);
  const int64_t kh = weight_in.size(1), kw = weight_in.size(2), C = acc.size(2), rows = n * kh * kw;
  auto targets = at::empty({rows}, sites_in.options().dtype(at::kLong));
  if (n == 0) return targets;
  c10::cuda::CUDAGuard guard(acc.device());
  auto sites = sites_in.contiguous();
  auto stream = c10::cuda::getCurrentCUDAStream();
  const bool* act = out_active.has_value() ? out_active->data_ptr<bool>() : nullptr;
  targets_kernel<<<blocks_for(rows), kThreads, 0, stream>>>(sites.data_ptr<int32_t>(), act, targets.data_ptr<int64_t>(),
                                                            n, kh, kw, acc.size(0), acc.size(1), stride, padding,
                                                            transposed);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (acc.numel() == 0) return targets;
  auto prod = tap_products(delta_in, weight_in);  // (n, K * Cout)
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_scatter_cuda", [&] {
    scatter_kernel<scalar_t><<<blocks_for(rows * C), kThreads, 0, stream>>>(
        acc.data_ptr<scalar_t>(), targets.data_ptr<int64_t>(), prod.data_ptr<scalar_t>(), rows, C);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return targets;
}

std::tuple<at::Tensor, at::Tensor> finalize_cuda(const at::Tensor& acc, at::Tensor& out, const at::Tensor& active,
                                                 const at::Tensor& sites_in, const at::Tensor& scale_in,
                                                 const at::Tensor& shift_in) {
  check_finalize_args(acc, out, active, sites_in, scale_in, shift_in);
  const int64_t m = sites_in.size(0), C = acc.size(2);
  auto changed = at::zeros({m}, acc.options().dtype(at::kBool));
  auto delta = at::empty({m, C}, acc.options());
  if (m == 0 || C == 0) return {changed, delta};
  c10::cuda::CUDAGuard guard(acc.device());
  auto sites = sites_in.contiguous();
  auto scale = scale_in.contiguous(), shift = shift_in.contiguous();
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_finalize_cuda", [&] {
    finalize_kernel<scalar_t><<<blocks_for(m * C), kThreads, 0, stream>>>(
        acc.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(), active.data_ptr<bool>(), sites.data_ptr<int32_t>(),
        scale.data_ptr<scalar_t>(), shift.data_ptr<scalar_t>(), changed.data_ptr<bool>(), delta.data_ptr<scalar_t>(),
        m, C, acc.size(0), acc.size(1), out.stride(0), out.stride(1), out.stride(2));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {changed, delta};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("sscater_scatter_", &scatter_cuda);
  m.impl("sscater_finalize_", &finalize_cuda);
}

}  // namespace sscater
}  // namespace lidarops
