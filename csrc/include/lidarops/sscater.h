// SSCATeR delta convolution: geometry and argument checks shared by the CPU and CUDA kernels
// (csrc/cpu/sscater_kernel.cpp, csrc/cuda/sscater_kernel.cu). Schemas: csrc/ops/sscater.cpp.
//
// State layout: an accumulator acc (Ho, Wo, Cout) holds, at EVERY site of the output grid, the
// convolution (without bias) of the layer's dense, zero-filled input. Because convolution is linear,
// a change of the input at a few sites updates it by scattering (I_curr - I_prev) (*) W from those sites
// only (SSCATeR, equation 2), whatever the sites' active status.
#pragma once

#include <limits>

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

// The output site (linear key oy * Wo + ox) that input row i of a padded site list reaches through
// tap k, or -1: no site (a row with a negative coordinate is padding), or outside the output grid.
LIDAROPS_HD int64_t tap_target(const int32_t* sites, int64_t i, int64_t k, int64_t kw, int64_t stride,
                               int64_t padding, int64_t Ho, int64_t Wo, bool transposed) {
  const int64_t y = sites[2 * i], x = sites[2 * i + 1];
  if (y < 0 || x < 0) return -1;
  const int64_t oy = reach(y, k / kw, stride, padding, Ho, transposed);
  const int64_t ox = oy < 0 ? -1 : reach(x, k % kw, stride, padding, Wo, transposed);
  return ox < 0 ? -1 : oy * Wo + ox;
}

// Layer geometry: kh, kw, stride >= 1 and padding >= 0, bounded so that the tap lists (rows x kh * kw)
// and the coordinate arithmetic (int32 site x stride) stay far from int64 overflow.
inline void check_geometry(int64_t kh, int64_t kw, int64_t stride, int64_t padding) {
  constexpr int64_t kMaxTaps = int64_t(1) << 20, kMaxStep = int64_t(1) << 24;
  TORCH_CHECK_VALUE(kh >= 1 && kw >= 1 && kh <= kMaxTaps && kw <= kMaxTaps && kh * kw <= kMaxTaps && stride >= 1 &&
                        stride <= kMaxStep && padding >= 0 && padding <= kMaxStep,
                    "kernel ", kh, "x", kw, ", stride ", stride, " and padding ", padding,
                    ": need kh, kw, stride >= 1, padding >= 0, kh * kw <= 2^20 and stride, padding <= 2^24");
}

// An optional row count (int64 (1,) on `ref`'s device): only the first count[0] rows of a padded list
// of `rows` rows are used (the count a previous op left on the device, so that no host sync is needed).
inline void check_count(const c10::optional<at::Tensor>& count, const at::Tensor& ref) {
  if (!count.has_value()) return;
  TORCH_CHECK_VALUE(count->numel() == 1 && count->scalar_type() == at::kLong && count->device() == ref.device(),
                    "count must be an int64 (1,) tensor on ", ref.device(), ", got ", count->scalar_type(), " ",
                    count->sizes(), " on ", count->device());
}

// A stamp value of the fused step: stamps are int32 and a touch writes value + 1, so value must leave
// room for it (a value that wrapped around would let a site be listed twice and overflow the
// (min(rows, Ho * Wo), 2) candidate list).
inline void check_stamp_value(int64_t value, const char* name) {
  TORCH_CHECK_VALUE(value >= std::numeric_limits<int32_t>::min() && value < std::numeric_limits<int32_t>::max(), name,
                    " must lie in [-2^31, 2^31 - 1) (stamps are int32 and a touch writes value + 1), got ", value);
}

