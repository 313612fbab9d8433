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

// ---- the fused layer step: no host synchronisation; lists padded to upper bounds --------------

// Pass 1: one thread per (input site, tap): cover += +-1 and the first touch of an output appends
// it to `touched` (stamp raised to value by atomicMax).
__global__ void cover_touch_kernel(int32_t* __restrict__ cover, int32_t* __restrict__ stamp, int32_t value,
                                   const int32_t* __restrict__ added, int64_t a, const int32_t* __restrict__ removed,
                                   int64_t r, int64_t kh, int64_t kw, int64_t stride, int64_t padding, int64_t Ho,
                                   int64_t Wo, int64_t* __restrict__ touched, unsigned long long* __restrict__ n) {
  const int64_t K = kh * kw;
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < (a + r) * K;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t i = t / K, k = t % K;
    const bool add = i < a;
    const int32_t* sp = add ? added + 2 * i : removed + 2 * (i - a);
    if (sp[0] < 0 || sp[1] < 0) continue;
    const int64_t oy = reach(sp[0], k / kw, stride, padding, Ho, false);
    const int64_t ox = oy < 0 ? -1 : reach(sp[1], k % kw, stride, padding, Wo, false);
    if (ox < 0) continue;
    const int64_t o = oy * Wo + ox;
    atomicAdd(cover + o, add ? 1 : -1);
    if (atomicMax(stamp + o, value) < value) touched[atomicAdd(n, 1ull)] = o;
  }
}

