// SSCATeR delta convolution on CUDA, same contract as the CPU kernels (csrc/cpu/sscater_kernel.cpp).
// The scatter and the gather are one tiled GEMM (tap_gemm_kernel: 64 x 64 outputs per 256-thread
// block, 4 x 4 per thread read as vectors from shared memory) whose A operand is read through the
// site list, one tap and one chunk of input channels per tile: the scatter multiplies the changed
// rows' deltas by the tap's weight and adds the products at the sites they reach; the gather reads
// each site's input shifted by the tap (implicit im2col). Partial sums meet through atomicAdd (several
// changed inputs reach one output site, and the taps and chunks of one site are split over tiles), so
// the order of the additions is not fixed and results agree with the CPU to rounding, not bit for
// bit. The kernel loops over its tiles with a fixed grid and reads its row count from the device when
// given one, so that a padded list whose length only the device knows costs no host synchronisation
// and no work beyond its rows. A tile whose rows all miss (tap outside the grid, inactive output,
// padding) is skipped. A delta whose channels are mostly exactly zero takes the channel-sparse kernel
// instead (sparse_rows_kernel), chosen on the device from the count of its zeros.
#include <algorithm>
#include <cstdlib>
#include <string>
#include <type_traits>

#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include "lidarops/cuda_launch.cuh"
#include "lidarops/sscater.h"

