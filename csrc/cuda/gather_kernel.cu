// gather (grouping) and its adjoint on CUDA.
//
// gather: a row copy per index, in the widest vector (16, 8, 4, 2 or 1 bytes) that divides the
// row and the alignment of both tensors; any dtype (the rows are copied as bytes, as on CPU).
// Indices outside [0, N) give rows of zeros (the wrapper only passes [-1, N)).
//
// gather_backward: deterministic and bit-identical to the CPU kernel. The indices of each cloud
// are sorted (stably) and each run of equal indices is summed by one thread per channel, in
// increasing position order, starting from 0, in float (half/bfloat16/float) or double, then cast
// back: exactly the CPU's `acc[j] += grad[l]` sequence. No atomics, so results do not depend on
// scheduling (and torch.use_deterministic_algorithms holds). Indices outside [0, n) are ignored.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include "lidarops/cuda_launch.cuh"

namespace lidarops {
namespace {

constexpr int kThreads = 256;

void check_gather_args(const at::Tensor& x, const at::Tensor& idx, const char* xname) {
  TORCH_CHECK_VALUE(x.dim() == 3, xname, " must be (B, N, C), got shape ", x.sizes());
  TORCH_CHECK_VALUE(idx.dim() == 2 && idx.size(0) == x.size(0), "idx must be (B, L) with B = ", x.size(0),
                    ", got shape ", idx.sizes());
  TORCH_CHECK_VALUE(idx.scalar_type() == at::kLong, "idx must be int64, got ", idx.scalar_type());
  TORCH_CHECK_VALUE(idx.device() == x.device(), "idx is on ", idx.device(), " but ", xname, " is on ", x.device());
}

// tpr threads per row (a power of two <= 32), kThreads / tpr rows per block, grid-stride over rows.
template <typename V>
__global__ void __launch_bounds__(kThreads)
    gather_kernel(const V* __restrict__ x, const int64_t* __restrict__ idx, int64_t N, int64_t L, int64_t rows,
                  int64_t vecs, int tpr, V* __restrict__ out) {
  const int rows_per_block = kThreads / tpr;
  const int col0 = threadIdx.x % tpr;
  for (int64_t r = blockIdx.x * static_cast<int64_t>(rows_per_block) + threadIdx.x / tpr; r < rows;
       r += static_cast<int64_t>(gridDim.x) * rows_per_block) {
    const int64_t j = idx[r];
    V* dst = out + r * vecs;
    if (j >= 0 && j < N) {
      const V* src = x + ((r / L) * N + j) * vecs;
      for (int64_t c = col0; c < vecs; c += tpr) dst[c] = src[c];
    } else {
      const V zero{};
      for (int64_t c = col0; c < vecs; c += tpr) dst[c] = zero;
    }
  }
}

template <typename V>
void launch_gather(const at::Tensor& x, const at::Tensor& idx, at::Tensor& out, int64_t row_bytes,
                   cudaStream_t stream) {
  const int64_t B = x.size(0), N = x.size(1), L = idx.size(1);
  const int64_t vecs = row_bytes / static_cast<int64_t>(sizeof(V)), rows = B * L;
  const int tpr = static_cast<int>(std::min<int64_t>(32, gpu::pow2_ceil(vecs)));
  const unsigned blocks = gpu::stride_blocks(rows, kThreads / tpr, 1 << 20);
  gather_kernel<V><<<blocks, kThreads, 0, stream>>>(static_cast<const V*>(x.data_ptr()), idx.data_ptr<int64_t>(), N,
                                                    L, rows, vecs, tpr, static_cast<V*>(out.data_ptr()));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

at::Tensor gather_cuda(const at::Tensor& x_in, const at::Tensor& idx_in) {
  check_gather_args(x_in, idx_in, "x");
  c10::cuda::CUDAGuard device_guard(x_in.device());
  auto x = x_in.contiguous();
  auto idx = idx_in.contiguous();
  const int64_t B = x.size(0), C = x.size(2), L = idx.size(1);
  auto out = at::empty({B, L, C}, x.options());
  if (out.numel() == 0) return out;
  const int64_t row_bytes = C * static_cast<int64_t>(x.element_size());
  const auto addr = reinterpret_cast<uintptr_t>(x.data_ptr()) | reinterpret_cast<uintptr_t>(out.data_ptr());
  auto fits = [&](int64_t w) { return row_bytes % w == 0 && addr % static_cast<uintptr_t>(w) == 0; };
  cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  if (fits(16)) launch_gather<uint4>(x, idx, out, row_bytes, stream);
  else if (fits(8)) launch_gather<uint2>(x, idx, out, row_bytes, stream);
  else if (fits(4)) launch_gather<uint32_t>(x, idx, out, row_bytes, stream);
  else if (fits(2)) launch_gather<uint16_t>(x, idx, out, row_bytes, stream);
  else launch_gather<uint8_t>(x, idx, out, row_bytes, stream);
  return out;
}

// Sort keys: the index where it lies in [0, n), else n (sorted last, ignored); 32-bit keys halve
// the radix sort's passes.
__global__ void backward_keys_kernel(const int64_t* __restrict__ idx, int64_t total, int64_t n,
                                     int32_t* __restrict__ keys) {
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < total;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t j = idx[t];
    keys[t] = static_cast<int32_t>(j >= 0 && j < n ? j : n);
  }
}

// Thread (b, p, c): if sorted position p of cloud b starts a run of index j < n, writes
// acc[b, j, c] = sum over the run, in position order (= increasing l: the sort is stable).
template <typename scalar_t, typename A>
__global__ void backward_sum_kernel(const scalar_t* __restrict__ grad, const int32_t* __restrict__ skeys,
                                    const int64_t* __restrict__ perm, int64_t B, int64_t L, int64_t C, int64_t n,
                                    A* __restrict__ acc) {
  const int64_t total = B * L * C;
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < total;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t pos = t / C, c = t - pos * C;  // pos = b * L + p
    const int64_t b = pos / L, p = pos - b * L;
    const int64_t j = skeys[pos];
    if (j >= n || (p > 0 && skeys[pos - 1] == j)) continue;
    const int64_t end = (b + 1) * L;
    A sum = A(0);
    for (int64_t q = pos; q < end && skeys[q] == j; ++q)
      sum += static_cast<A>(grad[(b * L + perm[q]) * C + c]);
    acc[(b * n + j) * C + c] = sum;
  }
}

at::Tensor gather_backward_cuda(const at::Tensor& grad_in, const at::Tensor& idx_in, int64_t n) {
  check_gather_args(grad_in, idx_in, "grad");
  TORCH_CHECK_VALUE(grad_in.size(1) == idx_in.size(1), "grad must be (B, L, C) with L = ", idx_in.size(1),
                    ", got shape ", grad_in.sizes());
  TORCH_CHECK_VALUE(n >= 0, "n must be >= 0, got ", n);
  TORCH_CHECK_VALUE(n < std::numeric_limits<int32_t>::max(), "n must be < 2^31 - 1 on CUDA, got ", n);
  TORCH_CHECK_VALUE(at::isFloatingType(grad_in.scalar_type()), "grad must be floating, got ", grad_in.scalar_type());
  c10::cuda::CUDAGuard device_guard(grad_in.device());
  auto grad = grad_in.contiguous();
  auto idx = idx_in.contiguous();
  const int64_t B = grad.size(0), L = grad.size(1), C = grad.size(2);
  auto acc_dtype = grad.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  auto acc = at::zeros({B, n, C}, grad.options().dtype(acc_dtype));
  if (acc.numel() == 0 || L == 0) return acc.to(grad.scalar_type());
  cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  auto keys = at::empty({B, L}, idx.options().dtype(at::kInt));
  backward_keys_kernel<<<gpu::stride_blocks(B * L, kThreads), kThreads, 0, stream>>>(idx.data_ptr<int64_t>(), B * L,
                                                                                      n, keys.data_ptr<int32_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  auto sorted = keys.sort(/*stable=*/true, /*dim=*/1, /*descending=*/false);
  auto skeys = std::get<0>(sorted).contiguous();
  auto perm = std::get<1>(sorted).contiguous();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, grad.scalar_type(), "lidarops_gather_backward_cuda", [&] {
    using T = acc_t<scalar_t>;
    backward_sum_kernel<scalar_t, T><<<gpu::stride_blocks(B * L * C, kThreads, 1 << 20), kThreads, 0, stream>>>(
        grad.data_ptr<scalar_t>(), skeys.data_ptr<int32_t>(), perm.data_ptr<int64_t>(), B, L, C, n,
        acc.data_ptr<T>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return acc.scalar_type() == grad.scalar_type() ? acc : acc.to(grad.scalar_type());
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("gather", &gather_cuda);
  m.impl("gather_backward", &gather_backward_cuda);
}

}  // namespace lidarops
