// Exact farthest point sampling on CUDA, bit-identical to the CPU kernel.
//
// Definition (as fps_cloud() in csrc/cpu/fps_kernel.cpp): dist[i] = +inf for the n valid points;
// step s outputs sel, marks dist[sel] = -1 (never selected again: real distances are >= 0), then
// dist[i] = min(dist[i], sqdist3(x_i, x_sel)) (updated only if strictly smaller, so NaN never
// enters) and the next sel is the argmax of dist, ties to the lowest index. Every path below
// computes the same rounded distances (sqdist3) and reduces with the same total order
// better(): (d, i) beats (d', i') iff d > d' or (d == d' and i < i'), so they agree bit for bit.
//
// Paths (the `method` argument: 0 auto, 1 one block per cloud, 2 several blocks per cloud):
// - fps_reg_kernel<T, P, false>: one block of 256 threads per cloud; thread t owns the points
//   t + 256 p (p < P), coordinates and min-distances in registers. One __syncthreads per step.
//   Auto uses it up to 4096 points per cloud (and on devices without clusters up to 8192 float /
//   4096 double points).
// - fps_push_kernel<P> (float, sm_90+): a thread-block cluster of C blocks per cloud (C <= 16),
//   block r owning points [r 256 P, (r + 1) 256 P); candidates exchanged by one-sided st.async
//   messages counted on mbarriers (see the comment above the kernel): no cluster barrier per step.
// - fps_reg_kernel<T, P, true> (double, or float if the push kernel cannot be scheduled; sm_90+):
//   the same split, but per step: update, warp argmax, block argmax by warp 0, publish the block's
//   candidate in shared memory, ONE cluster barrier, and every warp reads the C candidates through
//   distributed shared memory and takes the same winner.
// - fps_global_kernel<T>: one block of 1024 threads per cloud, any n, distances in global memory
//   (clouds too large for the registers of 16 blocks, or of one block without clusters).
//
// Race-freedom of the cluster step (iteration s writes slot buffer s & 1):
// - wslot[s&1][w] is written by warp w before the block barrier of step s and read by warp 0
//   after it; warp 0 finishes reading before it arrives at the cluster barrier of step s, and no
//   warp writes wslot again before passing that cluster barrier.
// - cslot[s&1] is written by warp 0 before the cluster barrier of step s (barrier.cluster.arrive
//   has release semantics, wait has acquire semantics, so the remote readers see it) and is read
//   by every warp of every block after that barrier. The next write to cslot[s&1] happens in step
//   s + 2, after the writer passed the cluster barrier of step s + 1, which every block reaches only
//   after its reads of step s. Hence two buffers and one cluster barrier per step suffice.
// - A final cluster barrier keeps every block alive until no block can still read its slots, and
//   the first remote read happens after a cluster barrier, so every block has started.
// The non-cluster variant uses the same double buffer with the block barrier: all warps read
// wslot[s&1] after the barrier of step s and reach the barrier of step s + 1 before anyone can
// write wslot[s&1] again in step s + 2.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <cooperative_groups.h>

#include <map>
#include <mutex>
#include <utility>

#include "lidarops/neighbors.cuh"

