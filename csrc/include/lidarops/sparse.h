// Sparse convolution helpers shared by the CPU and CUDA kernels: convolution geometry, linear
// coordinate keys, the coordinate table (dense index grid or open-addressing hash table) and the
// argument checks of the sparse ops.
//
// Conventions (see docs/sparse.md):
//   indices      int32 (N, 1 + D): batch in column 0, then the D spatial coordinates (spconv layout).
//   key          ((b * S0 + c0) * S1 + c1) * ... : int64 linear index of a site in the batch grid.
//   kernel map   int32 (N_out, K): for output row o and kernel offset k, the input row whose
//                coordinate feeds o through offset k, or -1. Offsets k are the row-major flattening of
//                the kernel window (last dimension fastest), the order of weight[Cout, *kernel, Cin].
//   regular      input p feeds output q through offset t when p = q * stride - padding + t * dilation.
//   transposed   input p feeds output q through offset t when q = p * stride - padding + t * dilation
//                (the adjoint pairing, i.e. conv_transposeNd without a kernel flip).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "lidarops/common.h"

namespace lidarops {
namespace sparse {

constexpr int kMaxDim = 4;
constexpr int64_t kEmptyKey = -1;

struct ConvGeometry {
  int ndim = 0;
  int64_t batch = 0;
  int64_t in_shape[kMaxDim] = {1, 1, 1, 1};
  int64_t out_shape[kMaxDim] = {1, 1, 1, 1};
  int64_t kernel[kMaxDim] = {1, 1, 1, 1};
  int64_t stride[kMaxDim] = {1, 1, 1, 1};
  int64_t pad[kMaxDim] = {0, 0, 0, 0};
  int64_t dil[kMaxDim] = {1, 1, 1, 1};
  int64_t kvol = 1;
  bool transposed = false;
};

// Offsets of kernel position k along each dimension (row-major, last dimension fastest).
LIDAROPS_HD void kernel_offsets(const ConvGeometry& g, int64_t k, int64_t* off) {
  for (int d = g.ndim - 1; d >= 0; --d) {
    off[d] = k % g.kernel[d];
    k /= g.kernel[d];
  }
}

// Linear key of (b, c) in a grid of shape `shape`.
LIDAROPS_HD int64_t site_key(int64_t b, const int64_t* c, const int64_t* shape, int ndim) {
  int64_t key = b;
  for (int d = 0; d < ndim; ++d) key = key * shape[d] + c[d];
  return key;
}

LIDAROPS_HD void decode_key(int64_t key, const int64_t* shape, int ndim, int64_t* b, int64_t* c) {
  for (int d = ndim - 1; d >= 0; --d) {
    c[d] = key % shape[d];
    key /= shape[d];
  }
  *b = key;
}

// Input coordinate p that feeds output coordinate q through kernel offset `off`; false if none.
LIDAROPS_HD bool input_of_output(const ConvGeometry& g, const int64_t* q, const int64_t* off, int64_t* p) {
  for (int d = 0; d < g.ndim; ++d) {
    int64_t v;
    if (!g.transposed) {
      v = q[d] * g.stride[d] - g.pad[d] + off[d] * g.dil[d];
    } else {
      const int64_t t = q[d] + g.pad[d] - off[d] * g.dil[d];
      if (t < 0 || t % g.stride[d] != 0) return false;
      v = t / g.stride[d];
    }
    if (v < 0 || v >= g.in_shape[d]) return false;
    p[d] = v;
  }
  return true;
}

// Output coordinate q fed by input coordinate p through kernel offset `off`; false if none.
LIDAROPS_HD bool output_of_input(const ConvGeometry& g, const int64_t* p, const int64_t* off, int64_t* q) {
  for (int d = 0; d < g.ndim; ++d) {
    int64_t v;
    if (!g.transposed) {
      const int64_t t = p[d] + g.pad[d] - off[d] * g.dil[d];
      if (t < 0 || t % g.stride[d] != 0) return false;
      v = t / g.stride[d];
    } else {
      v = p[d] * g.stride[d] - g.pad[d] + off[d] * g.dil[d];
    }
    if (v < 0 || v >= g.out_shape[d]) return false;
    q[d] = v;
  }
  return true;
}

// Read-only view of a coordinate table: key -> row, or -1.
struct TableView {
  const int32_t* dense = nullptr;  // dense index grid (one slot per site), or nullptr for the hash table
  const int64_t* keys = nullptr;   // hash table keys, kEmptyKey for a free slot
  const int32_t* vals = nullptr;   // hash table rows
  int64_t mask = 0;                // hash capacity - 1 (capacity is a power of two, >= 2 * entries)

