// SSCATeR delta convolution on CPU. The scatter runs, per kernel tap, one GEMM over the changed rows
// that reach a site, then adds the products into the accumulator with threads split over output
// channels: no two threads write the same element, so it needs no atomics and the result does not
// depend on the thread count.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/from_blob.h>
#include <ATen/ops/full.h>
#include <ATen/ops/mm.h>
#include <ATen/ops/zeros.h>

#include <algorithm>
#include <cstring>
#include <functional>
#include <type_traits>
#include <vector>

#include "lidarops/sscater.h"

namespace lidarops {
namespace sscater {
namespace {

// The channel-sparse scatter: each row's nonzero delta channels (a delta is zero where a channel was
// zero before and after ReLU) times the tap's weight rows, added straight into the rows the taps reach,
// with no gather of the delta and no product matrix. Threads split the output channels as the GEMM
// path's scatter-add does, and every element is its old value plus the row's products in channel
// order, whichever loop below serves it: the sums do not depend on the thread count. Four vectors of
// the destination stay in registers across a row's channels.
typedef float F32x16 __attribute__((vector_size(64)));
typedef double F64x8 __attribute__((vector_size(64)));

template <typename V, typename T>
__attribute__((always_inline)) inline V load_vec(const T* p) {
  V v;
  __builtin_memcpy(&v, p, sizeof(V));
  return v;
}

template <typename V, typename T>
__attribute__((always_inline)) inline void store_vec(T* p, const V& v) {
  __builtin_memcpy(p, &v, sizeof(V));
}

template <typename T, typename V>
__attribute__((always_inline)) inline void sparse_rows(T* acc, int64_t C, int64_t c0, int64_t c1,
                                                       const int64_t* target, const std::vector<int64_t>& rows,
                                                       int64_t K, const int64_t* off, const int32_t* ch, const T* val,
                                                       const T* wt, int64_t Cin) {
  constexpr int64_t L = sizeof(V) / sizeof(T);
  for (const int64_t i : rows) {
    const int64_t e0 = off[i], e1 = off[i + 1];
    for (int64_t k = 0; k < K; ++k) {
      const int64_t t = target[i * K + k];
      if (t < 0) continue;
      T* dst = acc + t * C;
      const T* wk = wt + k * Cin * C;
      int64_t b = c0;
      for (; b + 4 * L <= c1; b += 4 * L) {
        V s0 = load_vec<V>(dst + b), s1 = load_vec<V>(dst + b + L), s2 = load_vec<V>(dst + b + 2 * L),
          s3 = load_vec<V>(dst + b + 3 * L);
        for (int64_t e = e0; e < e1; ++e) {
          const T v = val[e];
          const T* w = wk + ch[e] * C + b;
          s0 += v * load_vec<V>(w);
          s1 += v * load_vec<V>(w + L);
          s2 += v * load_vec<V>(w + 2 * L);
          s3 += v * load_vec<V>(w + 3 * L);
        }
        store_vec(dst + b, s0), store_vec(dst + b + L, s1), store_vec(dst + b + 2 * L, s2);
        store_vec(dst + b + 3 * L, s3);
      }
      for (; b + L <= c1; b += L) {
        V s0 = load_vec<V>(dst + b);
        for (int64_t e = e0; e < e1; ++e) s0 += val[e] * load_vec<V>(wk + ch[e] * C + b);
        store_vec(dst + b, s0);
      }
      for (; b < c1; ++b) {
        T s0 = dst[b];
        for (int64_t e = e0; e < e1; ++e) s0 += val[e] * wk[ch[e] * C + b];
        dst[b] = s0;
      }
    }
  }
}

// Compiled for AVX-512, AVX2 and the baseline, picked at load time by the CPU: the extension is built
// without -march flags, and the sparse rows beat the GEMM only with wide vectors.
__attribute__((target_clones("avx512f", "avx2", "default"))) void sparse_rows_f32(
    float* acc, int64_t C, int64_t c0, int64_t c1, const int64_t* target, const std::vector<int64_t>& rows, int64_t K,
    const int64_t* off, const int32_t* ch, const float* val, const float* wt, int64_t Cin) {
  sparse_rows<float, F32x16>(acc, C, c0, c1, target, rows, K, off, ch, val, wt, Cin);
}

__attribute__((target_clones("avx512f", "avx2", "default"))) void sparse_rows_f64(
    double* acc, int64_t C, int64_t c0, int64_t c1, const int64_t* target, const std::vector<int64_t>& rows,
    int64_t K, const int64_t* off, const int32_t* ch, const double* val, const double* wt, int64_t Cin) {
  sparse_rows<double, F64x8>(acc, C, c0, c1, target, rows, K, off, ch, val, wt, Cin);
}

template <typename T>
void scatter_sparse(at::Tensor& acc, const at::Tensor& delta, const at::Tensor& weight_in, const int64_t* target,
                    int64_t n, int64_t K) {
  const int64_t C = acc.size(2), Cin = delta.size(1);
  // the nonzero channels of each row, and the rows that reach a site through some tap
  std::vector<int64_t> off(n + 1, 0), rows;
  std::vector<int32_t> ch;
  std::vector<T> val;
  ch.reserve(n * Cin / 2);
  val.reserve(n * Cin / 2);
  const T* d = delta.data_ptr<T>();
  for (int64_t i = 0; i < n; ++i) {
    bool reaches = false;
    for (int64_t k = 0; k < K && !reaches; ++k) reaches = target[i * K + k] >= 0;
    if (reaches) {
      for (int64_t c = 0; c < Cin; ++c)
        if (d[i * Cin + c] != T(0)) {
          ch.push_back(static_cast<int32_t>(c));
          val.push_back(d[i * Cin + c]);
        }
      if (static_cast<int64_t>(ch.size()) > off[i]) rows.push_back(i);
    }
    off[i + 1] = static_cast<int64_t>(ch.size());
  }
  if (rows.empty()) return;
  auto wt = weight_in.permute({1, 2, 3, 0}).reshape({K, Cin, C}).contiguous();  // (K, Cin, Cout)
  const T* w = wt.data_ptr<T>();
  T* a = acc.data_ptr<T>();
  constexpr int64_t kChunk = 64 / sizeof(T);  // one vector register: the smallest share of a thread
  at::parallel_for(0, (C + kChunk - 1) / kChunk, 1, [&](int64_t q0, int64_t q1) {
    const int64_t c0 = q0 * kChunk, c1 = std::min(C, q1 * kChunk);
    if constexpr (std::is_same_v<T, float>)
      sparse_rows_f32(a, C, c0, c1, target, rows, K, off.data(), ch.data(), val.data(), w, Cin);
    else
      sparse_rows_f64(a, C, c0, c1, target, rows, K, off.data(), ch.data(), val.data(), w, Cin);
  });
}

// The output site each (row, tap) pair of the first n rows reaches (tap_target; -1 also at an inactive output
// when act is given), rows in parallel; returns how many pairs reach a site.
int64_t fill_targets(int64_t* target, const int32_t* sp, int64_t n, int64_t kh, int64_t kw, int64_t stride,
                     int64_t padding, int64_t Ho, int64_t Wo, bool transposed, const bool* act) {
  const int64_t K = kh * kw;
  return at::parallel_reduce(
      0, n, 1024, int64_t(0),
      [&](int64_t i0, int64_t i1, int64_t sum) {
        for (int64_t i = i0; i < i1; ++i) {
          const int64_t y = sp[2 * i], x = sp[2 * i + 1];
          int64_t* row = target + i * K;
          for (int64_t ky = 0; ky < kh; ++ky) {  // tap k = ky * kw + kx, as tap_target
            const int64_t oy = y < 0 || x < 0 ? -1 : reach(y, ky, stride, padding, Ho, transposed);
            for (int64_t kx = 0; kx < kw; ++kx) {
              const int64_t ox = oy < 0 ? -1 : reach(x, kx, stride, padding, Wo, transposed);
              int64_t o = ox < 0 ? -1 : oy * Wo + ox;
              if (o >= 0 && act != nullptr && !act[o]) o = -1;
              row[ky * kw + kx] = o;
              sum += o >= 0;
            }
          }
        }
        return sum;
      },
      std::plus<int64_t>());
}

// Rows ahead of the one being worked on whose scattered map rows are fetched early: a changed site's rows lie
// anywhere in a map larger than the cache, and a load that waits for memory stalls the loop.
constexpr int64_t kAhead = 4;

// Ask for the n values from p on (one request per 64-byte line), to be written.
template <typename T>
inline void prefetch_range(T* p, int64_t n) {
#if defined(__GNUC__) || defined(__clang__)
  const char* b = reinterpret_cast<const char*>(p);
  for (int64_t off = 0; off < n * static_cast<int64_t>(sizeof(T)); off += 64) __builtin_prefetch(b + off, 1, 3);
#else
  (void)p, (void)n;
#endif
}

at::Tensor scatter_cpu(at::Tensor& acc, const at::Tensor& sites_in, const at::Tensor& delta_in,
                       const at::Tensor& weight_in, int64_t stride, int64_t padding, bool transposed,
                       const c10::optional<at::Tensor>& out_active, const c10::optional<at::Tensor>& count,
                       double channel_sparse) {
  check_scatter_args(acc, sites_in, delta_in, weight_in, stride, padding);
  TORCH_CHECK_VALUE(channel_sparse == channel_sparse, "channel_sparse must be a number (a share of zero delta "
                    "values), got nan");
  check_out_active(out_active, acc);
  check_count(count, acc);
  const int64_t n_rows = sites_in.size(0);
  const int64_t Ho = acc.size(0), Wo = acc.size(1), C = acc.size(2);
  const int64_t kh = weight_in.size(1), kw = weight_in.size(2), K = kh * kw;
  const int64_t n = count.has_value() ? std::clamp<int64_t>(count->item<int64_t>(), 0, n_rows) : n_rows;
  auto targets = n < n_rows ? at::full({n_rows * K}, -1, sites_in.options().dtype(at::kLong))
                            : at::empty({n_rows * K}, sites_in.options().dtype(at::kLong));
  if (n == 0) return targets;
  auto sites = sites_in.contiguous();
  const int32_t* sp = sites.data_ptr<int32_t>();
  int64_t* target = targets.data_ptr<int64_t>();
  const int64_t reaching = fill_targets(target, sp, n, kh, kw, stride, padding, Ho, Wo, transposed,
                                        out_active.has_value() ? out_active->data_ptr<bool>() : nullptr);
  if (acc.numel() == 0) return targets;
  auto delta = delta_in.contiguous();
  if (channel_sparse <= 1.0) {
    int64_t zeros = 0;
    AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_zeros_cpu", [&] {
      const scalar_t* d = delta.data_ptr<scalar_t>();
      zeros = at::parallel_reduce(0, n * delta.size(1), int64_t(1) << 16, int64_t(0),
                                  [d](int64_t j0, int64_t j1, int64_t sum) {
                                    int64_t z = 0;  // a local count: the loop vectorises
                                    for (int64_t j = j0; j < j1; ++j) z += d[j] == scalar_t(0);
                                    return sum + z;
                                  },
                                  std::plus<int64_t>());
    });
    if (static_cast<double>(zeros) >= channel_sparse * static_cast<double>(n * delta.size(1))) {
      AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_scatter_sparse_cpu",
                                 [&] { scatter_sparse<scalar_t>(acc, delta, weight_in, target, n, K); });
      return targets;
    }
  }
  // When most (row, tap) pairs reach a site (a submanifold or transposed layer where the change is dense):
  // one GEMM of each chunk of rows by every tap's weights (K * Cout columns), then the scatter-add. It skips
  // the per-tap gathers of the rows and runs one large GEMM; the products of the pairs that miss are wasted,
  // so strided layers (each row reaches about a quarter of its taps) and sparse outputs keep the per-tap path
  // below. A chunk's products (4 MB, one buffer for every chunk) stay in cache for the scatter-add; chunks four
  // times larger, written out to memory, made the op 10-15 % slower on a 2-core AVX-512 machine.
  const int64_t Cin = delta.size(1);
  if (reaching * 4 >= n * K * 3) {
    auto w_all = weight_in.permute({1, 2, 0, 3}).reshape({K * C, Cin});  // (K * Cout, Cin): a view for tap-major weights
    const int64_t chunk = std::min(n, std::max<int64_t>(1, (int64_t(1) << 20) / std::max<int64_t>(K * C, 1)));
    auto buffer = at::empty({chunk, K * C}, acc.options());
    for (int64_t r0 = 0; r0 < n; r0 += chunk) {
      const int64_t r1 = std::min(n, r0 + chunk);
      auto prod = buffer.narrow(0, 0, r1 - r0);  // (rows, K * Cout)
      at::mm_out(prod, delta.narrow(0, r0, r1 - r0), w_all.t());
      AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_scatter_rows_cpu", [&] {
        scalar_t* a = acc.data_ptr<scalar_t>();
        const scalar_t* p = prod.data_ptr<scalar_t>();
        at::parallel_for(0, C, std::max<int64_t>(1, 16384 / ((r1 - r0) * K)), [&](int64_t c0, int64_t c1) {
          for (int64_t i = r0; i < r1; ++i) {
            if (i + kAhead < r1)  // the target rows of the site kAhead ahead, while this one adds
              for (int64_t k = 0; k < K; ++k) {
                const int64_t o = target[(i + kAhead) * K + k];
                if (o >= 0) prefetch_range(a + o * C + c0, c1 - c0);
              }
            for (int64_t k = 0; k < K; ++k) {
              const int64_t o = target[i * K + k];
              if (o < 0) continue;
              scalar_t* dst = a + o * C;
              const scalar_t* src = p + ((i - r0) * K + k) * C;
              for (int64_t c = c0; c < c1; ++c) dst[c] += src[c];
            }
          }
        });
      });
    }
    return targets;
  }
  // Per tap: gather the rows that reach a site, one GEMM, scatter-add. Only the (changed input,
  // updated output) pairs cost a product, as in a gather-GEMM-scatter sparse convolution.
  auto w_taps = weight_in.permute({1, 2, 0, 3}).reshape({K, C, Cin});  // (K, Cout, Cin)
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