namespace lidarops {
namespace {

using gpu::clamp_len;
using gpu::kFullMask;

constexpr int kFpsThreads = 256;
constexpr int kFpsWarps = kFpsThreads / 32;
constexpr int kGlobalThreads = 1024;
constexpr int kMaxCluster = 16;

// Largest points per thread kept in registers (4 registers of T per point).
template <typename T>
constexpr int fps_pmax() {
  return std::is_same_v<T, double> ? 16 : 32;
}

template <typename T>
__device__ __forceinline__ bool better(T d0, int i0, T d1, int i1) {
  return d0 > d1 || (d0 == d1 && i0 < i1);
}

// Butterfly argmax over the lanes of a warp: every lane ends with the maximum under better(),
// a total order on (d, i), so the result does not depend on the order of the steps.
template <typename T>
__device__ __forceinline__ void warp_argmax(T& d, int& i) {
#pragma unroll
  for (int off = 16; off > 0; off >>= 1) {
    const T od = __shfl_xor_sync(kFullMask, d, off);
    const int oi = __shfl_xor_sync(kFullMask, i, off);
    if (better(od, oi, d, i)) {
      d = od;
      i = oi;
    }
  }
}

// A candidate: its min-distance, its index, its coordinates.
template <typename T>
struct FpsSlot {
  T d;
  int i;
  T x, y, z;
};

// Cluster primitives; compiled only for sm_90+ (the cluster kernel traps on older devices, where
// the host never launches it).
__device__ __forceinline__ void cluster_barrier() {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  cooperative_groups::this_cluster().sync();
#endif
}

template <typename S>
__device__ __forceinline__ S* cluster_map(S* p, int rank) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  return cooperative_groups::this_cluster().map_shared_rank(p, rank);
#else
  (void)rank;
  return p;
#endif
}

// min(cur, d) exactly as the CPU: `if (d < dist[i]) dist[i] = d` (NaN never enters).
template <typename T>
__device__ __forceinline__ T keep_min(T cur, T d) {
  return d < cur ? d : cur;
}

template <typename T, int P, bool kCluster>
__device__ __forceinline__ void fps_reg_body(const T* __restrict__ pts, const int64_t* __restrict__ lengths,
                                             const int64_t* __restrict__ start, int64_t N, int64_t K, int csize,
                                             int64_t* __restrict__ out) {
  __shared__ FpsSlot<T> wslot[2][kFpsWarps];
  __shared__ FpsSlot<T> cslot[2];
  const int rank = kCluster ? static_cast<int>(blockIdx.x % csize) : 0;  // == cluster block rank
  const int64_t b = kCluster ? blockIdx.x / csize : blockIdx.x;
  const int tid = threadIdx.x, lane = tid & 31, warp = tid >> 5;
  const int64_t n = clamp_len(lengths[b], N);
  const int64_t steps = n < K ? n : K;
  int64_t* o = out + b * K;
  if (rank == 0)
    for (int64_t s = steps + tid; s < K; s += kFpsThreads) o[s] = -1;
  if (steps == 0) return;  // the same for every block of the cluster: no barrier is skipped
  const T* cloud = pts + b * N * 3;
  const int base = rank * (kFpsThreads * P) + tid;  // point of slot p: base + p * kFpsThreads
  T x[P], y[P], z[P], dist[P];
#pragma unroll
  for (int p = 0; p < P; ++p) {
    const int i = base + p * kFpsThreads;
    if (i < n) {
      x[p] = cloud[3 * i];
      y[p] = cloud[3 * i + 1];
      z[p] = cloud[3 * i + 2];
      dist[p] = gpu::inf_value<T>();
    } else {  // no point: -1 like a selected one, never the argmax
      x[p] = y[p] = z[p] = T(0);
      dist[p] = T(-1);
    }
  }
  int64_t st = start[b];
  st = st < 0 ? 0 : (st >= n ? n - 1 : st);  // out-of-range values are rejected upstream
  int sel = static_cast<int>(st);
  T sx = cloud[3 * st], sy = cloud[3 * st + 1], sz = cloud[3 * st + 2];
  for (int64_t s = 0;; ++s) {
    if (rank == 0 && tid == 0) o[s] = sel;
    if (s + 1 >= steps) break;
    // Update with the last selected point; the thread's best (slots in increasing index order,
    // strict > keeps the lowest index among ties).
    T bd = T(-2);
    int bp = 0;
#pragma unroll
    for (int p = 0; p < P; ++p) {
      const T d = sqdist3<T>(x[p], y[p], z[p], sx, sy, sz);
      const T nd = base + p * kFpsThreads == sel ? T(-1) : keep_min(dist[p], d);
      dist[p] = nd;
      if (nd > bd) {
        bd = nd;
        bp = p;
      }
    }
    const int bi = base + bp * kFpsThreads;  // unique per (thread, slot)
    T wd = bd;
    int wi = bi;
    warp_argmax(wd, wi);
    const int buf = static_cast<int>(s & 1);
    if (bi == wi) {  // exactly one lane: indices are unique
      T bx = x[0], by = y[0], bz = z[0];
#pragma unroll
      for (int p = 1; p < P; ++p)
        if (bp == p) {
          bx = x[p];
          by = y[p];
          bz = z[p];
        }
      wslot[buf][warp] = FpsSlot<T>{wd, wi, bx, by, bz};
    }
    __syncthreads();
    if constexpr (!kCluster) {
      // Every warp reduces the block's candidates itself (lane l reads slot l mod 8).
      const FpsSlot<T> c = wslot[buf][lane % kFpsWarps];
      T cd = c.d;
      int ci = c.i;
      warp_argmax(cd, ci);
      const int src = __ffs(__ballot_sync(kFullMask, c.i == ci)) - 1;
      sel = ci;
      sx = __shfl_sync(kFullMask, c.x, src);
      sy = __shfl_sync(kFullMask, c.y, src);
      sz = __shfl_sync(kFullMask, c.z, src);
    } else {
      if (warp == 0) {
        const FpsSlot<T> c = wslot[buf][lane % kFpsWarps];
        T cd = c.d;
        int ci = c.i;
        warp_argmax(cd, ci);
        const int src = __ffs(__ballot_sync(kFullMask, c.i == ci)) - 1;
        if (lane == src) cslot[buf] = c;
      }
      cluster_barrier();
      // Every warp reads the cluster's candidates (lane l: block l mod csize) and takes the best.
      const FpsSlot<T> c = *cluster_map(&cslot[buf], lane % csize);
      T cd = c.d;
      int ci = c.i;
      warp_argmax(cd, ci);
      const int src = __ffs(__ballot_sync(kFullMask, c.i == ci)) - 1;
      sel = ci;
      sx = __shfl_sync(kFullMask, c.x, src);
      sy = __shfl_sync(kFullMask, c.y, src);
      sz = __shfl_sync(kFullMask, c.z, src);
    }
  }
  if constexpr (kCluster) cluster_barrier();  // no block exits while its slots may still be read
}

// Grid: csize * B blocks (kCluster: clusters of csize consecutive blocks), 256 threads.
template <typename T, int P, bool kCluster>
__global__ void __launch_bounds__(kFpsThreads, 1)
    fps_reg_kernel(const T* __restrict__ pts, const int64_t* __restrict__ lengths, const int64_t* __restrict__ start,
                   int64_t N, int64_t K, int csize, int64_t* __restrict__ out) {
  if constexpr (kCluster) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
    fps_reg_body<T, P, true>(pts, lengths, start, N, K, csize, out);
#else
    __trap();  // never launched: the host checks the compute capability
#endif
  } else {
    fps_reg_body<T, P, false>(pts, lengths, start, N, K, 1, out);
  }
}