namespace lidarops {
namespace sscater {
namespace {

constexpr int kThreads = 256;

// Every kernel here loops grid-stride, and many read their length on the device (a padded list): a
// bounded grid keeps the launch of a mostly empty list cheap.
inline unsigned blocks_for(int64_t n) { return gpu::stride_blocks(n, kThreads, 2048); }

// One thread per (row, tap): the reached output site, -1 outside the grid, on an inactive site, on a
// padding row or past the row count.
__global__ void targets_kernel(const int32_t* __restrict__ sites, const bool* __restrict__ active,
                               int64_t* __restrict__ target, int64_t rows, const int64_t* __restrict__ count,
                               int64_t kh, int64_t kw, int64_t Ho, int64_t Wo, int64_t stride, int64_t padding,
                               bool transposed) {
  const int64_t K = kh * kw;
  const int64_t n = count == nullptr ? rows : (*count < rows ? *count : rows);
  for (int64_t r = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; r < rows * K;
       r += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    int64_t o = r / K < n ? tap_target(sites, r / K, r % K, kw, stride, padding, Ho, Wo, transposed) : -1;
    if (o >= 0 && active != nullptr && !active[o]) o = -1;
    target[r] = o;
  }
}

// ---- tiled GEMM with a gathered A operand -------------------------------------------------------
//
// Both the scatter and the gather are sums over taps k and input channels ci of A_k[row, ci] *
// W[c, k, ci], added at a destination site per row. A tile is (64 rows, 64 output channels, one tap,
// a chunk of 64 input channels): splitting the reduction over taps and channel chunks gives enough
// tiles for the few hundred rows a step brings, and the partial sums meet through atomicAdd.
//   scatter: A_k[row] = delta[row], destination = the site the row reaches through tap k;
//   gather: A_k[row] = input at the row's site shifted by tap k, destination = the row's site (zeroed
//   first).
// Each tile lists its rows' source offsets and destinations once in shared memory, so the inner
// loads are a shared-memory read and an add.

// kChunk: input channels per tile, the fastest of 16-256 on the drone_bridge step (docs/notes/sscater.md).
// kGatherChunk: the gather's; a step adds only 45-250 sites per layer, so smaller chunks give more
// tiles and shorter dependency chains.
constexpr int kBM = 64, kBN = 64, kBK = 16, kChunk = 64, kGatherChunk = 16, kGemmThreads = 256;

template <typename T>
struct GemmTile {
  alignas(16) T a[kBK][kBM + 4];  // A^T step: a[kk][m] (rows of 16-byte multiples: vector reads)
  alignas(16) T b[kBK][kBN + 4];  // B step: b[kk][n]
  int64_t src[kBM];               // element offset of the row's A operand, -1: none (adds nothing)
  int64_t dst[kBM];               // destination site key, -1: none
};

// v[0..3] = p[0..3] (p 16-byte aligned for float: one shared-memory vector load)
__device__ __forceinline__ void load4(float (&v)[4], const float* p) {
  const float4 q = *reinterpret_cast<const float4*>(p);
  v[0] = q.x, v[1] = q.y, v[2] = q.z, v[3] = q.w;
}
__device__ __forceinline__ void load4(double (&v)[4], const double* p) {
#pragma unroll
  for (int i = 0; i < 4; ++i) v[i] = p[i];
}

// acc[0..3] += v[0..3]; one vector atomic on sm_90 for float when aligned
__device__ __forceinline__ void atomic_add4(float* acc, const float (&v)[4], bool aligned) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  if (aligned) {
    atomicAdd(reinterpret_cast<float4*>(acc), make_float4(v[0], v[1], v[2], v[3]));
    return;
  }
#endif
#pragma unroll
  for (int j = 0; j < 4; ++j) atomicAdd(acc + j, v[j]);
}
__device__ __forceinline__ void atomic_add4(double* acc, const double (&v)[4], bool) {
#pragma unroll
  for (int j = 0; j < 4; ++j) atomicAdd(acc + j, v[j]);
}

// The channel-sparse kernel takes a delta of n rows when at least `share` of its n * Cin values are
// exactly zero; every block of both kernels reads the same count and decides alike.
__device__ __forceinline__ bool sparse_chosen(const unsigned long long* zeros, double share, int64_t n, int64_t Cin) {
  return static_cast<double>(*zeros) >= share * static_cast<double>(n * Cin);
}

struct TapGemmArgs {
  int64_t rows, K, kw, Cin, C, chunk, chunks, col_tiles;
  // the scatter's kernel choice, made on the device (no host synchronisation): with zeros, the GEMM
  // stands aside when the channel-sparse kernel takes the delta (sparse_chosen)
  const unsigned long long* zeros;
  double sparse_share;
  int64_t ws0, ws1, ws2, ws3;  // weight (Cout, kh, kw, Cin) strides
  bool gather;
  // scatter
  const int64_t* target;  // (rows * K,) reached keys
  // gather
  const int32_t* sites;
  int64_t Ho, Wo, Hi, Wi, s0, s1, s2, stride, padding;
};

// MinBlocks: blocks each multiprocessor must hold (a register cap; 1: the compiler's choice)
template <typename T, int MinBlocks>
__global__ void __launch_bounds__(kGemmThreads, MinBlocks)
    tap_gemm_kernel(T* __restrict__ acc, const T* __restrict__ src, const T* __restrict__ w,
                    const int64_t* __restrict__ count, TapGemmArgs g) {
  __shared__ GemmTile<T> s;
  const int64_t n = count == nullptr ? g.rows : (*count < g.rows ? *count : g.rows);
  if (g.zeros != nullptr && sparse_chosen(g.zeros, g.sparse_share, n, g.Cin)) return;
  const int64_t per_row_tile = g.col_tiles * g.K * g.chunks;
  const int64_t tiles = (n + kBM - 1) / kBM * per_row_tile;
  const int tid = threadIdx.x, ty = tid / 16, tx = tid % 16;
  const int64_t sa = g.gather ? g.s2 : 1;  // A's stride along the input channels
  for (int64_t t = blockIdx.x; t < tiles; t += gridDim.x) {
    // tap and chunk fastest: neighbouring tiles share the rows' data in L2
    const int64_t k = t % g.K, chunk = t / g.K % g.chunks, col0 = t / (g.K * g.chunks) % g.col_tiles * kBN;
    const int64_t row0 = t / per_row_tile * kBM, ci0 = chunk * g.chunk;
    bool any = false;
    for (int i = tid; i < kBM; i += kGemmThreads) {
      const int64_t row = row0 + i;
      int64_t from = -1, to = -1;
      if (row < n) {
        if (g.gather) {
          int64_t y, x;
          if (site_at(g.sites, row, g.Ho, g.Wo, y, x)) {
            const int64_t iy = y * g.stride - g.padding + k / g.kw, ix = x * g.stride - g.padding + k % g.kw;
            if (iy >= 0 && iy < g.Hi && ix >= 0 && ix < g.Wi) {
              from = iy * g.s0 + ix * g.s1 + ci0 * g.s2;
              to = y * g.Wo + x;
            }
          }
        } else {
          to = g.target[row * g.K + k];
          from = to >= 0 ? row * g.Cin + ci0 : -1;
        }
      }
      s.src[i] = from;
      s.dst[i] = to;
      any = to >= 0;
    }
    if (!__syncthreads_or(any)) continue;  // block-uniform: no row of the tile adds anything
    const int64_t P = g.Cin - ci0 < g.chunk ? g.Cin - ci0 : g.chunk;
    const T* wk = w + (k / g.kw) * g.ws1 + (k % g.kw) * g.ws2 + ci0 * g.ws3;
    T r[4][4] = {};
    for (int p0 = 0; p0 < P; p0 += kBK) {
      for (int e = tid; e < kBM * kBK; e += kGemmThreads) {  // consecutive threads: consecutive channels
        const int m = e / kBK, kk = e % kBK;
        const int64_t off = s.src[m];
        s.a[kk][m] = off >= 0 && p0 + kk < P ? src[off + (p0 + kk) * sa] : T(0);
      }
      for (int e = tid; e < kBN * kBK; e += kGemmThreads) {
        const int c = e / kBK, kk = e % kBK;
        s.b[kk][c] = col0 + c < g.C && p0 + kk < P ? wk[(col0 + c) * g.ws0 + (p0 + kk) * g.ws3] : T(0);
      }
      __syncthreads();
#pragma unroll
      for (int kk = 0; kk < kBK; ++kk) {  // rows ty * 4 + i, columns tx * 4 + j
        T av[4], bv[4];
        load4(av, &s.a[kk][ty * 4]);
        load4(bv, &s.b[kk][tx * 4]);
#pragma unroll
        for (int i = 0; i < 4; ++i)
#pragma unroll
          for (int j = 0; j < 4; ++j) r[i][j] += av[i] * bv[j];
      }
      __syncthreads();
    }
    const int64_t c0 = col0 + tx * 4;
    const bool whole = c0 + 4 <= g.C, aligned = whole && g.C % 4 == 0;
#pragma unroll
    for (int i = 0; i < 4; ++i) {
      const int64_t o = s.dst[ty * 4 + i];
      if (o < 0 || s.src[ty * 4 + i] < 0) continue;
      T* dst = acc + o * g.C + c0;
      if (whole) {
        atomic_add4(dst, r[i], aligned);
      } else {
#pragma unroll
        for (int j = 0; j < 4; ++j)
          if (c0 + j < g.C) atomicAdd(dst + j, r[i][j]);
      }
    }
    __syncthreads();  // src / dst are rewritten by the next tile
  }
}

// The GEMM's tuning: the scatter's chunk of input channels; the grid, 8 blocks per multiprocessor or one full
// wave of resident blocks (wave: no partial last wave); and the blocks a multiprocessor must hold (min_blocks,
// a register cap for float). Defaults: kGemmTuning. LIDAROPS_SSCATER_TILING="chunk:N,wave:0|1,min_blocks:N"
// overrides them, for benchmarks/bm_sscater.py; read once.
struct GemmTuning {
  int64_t chunk;
  bool wave;
  int min_blocks;
};
constexpr GemmTuning kGemmTuning{kChunk, true, 4};

inline GemmTuning gemm_tuning() {
  static const GemmTuning tuning = [] {
    GemmTuning t = kGemmTuning;
    const char* env = std::getenv("LIDAROPS_SSCATER_TILING");
    std::string v(env == nullptr ? "" : env);
    while (!v.empty()) {
      const auto comma = v.find(',');
      const std::string item = v.substr(0, comma);
      v = comma == std::string::npos ? "" : v.substr(comma + 1);
      const auto colon = item.find(':');
      const std::string key = item.substr(0, colon);
      const long long n = colon == std::string::npos ? -1 : std::atoll(item.c_str() + colon + 1);
      TORCH_CHECK_VALUE(n >= 0 && (key == "chunk" || key == "wave" || key == "min_blocks"),
                        "LIDAROPS_SSCATER_TILING must be key:N items (chunk, wave, min_blocks) separated by commas, "
                        "got ", env);
      if (key == "chunk") t.chunk = std::max<int64_t>(kBK, (n + kBK - 1) / kBK * kBK);
      if (key == "wave") t.wave = n != 0;
      if (key == "min_blocks") t.min_blocks = n >= 4 ? 4 : 1;
    }
    return t;
  }();
  return tuning;
}

template <typename T, int MinBlocks>
unsigned gemm_blocks(int64_t tiles, const at::Tensor& on, bool wave) {
  const int64_t sms = gpu::device_props(on.get_device()).sms;
  int64_t cap = 8 * sms;
  if (wave) {  // as many blocks as the multiprocessors hold at once: each loops over its tiles
    // once per instantiation: another kind of device in the same process gets this grid (speed, not results)
    static const int resident = [] {
      int n = 0;
      C10_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&n, tap_gemm_kernel<T, MinBlocks>, kGemmThreads, 0));
      return std::max(n, 1);
    }();
    cap = resident * sms;
  }
  return static_cast<unsigned>(tiles < 1 ? 1 : (tiles < cap ? tiles : cap));
}

