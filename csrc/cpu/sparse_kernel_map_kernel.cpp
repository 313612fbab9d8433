// Kernel-map (rulebook) construction for sparse convolution on CPU: output sites of strided and
// transposed convolutions, the (output row, kernel offset) -> input row map, and its transpose.
//
// Input coordinates go into a coordinate table: a dense index grid (one int32 slot per site) when
// the grid is small, an open-addressing hash table (linear probing, capacity >= 2N) otherwise. Rows
// are inserted in order, so a duplicate coordinate is reported as the first pair of rows that collide.
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/full.h>

#include <algorithm>
#include <atomic>
#include <cstring>
#include <tuple>

#include "lidarops/sparse.h"

namespace lidarops {
namespace sparse {

namespace {

struct HostTable {
  at::Tensor dense, keys, vals;
  int64_t mask = 0;
  TableView view() const {
    TableView v;
    if (dense.defined()) {
      v.dense = dense.data_ptr<int32_t>();
    } else {
      v.keys = keys.data_ptr<int64_t>();
      v.vals = vals.data_ptr<int32_t>();
      v.mask = mask;
    }
    return v;
  }
};

bool row_in_range(const int32_t* r, const ConvGeometry& g) {
  if (r[0] < 0 || r[0] >= g.batch) return false;
  for (int d = 0; d < g.ndim; ++d)
    if (r[d + 1] < 0 || r[d + 1] >= g.in_shape[d]) return false;
  return true;
}

int64_t row_key(const int32_t* r, const int64_t* shape, int ndim) {
  int64_t c[kMaxDim];
  for (int d = 0; d < ndim; ++d) c[d] = r[d + 1];
  return site_key(r[0], c, shape, ndim);
}

void raise_duplicate(const char* name, const int32_t* ip, int ndim, int64_t first, int64_t second) {
  TORCH_CHECK_VALUE(false, name, " rows ", first, " and ", second, " both hold (batch, coordinates) = ",
                    describe_row(ip + second * (ndim + 1), ndim + 1),
                    "; a sparse tensor needs unique coordinates (merge duplicates first, e.g. by summing "
                    "their features)");
}

// Coordinate table of the rows of `idx` (contiguous CPU int32, (N, 1 + D)) in the grid g.in_shape.
// validate: raise for rows outside the grid and for duplicates; otherwise skip such rows (first wins).
HostTable build_table(const at::Tensor& idx, const ConvGeometry& g, int64_t method, bool validate, const char* name) {
  const int64_t n = idx.size(0);
  const int nd = g.ndim;
  const int32_t* ip = idx.data_ptr<int32_t>();
  if (validate) raise_if_out_of_range(idx, name, g.batch, g.in_shape, nd);
  TORCH_CHECK_VALUE(n < INT32_MAX, name, " has ", n, " rows; at most 2^31 - 2 are supported");
  const int64_t cells = grid_cells(g.batch, g.in_shape, nd);
  HostTable t;
  auto opts = idx.options();
  if (use_dense_table(cells, n, method)) {
    t.dense = at::full({cells}, -1, opts.dtype(at::kInt));
    int32_t* dp = t.dense.data_ptr<int32_t>();
    for (int64_t i = 0; i < n; ++i) {
      const int32_t* r = ip + i * (nd + 1);
      if (!validate && !row_in_range(r, g)) continue;
      const int64_t key = row_key(r, g.in_shape, nd);
      if (dp[key] >= 0) {
        if (validate) raise_duplicate(name, ip, nd, dp[key], i);
        continue;
      }
      dp[key] = static_cast<int32_t>(i);
    }
  } else {
    const int64_t cap = hash_capacity(n);
    t.mask = cap - 1;
    t.keys = at::full({cap}, kEmptyKey, opts.dtype(at::kLong));
    t.vals = at::full({cap}, -1, opts.dtype(at::kInt));
    int64_t* kp = t.keys.data_ptr<int64_t>();
    int32_t* vp = t.vals.data_ptr<int32_t>();
    for (int64_t i = 0; i < n; ++i) {
      const int32_t* r = ip + i * (nd + 1);
      if (!validate && !row_in_range(r, g)) continue;
      const int64_t key = row_key(r, g.in_shape, nd);
      uint64_t h = mix64(static_cast<uint64_t>(key)) & static_cast<uint64_t>(t.mask);
      while (kp[h] != kEmptyKey && kp[h] != key) h = (h + 1) & static_cast<uint64_t>(t.mask);
      if (kp[h] == key) {
        if (validate) raise_duplicate(name, ip, nd, vp[h], i);
        continue;
      }
      kp[h] = key;
      vp[h] = static_cast<int32_t>(i);
    }
  }
  return t;
}

std::vector<int64_t> offset_table(const ConvGeometry& g) {
  std::vector<int64_t> offs(static_cast<size_t>(g.kvol * g.ndim));
  for (int64_t k = 0; k < g.kvol; ++k) kernel_offsets(g, k, offs.data() + k * g.ndim);
  return offs;
}

// Growable open-addressing set of int64 keys (>= 0).
class KeySet {
 public:
  explicit KeySet(int64_t expected) : slots_(static_cast<size_t>(hash_capacity(expected)), kEmptyKey) {}
  void insert(int64_t key) {
    if (2 * (size_ + 1) > static_cast<int64_t>(slots_.size())) grow();
    place(key);
  }
  std::vector<int64_t> sorted_keys() const {
    std::vector<int64_t> out;
    out.reserve(static_cast<size_t>(size_));
    for (int64_t k : slots_)
      if (k != kEmptyKey) out.push_back(k);
    std::sort(out.begin(), out.end());
    return out;
  }

