// Sparse convolution forward on CUDA, tensor cores through WMMA (sm_80+): the tensor-core kernel of the
// layers the pipeline does not take (rows not 16-byte vectors, or K > 32). sparse_conv_kernel.cu picks it.
#include <ATen/ATen.h>
#include <c10/cuda/CUDAException.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <mma.h>

#include <cstdint>
#include <type_traits>

#include "sparse_conv_pipeline.cuh"

namespace lidarops {
namespace sparse {
namespace {

// ------------------------------------------------------------------------------------------------
// forward, tensor cores: 64 x 64 tile per block of 4 warps (2 x 2, each 32 x 32 = 2 x 2 WMMA
// fragments), 32 input channels per step, float accumulation. float16 / bfloat16: 16x16x16 fragments;
// float32 when torch allows TF32 for matmuls (torch.backends.cuda.matmul.allow_tf32): 16x16x8 TF32
// fragments. kVec: Cin a multiple of the 16-byte vector and 16-byte aligned tensors, so rows are
// loaded as 16-byte vectors.
// ------------------------------------------------------------------------------------------------
template <typename T>
struct MmaTraits;
template <>
struct MmaTraits<c10::Half> {
  using S = __half;  // shared-memory element
  using F = __half;  // fragment element
  static constexpr int KS = 16, VEC = 8;
};
template <>
struct MmaTraits<c10::BFloat16> {
  using S = __nv_bfloat16;
  using F = __nv_bfloat16;
  static constexpr int KS = 16, VEC = 8;
};
template <>
struct MmaTraits<float> {
  using S = float;
  using F = nvcuda::wmma::precision::tf32;
  static constexpr int KS = 8, VEC = 4;
};

constexpr int kWmmaThreads = 128;

#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
// float32 fragments are rounded to TF32 before the MMA; other types are used as loaded.
template <typename T, typename Frag>
__device__ __forceinline__ void round_tf32(Frag& f) {
  if constexpr (std::is_same_v<T, float>) {
#pragma unroll
    for (int t = 0; t < f.num_elements; ++t) f.x[t] = nvcuda::wmma::__float_to_tf32(f.x[t]);
  }
}

// One BK-channel step of a warp's (16 FM) x (16 FN) share of the block tile, whose rows start at
// m0 and columns at n0: A row-major (As[m * lda + kk]), B column-major (Bs[n * ldb + kk]); float32
// goes through TF32 fragments.
template <typename T, int BK, int FM, int FN, typename S, typename Acc>
__device__ __forceinline__ void wmma_tile_step(const S* As, int lda, const S* Bs, int ldb, int m0, int n0,
                                               Acc (&c)[FM][FN]) {
  using namespace nvcuda;
  using FE = typename MmaTraits<T>::F;
  constexpr int KS = MmaTraits<T>::KS;
#pragma unroll
  for (int ks = 0; ks < BK / KS; ++ks) {
    wmma::fragment<wmma::matrix_a, 16, 16, KS, FE, wmma::row_major> a[FM];
    wmma::fragment<wmma::matrix_b, 16, 16, KS, FE, wmma::col_major> b[FN];
#pragma unroll
    for (int i = 0; i < FM; ++i) {
      wmma::load_matrix_sync(a[i], As + (m0 + i * 16) * lda + ks * KS, lda);
      round_tf32<T>(a[i]);
    }
#pragma unroll
    for (int j = 0; j < FN; ++j) {
      wmma::load_matrix_sync(b[j], Bs + (n0 + j * 16) * ldb + ks * KS, ldb);
      round_tf32<T>(b[j]);
    }
#pragma unroll
    for (int i = 0; i < FM; ++i)
#pragma unroll
      for (int j = 0; j < FN; ++j) wmma::mma_sync(c[i][j], a[i], b[j], c[i][j]);
  }
}
#endif

template <typename T, bool kVec>
__global__ void __launch_bounds__(kWmmaThreads)
    conv_fwd_wmma_kernel(const T* __restrict__ x, const T* __restrict__ w, const int32_t* __restrict__ nbr,
                         const int32_t* __restrict__ order, T* __restrict__ out, int64_t n_out, int64_t cin,
                         int64_t cout, int64_t K, ConvEpilogue epi, int64_t n_in) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  using namespace nvcuda;
  using S = typename MmaTraits<T>::S;
  constexpr int KS = MmaTraits<T>::KS, V = MmaTraits<T>::VEC;
  constexpr int BM = 64, BN = 64, BK = 32;
  constexpr int LDA = BK + V, LDB = BK + V;  // in elements: rows stay 16-byte aligned, as WMMA needs
  constexpr int LDC = BN + 4;                // floats: a multiple of 4
  __shared__ __align__(32) S As[BM * LDA];   // row-major A tile: As[m * LDA + kk]
  __shared__ __align__(32) S Bs[BN * LDB];   // column-major B tile (kk fastest): Bs[n * LDB + kk]
  __shared__ __align__(32) float Cs[BM * LDC];
  __shared__ int32_t rows[BM];
  __shared__ int64_t orow[BM];
  const int tid = threadIdx.x, warp = tid / 32;
  const int wm = warp / 2, wn = warp % 2;
  const int64_t row0 = static_cast<int64_t>(blockIdx.x) * BM;
  const int64_t col0 = static_cast<int64_t>(blockIdx.y) * BN;
  const S zero{};  // value-initialised: +0 (no float conversion under __CUDA_NO_HALF_CONVERSIONS__)
  for (int m = tid; m < BM; m += kWmmaThreads) orow[m] = output_row(order, row0 + m, n_out);
  __syncthreads();