// BN + ReLU of one site's accumulator into its output row (channel stride sc; kUnit: sc == 1, known
// at compile time so that the loop vectorises), the change into delta; returns whether any channel
// changed.
template <typename T, bool kUnit>
bool finalize_row(const T* __restrict__ acc, const T* __restrict__ scale, const T* __restrict__ shift, bool on,
                  T* __restrict__ out, int64_t sc, T* __restrict__ delta, int64_t C) {
  const int64_t s = kUnit ? 1 : sc;
  int any = 0;
  for (int64_t c = 0; c < C; ++c) {
    T v = on ? acc[c] * scale[c] + shift[c] : T(0);
    v = v > T(0) ? v : T(0);
    const T old = out[c * s];
    delta[c] = v - old;
    any |= v != old;
    out[c * s] = v;
  }
  return any != 0;
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
    TORCH_CHECK_VALUE(sp[2 * i] >= 0 && sp[2 * i] < Ho && sp[2 * i + 1] >= 0 && sp[2 * i + 1] < Wo, "sites[", i,
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
        ch[i] = sc == 1 ? finalize_row<scalar_t, true>(ai, g, b, on, oi, sc, d + i * C, C)
                        : finalize_row<scalar_t, false>(ai, g, b, on, oi, sc, d + i * C, C);
      }
    });
  });
  return {changed, delta};
}

