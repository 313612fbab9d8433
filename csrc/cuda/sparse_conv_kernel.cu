// Sparse convolution on CUDA: one fused implicit-GEMM kernel over all kernel offsets.
//
// Forward, output-stationary: out (N_out x Cout) = A (N_out x K*Cin) . W^T, where row o of A is the
// concatenation over offsets k of features[kernel_map[o, k]] (zeros where the map is -1). A block
// owns a tile of output rows x output channels and walks every offset and input-channel chunk,
// gathering the input rows straight into shared memory; offsets with no input for any row of the
// tile are skipped (a block-wide vote). No atomics, no host synchronisation: each output element is
// summed by one thread in a fixed order, so results are deterministic. Layers with too few tiles to
// fill the GPU (the deep layers of a backbone: few sites, many channels) split each tile's offsets
// over up to four blocks (offset_splits); a second kernel adds their partial sums in a fixed order.
//   - float16 / bfloat16 (sm_80+, Cin and Cout >= 16): tensor cores with float accumulation; float32
//     likewise with TF32 when torch allows TF32 matmuls (off by default). Cin a multiple of the 16-byte
//     vector and K <= 32: mma.sync fed by a cp.async pipeline, or, on Hopper (compute capability 9.0,
//     sm_90a builds) for Cout > 64, wgmma fed by the same pipeline; otherwise WMMA 16x16x16 (TF32 16x16x8).
//   - float32 otherwise (sm_80+, Cin a multiple of 4, K <= 32): SIMT (FFMA) tiles fed by cp.async
//     pipelines, or, with algo="3xtf32" (experimental), the mma.sync kernel as 3xTF32;
//   - otherwise general SIMT tiles in float (float64 in float64).
// The pipelined kernels start with the tiles of the rows with the most offsets (heavy_first_tile).
// Rows are processed in the order given by sparse_kernel_map_order (grouped by their offset masks),
// so the rows of a tile share their offsets and the skipping is effective on real data.
// Backward: the features gradient is this kernel over the transposed map (csrc/ops/autograd); the
// weight gradient is a split-K reduction over output rows into per-split partial sums (float), added
// in a fixed order: deterministic too (sparse_conv_wgrad.cu).
// This file picks a layer's kernel family and registers the ops; the families have a file each
// (sparse_conv.cuh lists them). The ops' algo and splits arguments override the choices (sparse.h).
#include <ATen/ATen.h>
#include <ATen/Context.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <cub/device/device_radix_sort.cuh>

#include <cstdint>
#include <tuple>

#include "sparse_conv.cuh"

