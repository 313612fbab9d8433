// SSCATeR delta convolution on CPU. The scatter runs, per kernel tap, one GEMM over the changed rows
// that reach a site, then adds the products into the accumulator with threads split over output
// channels: no two threads write the same element, so it needs no atomics and the result does not
// depend on the thread count.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include "lidarops/sscater.h"

namespace lidarops {
namespace sscater {
namespace {

at::Tensor scatter_cpu(at::Tensor& acc, const at::Tensor& sites_in, const at::Tensor& delta_in,
                       const at::Tensor& weight_in, int64_t stride, int64_t padding, bool transposed,
                       const c10::optional<at::Tensor>& out_active) {
  check_scatter_args(acc, sites_in, delta_in, weight_in, stride, padding);
  check_out_active(out_active, acc);
  const int64_t n = sites_in.size(0);
  const int64_t Ho = acc.size(0), Wo = acc.size(1), C = acc.size(2);
  const int64_t kh = weight_in.size(1), kw = weight_in.size(2), K = kh * kw;
  auto targets = at::empty({n * K}, sites_in.options().dtype(at::kLong));
  if (n == 0) return targets;
  auto sites = sites_in.contiguous();
  const int32_t* sp = sites.data_ptr<int32_t>();
  int64_t* target = targets.data_ptr<int64_t>();
  for (int64_t i = 0; i < n; ++i)
    for (int64_t ky = 0; ky < kh; ++ky) {
      const int64_t oy = reach(sp[2 * i], ky, stride, padding, Ho, transposed);
      for (int64_t kx = 0; kx < kw; ++kx) {
        const int64_t ox = oy < 0 ? -1 : reach(sp[2 * i + 1], kx, stride, padding, Wo, transposed);
        int64_t o = ox < 0 ? -1 : oy * Wo + ox;
        target[i * K + ky * kw + kx] = o;
      }
    }
  if (out_active.has_value()) {
    const bool* act = out_active->data_ptr<bool>();
    for (int64_t r = 0; r < n * K; ++r)
      if (target[r] >= 0 && !act[target[r]]) target[r] = -1;
  }
  if (acc.numel() == 0) return targets;
  // Per tap: gather the rows that reach a site, one GEMM, scatter-add. Only the (changed input,
  // updated output) pairs cost a product, as in a gather-GEMM-scatter sparse convolution.
  auto delta = delta_in.contiguous();
  auto w_taps = weight_in.permute({1, 2, 0, 3}).reshape({K, C, weight_in.size(3)});  // (K, Cout, Cin)
  std::vector<int64_t> rows;
  rows.reserve(n);
  for (int64_t k = 0; k < K; ++k) {
    rows.clear();
    for (int64_t i = 0; i < n; ++i)
      if (target[i * K + k] >= 0) rows.push_back(i);
    if (rows.empty()) continue;
    const int64_t nk = static_cast<int64_t>(rows.size());
    auto idx = at::from_blob(rows.data(), {nk}, at::TensorOptions().dtype(at::kLong));
    auto prod = at::mm(delta.index_select(0, idx), w_taps[k].t());  // (nk, Cout)
    AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_scatter_cpu", [&] {
      scalar_t* a = acc.data_ptr<scalar_t>();
      const scalar_t* p = prod.data_ptr<scalar_t>();
      const int64_t grain = std::max<int64_t>(1, 16384 / nk);
      at::parallel_for(0, C, grain, [&](int64_t c0, int64_t c1) {
        for (int64_t j = 0; j < nk; ++j) {
          scalar_t* dst = a + target[rows[j] * K + k] * C;
          const scalar_t* src = p + j * C;
          for (int64_t c = c0; c < c1; ++c) dst[c] += src[c];
        }
      });
    });
  }
  return targets;
}

std::tuple<at::Tensor, at::Tensor> finalize_cpu(const at::Tensor& acc, at::Tensor& out, const at::Tensor& active,
                                                const at::Tensor& sites_in, const at::Tensor& scale_in,
                                                const at::Tensor& shift_in) {
  check_finalize_args(acc, out, active, sites_in, scale_in, shift_in);
  const int64_t m = sites_in.size(0), Ho = acc.size(0), Wo = acc.size(1), C = acc.size(2);
  auto changed = at::zeros({m}, acc.options().dtype(at::kBool));
  auto delta = at::empty({m, C}, acc.options());
  if (m == 0) return {changed, delta};
  auto sites = sites_in.contiguous();
  auto scale = scale_in.contiguous(), shift = shift_in.contiguous();
  const int32_t* sp = sites.data_ptr<int32_t>();
  for (int64_t i = 0; i < m; ++i)
    TORCH_CHECK(sp[2 * i] >= 0 && sp[2 * i] < Ho && sp[2 * i + 1] >= 0 && sp[2 * i + 1] < Wo, "sites[", i,
                "] = (", sp[2 * i], ", ", sp[2 * i + 1], ") lies outside the (", Ho, ", ", Wo, ") grid");
  const int64_t sy = out.stride(0), sx = out.stride(1), sc = out.stride(2);
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_finalize_cpu", [&] {
    const scalar_t* a = acc.data_ptr<scalar_t>();
    scalar_t* o = out.data_ptr<scalar_t>();
    const bool* act = active.data_ptr<bool>();
    const scalar_t* g = scale.data_ptr<scalar_t>();
    const scalar_t* b = shift.data_ptr<scalar_t>();
    bool* ch = changed.data_ptr<bool>();
    scalar_t* d = delta.data_ptr<scalar_t>();
    at::parallel_for(0, m, std::max<int64_t>(1, 2048 / std::max<int64_t>(C, 1)), [&](int64_t s, int64_t e) {
      for (int64_t i = s; i < e; ++i) {
        const int64_t y = sp[2 * i], x = sp[2 * i + 1];
        const bool on = act[y * Wo + x];
        const scalar_t* ai = a + (y * Wo + x) * C;
        scalar_t* oi = o + y * sy + x * sx;
        bool any = false;
        for (int64_t c = 0; c < C; ++c) {
          scalar_t v = on ? ai[c] * g[c] + b[c] : scalar_t(0);
          v = v > scalar_t(0) ? v : scalar_t(0);
          const scalar_t old = oi[c * sc];
          d[i * C + c] = v - old;
          any |= v != old;
          oi[c * sc] = v;
        }
        ch[i] = any;
      }
    });
  });
  return {changed, delta};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("sscater_scatter_", &scatter_cpu);
  m.impl("sscater_finalize_", &finalize_cpu);
}

}  // namespace sscater
}  // namespace lidarops