  LIDAROPS_HD int32_t find(int64_t key) const {
    if (dense != nullptr) return dense[key];
    uint64_t h = mix64(static_cast<uint64_t>(key)) & static_cast<uint64_t>(mask);
    while (true) {
      const int64_t k = keys[h];
      if (k == key) return vals[h];
      if (k == kEmptyKey) return -1;
      h = (h + 1) & static_cast<uint64_t>(mask);
    }
  }
};

inline int64_t hash_capacity(int64_t n) {
  int64_t cap = 16;
  while (cap < 2 * n) cap <<= 1;
  return cap;
}

// Table kind chosen for `cells` grid sites and `n` entries. method: 0 = auto, 1 = dense, 2 = hash.
// Auto takes the dense grid when it is at most 4M slots (16 MiB; every 2D pillar grid of a batch of a
// few frames) or at most 16 slots per entry, never above 2^28 slots.
inline bool use_dense_table(int64_t cells, int64_t n, int64_t method) {
  constexpr int64_t kSmall = int64_t(1) << 22, kMax = int64_t(1) << 28;
  if (method == 1) {
    TORCH_CHECK_VALUE(cells <= kMax, "method='dense' needs a grid of at most 2^28 sites, got ", cells,
                      " (batch_size * prod(spatial_shape)); use method='hash' or 'auto'");
    return true;
  }
  if (method == 2) return false;
  return cells <= kMax && (cells <= kSmall || cells <= 16 * n);
}

// ---- host-side argument handling (shared by the CPU and CUDA kernels) ----

inline void check_indices(const at::Tensor& indices, const char* name, int64_t ndim) {
  TORCH_CHECK_VALUE(indices.dim() == 2, name, " must be (N, 1 + D) int32, got shape ", indices.sizes());
  TORCH_CHECK_VALUE(indices.scalar_type() == at::kInt, name, " must be int32, got ", indices.scalar_type());
  if (ndim > 0)
    TORCH_CHECK_VALUE(indices.size(1) == 1 + ndim, name, " must be (N, ", 1 + ndim, ") for D = ", ndim,
                      ", got shape ", indices.sizes());
}

// Geometry from the op arguments; validates every list. out_shape may be empty (not needed).
inline ConvGeometry make_geometry(int64_t batch_size, at::IntArrayRef in_shape, at::IntArrayRef out_shape,
                                  at::IntArrayRef kernel, at::IntArrayRef stride, at::IntArrayRef padding,
                                  at::IntArrayRef dilation, bool transposed) {
  ConvGeometry g;
  const int64_t D = static_cast<int64_t>(in_shape.size());
  TORCH_CHECK_VALUE(D >= 1 && D <= kMaxDim, "spatial_shape must have 1 to ", kMaxDim, " dimensions, got ", in_shape);
  TORCH_CHECK_VALUE(batch_size >= 0, "batch_size must be >= 0, got ", batch_size);
  auto check_len = [&](at::IntArrayRef v, const char* name) {
    TORCH_CHECK_VALUE(static_cast<int64_t>(v.size()) == D, name, " must have ", D, " entries, got ", v);
  };
  check_len(kernel, "kernel_size");
  check_len(stride, "stride");
  check_len(padding, "padding");
  check_len(dilation, "dilation");
  if (!out_shape.empty()) check_len(out_shape, "out_spatial_shape");
  g.ndim = static_cast<int>(D);
  g.batch = batch_size;
  g.transposed = transposed;
  g.kvol = 1;
  // Keys must fit in int64: batch * prod(shape) < 2^62.
  double cells_in = static_cast<double>(std::max<int64_t>(batch_size, 1));
  double cells_out = cells_in;
  for (int64_t d = 0; d < D; ++d) {
    TORCH_CHECK_VALUE(in_shape[d] >= 1, "spatial_shape entries must be >= 1, got ", in_shape);
    TORCH_CHECK_VALUE(kernel[d] >= 1, "kernel_size entries must be >= 1, got ", kernel);
    TORCH_CHECK_VALUE(stride[d] >= 1, "stride entries must be >= 1, got ", stride);
    TORCH_CHECK_VALUE(padding[d] >= 0, "padding entries must be >= 0, got ", padding);
    TORCH_CHECK_VALUE(dilation[d] >= 1, "dilation entries must be >= 1, got ", dilation);
    g.in_shape[d] = in_shape[d];
    g.out_shape[d] = out_shape.empty() ? 1 : out_shape[d];
    if (!out_shape.empty()) TORCH_CHECK_VALUE(out_shape[d] >= 1, "out_spatial_shape entries must be >= 1, got ", out_shape);
    g.kernel[d] = kernel[d];
    g.stride[d] = stride[d];
    g.pad[d] = padding[d];
    g.dil[d] = dilation[d];
    g.kvol *= kernel[d];
    cells_in *= static_cast<double>(in_shape[d]);
    cells_out *= static_cast<double>(g.out_shape[d]);
  }
  TORCH_CHECK_VALUE(cells_in < 4.0e18 && cells_out < 4.0e18, "batch_size * prod(spatial_shape) must be below 2^62, got ",
                    batch_size, " x ", in_shape);
  TORCH_CHECK_VALUE(g.kvol <= (int64_t(1) << 20), "kernel volume must be at most 2^20, got ", g.kvol);
  return g;
}

inline int64_t grid_cells(int64_t batch, const int64_t* shape, int ndim) {
  int64_t c = batch;
  for (int d = 0; d < ndim; ++d) c *= shape[d];
  return c;
}

// Message for an indices row outside the batch / spatial grid (CPU-side, for errors).
inline std::string describe_row(const int32_t* row, int64_t ncols) {
  std::string s = "(";
  for (int64_t j = 0; j < ncols; ++j) {
    if (j) s += ", ";
    s += std::to_string(row[j]);
  }
  return s + ")";
}

inline std::string describe_shape(const int64_t* shape, int ndim) {
  std::string s = "[";
  for (int d = 0; d < ndim; ++d) {
    if (d) s += ", ";
    s += std::to_string(shape[d]);
  }
  return s + "]";
}

// First row of a CPU int32 indices tensor that lies outside [0, batch) x shape, or -1.
inline int64_t first_row_out_of_range(const int32_t* ip, int64_t n, int ndim, int64_t batch, const int64_t* shape) {
  for (int64_t i = 0; i < n; ++i) {
    const int32_t* r = ip + i * (ndim + 1);
    if (r[0] < 0 || r[0] >= batch) return i;
    for (int d = 0; d < ndim; ++d)
      if (r[d + 1] < 0 || r[d + 1] >= shape[d]) return i;
  }
  return -1;
}

// Throws ValueError for a row outside the grid (CPU tensor).
inline void raise_if_out_of_range(const at::Tensor& indices_cpu, const char* name, int64_t batch, const int64_t* shape,
                                  int ndim) {
  const int32_t* ip = indices_cpu.data_ptr<int32_t>();
  const int64_t bad = first_row_out_of_range(ip, indices_cpu.size(0), ndim, batch, shape);
  TORCH_CHECK_VALUE(bad < 0, name, " row ", bad, " = ", describe_row(ip + bad * (ndim + 1), ndim + 1),
                    " (batch, coordinates) lies outside batch_size ", batch, " / spatial_shape ",
                    describe_shape(shape, ndim), "; every coordinate must satisfy 0 <= c < spatial_shape");
}

// ---- argument checks of the convolution and pooling ops (shared by CPU and CUDA) ----

inline void check_map(const at::Tensor& nbr, const at::Tensor& like, const char* like_name) {
  TORCH_CHECK_VALUE(nbr.dim() == 2 && nbr.scalar_type() == at::kInt, "kernel_map must be (N_out, K) int32, got shape ",
                    nbr.sizes(), " and dtype ", nbr.scalar_type());
  TORCH_CHECK_VALUE(nbr.device() == like.device(), "kernel_map is on ", nbr.device(), " but ", like_name, " is on ",
                    like.device());
}

inline void check_conv_args(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& nbr) {
  TORCH_CHECK_VALUE(features.dim() == 2, "features must be (N_in, Cin), got shape ", features.sizes());
  TORCH_CHECK_VALUE(weight.dim() == 3, "weight must be (Cout, K, Cin), got shape ", weight.sizes());
  check_map(nbr, features, "features");
  TORCH_CHECK_VALUE(at::isFloatingType(features.scalar_type()), "features must be floating point, got ",
                    features.scalar_type());
  TORCH_CHECK_VALUE(weight.scalar_type() == features.scalar_type(), "weight dtype ", weight.scalar_type(),
                    " differs from features dtype ", features.scalar_type());
  TORCH_CHECK_VALUE(weight.device() == features.device(), "weight is on ", weight.device(), " but features is on ",
                    features.device());
  TORCH_CHECK_VALUE(weight.size(1) == nbr.size(1), "weight has K = ", weight.size(1),
                    " kernel offsets but kernel_map has ", nbr.size(1));
  TORCH_CHECK_VALUE(weight.size(2) == features.size(1), "weight expects Cin = ", weight.size(2),
                    " input channels but features has ", features.size(1));
}

// order: undefined, or an (N_out,) int32 permutation on the device of the map.
inline void check_order(const c10::optional<at::Tensor>& order, const at::Tensor& nbr) {
  if (!order.has_value() || !order->defined()) return;
  TORCH_CHECK_VALUE(order->dim() == 1 && order->size(0) == nbr.size(0) && order->scalar_type() == at::kInt,
                    "order must be an (N_out,) = (", nbr.size(0), ",) int32 permutation, got shape ", order->sizes(),
                    " and dtype ", order->scalar_type());
  TORCH_CHECK_VALUE(order->device() == nbr.device(), "order is on ", order->device(), " but kernel_map is on ",
                    nbr.device());
}

// Kernel choice of sparse_conv / sparse_conv_affine (the ops' `algo` and `splits`; docs/sparse.md).
// CUDA tuning: every choice computes the same sums in the dtype's precision ("3xtf32", experimental,
// excepted). The CPU kernels have one algorithm: they check the arguments and ignore them.
//   auto            the library's choice per layer
//   mma_sync        tensor-core layers on mma.sync, never wgmma
//   wgmma_2blocks   Hopper TF32 layers with Cout > 64: the 64 x 128 wgmma tiles with two blocks per
//   wgmma_3blocks   multiprocessor (four stages) or three (three stages), whatever the layer's size
//   3xtf32          float32 without TF32 on the tensor cores as three TF32 products
// splits: offset splits of the pipelined kernels, forced (clamped to K); 0: chosen per layer.
enum class ConvAlgo { kAuto, kMmaSync, kWgmma2Blocks, kWgmma3Blocks, k3xTF32 };

inline ConvAlgo check_conv_algo(c10::string_view algo, int64_t splits) {
  TORCH_CHECK_VALUE(splits >= 0, "splits must be >= 0 (0: chosen per layer), got ", splits);
  if (algo == "auto") return ConvAlgo::kAuto;
  if (algo == "mma_sync") return ConvAlgo::kMmaSync;
  if (algo == "wgmma_2blocks") return ConvAlgo::kWgmma2Blocks;
  if (algo == "wgmma_3blocks") return ConvAlgo::kWgmma3Blocks;
  TORCH_CHECK_VALUE(algo == "3xtf32", "algo must be one of 'auto', 'mma_sync', 'wgmma_2blocks', 'wgmma_3blocks', "
                    "'3xtf32', got '", std::string(algo), "'");
  return ConvAlgo::k3xTF32;
}

// Per-output-channel epilogue of the fused inference convolution (sparse_conv_affine):
// out = relu?(acc * scale[co] + shift[co]) on the float accumulator; a null scale / shift is 1 / 0.
// relu keeps NaN (as torch.relu).
struct ConvEpilogue {
  const float* scale = nullptr;
  const float* shift = nullptr;
  bool relu = false;
  template <typename A>
  LIDAROPS_HD A operator()(A v, int64_t co) const {
    if (scale != nullptr) v *= static_cast<A>(scale[co]);
    if (shift != nullptr) v += static_cast<A>(shift[co]);
    return relu && v < A(0) ? A(0) : v;
  }
};

// scale / shift of sparse_conv_affine: undefined, or float32 (Cout,) on the device of the features
// (checked); returned contiguous, or undefined.
inline at::Tensor epilogue_operand(const c10::optional<at::Tensor>& t, const char* name, int64_t cout,
                                   const at::Tensor& features) {
  if (!t.has_value() || !t->defined()) return at::Tensor();
  TORCH_CHECK_VALUE(t->dim() == 1 && t->size(0) == cout && t->scalar_type() == at::kFloat, name,
                    " must be a float32 (Cout,) = (", cout, ",) tensor, got shape ", t->sizes(), " and dtype ",
                    t->scalar_type());
  TORCH_CHECK_VALUE(t->device() == features.device(), name, " is on ", t->device(), " but features is on ",
                    features.device());
  return t->contiguous();
}

inline ConvEpilogue make_epilogue(const at::Tensor& scale, const at::Tensor& shift, bool relu) {
  return ConvEpilogue{scale.defined() ? scale.data_ptr<float>() : nullptr,
                      shift.defined() ? shift.data_ptr<float>() : nullptr, relu};
}

// A kernel-map entry as the kernels use it: the input row, or -1 (no input) for an entry outside
// [0, n_in). The CPU kernels raise for such entries; the CUDA kernels skip them, as reporting would
// need a host sync, so a map that does not belong to the features can never read out of bounds.
LIDAROPS_HD int32_t map_row(int32_t r, int64_t n_in) { return r >= 0 && r < n_in ? r : -1; }

// Sort key of a kernel-map row: bit k set when offset k (< 63) has an input.
LIDAROPS_HD int64_t row_mask(const int32_t* row, int64_t K) {
  int64_t mask = 0;
  const int64_t n = K < 63 ? K : 63;
  for (int64_t k = 0; k < n; ++k)
    if (row[k] >= 0) mask |= int64_t(1) << k;
  return mask;
}

inline void check_weight_grad_args(const at::Tensor& features, const at::Tensor& grad, const at::Tensor& nbr) {
  TORCH_CHECK_VALUE(features.dim() == 2, "features must be (N_in, Cin), got shape ", features.sizes());
  TORCH_CHECK_VALUE(grad.dim() == 2, "grad_out must be (N_out, Cout), got shape ", grad.sizes());
  check_map(nbr, features, "features");
  TORCH_CHECK_VALUE(grad.size(0) == nbr.size(0), "grad_out has ", grad.size(0), " rows but kernel_map has ",
                    nbr.size(0));
  TORCH_CHECK_VALUE(at::isFloatingType(features.scalar_type()), "features must be floating point, got ",
                    features.scalar_type());
  TORCH_CHECK_VALUE(grad.scalar_type() == features.scalar_type(), "grad_out dtype ", grad.scalar_type(),
                    " differs from features dtype ", features.scalar_type());
  TORCH_CHECK_VALUE(grad.device() == features.device(), "grad_out is on ", grad.device(), " but features is on ",
                    features.device());
}

// The grid of sparse_to_dense / sparse_from_dense: batch size, spatial shape, sites per sample.
struct DenseGrid {
  int64_t batch = 0, cells = 1;
  int ndim = 0;
  int64_t shape[kMaxDim] = {};
};

// Offset of a site in one channel plane of the (B, C, *S) map, b * C * cells + row-major position, or
// -1 when the batch index or a coordinate lies outside the grid.
LIDAROPS_HD int64_t dense_site_offset(const int32_t* row, const DenseGrid& g, int64_t C) {
  const int64_t b = row[0];
  if (b < 0 || b >= g.batch) return -1;
  int64_t lin = 0;
  for (int d = 0; d < g.ndim; ++d) {
    const int64_t c = row[1 + d];
    if (c < 0 || c >= g.shape[d]) return -1;
    lin = lin * g.shape[d] + c;
  }
  return b * C * g.cells + lin;
}

inline DenseGrid check_to_dense_args(const at::Tensor& features, const at::Tensor& indices, int64_t batch_size,
                                     at::IntArrayRef spatial_shape) {
  TORCH_CHECK_VALUE(features.dim() == 2, "features must be (N, C), got shape ", features.sizes());
  const int64_t D = static_cast<int64_t>(spatial_shape.size());
  TORCH_CHECK_VALUE(D >= 1 && D <= kMaxDim, "spatial_shape must have 1 to ", kMaxDim, " dimensions, got ",
                    spatial_shape);
  check_indices(indices, "indices", D);
  TORCH_CHECK_VALUE(indices.size(0) == features.size(0), "indices has ", indices.size(0), " rows but features has ",
                    features.size(0));
  TORCH_CHECK_VALUE(indices.device() == features.device(), "indices is on ", indices.device(),
                    " but features is on ", features.device());
  TORCH_CHECK_VALUE(batch_size >= 0, "batch_size must be >= 0, got ", batch_size);
  TORCH_CHECK_VALUE(at::isFloatingType(features.scalar_type()), "features must be floating point, got ",
                    features.scalar_type());
  DenseGrid g;
  g.batch = batch_size;
  g.ndim = static_cast<int>(D);
  for (int64_t d = 0; d < D; ++d) {
    TORCH_CHECK_VALUE(spatial_shape[d] >= 0, "spatial_shape must be >= 0, got ", spatial_shape);
    g.shape[d] = spatial_shape[d];
    g.cells *= spatial_shape[d];
  }
  return g;
}

inline DenseGrid check_from_dense_args(const at::Tensor& dense, const at::Tensor& indices) {
  TORCH_CHECK_VALUE(dense.dim() >= 3 && dense.dim() <= 2 + kMaxDim, "dense must be (B, C, *spatial) with 1 to ",
                    kMaxDim, " spatial dimensions, got shape ", dense.sizes());
  TORCH_CHECK_VALUE(indices.device() == dense.device(), "indices is on ", indices.device(), " but dense is on ",
                    dense.device());
  check_indices(indices, "indices", dense.dim() - 2);
  TORCH_CHECK_VALUE(at::isFloatingType(dense.scalar_type()), "dense must be floating point, got ",
                    dense.scalar_type());
  DenseGrid g;
  g.batch = dense.size(0);
  g.ndim = static_cast<int>(dense.dim() - 2);
  for (int d = 0; d < g.ndim; ++d) {
    g.shape[d] = dense.size(2 + d);
    g.cells *= g.shape[d];
  }
  return g;
}

inline void check_pool_args(const at::Tensor& features, const at::Tensor& nbr) {
  TORCH_CHECK_VALUE(features.dim() == 2, "features must be (N_in, C), got shape ", features.sizes());
  check_map(nbr, features, "features");
  TORCH_CHECK_VALUE(at::isFloatingType(features.scalar_type()), "features must be floating point, got ",
                    features.scalar_type());
}

inline void check_pool_backward_args(const at::Tensor& grad, const at::Tensor& arg, const at::Tensor& nbr_t) {
  TORCH_CHECK_VALUE(grad.dim() == 2, "grad must be (N_out, C), got shape ", grad.sizes());
  TORCH_CHECK_VALUE(arg.sizes() == grad.sizes() && arg.scalar_type() == at::kLong,
                    "argmax must be int64 with the shape of grad ", grad.sizes(), ", got shape ", arg.sizes(),
                    " and dtype ", arg.scalar_type());
  TORCH_CHECK_VALUE(nbr_t.dim() == 2 && nbr_t.scalar_type() == at::kInt, "kernel_map_t must be (N_in, K) int32, got shape ",
                    nbr_t.sizes(), " and dtype ", nbr_t.scalar_type());
  TORCH_CHECK_VALUE(at::isFloatingType(grad.scalar_type()), "grad must be floating point, got ", grad.scalar_type());
  TORCH_CHECK_VALUE(arg.device() == grad.device() && nbr_t.device() == grad.device(),
                    "argmax, kernel_map_t and grad must be on one device, got ", arg.device(), ", ", nbr_t.device(),
                    " and ", grad.device());
}

// Throws ValueError naming the first pair of rows with equal coordinates (CPU tensor).
void raise_if_duplicates(const at::Tensor& indices_cpu, const char* name, int64_t batch, const int64_t* shape, int ndim);

}  // namespace sparse
}  // namespace lidarops