// One block per cloud, any number of points: min-distances in global memory (each entry only
// ever touched by the same thread), one __syncthreads per step with double-buffered slots.
template <typename T>
__global__ void __launch_bounds__(kGlobalThreads)
    fps_global_kernel(const T* __restrict__ pts, const int64_t* __restrict__ lengths,
                      const int64_t* __restrict__ start, int64_t N, int64_t K, T* __restrict__ dist_ws,
                      int64_t* __restrict__ out) {
  constexpr int W = kGlobalThreads / 32;
  __shared__ T sd[2][W];
  __shared__ int si[2][W];
  const int64_t b = blockIdx.x;
  const int tid = threadIdx.x, lane = tid & 31, warp = tid >> 5;
  const int64_t n = clamp_len(lengths[b], N);
  const int64_t steps = n < K ? n : K;
  int64_t* o = out + b * K;
  for (int64_t s = steps + tid; s < K; s += kGlobalThreads) o[s] = -1;
  if (steps == 0) return;
  const T* cloud = pts + b * N * 3;
  T* dist = dist_ws + b * N;
  for (int64_t i = tid; i < n; i += kGlobalThreads) dist[i] = gpu::inf_value<T>();
  int64_t st = start[b];
  st = st < 0 ? 0 : (st >= n ? n - 1 : st);
  int sel = static_cast<int>(st);
  T sx = cloud[3 * st], sy = cloud[3 * st + 1], sz = cloud[3 * st + 2];
  for (int64_t s = 0;; ++s) {
    if (tid == 0) o[s] = sel;
    if (s + 1 >= steps) break;
    T bd = T(-2);
    int bi = std::numeric_limits<int>::max();
    for (int i = tid; i < n; i += kGlobalThreads) {
      const T d = sqdist3<T>(cloud[3 * i], cloud[3 * i + 1], cloud[3 * i + 2], sx, sy, sz);
      const T nd = i == sel ? T(-1) : keep_min(dist[i], d);
      dist[i] = nd;
      if (nd > bd) {
        bd = nd;
        bi = i;
      }
    }
    warp_argmax(bd, bi);
    const int buf = static_cast<int>(s & 1);
    if (lane == 0) {
      sd[buf][warp] = bd;
      si[buf][warp] = bi;
    }
    __syncthreads();
    T cd = sd[buf][lane];
    int ci = si[buf][lane];
    warp_argmax(cd, ci);
    sel = ci;
    sx = cloud[3 * sel];
    sy = cloud[3 * sel + 1];
    sz = cloud[3 * sel + 2];
  }
}