template <typename T, int MinBlocks>
void launch_tap_gemm_as(T* acc, const T* src, const T* w, const int64_t* count, const TapGemmArgs& g,
                        int64_t tiles, bool wave, const at::Tensor& on, cudaStream_t stream) {
  tap_gemm_kernel<T, MinBlocks><<<gemm_blocks<T, MinBlocks>(tiles, on, wave), kGemmThreads, 0, stream>>>(
      acc, src, w, count, g);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

template <typename T>
void launch_tap_gemm(T* acc, const T* src, const T* w, const int64_t* count, TapGemmArgs g, const at::Tensor& on,
                     cudaStream_t stream) {
  const GemmTuning tune = gemm_tuning();
  g.chunk = g.gather ? kGatherChunk : tune.chunk;
  g.chunks = (g.Cin + g.chunk - 1) / g.chunk;
  g.col_tiles = (g.C + kBN - 1) / kBN;
  const int64_t tiles = (g.rows + kBM - 1) / kBM * g.col_tiles * g.K * g.chunks;  // an upper bound (count)
  if constexpr (std::is_same<T, float>::value) {
    if (tune.min_blocks >= 4) return launch_tap_gemm_as<T, 4>(acc, src, w, count, g, tiles, tune.wave, on, stream);
  }
  launch_tap_gemm_as<T, 1>(acc, src, w, count, g, tiles, tune.wave, on, stream);
}

// ---- the channel-sparse scatter ------------------------------------------------------------------
//
// A changed site's channel that was zero before and after ReLU has a zero delta and adds nothing. One
// block per row: the row's nonzero channels are listed in shared memory (in channel order, by warp
// ballots), then each thread sums delta[ci] * W[k, ci, c] over them for its (tap, output channel) and
// adds the sum at the site the tap reaches. The weight is read (K, Cin, Cout), so a warp's reads of one
// (tap, channel) row are contiguous; unlike the GEMM no weight is reused across rows, which is why it
// pays only when most of the delta is zero (docs/sscater.md).

template <typename T>
__global__ void count_zeros_kernel(const T* __restrict__ delta, int64_t rows, const int64_t* __restrict__ count,
                                   int64_t Cin, unsigned long long* __restrict__ zeros) {
  const int64_t n = count == nullptr ? rows : (*count < rows ? *count : rows);
  unsigned long long local = 0;
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < n * Cin;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x)
    local += delta[t] == T(0);
  for (int o = 16; o > 0; o >>= 1) local += __shfl_down_sync(gpu::kFullMask, local, o);
  if ((threadIdx.x & 31) == 0 && local) atomicAdd(zeros, local);
}

template <typename T>
__global__ void __launch_bounds__(kThreads) sparse_rows_kernel(T* __restrict__ acc, const T* __restrict__ delta,
                                                               const T* __restrict__ wt,
                                                               const int64_t* __restrict__ target, int64_t rows,
                                                               const int64_t* __restrict__ count, int64_t K,
                                                               int64_t Cin, int64_t C,
                                                               const unsigned long long* __restrict__ zeros,
                                                               double share) {
  extern __shared__ __align__(16) unsigned char smem[];
  T* val = reinterpret_cast<T*>(smem);                  // (Cin,) the row's nonzero values
  int32_t* ch = reinterpret_cast<int32_t*>(val + Cin);  // (Cin,) and their channels
  __shared__ int warp_nz[kThreads / 32];
  const int64_t n = count == nullptr ? rows : (*count < rows ? *count : rows);
  if (zeros != nullptr && !sparse_chosen(zeros, share, n, Cin)) return;  // the GEMM takes this delta
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, warps = blockDim.x >> 5;
  for (int64_t row = blockIdx.x; row < n; row += gridDim.x) {
    bool reaches = false;
    for (int64_t k = threadIdx.x; k < K; k += blockDim.x) reaches |= target[row * K + k] >= 0;
    if (!__syncthreads_or(reaches)) continue;  // block-uniform: padding, or every tap misses
    int nnz = 0;
    for (int64_t base = 0; base < Cin; base += blockDim.x) {
      const int64_t c = base + threadIdx.x;
      const T v = c < Cin ? delta[row * Cin + c] : T(0);
      const bool nz = v != T(0);
      const unsigned ballot = __ballot_sync(gpu::kFullMask, nz);
      if (lane == 0) warp_nz[warp] = __popc(ballot);
      __syncthreads();
      int before = 0, total = 0;
      for (int w = 0; w < warps; ++w) {
        before += w < warp ? warp_nz[w] : 0;
        total += warp_nz[w];
      }
      if (nz) {
        const int pos = nnz + before + __popc(ballot & ((1u << lane) - 1u));
        val[pos] = v;
        ch[pos] = static_cast<int32_t>(c);
      }
      nnz += total;
      __syncthreads();  // warp_nz is rewritten by the next chunk; val / ch are read below
    }
    if (nnz > 0) {
      for (int64_t e = threadIdx.x; e < K * C; e += blockDim.x) {
        const int64_t k = e / C, c = e % C;
        const int64_t o = target[row * K + k];
        if (o < 0) continue;
        const T* wk = wt + k * Cin * C + c;
        T sum = T(0);
        for (int j = 0; j < nnz; ++j) sum += val[j] * wk[static_cast<int64_t>(ch[j]) * C];
        atomicAdd(acc + o * C + c, sum);
      }
    }
    __syncthreads();  // val / ch are rewritten by the block's next row
  }
}