namespace lidarops {
namespace sparse {
namespace {

bool aligned16(const void* p) { return (reinterpret_cast<uintptr_t>(p) & 15) == 0; }

// Columns of the wgmma tile (conv_fwd_wgmma_kernel) for a tensor-core layer, or 0 for the mma.sync
// tiles: wgmma needs an sm_90a build running on compute capability 9.0; algo "mma_sync" keeps mma.sync,
// for the tests and for comparisons. Against the mma.sync tiles:
//   - Cout <= 64: mma.sync's 32 x 64 tiles, which skip the 16-row fragments without an input at an
//     offset, stay as fast or faster;
//   - TF32: 64 x 128, each gathered row read once for 128 columns;
//   - 16-bit: 64 x 64 with four stages.
int wgmma_columns(int64_t cout, bool tf32, const DeviceProps& p, ConvAlgo algo) {
#ifdef LIDAROPS_SM90A
  if (p.cc_major != 9 || p.cc_minor != 0 || cout <= 64 || algo == ConvAlgo::kMmaSync) return 0;
  return tf32 ? 128 : 64;
#else
  return 0;
#endif
}

// Each row's offset mask (sparse.h, row_mask) as a radix key, and its row number as the value.
template <typename Key>
__global__ void row_mask_kernel(const int32_t* __restrict__ nbr, int64_t m, int64_t K, Key* __restrict__ masks,
                                int32_t* __restrict__ rows) {
  const int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x;
  if (t >= m) return;
  masks[t] = static_cast<Key>(row_mask(nbr + t * K, K));
  rows[t] = static_cast<int32_t>(t);
}

// A stable radix sort of the rows by their masks, over the mask's bits only (a 3 x 3 map: 9 bits, two
// passes, where a sort of 64-bit keys takes eight): the order torch's stable sort of the masks gives.
template <typename Key>
at::Tensor order_by_masks(const at::Tensor& nbr, int64_t m, int64_t K, cudaStream_t stream) {
  const int bits = static_cast<int>(K < 63 ? K : 63);
  auto order = at::empty({m}, nbr.options());
  // the masks (in, out), the row numbers and cub's scratch in one allocation: host time per map
  size_t temp_bytes = 0;
  if (bits > 0)
    C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(nullptr, temp_bytes, static_cast<Key*>(nullptr),
                                                   static_cast<Key*>(nullptr), static_cast<int32_t*>(nullptr),
                                                   static_cast<int32_t*>(nullptr), static_cast<int>(m), 0, bits,
                                                   stream));
  const int64_t key_bytes = 2 * m * static_cast<int64_t>(sizeof(Key));
  const int64_t temp_at = (key_bytes + 4 * m + 255) / 256 * 256;  // cub's scratch 256-byte aligned
  auto scratch = at::empty({temp_at + static_cast<int64_t>(temp_bytes)}, nbr.options().dtype(at::kByte));
  auto* base = static_cast<uint8_t*>(scratch.data_ptr());
  Key* k_in = reinterpret_cast<Key*>(base);
  int32_t* r_in = reinterpret_cast<int32_t*>(base + key_bytes);
  void* temp = base + temp_at;
  row_mask_kernel<Key><<<static_cast<unsigned>(ceil_div(m, 256)), 256, 0, stream>>>(
      nbr.data_ptr<int32_t>(), m, K, k_in, bits == 0 ? order.data_ptr<int32_t>() : r_in);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (bits == 0) return order;
  C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(temp, temp_bytes, k_in, k_in + m, r_in, order.data_ptr<int32_t>(),
                                                 static_cast<int>(m), 0, bits, stream));
  return order;
}

at::Tensor sparse_kernel_map_order_cuda(const at::Tensor& nbr_in) {
  TORCH_CHECK_VALUE(nbr_in.dim() == 2 && nbr_in.scalar_type() == at::kInt, "kernel_map must be (N_out, K) int32, got shape ",
                    nbr_in.sizes(), " and dtype ", nbr_in.scalar_type());
  const c10::cuda::OptionalCUDAGuard guard(nbr_in.device());
  auto nbr = nbr_in.contiguous();
  const int64_t m = nbr.size(0), K = nbr.size(1);
  TORCH_CHECK_VALUE(m < INT32_MAX, "kernel_map has ", m, " rows; at most 2^31 - 2 are supported");
  if (m == 0) return at::empty({0}, nbr.options());
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  return K <= 32 ? order_by_masks<uint32_t>(nbr, m, K, stream) : order_by_masks<uint64_t>(nbr, m, K, stream);
}

// Output rows with no input: every one is epi(0) (at::empty otherwise, so each kernel writes every row).
at::Tensor conv_without_inputs(at::Tensor& out, const ConvEpilogue& epi, const at::Tensor& scale,
                               const at::Tensor& shift) {
  if (!scale.defined() && !shift.defined()) return out.zero_();
  auto row = shift.defined() ? shift.clone() : at::zeros({out.size(1)}, out.options().dtype(at::kFloat));
  if (epi.relu) row.clamp_min_(0);  // scale * 0 = 0
  return out.copy_(row.unsqueeze(0).expand_as(out));
}

at::Tensor sparse_conv_cuda_impl(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& nbr_in,
                                 const c10::optional<at::Tensor>& order_in, const at::Tensor& scale,
                                 const at::Tensor& shift, bool relu, ConvAlgo algo, int64_t splits) {
  const c10::cuda::OptionalCUDAGuard guard(features.device());
  const ConvEpilogue epi = make_epilogue(scale, shift, relu);
  auto x = features.contiguous();
  auto w = weight.contiguous();
  auto nbr = nbr_in.contiguous();
  at::Tensor order_t;
  if (order_in.has_value() && order_in->defined()) order_t = order_in->contiguous();
  const int32_t* order = order_t.defined() ? order_t.data_ptr<int32_t>() : nullptr;
  const int64_t n_in = x.size(0), cin = x.size(1), cout = w.size(0), K = w.size(1), n_out = nbr.size(0);
  TORCH_CHECK_VALUE(ceil_div(n_out, 64) < (int64_t(1) << 31) && ceil_div(cout, 16) < 65536,
                    "sparse_conv: too many output rows or channels for one launch (", n_out, " x ", cout, ")");
  auto out = at::empty({n_out, cout}, x.options());
  if (n_out == 0 || cout == 0) return out;
  if (n_in == 0 || cin == 0 || K == 0) return conv_without_inputs(out, epi, scale, shift);
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  const auto dtype = x.scalar_type();
  const bool half_type = dtype == at::kHalf || dtype == at::kBFloat16;
  // float32 follows torch.backends.cuda.matmul.allow_tf32 (off by default: float32 accuracy)
  const bool tf32 = dtype == at::kFloat && at::globalContext().allowTF32CuBLAS();
  const bool x3 = dtype == at::kFloat && !tf32 && algo == ConvAlgo::k3xTF32;
  const DeviceProps props = device_props(x.get_device());
  const bool sm80 = props.cc_major >= 8;
  const bool tensor_cores = (half_type || tf32 || x3) && cin >= 16 && cout >= 16 && sm80;
  // rows of 16-byte vectors (8 halves or 4 floats), 16-byte aligned: the cp.async pipelines
  const bool vec_rows = cin % (half_type ? 8 : 4) == 0 && aligned16(x.data_ptr()) && aligned16(w.data_ptr());
  const bool pipelined = vec_rows && K <= kAsyncMaxK;
  const ConvLaunch launch{x, w, nbr, order, out, epi, props, stream, splits};
  if (tensor_cores && pipelined) {
    const Mma mode = dtype == at::kHalf       ? Mma::kF16
                     : dtype == at::kBFloat16 ? Mma::kBF16
                     : x3                     ? Mma::k3xTF32
                                              : Mma::kTF32;
    const int wg = x3 ? 0 : wgmma_columns(cout, mode == Mma::kTF32, props, algo);  // 3xTF32: mma.sync only
    if (wg != 0) conv_fwd_wgmma(launch, mode, wg, algo);
    else conv_fwd_mma(launch, mode);
    return out;
  }
  if (tensor_cores && !x3) {  // the plain WMMA kernel: rows not 16-byte vectors, or K > 32
    conv_fwd_wmma(launch, vec_rows);
    return out;
  }
  if (dtype == at::kFloat && pipelined && sm80) {
    conv_fwd_ffma(launch);
    return out;
  }
  conv_fwd_simt(launch);
  return out;
}

at::Tensor sparse_conv_cuda(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& nbr,
                            const c10::optional<at::Tensor>& order, c10::string_view algo, int64_t splits) {
  check_conv_args(features, weight, nbr);
  check_order(order, nbr);
  const ConvAlgo choice = check_conv_algo(algo, splits);
  return sparse_conv_cuda_impl(features, weight, nbr, order, at::Tensor(), at::Tensor(), false, choice, splits);
}

at::Tensor sparse_conv_affine_cuda(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& nbr,
                                   const c10::optional<at::Tensor>& order, const c10::optional<at::Tensor>& scale,
                                   const c10::optional<at::Tensor>& shift, bool relu, c10::string_view algo,
                                   int64_t splits) {
  check_conv_args(features, weight, nbr);
  check_order(order, nbr);
  const auto scale_c = epilogue_operand(scale, "scale", weight.size(0), features);  // checked in this order
  const auto shift_c = epilogue_operand(shift, "shift", weight.size(0), features);
  const ConvAlgo choice = check_conv_algo(algo, splits);
  return sparse_conv_cuda_impl(features, weight, nbr, order, scale_c, shift_c, relu, choice, splits);
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("sparse_kernel_map_order", &sparse_kernel_map_order_cuda);
  m.impl("sparse_conv", &sparse_conv_cuda);
  m.impl("sparse_conv_affine", &sparse_conv_affine_cuda);
}

}  // namespace sparse
}  // namespace lidarops