// ---- float, sm_90: clusters exchanging candidates by one-sided pushes ----
//
// fps_push_kernel<P> replaces the cluster barrier of fps_reg_kernel by messages. In step s every
// warp of every block sends its candidate (key, index, x, y, z) into slot [rank * 8 + warp] of
// buffer s & 1 of every block of the cluster with st.async, whose completion counts bytes on that
// block's mbarrier[s & 1]; a block waits on its own mbarrier until all 8 * csize candidates have
// landed, then every warp reduces them from its local shared memory. No cluster barrier inside
// the loop, and no block-level reduction before the exchange.
//
// Keys: a float distance d >= 0 maps to its bits + 1 (monotonic for non-negative floats, and NaN
// never enters the distances), selected or absent points (d = -1) to 0; the argmax is max key, then
// min index, computed with redux.sync. This is the order better() of the other paths.
//
// Why a slot is never overwritten before every block read it: block r sends step s + 2 into
// buffer s & 1 only after its wait of step s + 1 completed, i.e. after every warp of every block
// sent its step s + 1 candidate, which each warp does after reading its buffer s & 1 slots of step
// s (program order; the complete-tx of st.async has release semantics at cluster scope and the wait
// acquire semantics, so those reads happen before the overwrite). The same chain shows that the
// complete-tx of step s + 2 reaches mbarrier[s & 1] only after its phase of step s completed, so
// every phase counts exactly the 20 * 8 * csize bytes of one step; thread 0 adds the expected
// bytes (and the phase's single arrival) at the start of the step, possibly after some bytes have
// landed (the transaction count may go negative until then).
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
constexpr int kPushSlots = kMaxCluster * kFpsWarps;  // slots per buffer

__device__ __forceinline__ uint32_t fps_key(float d) { return d >= 0.f ? __float_as_uint(d) + 1u : 0u; }

__device__ __forceinline__ uint32_t smem_addr(const void* p) {
  return static_cast<uint32_t>(__cvta_generic_to_shared(p));
}

__device__ __forceinline__ uint32_t cluster_addr(uint32_t local, uint32_t rank) {
  uint32_t r;
  asm volatile("mapa.shared::cluster.u32 %0, %1, %2;" : "=r"(r) : "r"(local), "r"(rank));
  return r;
}

__device__ __forceinline__ void mbar_init(uint32_t bar, uint32_t count) {
  asm volatile("mbarrier.init.shared::cta.b64 [%0], %1;" ::"r"(bar), "r"(count) : "memory");
}

__device__ __forceinline__ void mbar_arrive_expect_tx(uint32_t bar, uint32_t bytes) {
  asm volatile(
      "{\n\t.reg .b64 state;\n\t"
      "mbarrier.arrive.expect_tx.release.cluster.shared::cta.b64 state, [%0], %1;\n\t}" ::"r"(bar),
      "r"(bytes)
      : "memory");
}

__device__ __forceinline__ bool mbar_try_wait(uint32_t bar, uint32_t parity) {
  uint32_t ok;
  asm volatile(
      "{\n\t.reg .pred p;\n\t"
      "mbarrier.try_wait.parity.acquire.cluster.shared::cta.b64 p, [%1], %2;\n\t"
      "selp.u32 %0, 1, 0, p;\n\t}"
      : "=r"(ok)
      : "r"(bar), "r"(parity)
      : "memory");
  return ok != 0;
}

__device__ __forceinline__ void st_async_v4(uint32_t addr, uint32_t a, uint32_t b, uint32_t c, uint32_t d,
                                            uint32_t bar) {
  asm volatile("st.async.shared::cluster.mbarrier::complete_tx::bytes.v4.b32 [%0], {%1, %2, %3, %4}, [%5];" ::"r"(
                   addr),
               "r"(a), "r"(b), "r"(c), "r"(d), "r"(bar)
               : "memory");
}

__device__ __forceinline__ void st_async_b32(uint32_t addr, uint32_t a, uint32_t bar) {
  asm volatile("st.async.shared::cluster.mbarrier::complete_tx::bytes.b32 [%0], %1, [%2];" ::"r"(addr), "r"(a),
               "r"(bar)
               : "memory");
}
#endif