// Shared memory of one block of the sparse kernel; a delta wider than the default 48 KiB allows stays
// on the GEMM.
inline int64_t sparse_rows_smem(int64_t Cin, int64_t elem) { return Cin * (elem + 4); }
constexpr int64_t kSparseSmemMax = 48 * 1024;

// The gather's destinations start from zero: one thread per (row, channel).
template <typename T>
__global__ void zero_sites_kernel(T* __restrict__ acc, const int32_t* __restrict__ sites, int64_t rows,
                                  const int64_t* __restrict__ count, int64_t Ho, int64_t Wo, int64_t C) {
  const int64_t n = count == nullptr ? rows : (*count < rows ? *count : rows);
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < n * C;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    int64_t y, x;
    if (site_at(sites, t / C, Ho, Wo, y, x)) acc[(y * Wo + x) * C + t % C] = T(0);
  }
}

template <typename T>
__global__ void finalize_kernel(const T* __restrict__ acc, T* __restrict__ out, const bool* __restrict__ active,
                                const int32_t* __restrict__ sites, const T* __restrict__ scale,
                                const T* __restrict__ shift, bool* __restrict__ changed, T* __restrict__ delta,
                                int64_t m, int64_t C, int64_t Ho, int64_t Wo, int64_t sy, int64_t sx, int64_t sc) {
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < m * C;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t i = t / C, c = t % C;
    const int64_t y = sites[2 * i], x = sites[2 * i + 1];
    if (y < 0 || y >= Ho || x < 0 || x >= Wo) continue;  // the wrapper validates; never write out of bounds
    T v = active[y * Wo + x] ? acc[(y * Wo + x) * C + c] * scale[c] + shift[c] : T(0);
    v = v > T(0) ? v : T(0);
    T* o = out + y * sy + x * sx + c * sc;
    const T old = *o;
    delta[t] = v - old;
    if (v != old) changed[i] = true;  // every writer stores the same value
    *o = v;
  }
}

at::Tensor scatter_cuda(at::Tensor& acc, const at::Tensor& sites_in, const at::Tensor& delta_in,
                        const at::Tensor& weight_in, int64_t stride, int64_t padding, bool transposed,
                        const c10::optional<at::Tensor>& out_active, const c10::optional<at::Tensor>& count,
                        double channel_sparse) {
  check_scatter_args(acc, sites_in, delta_in, weight_in, stride, padding);
  TORCH_CHECK_VALUE(channel_sparse == channel_sparse, "channel_sparse must be a number (a share of zero delta "
                    "values), got nan");
  check_out_active(out_active, acc);
  check_count(count, acc);
  const int64_t rows = sites_in.size(0);
  const int64_t kh = weight_in.size(1), kw = weight_in.size(2), K = kh * kw, C = acc.size(2), Cin = delta_in.size(1);
  auto targets = at::empty({rows * K}, sites_in.options().dtype(at::kLong));
  if (rows == 0) return targets;
  c10::cuda::CUDAGuard guard(acc.device());
  auto sites = sites_in.contiguous();
  auto stream = c10::cuda::getCurrentCUDAStream();
  const bool* act = out_active.has_value() ? out_active->data_ptr<bool>() : nullptr;
  const int64_t* cnt = count.has_value() ? count->data_ptr<int64_t>() : nullptr;
  targets_kernel<<<blocks_for(rows * K), kThreads, 0, stream>>>(sites.data_ptr<int32_t>(), act,
                                                                targets.data_ptr<int64_t>(), rows, cnt, kh, kw,
                                                                acc.size(0), acc.size(1), stride, padding, transposed);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (acc.numel() == 0 || Cin == 0) return targets;
  auto delta = delta_in.contiguous();
  // Which kernel: <= 0 the channel-sparse one, > 1 the GEMM, in between both are launched and the
  // share of zeros counted on the device picks the one that runs (no host synchronisation).
  const int64_t smem = sparse_rows_smem(Cin, static_cast<int64_t>(acc.element_size()));
  const bool sparse = channel_sparse <= 1.0 && smem <= kSparseSmemMax;
  const bool gemm = !sparse || channel_sparse > 0.0;
  at::Tensor zeros;
  if (sparse && gemm) zeros = at::zeros({1}, sites_in.options().dtype(at::kLong));
  auto* zp = zeros.defined() ? reinterpret_cast<unsigned long long*>(zeros.data_ptr<int64_t>()) : nullptr;
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_scatter_cuda", [&] {
    if (zp != nullptr) {
      count_zeros_kernel<scalar_t><<<blocks_for(rows * Cin), kThreads, 0, stream>>>(delta.data_ptr<scalar_t>(), rows,
                                                                                   cnt, Cin, zp);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
    if (gemm) {
      TapGemmArgs g{};
      g.rows = rows, g.K = K, g.kw = kw, g.Cin = Cin, g.C = C, g.gather = false;
      g.zeros = zp, g.sparse_share = channel_sparse;
      g.ws0 = weight_in.stride(0), g.ws1 = weight_in.stride(1), g.ws2 = weight_in.stride(2);
      g.ws3 = weight_in.stride(3);
      g.target = targets.data_ptr<int64_t>();
      launch_tap_gemm<scalar_t>(acc.data_ptr<scalar_t>(), delta.data_ptr<scalar_t>(), weight_in.data_ptr<scalar_t>(),
                                cnt, g, acc, stream);
    }
    if (sparse) {
      auto wt = weight_in.permute({1, 2, 3, 0}).reshape({K, Cin, C}).contiguous();  // (K, Cin, Cout)
      const int64_t cap = 8 * static_cast<int64_t>(gpu::device_props(acc.get_device()).sms);
      sparse_rows_kernel<scalar_t><<<static_cast<unsigned>(rows < cap ? rows : cap), kThreads, smem, stream>>>(
          acc.data_ptr<scalar_t>(), delta.data_ptr<scalar_t>(), wt.data_ptr<scalar_t>(), targets.data_ptr<int64_t>(),
          rows, cnt, K, Cin, C, zp, channel_sparse);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
  });
  return targets;
}