// ---- the fused layer step (sequential loops: the lists are short; finalize runs in parallel) ----

std::tuple<at::Tensor, at::Tensor, at::Tensor> cover_update_cpu(at::Tensor& cover, at::Tensor& active, at::Tensor& stamp,
                                                     int64_t value, const at::Tensor& added_in,
                                                     const at::Tensor& removed_in, int64_t kh, int64_t kw,
                                                     int64_t stride, int64_t padding) {
  check_cover_update_args(cover, active, stamp, added_in, removed_in, kh, kw, stride, padding);
  check_stamp_value(value, "value");
  const int64_t Ho = cover.size(0), Wo = cover.size(1), K = kh * kw;
  const int64_t a = added_in.size(0), r = removed_in.size(0), rows = std::min((a + r) * K, Ho * Wo);
  auto added_out = at::full({rows, 2}, -1, added_in.options());  // an output flips at most once
  auto removed_out = at::full({rows, 2}, -1, added_in.options());
  auto added = added_in.contiguous(), removed = removed_in.contiguous();
  int32_t* cv = cover.data_ptr<int32_t>();
  bool* act = active.data_ptr<bool>();
  int32_t* st = stamp.data_ptr<int32_t>();
  std::vector<int64_t> touched;
  touched.reserve(rows);
  for (int64_t i = 0; i < a + r; ++i) {
    const bool add = i < a;
    const int32_t* sp = add ? added.data_ptr<int32_t>() + 2 * i : removed.data_ptr<int32_t>() + 2 * (i - a);
    if (sp[0] < 0 || sp[1] < 0) continue;
    for (int64_t ky = 0; ky < kh; ++ky) {
      const int64_t oy = reach(sp[0], ky, stride, padding, Ho, false);
      if (oy < 0) continue;
      for (int64_t kx = 0; kx < kw; ++kx) {
        const int64_t ox = reach(sp[1], kx, stride, padding, Wo, false);
        if (ox < 0) continue;
        const int64_t o = oy * Wo + ox;
        cv[o] += add ? 1 : -1;
        if (st[o] < value) {
          st[o] = static_cast<int32_t>(value);
          touched.push_back(o);
        }
      }
    }
  }
  int32_t* ao = added_out.data_ptr<int32_t>();
  int32_t* ro = removed_out.data_ptr<int32_t>();
  int64_t na = 0, nr = 0;
  for (size_t i = 0; i < touched.size(); ++i) {
    const int64_t o = touched[i];
    const bool after = cv[o] > 0;
    if (after == act[o]) continue;
    act[o] = after;
    int32_t* dst = after ? ao + 2 * na++ : ro + 2 * nr++;
    dst[0] = static_cast<int32_t>(o / Wo);
    dst[1] = static_cast<int32_t>(o % Wo);
  }
  auto counts = at::empty({2}, added_in.options().dtype(at::kLong));
  counts.data_ptr<int64_t>()[0] = na;
  counts.data_ptr<int64_t>()[1] = nr;
  return {added_out, removed_out, counts};
}