// Grid: csize * B blocks in clusters of csize, 256 threads; dynamic shared memory: the block's
// coordinates, 3 * 256 * P floats.
template <int P>
__global__ void __launch_bounds__(kFpsThreads, 1)
    fps_push_kernel(const float* __restrict__ pts, const int64_t* __restrict__ lengths,
                    const int64_t* __restrict__ start, int64_t N, int64_t K, int csize, int64_t* __restrict__ out) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  constexpr int chunk = kFpsThreads * P;
  __shared__ alignas(16) uint32_t slots[2][kPushSlots][8];  // key, index, x, y, z (words 5-7 unused)
  __shared__ alignas(8) uint64_t mbar[2];
  extern __shared__ float coords[];  // x[chunk], y[chunk], z[chunk] of this block's points
  const int rank = static_cast<int>(blockIdx.x % csize);
  const int64_t b = blockIdx.x / csize;
  const int tid = threadIdx.x, lane = tid & 31, warp = tid >> 5;
  const int64_t n = clamp_len(lengths[b], N);
  const int64_t steps = n < K ? n : K;
  int64_t* o = out + b * K;
  if (rank == 0)
    for (int64_t s = steps + tid; s < K; s += kFpsThreads) o[s] = -1;
  if (steps == 0) return;  // the same for every block of the cluster
  const float* cloud = pts + b * N * 3;
  const int first = rank * chunk;  // first point of this block
  float x[P], y[P], z[P], dist[P];
#pragma unroll
  for (int p = 0; p < P; ++p) {
    const int l = p * kFpsThreads + tid, i = first + l;
    if (i < n) {
      x[p] = cloud[3 * i];
      y[p] = cloud[3 * i + 1];
      z[p] = cloud[3 * i + 2];
      dist[p] = gpu::inf_value<float>();
    } else {
      x[p] = y[p] = z[p] = 0.f;
      dist[p] = -1.f;
    }
    coords[l] = x[p];
    coords[chunk + l] = y[p];
    coords[2 * chunk + l] = z[p];
  }
  const uint32_t bar0 = smem_addr(&mbar[0]);
  if (tid == 0) {
    mbar_init(bar0, 1);
    mbar_init(bar0 + 8, 1);
    asm volatile("fence.mbarrier_init.release.cluster;" ::: "memory");
  }
  // Every block's mbarriers are initialised (and its coordinates written) before any message.
  cluster_barrier();
  const int nslots = csize * kFpsWarps;
  const uint32_t step_bytes = static_cast<uint32_t>(nslots) * 20u;
  int64_t st = start[b];
  st = st < 0 ? 0 : (st >= n ? n - 1 : st);
  int sel = static_cast<int>(st);
  float sx = cloud[3 * st], sy = cloud[3 * st + 1], sz = cloud[3 * st + 2];
  for (int64_t s = 0;; ++s) {
    if (rank == 0 && tid == 0) o[s] = sel;
    if (s + 1 >= steps) break;
    const int buf = static_cast<int>(s & 1);
    const uint32_t bar = bar0 + 8u * buf;
    if (tid == 0) mbar_arrive_expect_tx(bar, step_bytes);
    // Mark the selected point (its owner only), then update; fminf == the CPU's strict-less
    // update for every value that can occur (NaN never enters; -1 stays).
    const int rel = sel - first;
    if (rel >= 0 && rel < chunk && (rel & (kFpsThreads - 1)) == tid) {
#pragma unroll
      for (int p = 0; p < P; ++p)
        if (p * kFpsThreads + tid == rel) dist[p] = -1.f;
    }
    uint32_t kk[P];
    int pp[P];
#pragma unroll
    for (int p = 0; p < P; ++p) {
      dist[p] = fminf(dist[p], sqdist3<float>(x[p], y[p], z[p], sx, sy, sz));
      kk[p] = fps_key(dist[p]);
      pp[p] = p;
    }
    // Tree argmax over the slots; on equal keys the left (lower slot, lower index) wins.
#pragma unroll
    for (int w = 1; w < P; w <<= 1)
#pragma unroll
      for (int p = 0; p + w < P; p += 2 * w)
        if (kk[p + w] > kk[p]) {
          kk[p] = kk[p + w];
          pp[p] = pp[p + w];
        }
    const uint32_t my_i = static_cast<uint32_t>(first + pp[0] * kFpsThreads + tid);
    const uint32_t wk = __reduce_max_sync(kFullMask, kk[0]);
    const uint32_t wi = __reduce_min_sync(kFullMask, kk[0] == wk ? my_i : 0xffffffffu);
    if (lane < csize) {  // lane r sends the warp's candidate to block r
      const int l = static_cast<int>(wi) - first;  // in [0, chunk): a point of this block
      const uint32_t dst = cluster_addr(smem_addr(&slots[buf][rank * kFpsWarps + warp][0]), lane);
      const uint32_t rbar = cluster_addr(bar, lane);
      st_async_v4(dst, wk, wi, __float_as_uint(coords[l]), __float_as_uint(coords[chunk + l]), rbar);
      st_async_b32(dst + 16, __float_as_uint(coords[2 * chunk + l]), rbar);
    }
    while (!mbar_try_wait(bar, static_cast<uint32_t>((s >> 1) & 1))) {
    }
    // Every warp reduces the nslots candidates (lane l: slots l, l + 32, ...).
    uint32_t ck = 0, ci = 0xffffffffu;
    float cx = 0.f, cy = 0.f, cz = 0.f;
#pragma unroll
    for (int q = 0; q < kPushSlots / 32; ++q) {
      const int j = lane + 32 * q;
      if (j < nslots) {
        const uint4 v = *reinterpret_cast<const uint4*>(&slots[buf][j][0]);
        if (v.x > ck || (v.x == ck && v.y < ci)) {
          ck = v.x;
          ci = v.y;
          cx = __uint_as_float(v.z);
          cy = __uint_as_float(v.w);
          cz = __uint_as_float(slots[buf][j][4]);
        }
      }
    }
    const uint32_t bk = __reduce_max_sync(kFullMask, ck);
    const uint32_t bi = __reduce_min_sync(kFullMask, ck == bk ? ci : 0xffffffffu);
    const int src = __ffs(__ballot_sync(kFullMask, ck == bk && ci == bi)) - 1;
    sel = static_cast<int>(bi);
    sx = __shfl_sync(kFullMask, cx, src);
    sy = __shfl_sync(kFullMask, cy, src);
    sz = __shfl_sync(kFullMask, cz, src);
  }
  cluster_barrier();  // every message has landed before any block exits