std::tuple<at::Tensor, at::Tensor> finalize_cuda(const at::Tensor& acc, at::Tensor& out, const at::Tensor& active,
                                                 const at::Tensor& sites_in, const at::Tensor& scale_in,
                                                 const at::Tensor& shift_in) {
  check_finalize_args(acc, out, active, sites_in, scale_in, shift_in);
  const int64_t m = sites_in.size(0), C = acc.size(2);
  auto changed = at::zeros({m}, acc.options().dtype(at::kBool));
  auto delta = at::empty({m, C}, acc.options());
  if (m == 0 || C == 0) return {changed, delta};
  c10::cuda::CUDAGuard guard(acc.device());
  auto sites = sites_in.contiguous();
  auto scale = scale_in.contiguous(), shift = shift_in.contiguous();
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_finalize_cuda", [&] {
    finalize_kernel<scalar_t><<<blocks_for(m * C), kThreads, 0, stream>>>(
        acc.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(), active.data_ptr<bool>(), sites.data_ptr<int32_t>(),
        scale.data_ptr<scalar_t>(), shift.data_ptr<scalar_t>(), changed.data_ptr<bool>(), delta.data_ptr<scalar_t>(),
        m, C, acc.size(0), acc.size(1), out.stride(0), out.stride(1), out.stride(2));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {changed, delta};
}

// ---- the fused layer step: no host synchronisation; lists padded to upper bounds --------------

// Pass 1: one thread per (input site, tap): cover += +-1 and the first touch of an output appends
// it to `touched` (stamp raised to value by atomicMax).
__global__ void cover_touch_kernel(int32_t* __restrict__ cover, int32_t* __restrict__ stamp, int32_t value,
                                   const int32_t* __restrict__ added, int64_t a, const int32_t* __restrict__ removed,
                                   int64_t r, int64_t kh, int64_t kw, int64_t stride, int64_t padding, int64_t Ho,
                                   int64_t Wo, int64_t* __restrict__ touched, unsigned long long* __restrict__ n) {
  const int64_t K = kh * kw;
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < (a + r) * K;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t i = t / K, k = t % K;
    const bool add = i < a;
    const int32_t* sp = add ? added + 2 * i : removed + 2 * (i - a);
    if (sp[0] < 0 || sp[1] < 0) continue;
    const int64_t oy = reach(sp[0], k / kw, stride, padding, Ho, false);
    const int64_t ox = oy < 0 ? -1 : reach(sp[1], k % kw, stride, padding, Wo, false);
    if (ox < 0) continue;
    const int64_t o = oy * Wo + ox;
    atomicAdd(cover + o, add ? 1 : -1);
    if (atomicMax(stamp + o, value) < value) touched[atomicAdd(n, 1ull)] = o;
  }
}