 private:
  void place(int64_t key) {
    const uint64_t mask = slots_.size() - 1;
    uint64_t h = mix64(static_cast<uint64_t>(key)) & mask;
    while (slots_[h] != kEmptyKey) {
      if (slots_[h] == key) return;
      h = (h + 1) & mask;
    }
    slots_[h] = key;
    ++size_;
  }
  void grow() {
    std::vector<int64_t> old(slots_.size() * 2, kEmptyKey);
    old.swap(slots_);
    size_ = 0;
    for (int64_t k : old)
      if (k != kEmptyKey) place(k);
  }
  std::vector<int64_t> slots_;
  int64_t size_ = 0;
};

at::Tensor sparse_conv_out_indices_cpu(const at::Tensor& indices_in, int64_t batch_size, at::IntArrayRef spatial_shape,
                                       at::IntArrayRef out_spatial_shape, at::IntArrayRef kernel_size,
                                       at::IntArrayRef stride, at::IntArrayRef padding, at::IntArrayRef dilation,
                                       bool transposed, int64_t method, bool validate, bool /*checked*/) {
  TORCH_CHECK_VALUE(!out_spatial_shape.empty(), "out_spatial_shape must be given");
  const ConvGeometry g = make_geometry(batch_size, spatial_shape, out_spatial_shape, kernel_size, stride, padding,
                                       dilation, transposed);
  check_indices(indices_in, "indices", g.ndim);
  TORCH_CHECK_VALUE(method >= 0 && method <= 2, "method must be 0 (auto), 1 (dense) or 2 (hash), got ", method);
  auto idx = indices_in.contiguous();
  const int nd = g.ndim;
  const int64_t n = idx.size(0), K = g.kvol;
  if (validate) raise_if_out_of_range(idx, "indices", g.batch, g.in_shape, nd);
  const int32_t* ip = idx.data_ptr<int32_t>();
  // without validation, rows outside the batch or grid are skipped (as on CUDA)
  const std::vector<int64_t> offs = offset_table(g);
  const int64_t cells = grid_cells(g.batch, g.out_shape, nd);

  std::vector<int64_t> keys;
  if (n > 0 && use_dense_table(cells, n, method)) {
    std::vector<uint8_t> mark(static_cast<size_t>(cells), 0);
    uint8_t* mp = mark.data();
    at::parallel_for(0, n, 256, [&](int64_t s, int64_t e) {
      int64_t p[kMaxDim], q[kMaxDim];
      for (int64_t i = s; i < e; ++i) {
        const int32_t* r = ip + i * (nd + 1);
        if (!validate && !row_in_range(r, g)) continue;
        for (int d = 0; d < nd; ++d) p[d] = r[d + 1];
        for (int64_t k = 0; k < K; ++k)
          if (output_of_input(g, p, offs.data() + k * nd, q))
            __atomic_store_n(mp + site_key(r[0], q, g.out_shape, nd), uint8_t(1), __ATOMIC_RELAXED);
      }
    });
    for (int64_t c = 0; c < cells; ++c)
      if (mp[c]) keys.push_back(c);
  } else if (n > 0) {
    KeySet set(2 * n);
    int64_t p[kMaxDim], q[kMaxDim];
    for (int64_t i = 0; i < n; ++i) {
      const int32_t* r = ip + i * (nd + 1);
      if (!validate && !row_in_range(r, g)) continue;
      for (int d = 0; d < nd; ++d) p[d] = r[d + 1];
      for (int64_t k = 0; k < K; ++k)
        if (output_of_input(g, p, offs.data() + k * nd, q)) set.insert(site_key(r[0], q, g.out_shape, nd));
    }
    keys = set.sorted_keys();
  }
  const int64_t m = static_cast<int64_t>(keys.size());
  TORCH_CHECK_VALUE(m < INT32_MAX, "the convolution has ", m, " output sites; at most 2^31 - 2 are supported");
  auto out = at::empty({m, nd + 1}, idx.options());
  int32_t* op = out.data_ptr<int32_t>();
  at::parallel_for(0, m, 4096, [&](int64_t s, int64_t e) {
    int64_t b, c[kMaxDim];
    for (int64_t j = s; j < e; ++j) {
      decode_key(keys[j], g.out_shape, nd, &b, c);
      int32_t* r = op + j * (nd + 1);
      r[0] = static_cast<int32_t>(b);
      for (int d = 0; d < nd; ++d) r[d + 1] = static_cast<int32_t>(c[d]);
    }
  });
  return out;
}

at::Tensor sparse_kernel_map_cpu(const at::Tensor& indices_in, const at::Tensor& out_indices_in, int64_t batch_size,
                                 at::IntArrayRef spatial_shape, at::IntArrayRef kernel_size, at::IntArrayRef stride,
                                 at::IntArrayRef padding, at::IntArrayRef dilation, bool transposed, bool validate,
                                 int64_t method) {
  const ConvGeometry g = make_geometry(batch_size, spatial_shape, {}, kernel_size, stride, padding, dilation, transposed);
  check_indices(indices_in, "indices", g.ndim);
  check_indices(out_indices_in, "out_indices", g.ndim);
  TORCH_CHECK_VALUE(method >= 0 && method <= 2, "method must be 0 (auto), 1 (dense) or 2 (hash), got ", method);
  TORCH_CHECK_VALUE(indices_in.device() == out_indices_in.device(), "out_indices is on ", out_indices_in.device(),
                    " but indices is on ", indices_in.device());
  auto idx = indices_in.contiguous();
  auto oidx = out_indices_in.contiguous();
  const int nd = g.ndim;
  const int64_t m = oidx.size(0), K = g.kvol;
  auto nbr = at::empty({m, K}, idx.options());
  if (m == 0) {  // nothing to pair, but the sites are still checked (a strided layer may reach no output)
    if (validate && idx.size(0) > 0) build_table(idx, g, method, true, "indices");
    return nbr;
  }
  if (idx.size(0) == 0) return nbr.fill_(-1);
  const HostTable table = build_table(idx, g, method, validate, "indices");
  const TableView tv = table.view();
  const std::vector<int64_t> offs = offset_table(g);
  const int32_t* op = oidx.data_ptr<int32_t>();
  int32_t* np = nbr.data_ptr<int32_t>();
  // Regular pairing: p = base + off * dil with base = q * stride - padding, so the key of p is the key
  // of base plus a per-offset constant; only the bounds are checked per dimension.
  std::vector<int64_t> step(static_cast<size_t>(K * nd)), delta(static_cast<size_t>(K), 0);
  int64_t mult[kMaxDim];
  mult[nd - 1] = 1;
  for (int d = nd - 2; d >= 0; --d) mult[d] = mult[d + 1] * g.in_shape[d + 1];
  for (int64_t k = 0; k < K; ++k)
    for (int d = 0; d < nd; ++d) {
      step[k * nd + d] = offs[k * nd + d] * g.dil[d];
      delta[k] += step[k * nd + d] * mult[d];
    }
  const int64_t cells_per_sample = grid_cells(1, g.in_shape, nd);
  at::parallel_for(0, m, std::max<int64_t>(1, 4096 / K), [&](int64_t s, int64_t e) {
    int64_t q[kMaxDim], p[kMaxDim], base[kMaxDim];
    for (int64_t o = s; o < e; ++o) {
      const int32_t* r = op + o * (nd + 1);
      int32_t* row = np + o * K;
      const int64_t b = r[0];
      if (b < 0 || b >= g.batch) {  // not a site of this batch: no neighbours
        std::fill(row, row + K, -1);
        continue;
      }
      for (int d = 0; d < nd; ++d) q[d] = r[d + 1];
      if (g.transposed) {
        for (int64_t k = 0; k < K; ++k)
          row[k] = input_of_output(g, q, offs.data() + k * nd, p) ? tv.find(site_key(b, p, g.in_shape, nd)) : -1;
        continue;
      }
      int64_t base_key = b * cells_per_sample;
      for (int d = 0; d < nd; ++d) {
        base[d] = q[d] * g.stride[d] - g.pad[d];
        base_key += base[d] * mult[d];
      }
      for (int64_t k = 0; k < K; ++k) {
        const int64_t* st = step.data() + k * nd;
        bool inside = true;
        for (int d = 0; d < nd; ++d) {
          const int64_t v = base[d] + st[d];
          inside = inside && v >= 0 && v < g.in_shape[d];
        }
        row[k] = inside ? tv.find(base_key + delta[k]) : -1;
      }
    }
  });
  return nbr;
}

std::tuple<at::Tensor, int64_t> sparse_kernel_map_deferred_cpu(
    const at::Tensor& indices, const at::Tensor& out_indices, int64_t batch_size, at::IntArrayRef spatial_shape,
    at::IntArrayRef kernel_size, at::IntArrayRef stride, at::IntArrayRef padding, at::IntArrayRef dilation,
    bool transposed, int64_t method) {
  return {sparse_kernel_map_cpu(indices, out_indices, batch_size, spatial_shape, kernel_size, stride, padding,
                                dilation, transposed, /*validate=*/true, method),
          -1};  // checked already: nothing to redeem
}

void sparse_site_check_cpu(const at::Tensor& indices, int64_t ticket, int64_t, at::IntArrayRef) {
  TORCH_CHECK_VALUE(ticket == -1, "site-check ticket ", ticket, " was not issued for CPU indices (the CPU checks at "
                    "once and issues -1)");
}

at::Tensor sparse_site_check_slots_cpu(const at::Tensor&) {  // no slots: CPU indices are checked at once
  return at::empty({0}, at::TensorOptions().dtype(at::kLong));
}

at::Tensor sparse_kernel_map_transpose_cpu(const at::Tensor& nbr_in, int64_t n_in) {
  TORCH_CHECK_VALUE(nbr_in.dim() == 2 && nbr_in.scalar_type() == at::kInt, "kernel_map must be (N_out, K) int32, got shape ",
                    nbr_in.sizes(), " and dtype ", nbr_in.scalar_type());
  TORCH_CHECK_VALUE(n_in >= 0 && n_in < INT32_MAX, "n_in must lie in [0, 2^31 - 1), got ", n_in);
  auto nbr = nbr_in.contiguous();
  const int64_t m = nbr.size(0), K = nbr.size(1);
  auto out = at::full({n_in, K}, -1, nbr.options());
  if (m == 0 || n_in == 0 || K == 0) return out;
  const int32_t* np = nbr.data_ptr<int32_t>();
  int32_t* tp = out.data_ptr<int32_t>();
  for (int64_t t = 0; t < m * K; ++t)
    TORCH_CHECK_VALUE(np[t] >= -1 && np[t] < n_in, "kernel_map entries must lie in [-1, n_in = ", n_in, "), got ",
                      np[t], " at row ", t / K, ", offset ", t % K);
  // For a fixed offset the pairing is one-to-one, so the writes of different rows never collide.
  at::parallel_for(0, m, 4096, [&](int64_t s, int64_t e) {
    for (int64_t o = s; o < e; ++o)
      for (int64_t k = 0; k < K; ++k) {
        const int32_t i = np[o * K + k];
        if (i >= 0) tp[static_cast<int64_t>(i) * K + k] = static_cast<int32_t>(o);
      }
  });
  return out;
}

}  // namespace

void raise_if_duplicates(const at::Tensor& indices_cpu, const char* name, int64_t batch, const int64_t* shape, int ndim) {
  ConvGeometry g;
  g.ndim = ndim;
  g.batch = batch;
  for (int d = 0; d < ndim; ++d) g.in_shape[d] = shape[d];
  (void)build_table(indices_cpu.contiguous(), g, /*method=*/0, /*validate=*/true, name);
}

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("sparse_conv_out_indices", &sparse_conv_out_indices_cpu);
  m.impl("sparse_kernel_map", &sparse_kernel_map_cpu);
  m.impl("sparse_kernel_map_deferred", &sparse_kernel_map_deferred_cpu);
  m.impl("sparse_site_check", &sparse_site_check_cpu);
  m.impl("sparse_site_check_slots", &sparse_site_check_slots_cpu);
  m.impl("sparse_kernel_map_transpose", &sparse_kernel_map_transpose_cpu);
}

}  // namespace sparse
}  // namespace lidarops