#else
  __trap();  // never launched: the host checks the compute capability
#endif
}

// ---- host side ----

template <typename T, int P, bool kCluster>
void launch_reg(const T* pts, const int64_t* lengths, const int64_t* start, int64_t B, int64_t N, int64_t K,
                int csize, int64_t* out, cudaStream_t stream) {
  auto kernel = fps_reg_kernel<T, P, kCluster>;
  if constexpr (!kCluster) {
    kernel<<<static_cast<unsigned>(B), kFpsThreads, 0, stream>>>(pts, lengths, start, N, K, 1, out);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  } else {
    cudaLaunchConfig_t cfg = {};
    cfg.gridDim = dim3(static_cast<unsigned>(B * csize), 1, 1);
    cfg.blockDim = dim3(kFpsThreads, 1, 1);
    cfg.dynamicSmemBytes = 0;
    cfg.stream = stream;
    cudaLaunchAttribute attr[1];
    attr[0].id = cudaLaunchAttributeClusterDimension;
    attr[0].val.clusterDim.x = static_cast<unsigned>(csize);
    attr[0].val.clusterDim.y = 1;
    attr[0].val.clusterDim.z = 1;
    cfg.attrs = attr;
    cfg.numAttrs = 1;
    C10_CUDA_CHECK(cudaLaunchKernelEx(&cfg, kernel, pts, lengths, start, N, K, csize, out));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
}

// Whether a cluster of csize blocks of fps_reg_kernel<T, P, true> can be scheduled on the current
// device (cached: the answer depends only on the device, the kernel and csize).
template <typename T, int P>
bool cluster_fits(int csize, int device) {
  static std::mutex mutex;
  static std::map<std::pair<int, int>, bool> cache;
  std::lock_guard<std::mutex> lock(mutex);
  const auto key = std::make_pair(device, csize);
  if (auto it = cache.find(key); it != cache.end()) return it->second;
  auto kernel = fps_reg_kernel<T, P, true>;
  bool ok = true;
  if (csize > 8 && cudaFuncSetAttribute(kernel, cudaFuncAttributeNonPortableClusterSizeAllowed, 1) != cudaSuccess) {
    (void)cudaGetLastError();  // clear the error: this only means "not possible"
    ok = false;
  }
  if (ok) {
    cudaLaunchConfig_t cfg = {};
    cfg.gridDim = dim3(static_cast<unsigned>(csize), 1, 1);
    cfg.blockDim = dim3(kFpsThreads, 1, 1);
    cudaLaunchAttribute attr[1];
    attr[0].id = cudaLaunchAttributeClusterDimension;
    attr[0].val.clusterDim.x = static_cast<unsigned>(csize);
    attr[0].val.clusterDim.y = 1;
    attr[0].val.clusterDim.z = 1;
    cfg.attrs = attr;
    cfg.numAttrs = 1;
    int clusters = 0;
    if (cudaOccupancyMaxActiveClusters(&clusters, kernel, &cfg) != cudaSuccess) {
      (void)cudaGetLastError();
      clusters = 0;
    }
    ok = clusters > 0;
  }
  cache[key] = ok;
  return ok;
}

// Calls f(std::integral_constant<int, P>) for P in {1, 2, 4, 8, 16, 32} (up to fps_pmax<T>()).
template <typename T, typename F>
void dispatch_p(int p, F&& f) {
  switch (p) {
    case 1: f(std::integral_constant<int, 1>{}); return;
    case 2: f(std::integral_constant<int, 2>{}); return;
    case 4: f(std::integral_constant<int, 4>{}); return;
    case 8: f(std::integral_constant<int, 8>{}); return;
    case 16: f(std::integral_constant<int, 16>{}); return;
    case 32:
      if constexpr (fps_pmax<T>() >= 32) {
        f(std::integral_constant<int, 32>{});
        return;
      }
      break;
    default: break;
  }
  TORCH_CHECK(false, "fps: internal error, ", p, " points per thread");
}

template <int P>
constexpr size_t push_smem_bytes() {
  return static_cast<size_t>(3) * kFpsThreads * P * sizeof(float);
}

inline cudaLaunchConfig_t cluster_config(int64_t B, int csize, size_t smem, cudaStream_t stream,
                                         cudaLaunchAttribute* attr) {
  cudaLaunchConfig_t cfg = {};
  cfg.gridDim = dim3(static_cast<unsigned>(B * csize), 1, 1);
  cfg.blockDim = dim3(kFpsThreads, 1, 1);
  cfg.dynamicSmemBytes = smem;
  cfg.stream = stream;
  attr[0].id = cudaLaunchAttributeClusterDimension;
  attr[0].val.clusterDim.x = static_cast<unsigned>(csize);
  attr[0].val.clusterDim.y = 1;
  attr[0].val.clusterDim.z = 1;
  cfg.attrs = attr;
  cfg.numAttrs = 1;
  return cfg;
}

// Whether clusters of csize blocks of fps_push_kernel<P> can be scheduled on `device` (cached;
// also sets the kernel's shared-memory and cluster-size attributes once).
template <int P>
bool push_fits(int csize, int device) {
  static std::mutex mutex;
  static std::map<std::pair<int, int>, bool> cache;
  std::lock_guard<std::mutex> lock(mutex);
  const auto key = std::make_pair(device, csize);
  if (auto it = cache.find(key); it != cache.end()) return it->second;
  auto kernel = fps_push_kernel<P>;
  bool ok = cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                 static_cast<int>(push_smem_bytes<P>())) == cudaSuccess;
  if (ok && csize > 8)
    ok = cudaFuncSetAttribute(kernel, cudaFuncAttributeNonPortableClusterSizeAllowed, 1) == cudaSuccess;
  if (ok) {
    cudaLaunchAttribute attr[1];
    const cudaLaunchConfig_t cfg = cluster_config(1, csize, push_smem_bytes<P>(), nullptr, attr);
    int clusters = 0;
    ok = cudaOccupancyMaxActiveClusters(&clusters, kernel, &cfg) == cudaSuccess && clusters > 0;
  }
  if (!ok) (void)cudaGetLastError();  // "not possible" is an answer, not an error
  cache[key] = ok;
  return ok;
}