std::tuple<at::Tensor, at::Tensor> children_cpu(at::Tensor& active, const at::Tensor& added_in,
                                                const at::Tensor& removed_in, int64_t kh, int64_t kw, int64_t stride,
                                                int64_t padding) {
  check_children_args(active, added_in, removed_in, kh, kw, stride, padding);
  const int64_t Ho = active.size(0), Wo = active.size(1), K = kh * kw;
  bool* act = active.data_ptr<bool>();
  auto run = [&](const at::Tensor& in, bool on) {
    auto sites = in.contiguous();
    const int64_t n = sites.size(0);
    auto out = at::full({n * K, 2}, -1, sites.options());
    const int32_t* sp = sites.data_ptr<int32_t>();
    int32_t* op = out.data_ptr<int32_t>();
    for (int64_t i = 0; i < n; ++i) {
      if (sp[2 * i] < 0 || sp[2 * i + 1] < 0) continue;
      for (int64_t k = 0; k < K; ++k) {
        const int64_t oy = reach(sp[2 * i], k / kw, stride, padding, Ho, true);
        const int64_t ox = oy < 0 ? -1 : reach(sp[2 * i + 1], k % kw, stride, padding, Wo, true);
        if (ox < 0) continue;
        act[oy * Wo + ox] = on;
        op[2 * (i * K + k)] = static_cast<int32_t>(oy);
        op[2 * (i * K + k) + 1] = static_cast<int32_t>(ox);
      }
    }
    return out;
  };
  auto a = run(added_in, true);
  auto r = run(removed_in, false);  // after the added: a site under both ends inactive
  return {a, r};
}