inline void check_scatter_args(const at::Tensor& acc, const at::Tensor& sites, const at::Tensor& delta,
                               const at::Tensor& weight, int64_t stride, int64_t padding) {
  TORCH_CHECK_VALUE(acc.dim() == 3 && acc.is_contiguous(), "acc must be a contiguous (Ho, Wo, Cout) tensor, got shape ",
                    acc.sizes(), acc.is_contiguous() ? "" : " (not contiguous)");
  TORCH_CHECK_VALUE(acc.scalar_type() == at::kFloat || acc.scalar_type() == at::kDouble,
                    "acc must be float32 or float64, got ", acc.scalar_type());
  TORCH_CHECK_VALUE(sites.dim() == 2 && sites.size(1) == 2 && sites.scalar_type() == at::kInt,
                    "sites must be int32 (n, 2) (y, x), got ", sites.scalar_type(), " ", sites.sizes());
  TORCH_CHECK_VALUE(delta.dim() == 2 && delta.size(0) == sites.size(0), "delta must be (n = ", sites.size(0),
                    ", Cin), got ", delta.sizes());
  TORCH_CHECK_VALUE(weight.dim() == 4 && weight.size(0) == acc.size(2) && weight.size(3) == delta.size(1),
                    "weight must be (Cout = ", acc.size(2), ", kh, kw, Cin = ", delta.size(1), "), got ", weight.sizes());
  TORCH_CHECK_VALUE(delta.scalar_type() == acc.scalar_type() && weight.scalar_type() == acc.scalar_type(),
                    "delta and weight must have acc's dtype ", acc.scalar_type(), ", got ", delta.scalar_type(), " and ",
                    weight.scalar_type());
  check_geometry(1, 1, stride, padding);
  for (const auto* t : {&sites, &delta, &weight})
    TORCH_CHECK_VALUE(t->device() == acc.device(), "all tensors must be on acc's device ", acc.device(), ", got ",
                      t->device());
}

inline void check_out_active(const c10::optional<at::Tensor>& out_active, const at::Tensor& acc) {
  if (!out_active.has_value()) return;
  const auto& a = *out_active;
  TORCH_CHECK_VALUE(a.dim() == 2 && a.size(0) == acc.size(0) && a.size(1) == acc.size(1) && a.scalar_type() == at::kBool &&
                        a.is_contiguous() && a.device() == acc.device(),
                    "out_active must be a contiguous bool (Ho, Wo) map on acc's device, got ", a.scalar_type(), " ",
                    a.sizes(), " on ", a.device());
}

inline void check_finalize_args(const at::Tensor& acc, const at::Tensor& out, const at::Tensor& active,
                                const at::Tensor& sites, const at::Tensor& scale, const at::Tensor& shift,
                                const char* sites_name = "sites") {
  TORCH_CHECK_VALUE(acc.dim() == 3 && acc.is_contiguous() &&
                        (acc.scalar_type() == at::kFloat || acc.scalar_type() == at::kDouble),
                    "acc must be a contiguous float32/float64 (Ho, Wo, C) tensor, got ", acc.scalar_type(), " ",
                    acc.sizes());
  TORCH_CHECK_VALUE(out.dim() == 3 && out.sizes() == acc.sizes() && out.scalar_type() == acc.scalar_type(),
                    "out must be a (Ho, Wo, C) view of acc's shape and dtype (any strides), got ", out.sizes(), " ",
                    out.scalar_type());
  TORCH_CHECK_VALUE(active.dim() == 2 && active.size(0) == acc.size(0) && active.size(1) == acc.size(1) &&
                        active.scalar_type() == at::kBool && active.is_contiguous(),
                    "active must be a contiguous bool (Ho, Wo) map, got ", active.scalar_type(), " ", active.sizes());
  TORCH_CHECK_VALUE(sites.dim() == 2 && sites.size(1) == 2 && sites.scalar_type() == at::kInt, sites_name,
                    " must be int32 (m, 2) (y, x), got ", sites.scalar_type(), " ", sites.sizes());
  TORCH_CHECK_VALUE(scale.dim() == 1 && scale.size(0) == acc.size(2) && shift.sizes() == scale.sizes() &&
                        scale.scalar_type() == acc.scalar_type() && shift.scalar_type() == acc.scalar_type(),
                    "scale and shift must be (C = ", acc.size(2), ",) of acc's dtype, got ", scale.sizes(), " ",
                    scale.scalar_type(), " and ", shift.sizes(), " ", shift.scalar_type());
  for (const auto* t : {&out, &active, &sites, &scale, &shift})
    TORCH_CHECK_VALUE(t->device() == acc.device(), "all tensors must be on acc's device ", acc.device(), ", got ",
                      t->device());
}