template <int P>
void launch_push(const float* pts, const int64_t* lengths, const int64_t* start, int64_t B, int64_t N, int64_t K,
                 int csize, int64_t* out, cudaStream_t stream) {
  cudaLaunchAttribute attr[1];
  const cudaLaunchConfig_t cfg = cluster_config(B, csize, push_smem_bytes<P>(), stream, attr);
  C10_CUDA_CHECK(cudaLaunchKernelEx(&cfg, fps_push_kernel<P>, pts, lengths, start, N, K, csize, out));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

template <typename T>
void fps_launch(const at::Tensor& points, const at::Tensor& lengths, const at::Tensor& start, int64_t K,
                int64_t method, at::Tensor& out, cudaStream_t stream) {
  const int64_t B = points.size(0), N = points.size(1);
  const T* pp = points.data_ptr<T>();
  const int64_t* lp = lengths.data_ptr<int64_t>();
  const int64_t* sp = start.data_ptr<int64_t>();
  int64_t* op = out.data_ptr<int64_t>();
  constexpr int64_t pmax = fps_pmax<T>();
  const int64_t block_cap = kFpsThreads * pmax;  // points one block holds in registers
  const int device = points.device().index();
  const auto info = gpu::device_props(points.device().index());

  // Several blocks per cloud (thread-block clusters, sm_90+). Auto: only when one block would need
  // more than 16 points per thread; below that one block per cloud takes less time per step.
  if ((method == 2 || (method == 0 && N > kFpsThreads * 16)) && info.cc_major >= 9) {
    const int64_t need = gpu::pow2_ceil(gpu::ceil_div(N, block_cap));  // blocks to hold the cloud
    const int64_t fill = gpu::pow2_floor(std::max<int64_t>(1, info.sms / std::max<int64_t>(B, 1)));
    int64_t pref = gpu::pow2_ceil(gpu::ceil_div(N, kFpsThreads * 8));  // ~8 points per thread
    // The cluster barrier of fps_reg_kernel (double) grows costly beyond 4 blocks; the messages of
    // fps_push_kernel (float) do not.
    if (!std::is_same_v<T, float>) pref = std::min<int64_t>(pref, 4);
    int64_t csize = std::max(need, std::min({fill, pref, static_cast<int64_t>(kMaxCluster)}));
    if (method == 2) csize = std::max<int64_t>(csize, 2);
    for (; csize >= std::max<int64_t>(need, 2) && csize <= kMaxCluster; csize /= 2) {
      const int p = static_cast<int>(gpu::pow2_ceil(gpu::ceil_div(N, csize * kFpsThreads)));
      bool launched = false;
      dispatch_p<T>(p, [&](auto pc) {
        constexpr int P = decltype(pc)::value;
        if constexpr (std::is_same_v<T, float>) {
          if (push_fits<P>(static_cast<int>(csize), device)) {
            launch_push<P>(pp, lp, sp, B, N, K, static_cast<int>(csize), op, stream);
            launched = true;
            return;
          }
        }
        if (!cluster_fits<T, P>(static_cast<int>(csize), device)) return;
        launch_reg<T, P, true>(pp, lp, sp, B, N, K, static_cast<int>(csize), op, stream);
        launched = true;
      });
      if (launched) return;
    }
    // csize == 1 (auto on a full GPU), or no cluster could be scheduled: one block per cloud.
  }
  // One block per cloud.
  if (N <= block_cap) {
    const int p = static_cast<int>(gpu::pow2_ceil(gpu::ceil_div(N, kFpsThreads)));
    dispatch_p<T>(p, [&](auto pc) {
      constexpr int P = decltype(pc)::value;
      launch_reg<T, P, false>(pp, lp, sp, B, N, K, 1, op, stream);
    });
    return;
  }
  auto ws = at::empty({B, N}, points.options());
  fps_global_kernel<T><<<static_cast<unsigned>(B), kGlobalThreads, 0, stream>>>(pp, lp, sp, N, K, ws.data_ptr<T>(),
                                                                                op);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

at::Tensor fps_cuda(const at::Tensor& points_in, const at::Tensor& lengths_in, const at::Tensor& start_in, int64_t k,
                    int64_t method) {
  check_cloud(points_in, "points");
  check_lengths(lengths_in, points_in, "lengths");
  check_lengths(start_in, points_in, "start_idx");
  TORCH_CHECK_VALUE(k > 0, "k must be positive, got ", k);
  TORCH_CHECK_VALUE(method >= 0 && method <= 2, "method must be 0 (auto), 1 (one block per cloud) or 2 (several blocks "
                    "per cloud), got ", method);
  c10::cuda::CUDAGuard device_guard(points_in.device());
  const int64_t B = points_in.size(0), N = points_in.size(1);
  TORCH_CHECK_VALUE(N < std::numeric_limits<int32_t>::max(), "points: at most 2^31 - 2 points per cloud on CUDA, got ", N);
  auto out = at::empty({B, k}, points_in.options().dtype(at::kLong));
  if (B == 0) return out;
  if (N == 0) return out.fill_(-1);
  auto points = gpu::compute_tensor(points_in);  // half/bfloat16 -> float, exact
  auto lengths = lengths_in.contiguous();
  auto start = start_in.contiguous();
  cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, points_in.scalar_type(), "lidarops_fps_cuda", [&] {
    fps_launch<acc_t<scalar_t>>(points, lengths, start, k, method, out, stream);
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) { m.impl("fps", &fps_cuda); }

}  // namespace lidarops