void gather_cpu(at::Tensor& acc, const at::Tensor& input, const at::Tensor& weight_in, const at::Tensor& sites_in,
                int64_t stride, int64_t padding, const c10::optional<at::Tensor>& count) {
  check_gather_args(acc, input, weight_in, sites_in, stride, padding);
  check_count(count, acc);
  const int64_t m = count.has_value() ? std::clamp<int64_t>(count->item<int64_t>(), 0, sites_in.size(0))
                                      : sites_in.size(0);
  if (m == 0) return;
  const int64_t Ho = acc.size(0), Wo = acc.size(1), C = acc.size(2);
  const int64_t Hi = input.size(0), Wi = input.size(1), Ci = input.size(2);
  const int64_t kh = weight_in.size(1), kw = weight_in.size(2);
  auto w = weight_in.contiguous();
  auto sites = sites_in.contiguous();
  const int32_t* sp = sites.data_ptr<int32_t>();
  const int64_t s0 = input.stride(0), s1 = input.stride(1), s2 = input.stride(2), P = kh * kw * Ci;
  // im2col of the valid sites' windows, then one GEMM with the (Cout, kh * kw * Cin) weight
  std::vector<int64_t> rows;
  rows.reserve(m);
  for (int64_t i = 0; i < m; ++i) {
    int64_t y, x;
    if (site_at(sp, i, Ho, Wo, y, x)) rows.push_back(y * Wo + x);
  }
  const int64_t n = static_cast<int64_t>(rows.size());
  if (n == 0) return;
  auto patches = at::zeros({n, P}, acc.options());
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_gather_cpu", [&] {
    const scalar_t* in = input.data_ptr<scalar_t>();
    scalar_t* pp = patches.data_ptr<scalar_t>();
    at::parallel_for(0, n, 64, [&](int64_t b, int64_t e) {
      for (int64_t r = b; r < e; ++r) {
        for_window(rows[r] / Wo, rows[r] % Wo, kh, kw, stride, padding, Hi, Wi,
                   [&](int64_t ky, int64_t kx, int64_t iy, int64_t ix) {
                     const scalar_t* src = in + iy * s0 + ix * s1;
                     scalar_t* dst = pp + r * P + (ky * kw + kx) * Ci;
                     for (int64_t ci = 0; ci < Ci; ++ci) dst[ci] = src[ci * s2];
                   });
      }
    });
    auto res = at::mm(patches, w.view({C, P}).t()).contiguous();  // (n, Cout)
    scalar_t* a = acc.data_ptr<scalar_t>();
    const scalar_t* rp = res.data_ptr<scalar_t>();
    for (int64_t r = 0; r < n; ++r) std::copy(rp + r * C, rp + (r + 1) * C, a + rows[r] * C);
  });
}