// sscater_dense_finalize_'s arguments: y (C, Ho, Wo) and out (Ho, Wo, C), any strides; acc (Ho, Wo, C)
// contiguous; scale, shift (C,); active (Ho, Wo) bool contiguous; out_nchw (C, Ho, Wo) contiguous.
inline void check_dense_finalize_args(const at::Tensor& y, const at::Tensor& acc, const at::Tensor& out,
                                      const at::Tensor& scale, const at::Tensor& shift,
                                      const c10::optional<at::Tensor>& active,
                                      const c10::optional<at::Tensor>& out_nchw) {
  TORCH_CHECK_VALUE(acc.dim() == 3 && acc.is_contiguous() &&
                        (acc.scalar_type() == at::kFloat || acc.scalar_type() == at::kDouble),
                    "acc must be a contiguous float32/float64 (Ho, Wo, C) tensor, got ", acc.scalar_type(), " ",
                    acc.sizes());
  const int64_t Ho = acc.size(0), Wo = acc.size(1), C = acc.size(2);
  TORCH_CHECK_VALUE(y.dim() == 3 && y.size(0) == C && y.size(1) == Ho && y.size(2) == Wo &&
                        y.scalar_type() == acc.scalar_type(),
                    "y must be ", acc.scalar_type(), " (C, Ho, Wo) = (", C, ", ", Ho, ", ", Wo, "), got ",
                    y.scalar_type(), " ", y.sizes());
  TORCH_CHECK_VALUE(out.sizes() == acc.sizes() && out.scalar_type() == acc.scalar_type(),
                    "out must be a (Ho, Wo, C) view of acc's shape and dtype (any strides), got ", out.sizes(), " ",
                    out.scalar_type());
  TORCH_CHECK_VALUE(scale.dim() == 1 && scale.size(0) == C && shift.sizes() == scale.sizes() &&
                        scale.scalar_type() == acc.scalar_type() && shift.scalar_type() == acc.scalar_type(),
                    "scale and shift must be (C = ", C, ",) of acc's dtype, got ", scale.sizes(), " ",
                    scale.scalar_type(), " and ", shift.sizes(), " ", shift.scalar_type());
  if (active.has_value())
    TORCH_CHECK_VALUE(active->dim() == 2 && active->size(0) == Ho && active->size(1) == Wo &&
                          active->scalar_type() == at::kBool && active->is_contiguous(),
                      "active must be a contiguous bool (Ho, Wo) map, got ", active->scalar_type(), " ",
                      active->sizes());
  if (out_nchw.has_value())
    TORCH_CHECK_VALUE(out_nchw->dim() == 3 && out_nchw->size(0) == C && out_nchw->size(1) == Ho &&
                          out_nchw->size(2) == Wo && out_nchw->scalar_type() == acc.scalar_type() &&
                          out_nchw->is_contiguous(),
                      "out_nchw must be a contiguous ", acc.scalar_type(), " (C, Ho, Wo) tensor, got ",
                      out_nchw->scalar_type(), " ", out_nchw->sizes());
  for (const auto* t : {&y, &out, &scale, &shift})
    TORCH_CHECK_VALUE(t->device() == acc.device(), "all tensors must be on acc's device ", acc.device(), ", got ",
                      t->device());
  for (const auto* t : {&active, &out_nchw})
    TORCH_CHECK_VALUE(!t->has_value() || (*t)->device() == acc.device(), "all tensors must be on acc's device ",
                      acc.device(), ", got ", (*t)->device());
}