  wmma::fragment<wmma::accumulator, 16, 16, KS, float> c[2][2];
#pragma unroll
  for (int i = 0; i < 2; ++i)
#pragma unroll
    for (int j = 0; j < 2; ++j) wmma::fill_fragment(c[i][j], 0.0f);

  const S* xs = reinterpret_cast<const S*>(x);
  const S* ws = reinterpret_cast<const S*>(w);
  for (int64_t k = 0; k < K; ++k) {
    if (!__syncthreads_or(offset_rows<BM, kWmmaThreads>(nbr, orow, K, k, n_in, rows))) continue;
    for (int64_t c0 = 0; c0 < cin; c0 += BK) {
      // A: BM rows x BK channels, V channels (16 bytes) per item
      for (int e = tid; e < BM * (BK / V); e += kWmmaThreads) {
        const int m = e / (BK / V), v = e % (BK / V);
        const int32_t r = rows[m];
        const int64_t ci = c0 + v * V;
        S* dst = As + m * LDA + v * V;
        if (kVec && r >= 0 && ci + V <= cin) {
          *reinterpret_cast<int4*>(dst) = __ldg(reinterpret_cast<const int4*>(xs + static_cast<int64_t>(r) * cin + ci));
        } else {
#pragma unroll
          for (int t = 0; t < V; ++t)
            dst[t] = (r >= 0 && ci + t < cin) ? xs[static_cast<int64_t>(r) * cin + ci + t] : zero;
        }
      }
      // B: BN output channels x BK input channels of W[co, k, ci]
      for (int e = tid; e < BN * (BK / V); e += kWmmaThreads) {
        const int n = e / (BK / V), v = e % (BK / V);
        const int64_t co = col0 + n, ci = c0 + v * V;
        S* dst = Bs + n * LDB + v * V;
        if (co < cout) {
          const S* src = ws + (co * K + k) * cin + ci;
          if (kVec && ci + V <= cin) {
            *reinterpret_cast<int4*>(dst) = __ldg(reinterpret_cast<const int4*>(src));
          } else {
#pragma unroll
            for (int t = 0; t < V; ++t) dst[t] = ci + t < cin ? src[t] : zero;
          }
        } else {
#pragma unroll
          for (int t = 0; t < V; ++t) dst[t] = zero;
        }
      }
      __syncthreads();
      wmma_tile_step<T, BK, 2, 2>(As, LDA, Bs, LDB, wm * 32, wn * 32, c);
      __syncthreads();
    }
  }
#pragma unroll
  for (int i = 0; i < 2; ++i)
#pragma unroll
    for (int j = 0; j < 2; ++j)
      wmma::store_matrix_sync(Cs + (wm * 32 + i * 16) * LDC + wn * 32 + j * 16, c[i][j], LDC, wmma::mem_row_major);
  __syncthreads();
  for (int e = tid; e < BM * BN; e += kWmmaThreads) {
    const int m = e / BN, n = e % BN;
    const int64_t o = orow[m], co = col0 + n;
    if (o >= 0 && co < cout) out[o * cout + co] = static_cast<T>(epi(Cs[m * LDC + n], co));
  }
#else
  __trap();  // launched only on sm_80+ (checked on the host)
#endif
}

}  // namespace

void conv_fwd_wmma(const ConvLaunch& a, bool vec_rows) {
  const at::Tensor &x = a.x, &w = a.w, &nbr = a.nbr;
  const int64_t n_in = x.size(0), cin = x.size(1), cout = w.size(0), K = w.size(1), n_out = nbr.size(0);
  const dim3 grid(static_cast<unsigned>(ceil_div(n_out, 64)), static_cast<unsigned>(ceil_div(cout, 64)));
  auto launch = [&](auto tag) {
    using scalar_t = decltype(tag);
    auto kernel = vec_rows ? conv_fwd_wmma_kernel<scalar_t, true> : conv_fwd_wmma_kernel<scalar_t, false>;
    kernel<<<grid, kWmmaThreads, 0, a.stream>>>(x.data_ptr<scalar_t>(), w.data_ptr<scalar_t>(), nbr.data_ptr<int32_t>(),
                                                a.order, a.out.data_ptr<scalar_t>(), n_out, cin, cout, K, a.epi, n_in);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  };
  const auto dtype = x.scalar_type();
  if (dtype == at::kHalf) launch(c10::Half{});
  else if (dtype == at::kBFloat16) launch(c10::BFloat16{});
  else launch(float{});
}

}  // namespace sparse
}  // namespace lidarops
