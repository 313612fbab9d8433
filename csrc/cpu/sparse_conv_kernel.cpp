// Sparse convolution on CPU: gather - GEMM - scatter.
//
// Forward: the output rows are split into a few blocks (about two per thread), each owned by one
// task of a single parallel region. For each kernel offset a task lists the rows of its block that
// have an input there, gathers those input rows into a contiguous buffer, multiplies them by
// W[:, k, :]^T with one BLAS call, and adds the products into its own output rows: no races, and
// every output row sums its offsets in the same order (deterministic for a given thread count).
// The centre offset of a submanifold map (row o reads row o) skips the gather.
// Weight gradient: one task per kernel offset, dW[:, k, :] = G_k^T X_k over the pairs of offset k.
// half/bfloat16 are computed in float32, float64 in float64. One parallel region per call: on a
// shared, oversubscribed CPU every region costs a thread rendezvous.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/mm.h>
#include <ATen/ops/zeros.h>

#include <cstring>

#include "lidarops/sparse.h"

namespace lidarops {
namespace sparse {
namespace {

at::ScalarType compute_type(at::ScalarType t) { return t == at::kDouble ? at::kDouble : at::kFloat; }

void check_map_values(const at::Tensor& nbr, int64_t n_in) {
  const int32_t* np = nbr.data_ptr<int32_t>();
  const int64_t total = nbr.numel(), K = nbr.size(1);
  for (int64_t t = 0; t < total; ++t)
    TORCH_CHECK_VALUE(np[t] >= -1 && np[t] < n_in, "kernel_map entries must lie in [-1, N_in = ", n_in, "), got ",
                      np[t], " at row ", t / K, ", offset ", t % K);
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
// tiling hint) and `algo` / `splits` (the CUDA kernel choice) are checked and ignored.
at::Tensor sparse_conv_cpu_impl(const at::Tensor& features_in, const at::Tensor& weight_in, const at::Tensor& nbr_in,
                                const ConvEpilogue& epi) {
  const auto dtype = features_in.scalar_type();
  const auto ct = compute_type(dtype);
  const int64_t n_in = features_in.size(0), cin = features_in.size(1);
  const int64_t cout = weight_in.size(0), K = weight_in.size(1), n_out = nbr_in.size(0);
  if (n_out == 0 || cout == 0 || cin == 0 || n_in == 0 || K == 0) {
    auto acc = at::zeros({n_out, cout}, features_in.options().dtype(ct));
    if (n_out > 0 && cout > 0 && (epi.scale || epi.shift || epi.relu)) {  // every row is epi(0)
      AT_DISPATCH_FLOATING_TYPES(ct, "lidarops_sparse_conv_cpu_empty", [&] {
        scalar_t* ap = acc.data_ptr<scalar_t>();
        for (int64_t o = 0; o < n_out; ++o)
          for (int64_t c = 0; c < cout; ++c) ap[o * cout + c] = epi(scalar_t(0), c);
      });
    }
    return acc.to(dtype);
  }
  auto acc = at::empty({n_out, cout}, features_in.options().dtype(ct));  // every block writes its rows
  auto nbr = nbr_in.contiguous();
  check_map_values(nbr, n_in);
  // plain data inside the kernel (the out= BLAS calls refuse tensors that require grad)
  auto x = features_in.detach().to(ct).contiguous();
  auto w = weight_in.detach().to(ct).contiguous();
  const int32_t* np = nbr.data_ptr<int32_t>();
  // about two blocks per thread, at least 256 rows each (small maps: one block, no parallel region)
  const int64_t threads = at::get_num_threads();
  const int64_t block = std::max<int64_t>(256, (n_out + 2 * threads - 1) / (2 * threads));
  const int64_t nblocks = (n_out + block - 1) / block;
  AT_DISPATCH_FLOATING_TYPES(ct, "lidarops_sparse_conv_cpu", [&] {
    const scalar_t* xp = x.data_ptr<scalar_t>();
    scalar_t* ap = acc.data_ptr<scalar_t>();
    at::parallel_for(0, nblocks, 1, [&](int64_t b0, int64_t b1) {
      // pairs of the block, grouped by offset: two row-major passes over the map rows (a scan of
      // one offset's column would stride through memory)
      std::vector<int64_t> start(static_cast<size_t>(K + 1)), fill(static_cast<size_t>(K));
      std::vector<uint8_t> same_rows(static_cast<size_t>(K));
      std::vector<int64_t> in_rows, out_rows;
      at::Tensor gbuf, ybuf;
      for (int64_t blk = b0; blk < b1; ++blk) {
        const int64_t o0 = blk * block, o1 = std::min(n_out, o0 + block);
        std::fill(start.begin(), start.end(), 0);
        for (int64_t o = o0; o < o1; ++o)
          for (int64_t k = 0; k < K; ++k) start[k + 1] += np[o * K + k] >= 0;
        for (int64_t k = 0; k < K; ++k) start[k + 1] += start[k];
        in_rows.resize(static_cast<size_t>(start[K]));
        out_rows.resize(static_cast<size_t>(start[K]));
        std::copy(start.begin(), start.end() - 1, fill.begin());
        std::fill(same_rows.begin(), same_rows.end(), uint8_t(1));
        for (int64_t o = o0; o < o1; ++o)
          for (int64_t k = 0; k < K; ++k) {
            const int32_t i = np[o * K + k];
            if (i < 0) continue;
            same_rows[k] &= static_cast<uint8_t>(i == o);
            in_rows[fill[k]] = i;
            out_rows[fill[k]++] = o;
          }
        int64_t most = 0;
        for (int64_t k = 0; k < K; ++k) most = std::max(most, start[k + 1] - start[k]);
        if (!gbuf.defined() || gbuf.size(0) < most) {
          gbuf = at::empty({most, cin}, x.options());
          ybuf = at::empty({most, cout}, x.options());
        }
        scalar_t* gp = gbuf.data_ptr<scalar_t>();
        const scalar_t* yp = ybuf.data_ptr<scalar_t>();
        // An offset where every row reads itself (the centre of a submanifold map) is written straight
        // into the block's rows, first; otherwise the rows start from zero.
        int64_t first = -1;
        for (int64_t k = 0; k < K && first < 0; ++k)
          if (same_rows[k] && start[k + 1] - start[k] == o1 - o0 && o1 <= n_in) first = k;
        if (first >= 0) {
          auto rows_out = acc.narrow(0, o0, o1 - o0);
          at::mm_out(rows_out, x.narrow(0, o0, o1 - o0), w.select(1, first).t());
        } else {
          std::fill(ap + o0 * cout, ap + o1 * cout, scalar_t(0));
        }
        for (int64_t k = 0; k < K; ++k) {
          const int64_t cnt = start[k + 1] - start[k];
          if (cnt == 0 || k == first) continue;
          const int64_t* ir = in_rows.data() + start[k];
          const int64_t* orr = out_rows.data() + start[k];
          auto wk_t = w.select(1, k).t();  // (Cin, Cout) view
          auto y = ybuf.narrow(0, 0, cnt);
          if (same_rows[k] && cnt == o1 - o0 && o1 <= n_in) {
            at::mm_out(y, x.narrow(0, o0, cnt), wk_t);
          } else {
            for (int64_t j = 0; j < cnt; ++j)
              std::memcpy(gp + j * cin, xp + ir[j] * cin, static_cast<size_t>(cin) * sizeof(scalar_t));
            at::mm_out(y, gbuf.narrow(0, 0, cnt), wk_t);
          }
          for (int64_t j = 0; j < cnt; ++j) {
            scalar_t* d = ap + orr[j] * cout;
            const scalar_t* a = yp + j * cout;
            for (int64_t c = 0; c < cout; ++c) d[c] += a[c];
          }
        }
        if (epi.scale || epi.shift || epi.relu)
          for (int64_t o = o0; o < o1; ++o)
            for (int64_t c = 0; c < cout; ++c) ap[o * cout + c] = epi(ap[o * cout + c], c);
      }
    });
  });
  return acc.to(dtype);
}

at::Tensor sparse_conv_cpu(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& nbr,
                           const c10::optional<at::Tensor>& order, c10::string_view algo, int64_t splits) {
  check_conv_args(features, weight, nbr);
  check_order(order, nbr);
  check_conv_algo(algo, splits);
  return sparse_conv_cpu_impl(features, weight, nbr, ConvEpilogue{});
}

at::Tensor sparse_conv_affine_cpu(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& nbr,
                                  const c10::optional<at::Tensor>& order, const c10::optional<at::Tensor>& scale_in,
                                  const c10::optional<at::Tensor>& shift_in, bool relu, c10::string_view algo,
                                  int64_t splits) {
  check_conv_args(features, weight, nbr);
  check_order(order, nbr);
  const auto scale = epilogue_operand(scale_in, "scale", weight.size(0), features);
  const auto shift = epilogue_operand(shift_in, "shift", weight.size(0), features);
  check_conv_algo(algo, splits);
  return sparse_conv_cpu_impl(features, weight, nbr, make_epilogue(scale, shift, relu));
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
  check_map_values(nbr, n_in);
  auto x = features_in.detach().to(ct).contiguous();
  auto gr = grad_in.detach().to(ct).contiguous();
  const int32_t* np = nbr.data_ptr<int32_t>();
  // pairs grouped by offset (two row-major passes), then one task per offset
  std::vector<int64_t> start(static_cast<size_t>(K + 1), 0), fill(static_cast<size_t>(K));
  for (int64_t o = 0; o < n_out; ++o)
    for (int64_t k = 0; k < K; ++k) start[k + 1] += np[o * K + k] >= 0;
  for (int64_t k = 0; k < K; ++k) start[k + 1] += start[k];
  std::vector<int64_t> in_rows(static_cast<size_t>(start[K])), out_rows(static_cast<size_t>(start[K]));
  std::copy(start.begin(), start.end() - 1, fill.begin());
  for (int64_t o = 0; o < n_out; ++o)
    for (int64_t k = 0; k < K; ++k) {
      const int32_t i = np[o * K + k];
      if (i < 0) continue;
      in_rows[fill[k]] = i;
      out_rows[fill[k]++] = o;
    }
  // small maps inline: a parallel region costs more than it saves
  const int64_t grain = start[K] * (cin + cout) < (int64_t(1) << 18) ? K : 1;
  AT_DISPATCH_FLOATING_TYPES(ct, "lidarops_sparse_conv_weight_grad_cpu", [&] {
    const scalar_t* xp = x.data_ptr<scalar_t>();
    const scalar_t* gp = gr.data_ptr<scalar_t>();
    at::parallel_for(0, K, grain, [&](int64_t k0, int64_t k1) {
      int64_t rows = 0;
      for (int64_t k = k0; k < k1; ++k) rows = std::max(rows, start[k + 1] - start[k]);
      auto xbuf = at::empty({rows, cin}, x.options());
      auto gbuf = at::empty({rows, cout}, x.options());
      auto dwk = at::empty({cout, cin}, x.options());
      scalar_t* xs = xbuf.data_ptr<scalar_t>();
      scalar_t* gs = gbuf.data_ptr<scalar_t>();
      for (int64_t k = k0; k < k1; ++k) {
        const int64_t cnt = start[k + 1] - start[k];
        if (cnt == 0) continue;
        for (int64_t j = 0; j < cnt; ++j) {
          const int64_t p = start[k] + j;
          std::memcpy(xs + j * cin, xp + in_rows[p] * cin, static_cast<size_t>(cin) * sizeof(scalar_t));
          std::memcpy(gs + j * cout, gp + out_rows[p] * cout, static_cast<size_t>(cout) * sizeof(scalar_t));
        }
        at::mm_out(dwk, gbuf.narrow(0, 0, cnt).t(), xbuf.narrow(0, 0, cnt));
        dw.select(1, k).copy_(dwk);
      }
    });
  });
  return dw.to(dtype);
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("sparse_kernel_map_order", &sparse_kernel_map_order_cpu);
  m.impl("sparse_conv", &sparse_conv_cpu);
  m.impl("sparse_conv_affine", &sparse_conv_affine_cpu);
  m.impl("sparse_conv_weight_grad", &sparse_conv_weight_grad_cpu);
}

}  // namespace sparse
}  // namespace lidarops