// ---- the fused layer step ----------------------------------------------------------------------

inline void check_map(const at::Tensor& t, const char* name, at::ScalarType dt, const at::Tensor& ref) {
  TORCH_CHECK_VALUE(t.dim() == 2 && t.scalar_type() == dt && t.is_contiguous() && t.device() == ref.device(), name,
                    " must be a contiguous ", dt, " (H, W) map on ", ref.device(), ", got ", t.scalar_type(), " ", t.sizes(),
                    " on ", t.device());
}

inline void check_sites(const at::Tensor& t, const char* name, const at::Tensor& ref) {
  TORCH_CHECK_VALUE(t.dim() == 2 && t.size(1) == 2 && t.scalar_type() == at::kInt && t.device() == ref.device(), name,
                    " must be int32 (n, 2) (y, x) on ", ref.device(), ", got ", t.scalar_type(), " ", t.sizes(), " on ",
                    t.device());
}

inline void check_same_hw(const at::Tensor& a, const at::Tensor& b, const char* na, const char* nb) {
  TORCH_CHECK_VALUE(a.size(0) == b.size(0) && a.size(1) == b.size(1), na, " and ", nb, " must cover the same (H, W) grid, got ",
                    a.sizes(), " and ", b.sizes());
}

inline void check_cover_update_args(const at::Tensor& cover, const at::Tensor& active, const at::Tensor& stamp,
                                    const at::Tensor& added_in, const at::Tensor& removed_in, int64_t kh, int64_t kw,
                                    int64_t stride, int64_t padding) {
  check_map(cover, "cover", at::kInt, cover);
  check_map(active, "active", at::kBool, cover);
  check_map(stamp, "stamp", at::kInt, cover);
  check_same_hw(cover, active, "cover", "active");
  check_same_hw(cover, stamp, "cover", "stamp");
  check_sites(added_in, "added", cover);
  check_sites(removed_in, "removed", cover);
  check_geometry(kh, kw, stride, padding);
}

inline void check_children_args(const at::Tensor& active, const at::Tensor& added_in, const at::Tensor& removed_in,
                                int64_t kh, int64_t kw, int64_t stride, int64_t padding) {
  check_map(active, "active", at::kBool, active);
  check_sites(added_in, "added", active);
  check_sites(removed_in, "removed", active);
  check_geometry(kh, kw, stride, padding);
}

inline void check_gather_args(const at::Tensor& acc, const at::Tensor& input, const at::Tensor& weight,
                              const at::Tensor& sites, int64_t stride, int64_t padding) {
  TORCH_CHECK_VALUE(acc.dim() == 3 && acc.is_contiguous() && (acc.scalar_type() == at::kFloat || acc.scalar_type() == at::kDouble),
                    "acc must be a contiguous float32/float64 (Ho, Wo, Cout) tensor, got ", acc.scalar_type(), " ", acc.sizes());
  TORCH_CHECK_VALUE(input.dim() == 3 && input.scalar_type() == acc.scalar_type() && input.device() == acc.device(),
                    "input must be (Hi, Wi, Cin) of acc's dtype and device, got ", input.scalar_type(), " ", input.sizes(),
                    " on ", input.device());
  TORCH_CHECK_VALUE(weight.dim() == 4 && weight.size(0) == acc.size(2) && weight.size(3) == input.size(2) &&
                        weight.scalar_type() == acc.scalar_type() && weight.device() == acc.device(),
                    "weight must be (Cout = ", acc.size(2), ", kh, kw, Cin = ", input.size(2), ") of acc's dtype and device, got ",
                    weight.scalar_type(), " ", weight.sizes(), " on ", weight.device());
  check_sites(sites, "sites", acc);
  check_geometry(1, 1, stride, padding);
}