std::tuple<at::Tensor, at::Tensor> touch_cpu(at::Tensor& stamp, at::Tensor& acc, int64_t value,
                                             const at::Tensor& targets_in, const at::Tensor& added_in,
                                             const at::Tensor& removed_in) {
  check_touch_args(stamp, acc, targets_in, added_in, removed_in);
  check_stamp_value(value, "value");
  const int64_t Ho = acc.size(0), Wo = acc.size(1), C = acc.size(2), HW = Ho * Wo;
  const int64_t R = targets_in.size(0), a = added_in.size(0), r = removed_in.size(0);
  auto cand = at::full({std::min(R + a + r, HW), 2}, -1, added_in.options());  // each site at most once
  auto count = at::zeros({1}, targets_in.options());
  auto targets = targets_in.contiguous();
  auto added = added_in.contiguous(), removed = removed_in.contiguous();
  int32_t* st = stamp.data_ptr<int32_t>();
  int32_t* cp = cand.data_ptr<int32_t>();
  int64_t m = 0;
  auto mark = [&](int64_t o, int64_t v) {
    const int32_t old = st[o];
    if (old < v) st[o] = static_cast<int32_t>(v);
    if (old < value) {
      cp[2 * m] = static_cast<int32_t>(o / Wo);
      cp[2 * m + 1] = static_cast<int32_t>(o % Wo);
      ++m;
    }
  };
  const int64_t* tp = targets.data_ptr<int64_t>();
  for (int64_t i = 0; i < R; ++i)
    if (tp[i] >= 0 && tp[i] < HW) mark(tp[i], value);
  const int32_t* ap = added.data_ptr<int32_t>();
  for (int64_t i = 0; i < a; ++i) {
    int64_t y, x;
    if (site_at(ap, i, Ho, Wo, y, x)) mark(y * Wo + x, value + 1);
  }
  const int32_t* rp = removed.data_ptr<int32_t>();
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_touch_cpu", [&] {
    scalar_t* ac = acc.data_ptr<scalar_t>();
    for (int64_t i = 0; i < r; ++i) {
      int64_t y, x;
      if (!site_at(rp, i, Ho, Wo, y, x)) continue;
      mark(y * Wo + x, value + 1);
      std::fill(ac + (y * Wo + x) * C, ac + (y * Wo + x + 1) * C, scalar_t(0));
    }
  });
  count.data_ptr<int64_t>()[0] = m;
  return {cand, count};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> finalize_compact_cpu(const at::Tensor& acc, at::Tensor& out,
                                                                    const at::Tensor& active, const at::Tensor& cand,
                                                                    const at::Tensor& count, const at::Tensor& stamp,
                                                                    int64_t status_value, const at::Tensor& scale_in,
                                                                    const at::Tensor& shift_in) {
  check_finalize_args(acc, out, active, cand, scale_in, shift_in, "cand");
  check_finalize_compact_args(acc, cand, count, stamp, status_value);
  // count is the caller's: clamped to the rows of cand (the CUDA kernel reads it on the device)
  const int64_t m = std::clamp<int64_t>(count.item<int64_t>(), 0, cand.size(0));
  const int64_t R = cand.size(0), Ho = acc.size(0), Wo = acc.size(1), C = acc.size(2);
  auto sites = cand.contiguous();
  const int32_t* sp = sites.data_ptr<int32_t>();
  for (int64_t i = 0; i < m; ++i)
    TORCH_CHECK_VALUE(sp[2 * i] >= 0 && sp[2 * i] < Ho && sp[2 * i + 1] >= 0 && sp[2 * i + 1] < Wo, "cand[", i,
                      "] = (", sp[2 * i], ", ", sp[2 * i + 1], ") lies outside the (", Ho, ", ", Wo, ") grid");
  auto sites_out = at::empty({R, 2}, cand.options());
  auto delta_out = at::empty({R, C}, acc.options());
  auto counts = at::zeros({3}, count.options());
  auto scale = scale_in.contiguous(), shift = shift_in.contiguous();
  const int32_t* st = stamp.data_ptr<int32_t>();
  const bool* act = active.data_ptr<bool>();
  int32_t* so = sites_out.data_ptr<int32_t>();
  const int64_t sy = out.stride(0), sx = out.stride(1), sc = out.stride(2);
  // Each chunk of rows evaluates its sites and writes the changed ones' deltas and sites compacted from
  // its own first row (a row's compacted place is never after it, so chunks write disjoint rows and no
  // row is overwritten before it is read); the chunks' runs are then moved down to their places in order.
  // One pass over the rows and no (m, C) temporary: the deltas are written where they end up, or moved once.
  const int64_t chunk = std::max<int64_t>(std::max<int64_t>(1, 8192 / std::max<int64_t>(C, 1)),
                                          (m + 4 * at::get_num_threads() - 1) / (4 * at::get_num_threads()));
  const int64_t chunks = m == 0 ? 0 : (m + chunk - 1) / chunk;
  std::vector<int64_t> kept(chunks, 0), flagged(chunks, 0);
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_finalize_compact_cpu", [&] {
    const scalar_t* a = acc.data_ptr<scalar_t>();
    scalar_t* o = out.data_ptr<scalar_t>();
    const scalar_t* g = scale.data_ptr<scalar_t>();
    const scalar_t* b = shift.data_ptr<scalar_t>();
    scalar_t* d = delta_out.data_ptr<scalar_t>();
    at::parallel_for(0, chunks, 1, [&](int64_t k0, int64_t k1) {
      for (int64_t k = k0; k < k1; ++k) {
        const int64_t i0 = k * chunk, i1 = std::min(m, i0 + chunk);
        int64_t n = i0, f = 0;  // the chunk's next compacted row
        for (int64_t i = i0; i < i1; ++i) {
          if (i + kAhead < i1) {  // the rows ahead, as in the scatter
            const int64_t y2 = sp[2 * (i + kAhead)], x2 = sp[2 * (i + kAhead) + 1];
            prefetch_range(a + (y2 * Wo + x2) * C, C);
            if (sc == 1) prefetch_range(o + y2 * sy + x2 * sx, C);
          }
          const int64_t y = sp[2 * i], x = sp[2 * i + 1], s = y * Wo + x;
          const scalar_t* ai = a + s * C;
          scalar_t* oi = o + y * sy + x * sx;
          const bool ch = sc == 1 ? finalize_row<scalar_t, true>(ai, g, b, act[s], oi, sc, d + n * C, C)
                                  : finalize_row<scalar_t, false>(ai, g, b, act[s], oi, sc, d + n * C, C);
          f += ch || st[s] == status_value;
          if (!ch) continue;
          so[2 * n] = static_cast<int32_t>(y);
          so[2 * n + 1] = static_cast<int32_t>(x);
          ++n;
        }
        kept[k] = n - i0;
        flagged[k] = f;
      }
    });
    int64_t n = 0, f = 0;
    for (int64_t k = 0; k < chunks; ++k) {
      const int64_t i0 = k * chunk;
      if (n != i0 && kept[k] > 0) {  // down, over rows already moved or spent: memmove for the overlap
        std::memmove(d + n * C, d + i0 * C, sizeof(scalar_t) * kept[k] * C);
        std::memmove(so + 2 * n, so + 2 * i0, sizeof(int32_t) * 2 * kept[k]);
      }
      n += kept[k];
      f += flagged[k];
    }
    // padding rows: (-1, -1) sites, zero deltas
    std::fill(so + 2 * n, so + 2 * R, int32_t(-1));
    std::fill(d + n * C, d + R * C, scalar_t(0));
    int64_t* cn = counts.data_ptr<int64_t>();
    cn[0] = n;
    cn[1] = f;
    cn[2] = m;
  });
  return {sites_out, delta_out, counts};
}