// Pass 2: each touched output whose cover crossed zero flips `active` and is listed at its row.
__global__ void cover_flip_kernel(const int32_t* __restrict__ cover, bool* __restrict__ active,
                                  const int64_t* __restrict__ touched, const unsigned long long* __restrict__ n,
                                  int64_t rows, int64_t Wo, int32_t* __restrict__ added_out,
                                  int32_t* __restrict__ removed_out, unsigned long long* __restrict__ counts) {
  const int64_t m = static_cast<int64_t>(*n) < rows ? static_cast<int64_t>(*n) : rows;
  for (int64_t i = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; i < m;
       i += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t o = touched[i];
    const bool after = cover[o] > 0;
    if (after == active[o]) continue;
    active[o] = after;
    const unsigned long long j = atomicAdd(counts + (after ? 0 : 1), 1ull);
    int32_t* dst = (after ? added_out : removed_out) + 2 * j;
    dst[0] = static_cast<int32_t>(o / Wo);
    dst[1] = static_cast<int32_t>(o % Wo);
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> cover_update_cuda(at::Tensor& cover, at::Tensor& active, at::Tensor& stamp,
                                                      int64_t value, const at::Tensor& added_in,
                                                      const at::Tensor& removed_in, int64_t kh, int64_t kw,
                                                      int64_t stride, int64_t padding) {
  check_cover_update_args(cover, active, stamp, added_in, removed_in, kh, kw, stride, padding);
  check_stamp_value(value, "value");
  c10::cuda::CUDAGuard guard(cover.device());
  const int64_t Ho = cover.size(0), Wo = cover.size(1), K = kh * kw;
  const int64_t a = added_in.size(0), r = removed_in.size(0), taps = (a + r) * K;
  const int64_t rows = std::min(taps, Ho * Wo);  // each output is touched (and flips) at most once
  auto added_out = at::full({rows, 2}, -1, added_in.options());
  auto removed_out = at::full({rows, 2}, -1, added_in.options());
  auto n = at::zeros({3}, added_in.options().dtype(at::kLong));  // touched, then the two counts
  auto counts = n.narrow(0, 1, 2);
  if (rows == 0) return {added_out, removed_out, counts};
  auto added = added_in.contiguous(), removed = removed_in.contiguous();
  auto touched = at::empty({rows}, added_in.options().dtype(at::kLong));
  auto* np = reinterpret_cast<unsigned long long*>(n.data_ptr<int64_t>());
  auto stream = c10::cuda::getCurrentCUDAStream();
  cover_touch_kernel<<<blocks_for(taps), kThreads, 0, stream>>>(
      cover.data_ptr<int32_t>(), stamp.data_ptr<int32_t>(), static_cast<int32_t>(value), added.data_ptr<int32_t>(), a,
      removed.data_ptr<int32_t>(), r, kh, kw, stride, padding, Ho, Wo, touched.data_ptr<int64_t>(), np);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  cover_flip_kernel<<<blocks_for(rows), kThreads, 0, stream>>>(cover.data_ptr<int32_t>(), active.data_ptr<bool>(),
                                                               touched.data_ptr<int64_t>(), np, rows, Wo,
                                                               added_out.data_ptr<int32_t>(),
                                                               removed_out.data_ptr<int32_t>(), np + 1);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {added_out, removed_out, counts};
}

// One thread per (site, tap): the child becomes `on`.
__global__ void children_kernel(bool* __restrict__ active, const int32_t* __restrict__ sites, int64_t n, int64_t kh,
                                int64_t kw, int64_t stride, int64_t padding, int64_t Ho, int64_t Wo, bool on,
                                int32_t* __restrict__ out) {
  const int64_t K = kh * kw;
  for (int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; t < n * K;
       t += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t i = t / K, k = t % K;
    if (sites[2 * i] < 0 || sites[2 * i + 1] < 0) continue;
    const int64_t oy = reach(sites[2 * i], k / kw, stride, padding, Ho, true);
    const int64_t ox = oy < 0 ? -1 : reach(sites[2 * i + 1], k % kw, stride, padding, Wo, true);
    if (ox < 0) continue;
    active[oy * Wo + ox] = on;
    out[2 * t] = static_cast<int32_t>(oy);
    out[2 * t + 1] = static_cast<int32_t>(ox);
  }
}

std::tuple<at::Tensor, at::Tensor> children_cuda(at::Tensor& active, const at::Tensor& added_in,
                                                 const at::Tensor& removed_in, int64_t kh, int64_t kw, int64_t stride,
                                                 int64_t padding) {
  check_children_args(active, added_in, removed_in, kh, kw, stride, padding);
  c10::cuda::CUDAGuard guard(active.device());
  const int64_t Ho = active.size(0), Wo = active.size(1), K = kh * kw;
  auto stream = c10::cuda::getCurrentCUDAStream();
  auto run = [&](const at::Tensor& in, bool on) {
    auto sites = in.contiguous();
    const int64_t n = sites.size(0);
    auto out = at::full({n * K, 2}, -1, sites.options());
    if (n > 0) {
      children_kernel<<<blocks_for(n * K), kThreads, 0, stream>>>(active.data_ptr<bool>(), sites.data_ptr<int32_t>(),
                                                                  n, kh, kw, stride, padding, Ho, Wo, on,
                                                                  out.data_ptr<int32_t>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
    return out;
  };
  auto a = run(added_in, true);
  auto r = run(removed_in, false);  // launched after the added: a site under both ends inactive
  return {a, r};
}

void gather_cuda(at::Tensor& acc, const at::Tensor& input, const at::Tensor& weight_in, const at::Tensor& sites_in,
                 int64_t stride, int64_t padding, const c10::optional<at::Tensor>& count) {
  check_gather_args(acc, input, weight_in, sites_in, stride, padding);
  check_count(count, acc);
  const int64_t m = sites_in.size(0), C = acc.size(2);
  if (m == 0 || C == 0) return;
  c10::cuda::CUDAGuard guard(acc.device());
  auto w = weight_in.contiguous();
  auto sites = sites_in.contiguous();
  auto stream = c10::cuda::getCurrentCUDAStream();
  const int64_t* cnt = count.has_value() ? count->data_ptr<int64_t>() : nullptr;
  TapGemmArgs g{};
  g.rows = m, g.K = w.size(1) * w.size(2), g.kw = w.size(2), g.Cin = input.size(2), g.C = C, g.gather = true;
  g.ws0 = w.stride(0), g.ws1 = w.stride(1), g.ws2 = w.stride(2), g.ws3 = w.stride(3);
  g.sites = sites.data_ptr<int32_t>();
  g.Ho = acc.size(0), g.Wo = acc.size(1), g.Hi = input.size(0), g.Wi = input.size(1);
  g.s0 = input.stride(0), g.s1 = input.stride(1), g.s2 = input.stride(2), g.stride = stride, g.padding = padding;
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_gather_cuda", [&] {
    zero_sites_kernel<scalar_t><<<blocks_for(m * C), kThreads, 0, stream>>>(acc.data_ptr<scalar_t>(), g.sites, m, cnt,
                                                                            g.Ho, g.Wo, C);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    if (g.Cin > 0)
      launch_tap_gemm<scalar_t>(acc.data_ptr<scalar_t>(), input.data_ptr<scalar_t>(), w.data_ptr<scalar_t>(), cnt, g,
                                acc, stream);
  });
}

// Slot for an append to a list whose length is *n, taken by the lanes of a warp with `take` set:
// one atomic per warp (a ballot counts the lanes). Every lane of the warp must call it. Per-lane
// atomics on one counter would serialise there.
__device__ __forceinline__ unsigned long long warp_append(bool take, unsigned long long* n) {
  const unsigned mask = __ballot_sync(0xffffffffu, take);
  if (mask == 0) return 0;
  const int lane = threadIdx.x & 31, leader = __ffs(mask) - 1;
  unsigned long long base = 0;
  if (lane == leader) base = atomicAdd(n, static_cast<unsigned long long>(__popc(mask)));
  base = __shfl_sync(0xffffffffu, base, leader);
  return base + __popc(mask & ((1u << lane) - 1u));
}

// A warp per row of sites (count-free: padding rows are skipped): zero the accumulator there, the
// channels spread over the lanes.
template <typename T>
__global__ void zero_rows_kernel(T* __restrict__ acc, const int32_t* __restrict__ sites, int64_t rows, int64_t Ho,
                                 int64_t Wo, int64_t C) {
  const int lane = threadIdx.x & 31;
  const int64_t warps = static_cast<int64_t>(gridDim.x) * (blockDim.x >> 5);
  for (int64_t i = (blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x) >> 5; i < rows; i += warps) {
    int64_t y, x;
    if (!site_at(sites, i, Ho, Wo, y, x)) continue;  // warp-uniform
    for (int64_t c = lane; c < C; c += 32) acc[(y * Wo + x) * C + c] = T(0);
  }
}

// One thread per entry of targets ++ added ++ removed: raise the stamp; the first touch appends.
// The removed sites' accumulators are zeroed first by zero_rows_kernel, a warp per site, because one
// thread looping over a site's 64-256 channels here made this kernel several times slower. The loop bounds are block-uniform (blockDim is a multiple of 32), so whole warps
// reach the append.
__global__ void touch_kernel(int32_t* __restrict__ stamp, int32_t value, const int64_t* __restrict__ targets,
                             int64_t R, const int32_t* __restrict__ added, int64_t a,
                             const int32_t* __restrict__ removed, int64_t r, int64_t Ho, int64_t Wo,
                             int32_t* __restrict__ cand, unsigned long long* __restrict__ n) {
  const int64_t total = R + a + r;
  for (int64_t t0 = blockIdx.x * static_cast<int64_t>(blockDim.x); t0 < total;
       t0 += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t t = t0 + threadIdx.x;
    int64_t o = -1;
    int32_t v = value + 1;
    if (t < R) {
      o = targets[t];
      if (o >= Ho * Wo) o = -1;
      v = value;
    } else if (t < total) {
      int64_t y, x;
      const bool add = t < R + a;
      if (site_at(add ? added : removed, add ? t - R : t - R - a, Ho, Wo, y, x)) o = y * Wo + x;
    }
    const bool first = o >= 0 && atomicMax(stamp + o, v) < value;
    const unsigned long long j = warp_append(first, n);
    if (first) {
      cand[2 * j] = static_cast<int32_t>(o / Wo);
      cand[2 * j + 1] = static_cast<int32_t>(o % Wo);
    }
  }
}

std::tuple<at::Tensor, at::Tensor> touch_cuda(at::Tensor& stamp, at::Tensor& acc, int64_t value,
                                              const at::Tensor& targets_in, const at::Tensor& added_in,
                                              const at::Tensor& removed_in) {
  check_touch_args(stamp, acc, targets_in, added_in, removed_in);
  check_stamp_value(value, "value");
  c10::cuda::CUDAGuard guard(acc.device());
  const int64_t R = targets_in.size(0), a = added_in.size(0), r = removed_in.size(0);
  auto cand = at::full({std::min(R + a + r, acc.size(0) * acc.size(1)), 2}, -1, added_in.options());  // each site once
  auto count = at::zeros({1}, targets_in.options());
  if (R + a + r == 0) return {cand, count};
  auto targets = targets_in.contiguous();
  auto added = added_in.contiguous(), removed = removed_in.contiguous();
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_touch_cuda", [&] {
    if (r > 0 && acc.size(2) > 0) {
      zero_rows_kernel<scalar_t><<<blocks_for(r * 32), kThreads, 0, stream>>>(
          acc.data_ptr<scalar_t>(), removed.data_ptr<int32_t>(), r, acc.size(0), acc.size(1), acc.size(2));
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
  });
  touch_kernel<<<blocks_for(R + a + r), kThreads, 0, stream>>>(
      stamp.data_ptr<int32_t>(), static_cast<int32_t>(value), targets.data_ptr<int64_t>(), R, added.data_ptr<int32_t>(),
      a, removed.data_ptr<int32_t>(), r, acc.size(0), acc.size(1), cand.data_ptr<int32_t>(),
      reinterpret_cast<unsigned long long*>(count.data_ptr<int64_t>()));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {cand, count};
}

// One warp per candidate row (count read on the device): BN + ReLU per channel; the warp votes on
// "changed" (pass 1, reads only); the block then takes the compacted slots of its changed rows with
// one atomic (and one for the rows changed or with a status change), and pass 2 recomputes the same
// values to write the output and the delta there. The row loop is block-uniform (__syncthreads).
constexpr int kFinalizeWarps = kThreads / 32;

template <typename T>
__global__ void __launch_bounds__(kThreads) finalize_compact_kernel(
    const T* __restrict__ acc, T* __restrict__ out, const bool* __restrict__ active, const int32_t* __restrict__ cand,
    const int64_t* __restrict__ count, int64_t rows, const int32_t* __restrict__ stamp, int32_t status_value,
    const T* __restrict__ scale, const T* __restrict__ shift, int64_t C, int64_t Ho, int64_t Wo, int64_t sy,
    int64_t sx, int64_t sc, int32_t* __restrict__ sites_out, T* __restrict__ delta_out,
    unsigned long long* __restrict__ counts) {
  __shared__ int s_changed[kFinalizeWarps], s_flagged[kFinalizeWarps];
  __shared__ unsigned long long s_base;
  // count is the caller's: clamped to [0, rows], as on CPU; counts[2] = the rows evaluated
  const int64_t m = *count < 0 ? 0 : (*count < rows ? *count : rows);
  if (blockIdx.x == 0 && threadIdx.x == 0) counts[2] = static_cast<unsigned long long>(m);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  for (int64_t i0 = blockIdx.x * static_cast<int64_t>(kFinalizeWarps); i0 < m;
       i0 += static_cast<int64_t>(gridDim.x) * kFinalizeWarps) {
    const int64_t i = i0 + warp;
    int64_t y = 0, x = 0;
    const bool row = i < m && site_at(cand, i, Ho, Wo, y, x);  // warp-uniform
    if (!row) y = x = 0;  // (no row: the pointers below stay in bounds, unread)
    const bool on = row && active[y * Wo + x];
    const T* ai = acc + (y * Wo + x) * C;
    T* oi = out + y * sy + x * sx;
    auto value = [&](int64_t c) {
      const T v = on ? ai[c] * scale[c] + shift[c] : T(0);
      return v > T(0) ? v : T(0);
    };
    bool changed = false, flagged = false;
    if (row) {
      bool any = false;
      for (int64_t c = lane; c < C; c += 32) any |= value(c) != oi[c * sc];
      changed = __any_sync(0xffffffffu, any);
      flagged = changed || stamp[y * Wo + x] == status_value;
    }
    if (lane == 0) {
      s_changed[warp] = changed;
      s_flagged[warp] = flagged;
    }
    __syncthreads();
    if (threadIdx.x == 0) {
      int nc = 0, nf = 0;
      for (int w = 0; w < kFinalizeWarps; ++w) nc += s_changed[w], nf += s_flagged[w];
      if (nf) atomicAdd(counts + 1, static_cast<unsigned long long>(nf));
      s_base = nc ? atomicAdd(counts, static_cast<unsigned long long>(nc)) : 0ull;
    }
    __syncthreads();
    if (changed) {  // nothing to write otherwise: the stored values are the new ones
      unsigned long long j = s_base;
      for (int w = 0; w < warp; ++w) j += s_changed[w];
      if (lane == 0) {
        sites_out[2 * j] = static_cast<int32_t>(y);
        sites_out[2 * j + 1] = static_cast<int32_t>(x);
      }
      for (int64_t c = lane; c < C; c += 32) {
        const T v = value(c);
        delta_out[j * C + c] = v - oi[c * sc];
        oi[c * sc] = v;
      }
    }
    __syncthreads();  // the shared counts are rewritten by the next rows
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> finalize_compact_cuda(const at::Tensor& acc, at::Tensor& out,
                                                                     const at::Tensor& active, const at::Tensor& cand,
                                                                     const at::Tensor& count, const at::Tensor& stamp,
                                                                     int64_t status_value, const at::Tensor& scale_in,
                                                                     const at::Tensor& shift_in) {
  check_finalize_args(acc, out, active, cand, scale_in, shift_in, "cand");
  check_finalize_compact_args(acc, cand, count, stamp, status_value);
  c10::cuda::CUDAGuard guard(acc.device());
  const int64_t rows = cand.size(0), C = acc.size(2);
  auto sites_out = at::full({rows, 2}, -1, cand.options());
  auto delta_out = at::empty({rows, C}, acc.options());  // padding rows: unspecified
  auto counts = at::zeros({3}, count.options());
  auto stream = c10::cuda::getCurrentCUDAStream();
  if (rows == 0) return {sites_out, delta_out, counts};  // counts[2] = 0 rows evaluated
  auto cnd = cand.contiguous();
  auto scale = scale_in.contiguous(), shift = shift_in.contiguous();
  const unsigned blocks = blocks_for(rows * 32);
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_finalize_compact_cuda", [&] {
    finalize_compact_kernel<scalar_t><<<blocks, kThreads, 0, stream>>>(
        acc.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(), active.data_ptr<bool>(), cnd.data_ptr<int32_t>(),
        count.data_ptr<int64_t>(), rows, stamp.data_ptr<int32_t>(), static_cast<int32_t>(status_value),
        scale.data_ptr<scalar_t>(), shift.data_ptr<scalar_t>(), C, acc.size(0), acc.size(1), out.stride(0),
        out.stride(1), out.stride(2), sites_out.data_ptr<int32_t>(), delta_out.data_ptr<scalar_t>(),
        reinterpret_cast<unsigned long long*>(counts.data_ptr<int64_t>()));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {sites_out, delta_out, counts};
}

// A tile of 32 sites x 32 channels per block (32 x 8 threads): y is read and out_nchw written along the sites
// (coalesced for NCHW), acc and out written along the channels (coalesced for channels-last maps).
template <typename T>
__global__ void __launch_bounds__(256) dense_finalize_kernel(
    const T* __restrict__ y, T* __restrict__ acc, T* __restrict__ out, T* __restrict__ nchw,
    const bool* __restrict__ active, const T* __restrict__ scale, const T* __restrict__ shift, int64_t C, int64_t Wo,
    int64_t S, int64_t ysc, int64_t ysy, int64_t ysx, int64_t osy, int64_t osx, int64_t osc) {
  __shared__ T tile[32][33];
  const int64_t s0 = static_cast<int64_t>(blockIdx.x) * 32, c0 = static_cast<int64_t>(blockIdx.y) * 32;
  for (int i = threadIdx.y; i < 32; i += 8) {
    const int64_t c = c0 + i, s = s0 + threadIdx.x;
    if (c < C && s < S) {
      const bool on = active == nullptr || active[s];
      const T v = on ? y[c * ysc + (s / Wo) * ysy + (s % Wo) * ysx] : T(0);
      tile[i][threadIdx.x] = v;
      if (nchw != nullptr) {
        const T f = on ? v * scale[c] + shift[c] : T(0);
        nchw[c * S + s] = f > T(0) ? f : T(0);
      }
    }
  }
  __syncthreads();
  for (int i = threadIdx.y; i < 32; i += 8) {
    const int64_t s = s0 + i, c = c0 + threadIdx.x;
    if (c < C && s < S) {
      const bool on = active == nullptr || active[s];
      const T v = tile[threadIdx.x][i];
      const T f = on ? v * scale[c] + shift[c] : T(0);
      acc[s * C + c] = v;
      out[(s / Wo) * osy + (s % Wo) * osx + c * osc] = f > T(0) ? f : T(0);
    }
  }
}

void dense_finalize_cuda(const at::Tensor& y, at::Tensor& acc, at::Tensor& out, const at::Tensor& scale_in,
                         const at::Tensor& shift_in, const c10::optional<at::Tensor>& active,
                         const c10::optional<at::Tensor>& out_nchw) {
  check_dense_finalize_args(y, acc, out, scale_in, shift_in, active, out_nchw);
  const int64_t Wo = acc.size(1), C = acc.size(2), S = acc.size(0) * Wo;
  if (acc.numel() == 0) return;
  c10::cuda::CUDAGuard guard(acc.device());
  auto stream = c10::cuda::getCurrentCUDAStream();
  auto scale = scale_in.contiguous(), shift = shift_in.contiguous();
  const dim3 grid(static_cast<unsigned>((S + 31) / 32), static_cast<unsigned>((C + 31) / 32));
  TORCH_CHECK_VALUE((S + 31) / 32 < (int64_t(1) << 31) && (C + 31) / 32 < 65536, "the (Ho, Wo, C) = ", acc.sizes(),
                    " map is too large for one launch");
  AT_DISPATCH_FLOATING_TYPES(acc.scalar_type(), "lidarops_sscater_dense_finalize_cuda", [&] {
    dense_finalize_kernel<scalar_t><<<grid, dim3(32, 8), 0, stream>>>(
        y.data_ptr<scalar_t>(), acc.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(),
        out_nchw.has_value() ? out_nchw->data_ptr<scalar_t>() : nullptr,
        active.has_value() ? active->data_ptr<bool>() : nullptr, scale.data_ptr<scalar_t>(),
        shift.data_ptr<scalar_t>(), C, Wo, S, y.stride(0), y.stride(1), y.stride(2), out.stride(0), out.stride(1),
        out.stride(2));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("sscater_scatter_", &scatter_cuda);
  m.impl("sscater_finalize_", &finalize_cuda);
  m.impl("sscater_cover_update_", &cover_update_cuda);
  m.impl("sscater_children_", &children_cuda);
  m.impl("sscater_gather_", &gather_cuda);
  m.impl("sscater_touch_", &touch_cuda);
  m.impl("sscater_finalize_compact_", &finalize_compact_cuda);
  m.impl("sscater_dense_finalize_", &dense_finalize_cuda);
}

}  // namespace sscater
}  // namespace lidarops
