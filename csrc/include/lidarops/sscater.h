// SSCATeR delta convolution: geometry and argument checks shared by the CPU and CUDA kernels
// (csrc/cpu/sscater_kernel.cpp, csrc/cuda/sscater_kernel.cu). Schemas: csrc/ops/sscater.cpp.
//
// State layout: an accumulator acc (Ho, Wo, Cout) holds, at EVERY site of the output grid, the
// convolution (without bias) of the layer's dense, zero-filled input. Because convolution is linear,
// a change of the input at a few sites updates it by scattering (I_curr - I_prev) (*) W from those sites
// only (SSCATeR, equation 2), whatever the sites' active status.
#pragma once

#include "lidarops/common.h"

namespace lidarops {
namespace sscater {

// Output site reached from input coordinate i through kernel tap k along one axis, or -1.
//   regular convolution: o * stride - padding + k = i
//   transposed convolution: o = i * stride - padding + k
LIDAROPS_HD int64_t reach(int64_t i, int64_t k, int64_t stride, int64_t padding, int64_t n_out, bool transposed) {
  int64_t o;
  if (transposed) {
    o = i * stride - padding + k;
  } else {
    const int64_t t = i + padding - k;
    if (t < 0 || t % stride != 0) return -1;
    o = t / stride;
  }
  return (o >= 0 && o < n_out) ? o : -1;
}

inline void check_scatter_args(const at::Tensor& acc, const at::Tensor& sites, const at::Tensor& delta,
                               const at::Tensor& weight, int64_t stride, int64_t padding) {
  TORCH_CHECK(acc.dim() == 3 && acc.is_contiguous(), "acc must be a contiguous (Ho, Wo, Cout) tensor, got shape ",
              acc.sizes(), acc.is_contiguous() ? "" : " (not contiguous)");
  TORCH_CHECK(acc.scalar_type() == at::kFloat || acc.scalar_type() == at::kDouble,
              "acc must be float32 or float64, got ", acc.scalar_type());
  TORCH_CHECK(sites.dim() == 2 && sites.size(1) == 2 && sites.scalar_type() == at::kInt,
              "sites must be int32 (n, 2) (y, x), got ", sites.scalar_type(), " ", sites.sizes());
  TORCH_CHECK(delta.dim() == 2 && delta.size(0) == sites.size(0), "delta must be (n = ", sites.size(0),
              ", Cin), got ", delta.sizes());
  TORCH_CHECK(weight.dim() == 4 && weight.size(0) == acc.size(2) && weight.size(3) == delta.size(1),
              "weight must be (Cout = ", acc.size(2), ", kh, kw, Cin = ", delta.size(1), "), got ", weight.sizes());
  TORCH_CHECK(delta.scalar_type() == acc.scalar_type() && weight.scalar_type() == acc.scalar_type(),
              "delta and weight must have acc's dtype ", acc.scalar_type(), ", got ", delta.scalar_type(), " and ",
              weight.scalar_type());
  TORCH_CHECK(stride >= 1 && padding >= 0, "stride must be >= 1 and padding >= 0, got ", stride, " and ", padding);
  for (const auto* t : {&sites, &delta, &weight})
    TORCH_CHECK(t->device() == acc.device(), "all tensors must be on acc's device ", acc.device(), ", got ",
                t->device());
}

inline void check_out_active(const c10::optional<at::Tensor>& out_active, const at::Tensor& acc) {
  if (!out_active.has_value()) return;
  const auto& a = *out_active;
  TORCH_CHECK(a.dim() == 2 && a.size(0) == acc.size(0) && a.size(1) == acc.size(1) && a.scalar_type() == at::kBool &&
                  a.is_contiguous() && a.device() == acc.device(),
              "out_active must be a contiguous bool (Ho, Wo) map on acc's device, got ", a.scalar_type(), " ",
              a.sizes(), " on ", a.device());
}

inline void check_finalize_args(const at::Tensor& acc, const at::Tensor& out, const at::Tensor& active,
                                const at::Tensor& sites, const at::Tensor& scale, const at::Tensor& shift) {
  TORCH_CHECK(acc.dim() == 3 && acc.is_contiguous(), "acc must be a contiguous (Ho, Wo, C) tensor, got ",
              acc.sizes());
  TORCH_CHECK(out.dim() == 3 && out.sizes() == acc.sizes() && out.scalar_type() == acc.scalar_type(),
              "out must be a (Ho, Wo, C) view of acc's shape and dtype (any strides), got ", out.sizes(), " ",
              out.scalar_type());
  TORCH_CHECK(active.dim() == 2 && active.size(0) == acc.size(0) && active.size(1) == acc.size(1) &&
                  active.scalar_type() == at::kBool && active.is_contiguous(),
              "active must be a contiguous bool (Ho, Wo) map, got ", active.scalar_type(), " ", active.sizes());
  TORCH_CHECK(sites.dim() == 2 && sites.size(1) == 2 && sites.scalar_type() == at::kInt,
              "sites must be int32 (m, 2) (y, x), got ", sites.scalar_type(), " ", sites.sizes());
  TORCH_CHECK(scale.dim() == 1 && scale.size(0) == acc.size(2) && shift.sizes() == scale.sizes() &&
                  scale.scalar_type() == acc.scalar_type() && shift.scalar_type() == acc.scalar_type(),
              "scale and shift must be (C = ", acc.size(2), ",) of acc's dtype, got ", scale.sizes(), " ",
              scale.scalar_type(), " and ", shift.sizes(), " ", shift.scalar_type());
  for (const auto* t : {&out, &active, &sites, &scale, &shift})
    TORCH_CHECK(t->device() == acc.device(), "all tensors must be on acc's device ", acc.device(), ", got ",
                t->device());
}

// Products of every changed input row with every kernel tap: (n, K * Cout), row i holding
// delta[i] @ W[:, k, :]^T for k = 0..K-1 (one GEMM for the whole layer). A weight whose memory is
// tap-major (a (Cout, kh, kw, Cin) view of a contiguous (kh, kw, Cout, Cin) tensor, as the streaming
// backbone keeps it) is used in place; any other layout is copied into that order first.
inline at::Tensor tap_products(const at::Tensor& delta, const at::Tensor& weight) {
  const int64_t cout = weight.size(0), K = weight.size(1) * weight.size(2), cin = weight.size(3);
  auto w_taps = weight.permute({1, 2, 0, 3}).reshape({K * cout, cin});  // row k * Cout + c
  return at::mm(delta.contiguous(), w_taps.t());  // (n, K * Cout): column k * Cout + c
}

}  // namespace sscater
}  // namespace lidarops