void dense_finalize_cpu(const at::Tensor& y, at::Tensor& acc, at::Tensor& out, const at::Tensor& scale_in,
                        const at::Tensor& shift_in, const c10::optional<at::Tensor>& active,
                        const c10::optional<at::Tensor>& out_nchw) {
  check_dense_finalize_args(y, acc, out, scale_in, shift_in, active, out_nchw);
  const int64_t Ho = acc.size(0), Wo = acc.size(1), C = acc.size(2), S = Ho * Wo;
  if (acc.numel() == 0) return;
  auto scale = scale_in.contiguous(), shift = shift_in.contiguous();
  const int64_t ysc = y.stride(0), ysy = y.stride(1), ysx = y.stride(2);
  const int64_t osy = out.stride(0), osx = out.stride(1), osc = out.stride(2);
  const bool* act = active.has_value() ? active->data_ptr<bool>() : nullptr;
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_dense_finalize_cpu", [&] {
    const scalar_t* yp = y.data_ptr<scalar_t>();
    const scalar_t* sc = scale.data_ptr<scalar_t>();
    const scalar_t* sh = shift.data_ptr<scalar_t>();
    scalar_t* a = acc.data_ptr<scalar_t>();
    scalar_t* o = out.data_ptr<scalar_t>();
    scalar_t* nchw = out_nchw.has_value() ? out_nchw->data_ptr<scalar_t>() : nullptr;
    at::parallel_for(0, S, std::max<int64_t>(1, 4096 / std::max<int64_t>(C, 1)), [&](int64_t s0, int64_t s1) {
      for (int64_t s = s0; s < s1; ++s) {
        const int64_t iy = s / Wo, ix = s % Wo;
        const bool on = act == nullptr || act[s];
        const scalar_t* ys = yp + iy * ysy + ix * ysx;
        scalar_t* as = a + s * C;
        scalar_t* os = o + iy * osy + ix * osx;
        for (int64_t c = 0; c < C; ++c) {
          const scalar_t v = on ? ys[c * ysc] : scalar_t(0);
          scalar_t f = on ? v * sc[c] + sh[c] : scalar_t(0);
          f = f > scalar_t(0) ? f : scalar_t(0);
          as[c] = v;
          os[c * osc] = f;
          if (nchw != nullptr) nchw[c * S + s] = f;
        }
      }
    });
  });
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("sscater_scatter_", &scatter_cpu);
  m.impl("sscater_finalize_", &finalize_cpu);
  m.impl("sscater_cover_update_", &cover_update_cpu);
  m.impl("sscater_children_", &children_cpu);
  m.impl("sscater_gather_", &gather_cpu);
  m.impl("sscater_touch_", &touch_cpu);
  m.impl("sscater_finalize_compact_", &finalize_compact_cpu);
  m.impl("sscater_dense_finalize_", &dense_finalize_cpu);
}

}  // namespace sscater
}  // namespace lidarops