inline void check_touch_args(const at::Tensor& stamp, const at::Tensor& acc, const at::Tensor& targets,
                             const at::Tensor& added, const at::Tensor& removed) {
  TORCH_CHECK_VALUE(acc.dim() == 3 && acc.is_contiguous() && (acc.scalar_type() == at::kFloat || acc.scalar_type() == at::kDouble),
                    "acc must be a contiguous float32/float64 (Ho, Wo, C) tensor, got ", acc.scalar_type(), " ", acc.sizes());
  check_map(stamp, "stamp", at::kInt, acc);
  check_same_hw(stamp, acc, "stamp", "acc");
  TORCH_CHECK_VALUE(targets.dim() == 1 && targets.scalar_type() == at::kLong && targets.device() == acc.device(),
                    "targets must be int64 (R,) on acc's device, got ", targets.scalar_type(), " ", targets.sizes(), " on ",
                    targets.device());
  check_sites(added, "added", acc);
  check_sites(removed, "removed", acc);
}

// After check_finalize_args(acc, out, active, cand, scale, shift).
inline void check_finalize_compact_args(const at::Tensor& acc, const at::Tensor& cand, const at::Tensor& count,
                                        const at::Tensor& stamp, int64_t status_value) {
  TORCH_CHECK_VALUE(count.numel() == 1 && count.scalar_type() == at::kLong && count.device() == acc.device(),
                    "count must be an int64 (1,) tensor on acc's device ", acc.device(), ", got ", count.scalar_type(),
                    " ", count.sizes(), " on ", count.device());
  check_map(stamp, "stamp", at::kInt, acc);
  check_same_hw(stamp, acc, "stamp", "acc");
  check_sites(cand, "cand", acc);
  check_stamp_value(status_value, "status_value");
}

// Calls f(ky, kx, iy, ix) for each tap of output site (y, x) whose input (iy, ix) lies in the
// (Hi, Wi) grid (regular convolution geometry).
template <typename F>
LIDAROPS_HD void for_window(int64_t y, int64_t x, int64_t kh, int64_t kw, int64_t stride, int64_t padding, int64_t Hi,
                            int64_t Wi, F&& f) {
  for (int64_t ky = 0; ky < kh; ++ky) {
    const int64_t iy = y * stride - padding + ky;
    if (iy < 0 || iy >= Hi) continue;
    for (int64_t kx = 0; kx < kw; ++kx) {
      const int64_t ix = x * stride - padding + kx;
      if (ix >= 0 && ix < Wi) f(ky, kx, iy, ix);
    }
  }
}

// The full convolution (no bias) of input (Hi, Wi, Ci; strides s0, s1, s2) at output site (y, x),
// channel c, with a contiguous weight (Cout, kh, kw, Ci): zero outside the input grid.
template <typename T>
LIDAROPS_HD T conv_at(const T* in, int64_t s0, int64_t s1, int64_t s2, int64_t Hi, int64_t Wi, int64_t Ci,
                      const T* w, int64_t kh, int64_t kw, int64_t y, int64_t x, int64_t c, int64_t stride,
                      int64_t padding) {
  T sum = T(0);
  for_window(y, x, kh, kw, stride, padding, Hi, Wi, [&](int64_t ky, int64_t kx, int64_t iy, int64_t ix) {
    const T* src = in + iy * s0 + ix * s1;
    const T* wk = w + ((c * kh + ky) * kw + kx) * Ci;
    for (int64_t ci = 0; ci < Ci; ++ci) sum += src[ci * s2] * wk[ci];
  });
  return sum;
}

// A padded site list's row i: (y, x) or none (y < 0).
LIDAROPS_HD bool site_at(const int32_t* s, int64_t i, int64_t H, int64_t W, int64_t& y, int64_t& x) {
  y = s[2 * i];
  x = s[2 * i + 1];
  return y >= 0 && y < H && x >= 0 && x < W;
}

}  // namespace sscater
}  // namespace lidarops
