// Sparse convolution on CPU: gather - GEMM - scatter per kernel offset.
//
// For each offset k the (output row, input row) pairs of the kernel map are listed; the input rows
// are gathered into a contiguous buffer (in parallel), multiplied by W[:, k, :]^T with one BLAS call
// (at::mm_out, itself multithreaded), and the product rows are added into the output (in parallel:
// for a fixed offset every output row appears at most once, so there are no races). Offsets are
// processed one after the other, so the summation order is fixed and results are deterministic.
// half/bfloat16 are computed in float32, float64 in float64.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include <cstring>

#include "lidarops/sparse.h"

namespace lidarops {
namespace sparse {
namespace {

at::ScalarType compute_type(at::ScalarType t) { return t == at::kDouble ? at::kDouble : at::kFloat; }

// The pairs of each kernel offset: rows [start[k], start[k + 1]) of in_rows / out_rows.
struct PairLists {
  std::vector<int64_t> start, in_rows, out_rows;
  int64_t count(int64_t k) const { return start[k + 1] - start[k]; }
  int64_t max_count() const {
    int64_t m = 0;
    for (size_t k = 0; k + 1 < start.size(); ++k) m = std::max(m, start[k + 1] - start[k]);
    return m;
  }
  // Offset k maps every row to itself (the centre of a submanifold convolution).
  bool identity(int64_t k, int64_t n_in, int64_t n_out) const {
    if (n_in != n_out || count(k) != n_out) return false;
    const int64_t* ir = in_rows.data() + start[k];
    for (int64_t j = 0; j < n_out; ++j)
      if (ir[j] != j) return false;
    return true;
  }
};

PairLists pair_lists(const at::Tensor& nbr, int64_t n_in) {
  const int64_t m = nbr.size(0), K = nbr.size(1);
  const int32_t* np = nbr.data_ptr<int32_t>();
  for (int64_t t = 0; t < m * K; ++t)
    TORCH_CHECK_VALUE(np[t] >= -1 && np[t] < n_in, "kernel_map entries must lie in [-1, N_in = ", n_in, "), got ",
                      np[t], " at row ", t / K, ", offset ", t % K);
  PairLists p;
  p.start.assign(static_cast<size_t>(K + 1), 0);
  std::vector<int64_t> counts(static_cast<size_t>(K), 0);
  // one task per offset, but small maps run inline: a parallel region costs more than it saves
  const int64_t grain = m * K < (int64_t(1) << 16) ? K : 1;
  at::parallel_for(0, K, grain, [&](int64_t s, int64_t e) {
    for (int64_t k = s; k < e; ++k) {
      int64_t c = 0;
      for (int64_t o = 0; o < m; ++o) c += np[o * K + k] >= 0;
      counts[k] = c;
    }
  });
  for (int64_t k = 0; k < K; ++k) p.start[k + 1] = p.start[k] + counts[k];
  p.in_rows.resize(static_cast<size_t>(p.start[K]));
  p.out_rows.resize(static_cast<size_t>(p.start[K]));
  at::parallel_for(0, K, grain, [&](int64_t s, int64_t e) {
    for (int64_t k = s; k < e; ++k) {
      int64_t j = p.start[k];
      for (int64_t o = 0; o < m; ++o) {
        const int32_t i = np[o * K + k];
        if (i >= 0) {
          p.in_rows[j] = i;
          p.out_rows[j] = o;
          ++j;
        }
      }
    }
  });
  return p;
}

// dst[j, :] = src[rows[j], :] for j < count (rows of `cols` elements of type T).
template <typename T>
void gather_rows(const T* src, const int64_t* rows, int64_t count, int64_t cols, T* dst) {
  const size_t bytes = static_cast<size_t>(cols) * sizeof(T);
  at::parallel_for(0, count, std::max<int64_t>(1, 16384 / std::max<int64_t>(cols, 1)), [&](int64_t s, int64_t e) {
    for (int64_t j = s; j < e; ++j) std::memcpy(dst + j * cols, src + rows[j] * cols, bytes);
  });
}

// dst[rows[j], :] += src[j, :]; rows must be distinct.
template <typename T>
void scatter_add_rows(const T* src, const int64_t* rows, int64_t count, int64_t cols, T* dst) {
  at::parallel_for(0, count, std::max<int64_t>(1, 16384 / std::max<int64_t>(cols, 1)), [&](int64_t s, int64_t e) {
    for (int64_t j = s; j < e; ++j) {
      T* d = dst + rows[j] * cols;
      const T* a = src + j * cols;
      for (int64_t c = 0; c < cols; ++c) d[c] += a[c];
    }
  });
}

at::Tensor sparse_kernel_map_order_cpu(const at::Tensor& nbr_in) {
  TORCH_CHECK_VALUE(nbr_in.dim() == 2 && nbr_in.scalar_type() == at::kInt, "kernel_map must be (N_out, K) int32, got shape ",
                    nbr_in.sizes(), " and dtype ", nbr_in.scalar_type());
  auto nbr = nbr_in.contiguous();
  const int64_t m = nbr.size(0), K = nbr.size(1);
  auto masks = at::empty({m}, nbr.options().dtype(at::kLong));
  const int32_t* np = nbr.data_ptr<int32_t>();
  int64_t* mp = masks.data_ptr<int64_t>();
  at::parallel_for(0, m, 16384, [&](int64_t s, int64_t e) {
    for (int64_t o = s; o < e; ++o) mp[o] = row_mask(np + o * K, K);
  });
  return std::get<1>(masks.sort(/*stable=*/true, /*dim=*/0, /*descending=*/false)).to(at::kInt);
}

// The CPU kernel lists the pairs of each offset, so it never touches absent pairs; `order` (a GPU
// tiling hint) is checked and ignored.
at::Tensor sparse_conv_cpu(const at::Tensor& features_in, const at::Tensor& weight_in, const at::Tensor& nbr_in,
                           const c10::optional<at::Tensor>& order) {
  check_conv_args(features_in, weight_in, nbr_in);
  check_order(order, nbr_in);
  const auto dtype = features_in.scalar_type();
  const auto ct = compute_type(dtype);
  const int64_t n_in = features_in.size(0), cin = features_in.size(1);
  const int64_t cout = weight_in.size(0), K = weight_in.size(1), n_out = nbr_in.size(0);
  auto acc = at::zeros({n_out, cout}, features_in.options().dtype(ct));
  if (n_out == 0 || cout == 0 || cin == 0 || n_in == 0 || K == 0) return acc.to(dtype);
  auto nbr = nbr_in.contiguous();
  const PairLists pairs = pair_lists(nbr, n_in);
  auto x = features_in.to(ct).contiguous();
  auto w = weight_in.to(ct).contiguous();
  const int64_t max_rows = pairs.max_count();
  auto gbuf = at::empty({max_rows, cin}, x.options());
  auto ybuf = at::empty({max_rows, cout}, x.options());
  AT_DISPATCH_FLOATING_TYPES(ct, "lidarops_sparse_conv_cpu", [&] {
    for (int64_t k = 0; k < K; ++k) {
      const int64_t rows = pairs.count(k);
      if (rows == 0) continue;
      auto wk_t = w.select(1, k).t();  // (Cin, Cout) view
      if (pairs.identity(k, n_in, n_out)) {
        acc.addmm_(x, wk_t);
        continue;
      }
      auto g = gbuf.narrow(0, 0, rows);
      auto y = ybuf.narrow(0, 0, rows);
      gather_rows(x.data_ptr<scalar_t>(), pairs.in_rows.data() + pairs.start[k], rows, cin, g.data_ptr<scalar_t>());
      at::mm_out(y, g, wk_t);
      scatter_add_rows(y.data_ptr<scalar_t>(), pairs.out_rows.data() + pairs.start[k], rows, cout,
                       acc.data_ptr<scalar_t>());
    }
  });
  return acc.to(dtype);
}

at::Tensor sparse_conv_weight_grad_cpu(const at::Tensor& features_in, const at::Tensor& grad_in,
                                       const at::Tensor& nbr_in) {
  check_weight_grad_args(features_in, grad_in, nbr_in);
  const auto dtype = features_in.scalar_type();
  const auto ct = compute_type(dtype);
  const int64_t n_in = features_in.size(0), cin = features_in.size(1);
  const int64_t cout = grad_in.size(1), K = nbr_in.size(1), n_out = nbr_in.size(0);
  auto dw = at::zeros({cout, K, cin}, features_in.options().dtype(ct));
  if (n_out == 0 || cout == 0 || cin == 0 || n_in == 0 || K == 0) return dw.to(dtype);
  auto nbr = nbr_in.contiguous();
  const PairLists pairs = pair_lists(nbr, n_in);
  auto x = features_in.to(ct).contiguous();
  auto gr = grad_in.to(ct).contiguous();
  const int64_t max_rows = pairs.max_count();
  auto xbuf = at::empty({max_rows, cin}, x.options());
  auto gbuf = at::empty({max_rows, cout}, x.options());
  auto dwk = at::empty({cout, cin}, x.options());
  AT_DISPATCH_FLOATING_TYPES(ct, "lidarops_sparse_conv_weight_grad_cpu", [&] {
    for (int64_t k = 0; k < K; ++k) {
      const int64_t rows = pairs.count(k);
      if (rows == 0) continue;
      if (pairs.identity(k, n_in, n_out)) {
        at::mm_out(dwk, gr.t(), x);
      } else {
        auto xs = xbuf.narrow(0, 0, rows);
        auto gs = gbuf.narrow(0, 0, rows);
        gather_rows(x.data_ptr<scalar_t>(), pairs.in_rows.data() + pairs.start[k], rows, cin, xs.data_ptr<scalar_t>());
        gather_rows(gr.data_ptr<scalar_t>(), pairs.out_rows.data() + pairs.start[k], rows, cout,
                    gs.data_ptr<scalar_t>());
        at::mm_out(dwk, gs.t(), xs);
      }
      dw.select(1, k).copy_(dwk);
    }
  });
  return dw.to(dtype);
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("sparse_kernel_map_order", &sparse_kernel_map_order_cpu);
  m.impl("sparse_conv", &sparse_conv_cpu);
  m.impl("sparse_conv_weight_grad", &sparse_conv_weight_grad_cpu);
}

}  // namespace sparse
}  // namespace lidarops