// Pass 2: each touched output whose cover crossed zero flips `active` and is listed at its row.
__global__ void cover_flip_kernel(const int32_t* __restrict__ cover, bool* __restrict__ active,
                                  const int64_t* __restrict__ touched, const unsigned long long* __restrict__ n,
                                  int64_t rows, int64_t Wo, int32_t* __restrict__ added_out,
                                  int32_t* __restrict__ removed_out, unsigned long long* __restrict__ counts) {
  const int64_t m = static_cast<int64_t>(*n) < rows ? static_cast<int64_t>(*n) : rows;
  for (int64_t i = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; i < m;
       i += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t o = touched[i];
    const bool after = cover[o] > 0;
    if (after == active[o]) continue;
    active[o] = after;
    const unsigned long long j = atomicAdd(counts + (after ? 0 : 1), 1ull);
    int32_t* dst = (after ? added_out : removed_out) + 2 * j;
    dst[0] = static_cast<int32_t>(o / Wo);
    dst[1] = static_cast<int32_t>(o % Wo);
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> cover_update_cuda(at::Tensor& cover, at::Tensor& active, at::Tensor& stamp,
                                                      int64_t value, const at::Tensor& added_in,
                                                      const at::Tensor& removed_in, int64_t kh, int64_t kw,
                                                      int64_t stride, int64_t padding) {
  check_cover_update_args(cover, active, stamp, added_in, removed_in, kh, kw, stride, padding);
  c10::cuda::CUDAGuard guard(cover.device());
  const int64_t Ho = cover.size(0), Wo = cover.size(1), K = kh * kw;
  const int64_t a = added_in.size(0), r = removed_in.size(0), rows = (a + r) * K;
  auto added_out = at::full({rows, 2}, -1, added_in.options());
  auto removed_out = at::full({rows, 2}, -1, added_in.options());
  auto n = at::zeros({3}, added_in.options().dtype(at::kLong));  // touched, then the two counts
  auto counts = n.narrow(0, 1, 2);
  if (rows == 0) return {added_out, removed_out, counts};
  auto added = added_in.contiguous(), removed = removed_in.contiguous();
  auto touched = at::empty({rows}, added_in.options().dtype(at::kLong));
  auto* np = reinterpret_cast<unsigned long long*>(n.data_ptr<int64_t>());
  auto stream = c10::cuda::getCurrentCUDAStream();
  cover_touch_kernel<<<blocks_for(rows), kThreads, 0, stream>>>(
      cover.data_ptr<int32_t>(), stamp.data_ptr<int32_t>(), static_cast<int32_t>(value), added.data_ptr<int32_t>(), a,
      removed.data_ptr<int32_t>(), r, kh, kw, stride, padding, Ho, Wo, touched.data_ptr<int64_t>(), np);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  cover_flip_kernel<<<blocks_for(rows), kThreads, 0, stream>>>(cover.data_ptr<int32_t>(), active.data_ptr<bool>(),
                                                               touched.data_ptr<int64_t>(), np, rows, Wo,
                                                               added_out.data_ptr<int32_t>(),
                                                               removed_out.data_ptr<int32_t>(), np + 1);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {added_out, removed_out, counts};
}

// One thread per (site, tap): the child becomes `on`.
__global__ void children_kernel(bool* __restrict__ active, const int32_t* __restrict__ sites, int64_t n, int64_t kh,
                                int64_t kw, int64_t stride, int64_t padding, int64_t Ho, int64_t Wo, bool on,
                                int32_t* __restrict__ out) {
  const int64_t K = kh * kw;
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < n * K;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t i = t / K, k = t % K;
    if (sites[2 * i] < 0 || sites[2 * i + 1] < 0) continue;
    const int64_t oy = reach(sites[2 * i], k / kw, stride, padding, Ho, true);
    const int64_t ox = oy < 0 ? -1 : reach(sites[2 * i + 1], k % kw, stride, padding, Wo, true);
    if (ox < 0) continue;
    active[oy * Wo + ox] = on;
    out[2 * t] = static_cast<int32_t>(oy);
    out[2 * t + 1] = static_cast<int32_t>(ox);
  }
}

std::tuple<at::Tensor, at::Tensor> children_cuda(at::Tensor& active, const at::Tensor& added_in,
                                                 const at::Tensor& removed_in, int64_t kh, int64_t kw, int64_t stride,
                                                 int64_t padding) {
  check_children_args(active, added_in, removed_in, kh, kw, stride, padding);
  c10::cuda::CUDAGuard guard(active.device());
  const int64_t Ho = active.size(0), Wo = active.size(1), K = kh * kw;
  auto stream = c10::cuda::getCurrentCUDAStream();
  auto run = [&](const at::Tensor& in, bool on) {
    auto sites = in.contiguous();
    const int64_t n = sites.size(0);
    auto out = at::full({n * K, 2}, -1, sites.options());
    if (n > 0) {
      children_kernel<<<blocks_for(n * K), kThreads, 0, stream>>>(active.data_ptr<bool>(), sites.data_ptr<int32_t>(),
                                                                  n, kh, kw, stride, padding, Ho, Wo, on,
                                                                  out.data_ptr<int32_t>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
    return out;
  };
  auto a = run(added_in, true);
  auto r = run(removed_in, false);  // launched after the added: a site under both ends inactive
  return {a, r};
}

// One thread per (site, output channel).
template <typename T>
__global__ void gather_kernel(T* __restrict__ acc, const T* __restrict__ in, const T* __restrict__ w,
                              const int32_t* __restrict__ sites, int64_t m, int64_t Ho, int64_t Wo, int64_t C,
                              int64_t Hi, int64_t Wi, int64_t Ci, int64_t s0, int64_t s1, int64_t s2, int64_t kh,
                              int64_t kw, int64_t stride, int64_t padding) {
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < m * C;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t i = t / C, c = t % C;
    int64_t y, x;
    if (!site_at(sites, i, Ho, Wo, y, x)) continue;
    acc[(y * Wo + x) * C + c] = conv_at(in, s0, s1, s2, Hi, Wi, Ci, w, kh, kw, y, x, c, stride, padding);
  }
}

void gather_cuda(at::Tensor& acc, const at::Tensor& input, const at::Tensor& weight_in, const at::Tensor& sites_in,
                 int64_t stride, int64_t padding) {
  check_gather_args(acc, input, weight_in, sites_in, stride, padding);
  const int64_t m = sites_in.size(0), C = acc.size(2);
  if (m == 0 || C == 0) return;
  c10::cuda::CUDAGuard guard(acc.device());
  auto w = weight_in.contiguous();
  auto sites = sites_in.contiguous();
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_gather_cuda", [&] {
    gather_kernel<scalar_t><<<blocks_for(m * C), kThreads, 0, stream>>>(
        acc.data_ptr<scalar_t>(), input.data_ptr<scalar_t>(), w.data_ptr<scalar_t>(), sites.data_ptr<int32_t>(), m,
        acc.size(0), acc.size(1), C, input.size(0), input.size(1), input.size(2), input.stride(0), input.stride(1),
        input.stride(2), w.size(1), w.size(2), stride, padding);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

// One thread per entry of targets ++ added ++ removed: raise the stamp; the first touch appends.
// Removed sites also get their accumulator zeroed.
template <typename T>
__global__ void touch_kernel(int32_t* __restrict__ stamp, T* __restrict__ acc, int32_t value,
                             const int64_t* __restrict__ targets, int64_t R, const int32_t* __restrict__ added,
                             int64_t a, const int32_t* __restrict__ removed, int64_t r, int64_t Ho, int64_t Wo,
                             int64_t C, int32_t* __restrict__ cand, unsigned long long* __restrict__ n) {
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < R + a + r;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    int64_t o;
    int32_t v = value + 1;
    if (t < R) {
      o = targets[t];
      if (o < 0 || o >= Ho * Wo) continue;
      v = value;
    } else {
      int64_t y, x;
      const bool add = t < R + a;
      if (!site_at(add ? added : removed, add ? t - R : t - R - a, Ho, Wo, y, x)) continue;
      o = y * Wo + x;
      if (!add)
        for (int64_t c = 0; c < C; ++c) acc[o * C + c] = T(0);
    }
    if (atomicMax(stamp + o, v) < value) {
      const unsigned long long j = atomicAdd(n, 1ull);
      cand[2 * j] = static_cast<int32_t>(o / Wo);
      cand[2 * j + 1] = static_cast<int32_t>(o % Wo);
    }
  }
}

std::tuple<at::Tensor, at::Tensor> touch_cuda(at::Tensor& stamp, at::Tensor& acc, int64_t value,
                                              const at::Tensor& targets_in, const at::Tensor& added_in,
                                              const at::Tensor& removed_in) {
  check_touch_args(stamp, acc, targets_in, added_in, removed_in);
  c10::cuda::CUDAGuard guard(acc.device());
  const int64_t R = targets_in.size(0), a = added_in.size(0), r = removed_in.size(0);
  auto cand = at::full({R + a + r, 2}, -1, added_in.options());
  auto count = at::zeros({1}, targets_in.options());
  if (R + a + r == 0) return {cand, count};
  auto targets = targets_in.contiguous();
  auto added = added_in.contiguous(), removed = removed_in.contiguous();
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_touch_cuda", [&] {
    touch_kernel<scalar_t><<<blocks_for(R + a + r), kThreads, 0, stream>>>(
        stamp.data_ptr<int32_t>(), acc.data_ptr<scalar_t>(), static_cast<int32_t>(value), targets.data_ptr<int64_t>(), R,
        added.data_ptr<int32_t>(), a, removed.data_ptr<int32_t>(), r, acc.size(0), acc.size(1), acc.size(2),
        cand.data_ptr<int32_t>(), reinterpret_cast<unsigned long long*>(count.data_ptr<int64_t>()));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {cand, count};
}

// One warp per candidate row (count read on the device): BN + ReLU per channel; the warp votes on
// "changed" (pass 1, reads only), a changed row takes its compacted slot from an atomic counter, and
// pass 2 recomputes the same values to write the output and the delta there.
template <typename T>
__global__ void finalize_compact_kernel(const T* __restrict__ acc, T* __restrict__ out, const bool* __restrict__ active,
                                        const int32_t* __restrict__ cand, const int64_t* __restrict__ count,
                                        int64_t rows, const int32_t* __restrict__ stamp, int32_t status_value,
                                        const T* __restrict__ scale, const T* __restrict__ shift, int64_t C, int64_t Ho,
                                        int64_t Wo, int64_t sy, int64_t sx, int64_t sc, int32_t* __restrict__ sites_out,
                                        T* __restrict__ delta_out, unsigned long long* __restrict__ counts) {
  const int64_t m = *count < rows ? *count : rows;
  const int lane = threadIdx.x & 31;
  const int64_t warps = static_cast<int64_t>(gridDim.x) * (blockDim.x >> 5);
  for (int64_t i = (blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x) >> 5; i < m; i += warps) {
    int64_t y, x;
    if (!site_at(cand, i, Ho, Wo, y, x)) continue;  // warp-uniform
    const bool on = active[y * Wo + x];
    const T* ai = acc + (y * Wo + x) * C;
    T* oi = out + y * sy + x * sx;
    auto value = [&](int64_t c) {
      const T v = on ? ai[c] * scale[c] + shift[c] : T(0);
      return v > T(0) ? v : T(0);
    };
    bool any = false;
    for (int64_t c = lane; c < C; c += 32) any |= value(c) != oi[c * sc];
    const bool changed = __any_sync(0xffffffffu, any);
    const bool status = stamp[y * Wo + x] == status_value;
    unsigned long long j = 0;
    if (lane == 0) {
      if (changed || status) atomicAdd(counts + 1, 1ull);
      if (changed) j = atomicAdd(counts, 1ull);
    }
    if (!changed) continue;  // nothing to write: the stored values are the new ones
    j = __shfl_sync(0xffffffffu, j, 0);
    if (lane == 0) {
      sites_out[2 * j] = static_cast<int32_t>(y);
      sites_out[2 * j + 1] = static_cast<int32_t>(x);
    }
    for (int64_t c = lane; c < C; c += 32) {
      const T v = value(c);
      delta_out[j * C + c] = v - oi[c * sc];
      oi[c * sc] = v;
    }
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> finalize_compact_cuda(const at::Tensor& acc, at::Tensor& out,
                                                                     const at::Tensor& active, const at::Tensor& cand,
                                                                     const at::Tensor& count, const at::Tensor& stamp,
                                                                     int64_t status_value, const at::Tensor& scale_in,
                                                                     const at::Tensor& shift_in) {
  TORCH_CHECK(count.numel() == 1 && count.scalar_type() == at::kLong && count.device() == acc.device(),
              "count must be int64 (1,) on acc's device, got ", count.sizes());
  check_map(stamp, "stamp", at::kInt, acc);
  check_same_hw(stamp, acc, "stamp", "acc");
  check_finalize_args(acc, out, active, cand, scale_in, shift_in);
  c10::cuda::CUDAGuard guard(acc.device());
  const int64_t rows = cand.size(0), C = acc.size(2);
  auto sites_out = at::full({rows, 2}, -1, cand.options());
  auto delta_out = at::zeros({rows, C}, acc.options());  // padding rows: zero
  auto counts = at::zeros({3}, count.options());
  auto stream = c10::cuda::getCurrentCUDAStream();
  // counts[2] = the rows evaluated
  counts.narrow(0, 2, 1).copy_(count.view({1}));
  if (rows == 0 || C == 0) return {sites_out, delta_out, counts};
  auto cnd = cand.contiguous();
  auto scale = scale_in.contiguous(), shift = shift_in.contiguous();
  const unsigned blocks = blocks_for(rows * 32);
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_finalize_compact_cuda", [&] {
    finalize_compact_kernel<scalar_t><<<blocks, kThreads, 0, stream>>>(
        acc.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(), active.data_ptr<bool>(), cnd.data_ptr<int32_t>(),
        count.data_ptr<int64_t>(), rows, stamp.data_ptr<int32_t>(), static_cast<int32_t>(status_value),
        scale.data_ptr<scalar_t>(), shift.data_ptr<scalar_t>(), C, acc.size(0), acc.size(1), out.stride(0),
        out.stride(1), out.stride(2), sites_out.data_ptr<int32_t>(), delta_out.data_ptr<scalar_t>(),
        reinterpret_cast<unsigned long long*>(counts.data_ptr<int64_t>()));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {sites_out, delta_out, counts};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("sscater_scatter_", &scatter_cuda);
  m.impl("sscater_finalize_", &finalize_cuda);
  m.impl("sscater_cover_update_", &cover_update_cuda);
  m.impl("sscater_children_", &children_cuda);
  m.impl("sscater_gather_", &gather_cuda);
  m.impl("sscater_touch_", &touch_cuda);
  m.impl("sscater_finalize_compact_", &finalize_compact_cuda);
}

}  // namespace sscater
}  // namespace lidarops
