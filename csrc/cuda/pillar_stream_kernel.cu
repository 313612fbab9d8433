// Pillarization ops on CUDA. Same results as the CPU kernels (csrc/cpu/pillar_stream_kernel.cpp):
// the queues hold the same points in the same order (sorted by t, ties in arrival order), so the
// gathered pillars and their features are bit-identical; only which pool slot a pillar gets differs
// (invisible: outputs are indexed by pillar key).
//
// pillar_decorate: one thread per pillar computes the mean (float64, slot order) and the centre, then
//   one thread per (pillar, slot) writes the 9 features.
// pillar_stream_gather: one thread per (pillar, slot).
// pillar_stream_push, without any host synchronisation:
//   plan (reads the state, writes scratch):
//     1. keys: the pillar key of each new point; outside / late points counted and sorted last.
//     2. expiry count: one block per run binary-searches the run's expired prefix (runs are sorted by
//        t) and counts, per slot, the entries it holds (integer atomics); the first counter of a slot
//        appends it to the list of touched slots.
//     3. two stable sorts (ATen): the entering points by t (the log run), then by pillar key (the
//        queues): (key, t, arrival) order, each pillar a segment.
//     4. per segment: its pillar's length after the push; per touched slot: does it become empty;
//        the free-stack entries the new pillars will pop; one thread then decides the flags. In drop
//        mode the segments are first cut to what fits (the overflow rule: new pillars ranked in key
//        order by an inclusive sum, against the slots free after the expiry), and the log's positions
//        of the admitted points are another inclusive sum.
//   Every state value used as an index is checked where the plan reads it (as the CPU plan does): a
//   bad value is skipped and sets a kPsBad* bit of stats[kPsOverflow], so the apply does nothing.
//   apply (every kernel returns at once when the plan overflowed, so an overflowing push changes nothing):
//     5. expiry: advance each touched queue's head; free the slots that become empty (atomic push on
//        the free stack).
//     6. insert: one thread per segment takes a slot when its pillar was empty (atomic pop: pops and
//        pushes are in different kernels) and merges its points into the queue from the back.
//     7. log: the entering points, in t order, at [log_head, log_head + points_in).
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <algorithm>
#include <cstdint>
#include <limits>

#include "lidarops/cuda_launch.cuh"
#include "lidarops/pillar_stream.h"

namespace lidarops {
namespace {

constexpr int kThreads = 256;
constexpr int64_t kSortLast = std::numeric_limits<int64_t>::max();

inline unsigned int num_blocks(int64_t n) { return gpu::stride_blocks(n, kThreads); }

__device__ __forceinline__ unsigned long long* ull(int64_t* p) { return reinterpret_cast<unsigned long long*>(p); }

// ---- pillar_decorate ----

template <typename scalar_t>
__global__ void pillar_centre_mean_kernel(const scalar_t* __restrict__ raw, const int32_t* __restrict__ num_points,
                                          const int32_t* __restrict__ coords, int64_t P, int64_t N, double x0,
                                          double y0, double vx, double vy, double* __restrict__ ctr) {
  LIDAROPS_GRID_STRIDE(p, P) {
    int64_t n = num_points[p];
    n = n < 0 ? 0 : (n > N ? N : n);
    double* c = ctr + 5 * p;
    pillar_mean(raw + p * N * 4, n, c);
    c[3] = pillar_centre(x0, vx, coords[3 * p + 2]);
    c[4] = pillar_centre(y0, vy, coords[3 * p + 1]);
  }
}

template <typename scalar_t>
__global__ void pillar_decorate_kernel(const scalar_t* __restrict__ raw, const int32_t* __restrict__ num_points,
                                       const double* __restrict__ ctr, int64_t P, int64_t N,
                                       scalar_t* __restrict__ out) {
  LIDAROPS_GRID_STRIDE(i, P * N) {
    const int64_t p = i / N, k = i - p * N;
    if (k >= num_points[p]) continue;  // padding stays zero
    const double* c = ctr + 5 * p;
    decorate_point(raw + i * 4, c, c[3], c[4], out + i * 9);
  }
}

at::Tensor pillar_decorate_cuda(const at::Tensor& raw_in, const at::Tensor& num_points_in, const at::Tensor& coords_in,
                                at::ArrayRef<double> pillar_size, at::ArrayRef<double> origin) {
  check_pillar_decorate_args(raw_in, num_points_in, coords_in, pillar_size, origin);
  const c10::cuda::CUDAGuard guard(raw_in.device());
  auto raw = raw_in.contiguous();
  auto num_points = num_points_in.contiguous();
  auto coords = coords_in.contiguous();
  const int64_t P = raw.size(0), N = raw.size(1);
  auto out = at::zeros({P, N, 9}, raw.options());
  if (out.numel() == 0) return out;
  auto ctr = at::empty({P, 5}, raw.options().dtype(at::kDouble));
  const auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(raw.scalar_type(), "lidarops_pillar_decorate_cuda", [&] {
    pillar_centre_mean_kernel<scalar_t><<<num_blocks(P), kThreads, 0, stream>>>(
        raw.data_ptr<scalar_t>(), num_points.data_ptr<int32_t>(), coords.data_ptr<int32_t>(), P, N, origin[0],
        origin[1], pillar_size[0], pillar_size[1], ctr.data_ptr<double>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    pillar_decorate_kernel<scalar_t><<<num_blocks(P * N), kThreads, 0, stream>>>(
        raw.data_ptr<scalar_t>(), num_points.data_ptr<int32_t>(), ctr.data_ptr<double>(), P, N,
        out.data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return out;
}

// ---- pillar_stream_gather ----

__global__ void pillar_gather_kernel(const float* __restrict__ pool, const int32_t* __restrict__ head,
                                     const int32_t* __restrict__ count, const int32_t* __restrict__ cell_slot,
                                     const int64_t* __restrict__ cells, int64_t P, int64_t M, int64_t N, int64_t C,
                                     float* __restrict__ raw, int32_t* __restrict__ num_points) {
  LIDAROPS_GRID_STRIDE(i, P * N) {
    const int64_t p = i / N, k = i - p * N;
    const int64_t cell = cells[p];
    const int32_t slot = cell >= 0 && cell < C ? cell_slot[cell] : -1;
    if (slot == -1) continue;
    // a slot, head or count out of range is never used as an index: the pillar reports -1 points
    if (slot < 0 || slot >= M || !ps_queue_ok(head[slot], count[slot], N)) {
      if (k == 0) num_points[p] = -1;
      continue;
    }
    const int64_t n = count[slot];
    if (k == 0) num_points[p] = static_cast<int32_t>(n);
    if (k >= n) continue;
    const float4 v = reinterpret_cast<const float4*>(pool)[slot * N + (head[slot] + k) % N];
    reinterpret_cast<float4*>(raw)[i] = v;
  }
}

std::tuple<at::Tensor, at::Tensor> pillar_stream_gather_cuda(const at::Tensor& pool_xyzi, const at::Tensor& head,
                                                             const at::Tensor& count, const at::Tensor& cell_slot,
                                                             const at::Tensor& cells_in) {
  check_pillar_gather_args(pool_xyzi, head, count, cell_slot, cells_in);
  const c10::cuda::CUDAGuard guard(pool_xyzi.device());
  auto cells = cells_in.contiguous();
  const int64_t P = cells.size(0), M = pool_xyzi.size(0), N = pool_xyzi.size(1), C = cell_slot.size(0);
  auto raw = at::zeros({P, N, 4}, pool_xyzi.options());
  auto num_points = at::zeros({P}, pool_xyzi.options().dtype(at::kInt));
  if (P * N == 0) return {raw, num_points};  // (N = 0: no slot holds a point)
  pillar_gather_kernel<<<num_blocks(P * N), kThreads, 0, c10::cuda::getCurrentCUDAStream()>>>(
      pool_xyzi.data_ptr<float>(), head.data_ptr<int32_t>(), count.data_ptr<int32_t>(), cell_slot.data_ptr<int32_t>(),
      cells.data_ptr<int64_t>(), P, M, N, C, raw.data_ptr<float>(), num_points.data_ptr<int32_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {raw, num_points};
}

// ---- pillar_stream_push: plan ----

// scalars (nullable): log_head and the bits of cutoff, read on the device in place of the arguments.
__device__ __forceinline__ double ps_cutoff(const int64_t* scalars, double cutoff) {
  return scalars != nullptr ? __longlong_as_double(scalars[1]) : cutoff;
}

__global__ void ps_keys_kernel(const float* __restrict__ points, const double* __restrict__ t, int64_t n,
                               VoxelGrid<float> g, double cutoff_arg, const int64_t* __restrict__ scalars,
                               int64_t* __restrict__ ckey, double* __restrict__ tkey, int64_t* __restrict__ stats) {
  const double cutoff = ps_cutoff(scalars, cutoff_arg);
  LIDAROPS_GRID_STRIDE(i, n) {
    const float* q = points + 4 * i;
    const int64_t key = voxel_key(g, q[0], q[1], q[2]);
    const double ti = t[i];
    const bool enters = key != kNoVoxel && ti > cutoff;
    if (key == kNoVoxel) atomicAdd(ull(stats + kPsPointsOutside), 1ULL);
    else if (!enters) atomicAdd(ull(stats + kPsPointsLate), 1ULL);
    else atomicAdd(ull(stats + kPsPointsIn), 1ULL);
    ckey[i] = enters ? key : kSortLast;
    tkey[i] = enters ? ti : std::numeric_limits<double>::infinity();
  }
}

// One block per run: the run's expired prefix (binary search: the run is sorted by t), then one
// count per entry on its pillar's slot.
__global__ void ps_expire_count_kernel(const int64_t* __restrict__ runs, const int32_t* __restrict__ log_cell,
                                       const double* __restrict__ log_t, int64_t L, int64_t cells, int64_t M,
                                       double cutoff_arg, const int64_t* __restrict__ scalars,
                                       const int32_t* __restrict__ cell_slot,
                                       const int32_t* __restrict__ slot_cell, int32_t* __restrict__ pops,
                                       int32_t* __restrict__ touched, int64_t* __restrict__ run_pops,
                                       int64_t* __restrict__ stats) {
  __shared__ int64_t expired;
  const double cutoff = ps_cutoff(scalars, cutoff_arg);
  const int64_t r = blockIdx.x;
  const int64_t start = runs[2 * r], end = runs[2 * r + 1];
  if (threadIdx.x == 0 && !(0 <= start && start <= end && end - start <= L)) {
    atomicOr(ull(stats + kPsOverflow), static_cast<unsigned long long>(kPsBadRuns));
    expired = 0;
  } else if (threadIdx.x == 0) {
    int64_t lo = start, hi = end;  // first position with t > cutoff
    while (lo < hi) {
      const int64_t mid = lo + (hi - lo) / 2;
      if (log_t[mid % L] <= cutoff) lo = mid + 1;
      else hi = mid;
    }
    expired = lo - start;
    run_pops[r] = expired;
    if (expired) atomicAdd(ull(stats + kPsPointsOut), static_cast<unsigned long long>(expired));
  }
  __syncthreads();
  for (int64_t e = threadIdx.x; e < expired; e += blockDim.x) {
    const int64_t cell = log_cell[(start + e) % L];
    const int32_t slot = cell >= 0 && cell < cells ? cell_slot[cell] : -1;
    if (slot == -1) {
      atomicOr(ull(stats + kPsOverflow), static_cast<unsigned long long>(kPsBadLog));
      continue;
    }
    if (slot < 0 || slot >= M || slot_cell[slot] != cell) {
      atomicOr(ull(stats + kPsOverflow), static_cast<unsigned long long>(kPsBadCellSlot));
      continue;
    }
    if (atomicAdd(pops + slot, 1) == 0)
      touched[atomicAdd(ull(stats + kPsTouchedSlots), 1ULL)] = slot;
  }
}

// The points a pillar keeps after the expiry (0 for a pillar without a slot). State values are only
// bounds-guarded: ps_segments_kernel and ps_touched_plan_kernel check them.
__device__ __forceinline__ int64_t ps_kept(int32_t slot, int64_t M, int64_t N, const int32_t* count,
                                          const int32_t* pops) {
  if (slot < 0 || slot >= M) return 0;
  const int64_t has = static_cast<int64_t>(count[slot]) - pops[slot];
  return has < 0 ? 0 : (has > N ? N : has);
}

// Drop mode: the touched pillars that keep no point (for the slots free after the expiry).
__global__ void ps_fully_expired_kernel(const int32_t* __restrict__ touched, int64_t M,
                                        const int32_t* __restrict__ count, const int32_t* __restrict__ pops,
                                        const int64_t* __restrict__ stats, int64_t* __restrict__ fully_expired) {
  const int64_t T = stats[kPsTouchedSlots];
  LIDAROPS_GRID_STRIDE(i, T < M ? T : M) {
    const int32_t slot = touched[i];
    if (pops[slot] >= count[slot]) atomicAdd(ull(fully_expired), 1ULL);
  }
}

// Drop mode: 1 at the head of each segment whose pillar keeps no point (is new); their inclusive sum
// over the key-sorted points ranks the new pillars in key order.
__global__ void ps_new_flags_kernel(const int64_t* __restrict__ skeys, int64_t n, int64_t M, int64_t N,
                                    const int32_t* __restrict__ cell_slot, const int32_t* __restrict__ count,
                                    const int32_t* __restrict__ pops, int64_t* __restrict__ is_new) {
  LIDAROPS_GRID_STRIDE(j, n) {
    const int64_t key = skeys[j];
    const bool head = key != kSortLast && (j == 0 || skeys[j - 1] != key);
    is_new[j] = head && ps_kept(cell_slot[key], M, N, count, pops) == 0;
  }
}

// One thread per segment head of the (key, t, arrival)-sorted entering points. In drop mode
// (new_rank != nullptr) the segment keeps the points that fit (the overflow rule, as the CPU's
// plan_drops): its first N - kept ones, none for a new pillar ranked beyond the free slots; the others
// are marked in dropped (by point) and counted.
__global__ void ps_segments_kernel(const int64_t* __restrict__ skeys, const int64_t* __restrict__ order_c, int64_t n,
                                   int64_t M, int64_t N, const int32_t* __restrict__ cell_slot,
                                   const int32_t* __restrict__ slot_cell, const int32_t* __restrict__ head,
                                   const int32_t* __restrict__ count, const int32_t* __restrict__ pops,
                                   const int64_t* __restrict__ new_rank, const int32_t* __restrict__ num_free,
                                   const int64_t* __restrict__ fully_expired, bool* __restrict__ dropped,
                                   int32_t* __restrict__ gains, int64_t* __restrict__ seg_start,
                                   int64_t* __restrict__ seg_len, int64_t* __restrict__ stats) {
  LIDAROPS_GRID_STRIDE(j, n) {
    const int64_t key = skeys[j];
    if (key == kSortLast || (j > 0 && skeys[j - 1] == key)) continue;
    int64_t k = 1;
    while (j + k < n && skeys[j + k] == key) ++k;
    const int32_t slot = cell_slot[key];
    if (slot != -1 && (slot < 0 || slot >= M || slot_cell[slot] != key)) {
      atomicOr(ull(stats + kPsOverflow), static_cast<unsigned long long>(kPsBadCellSlot));
      continue;
    }
    if (slot != -1 && !ps_queue_ok(head[slot], count[slot], N)) {
      atomicOr(ull(stats + kPsOverflow), static_cast<unsigned long long>(kPsBadQueue));
      continue;
    }
    const int64_t has = ps_kept(slot, M, N, count, pops);
    if (new_rank != nullptr) {
      const int64_t free = static_cast<int64_t>(num_free[0]) + fully_expired[0];
      const bool no_slot = has == 0 && new_rank[j] > free;
      const int64_t keep = no_slot ? 0 : (k < N - has ? k : N - has);
      for (int64_t q = keep; q < k; ++q) dropped[order_c[j + q]] = true;
      if (keep < k)
        atomicAdd(ull(stats + (no_slot ? kPsDroppedPillars : kPsDroppedPoints)),
                  static_cast<unsigned long long>(k - keep));
      if (keep == 0) continue;
      k = keep;
    }
    const int64_t s = static_cast<int64_t>(atomicAdd(ull(stats + kPsSegments), 1ULL));
    seg_start[s] = j;
    seg_len[s] = k;
    if (slot == -1) atomicAdd(ull(stats + kPsNewPillars), 1ULL);
    else gains[slot] = static_cast<int32_t>(k);
    atomicMax(reinterpret_cast<long long*>(stats + kPsMaxPointsNeeded), static_cast<long long>(has + k));
  }
}

__global__ void ps_touched_plan_kernel(const int32_t* __restrict__ touched, int64_t M, int64_t N,
                                       const int32_t* __restrict__ head, const int32_t* __restrict__ count,
                                       const int32_t* __restrict__ pops, const int32_t* __restrict__ gains,
                                       int64_t* __restrict__ stats) {
  const int64_t T = stats[kPsTouchedSlots];
  LIDAROPS_GRID_STRIDE(i, T < M ? T : M) {
    const int32_t slot = touched[i];
    if (!ps_queue_ok(head[slot], count[slot], N) || pops[slot] < 0 || pops[slot] > count[slot]) {
      atomicOr(ull(stats + kPsOverflow), static_cast<unsigned long long>(kPsBadQueue));
      continue;
    }
    if (pops[slot] == count[slot] && gains[slot] == 0) atomicAdd(ull(stats + kPsEmptied), 1ULL);
  }
}

// The free stack: the frees push `emptied` slots, then the new pillars pop; the pops that reach
// below the freed slots take old entries, which must be free slots.
__global__ void ps_free_check_kernel(const int32_t* __restrict__ num_free, const int32_t* __restrict__ free_slots,
                                     const int32_t* __restrict__ slot_cell, int64_t M, int64_t* __restrict__ stats) {
  const int64_t nf0 = num_free[0], emptied = stats[kPsEmptied];
  if (nf0 < 0 || nf0 > M || nf0 + emptied > M) {
    if (blockIdx.x == 0 && threadIdx.x == 0)
      atomicOr(ull(stats + kPsOverflow), static_cast<unsigned long long>(kPsBadNumFree));
    return;
  }
  const int64_t from_old = stats[kPsNewPillars] - emptied;
  const int64_t lo = nf0 - from_old > 0 ? nf0 - from_old : 0;
  LIDAROPS_GRID_STRIDE(i, nf0 - lo) {
    const int32_t slot = free_slots[lo + i];
    if (slot < 0 || slot >= M || slot_cell[slot] != -1)
      atomicOr(ull(stats + kPsOverflow), static_cast<unsigned long long>(kPsBadFreeSlots));
  }
}

__global__ void ps_finalize_kernel(const int32_t* __restrict__ num_free, int64_t M, int64_t N,
                                   const int64_t* __restrict__ scalars, int64_t* __restrict__ stats) {
  if (scalars != nullptr && (!(scalars[0] >= 0 && scalars[0] < kPsMaxLogHead) || isnan(ps_cutoff(scalars, 0.0))))
    stats[kPsOverflow] |= kPsBadLog;  // before the apply kernels, which then change nothing
  const int64_t active_after = (M - num_free[0]) - stats[kPsEmptied] + stats[kPsNewPillars];
  stats[kPsPillarsNeeded] = active_after;
  stats[kPsPointsIn] -= stats[kPsDroppedPoints] + stats[kPsDroppedPillars];
  stats[kPsOverflow] |= (stats[kPsMaxPointsNeeded] > N ? kPsOverflowPoints : 0) |
                        (active_after > M ? kPsOverflowPillars : 0);
}

// ---- pillar_stream_push: apply (no-ops when the plan overflowed) ----

__global__ void ps_apply_expiry_kernel(const int32_t* __restrict__ touched, int64_t M, int64_t N,
                                       const int32_t* __restrict__ pops, const int32_t* __restrict__ gains,
                                       int32_t* __restrict__ head, int32_t* __restrict__ count,
                                       int32_t* __restrict__ slot_cell, int32_t* __restrict__ cell_slot,
                                       int32_t* __restrict__ free_slots, int32_t* __restrict__ num_free,
                                       bool* __restrict__ change_map, int64_t* __restrict__ run_pops, int64_t R,
                                       const int64_t* __restrict__ stats) {
  if (stats[kPsOverflow]) {  // nothing expires: the push changes nothing
    LIDAROPS_GRID_STRIDE(r, R) run_pops[r] = 0;
    return;
  }
  const int64_t T = stats[kPsTouchedSlots];
  LIDAROPS_GRID_STRIDE(i, T < M ? T : M) {
    const int32_t slot = touched[i];
    const int32_t k = pops[slot];
    head[slot] = static_cast<int32_t>((head[slot] + k) % N);
    count[slot] -= k;
    const int32_t cell = slot_cell[slot];
    change_map[cell] = true;
    if (count[slot] == 0 && gains[slot] == 0) {
      cell_slot[cell] = -1;
      slot_cell[slot] = -1;
      head[slot] = 0;
      free_slots[atomicAdd(num_free, 1)] = slot;
    }
  }
}

__global__ void ps_insert_kernel(const int64_t* __restrict__ skeys, const int64_t* __restrict__ order_c,
                                 const int64_t* __restrict__ seg_start, const int64_t* __restrict__ seg_len, int64_t n,
                                 int64_t N, const float* __restrict__ points, const double* __restrict__ t,
                                 float* __restrict__ pool, double* __restrict__ pool_t, int32_t* __restrict__ head,
                                 int32_t* __restrict__ count, int32_t* __restrict__ slot_cell,
                                 int32_t* __restrict__ cell_slot, const int32_t* __restrict__ free_slots,
                                 int32_t* __restrict__ num_free, bool* __restrict__ change_map,
                                 const int64_t* __restrict__ stats) {
  if (stats[kPsOverflow]) return;
  const int64_t S = stats[kPsSegments];
  LIDAROPS_GRID_STRIDE(s, S < n ? S : n) {
    const int64_t b = seg_start[s], k = seg_len[s];
    const int64_t cell = skeys[b];
    int32_t slot = cell_slot[cell];
    if (slot < 0) {
      slot = free_slots[atomicSub(num_free, 1) - 1];  // the plan checked that enough are free
      cell_slot[cell] = slot;
      slot_cell[slot] = static_cast<int32_t>(cell);
      head[slot] = 0;
      count[slot] = 0;
    }
    change_map[cell] = true;
    // Merge from the back, as the CPU kernel: later queue points move, ties keep queue points first.
    const int64_t h = head[slot], c = count[slot];
    float4* qx = reinterpret_cast<float4*>(pool) + slot * N;
    double* qt = pool_t + slot * N;
    int64_t i = c - 1, j = k - 1, w = c + k - 1;
    while (j >= 0) {
      const int64_t src = order_c[b + j];
      const int64_t wq = (h + w) % N;
      const double ts = t[src];
      if (i >= 0 && qt[(h + i) % N] > ts) {
        const int64_t iq = (h + i) % N;
        qx[wq] = qx[iq];
        qt[wq] = qt[iq];
        --i;
      } else {
        qx[wq] = reinterpret_cast<const float4*>(points)[src];
        qt[wq] = ts;
        --j;
      }
      --w;
    }
    count[slot] = static_cast<int32_t>(c + k);
  }
}

// The entering points in t order; in drop mode (pos != nullptr) the admitted ones only, at their
// inclusive-sum positions.
__global__ void ps_log_kernel(const double* __restrict__ sorted_t, const int64_t* __restrict__ order_t,
                              const int64_t* __restrict__ ckey, const double* __restrict__ t,
                              const int64_t* __restrict__ pos, int64_t n, int64_t log_head_arg,
                              const int64_t* __restrict__ scalars, int64_t L, int32_t* __restrict__ log_cell,
                              double* __restrict__ log_t, const int64_t* __restrict__ stats) {
  if (stats[kPsOverflow]) return;
  const int64_t log_head = scalars != nullptr ? scalars[0] : log_head_arg;
  LIDAROPS_GRID_STRIDE(j, n) {
    if (isinf(sorted_t[j])) continue;  // the entering points come first in t order
    int64_t at = j;
    if (pos != nullptr) {
      at = pos[j] - 1;
      if (j > 0 ? pos[j - 1] > at : at < 0) continue;  // dropped
    }
    const int64_t i = order_t[j], q = (log_head + at) % L;
    log_cell[q] = static_cast<int32_t>(ckey[i]);
    log_t[q] = t[i];
  }
}

// Drop mode: 1 for each admitted point, in t order (for the log's positions).
__global__ void ps_admitted_kernel(const double* __restrict__ sorted_t, const int64_t* __restrict__ order_t,
                                   const bool* __restrict__ dropped, int64_t n, int64_t* __restrict__ admitted) {
  LIDAROPS_GRID_STRIDE(j, n) admitted[j] = !isinf(sorted_t[j]) && !dropped[order_t[j]];
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> pillar_stream_push_cuda(
    at::Tensor& pool_xyzi, at::Tensor& pool_t, at::Tensor& head, at::Tensor& count, at::Tensor& slot_cell,
    at::Tensor& cell_slot, at::Tensor& free_slots, at::Tensor& num_free, at::Tensor& log_cell, at::Tensor& log_t,
    const at::Tensor& points_in, const at::Tensor& t_in, const at::Tensor& runs_in, int64_t log_head, double cutoff,
    at::ArrayRef<double> point_range, at::ArrayRef<double> pillar_size, at::IntArrayRef grid_hw, bool drop,
    const c10::optional<at::Tensor>& scalars_in) {
  at::Tensor scalars;
  if (scalars_in.has_value()) {
    check_pillar_stream_scalars(*scalars_in, pool_xyzi);
    scalars = scalars_in->contiguous();
  }
  const int64_t* sc = scalars.defined() ? scalars.data_ptr<int64_t>() : nullptr;
  const PillarStreamArgs a =
      check_pillar_stream_push_args(pool_xyzi, pool_t, head, count, slot_cell, cell_slot, free_slots, num_free,
                                    log_cell, log_t, points_in, t_in, runs_in, sc ? 0 : log_head,
                                    sc ? 0.0 : cutoff, point_range, pillar_size, grid_hw);  // scalars: read there
  const VoxelGrid<float> g = pillar_voxel_grid(point_range, pillar_size, a);
  const c10::cuda::CUDAGuard guard(pool_xyzi.device());
  const auto stream = c10::cuda::getCurrentCUDAStream();
  auto points = points_in.contiguous();
  if (reinterpret_cast<uintptr_t>(points.data_ptr()) % alignof(float4) != 0) points = points.clone();  // float4 loads
  auto t = t_in.contiguous();
  auto runs = runs_in.contiguous();
  const int64_t n = points.size(0), R = runs.size(0), M = a.M, N = a.N, L = a.L;
  const auto opts = points.options();
  auto change_map = at::zeros({a.H, a.W}, opts.dtype(at::kBool));
  auto stats = at::zeros({kNumPillarStreamStats}, opts.dtype(at::kLong));
  auto run_pops = at::zeros({R}, opts.dtype(at::kLong));
  auto pops = at::zeros({M}, opts.dtype(at::kInt));
  auto gains = at::zeros({M}, opts.dtype(at::kInt));
  auto touched = at::empty({M}, opts.dtype(at::kInt));
  int64_t* st = stats.data_ptr<int64_t>();

  // plan
  at::Tensor ckey = at::empty({n}, opts.dtype(at::kLong)), tkey = at::empty({n}, opts.dtype(at::kDouble));
  at::Tensor sorted_t, order_t, skeys, order_c;
  at::Tensor fully_expired, dropped, rank, log_pos;  // drop mode
  auto seg_start = at::empty({n}, opts.dtype(at::kLong)), seg_len = at::empty({n}, opts.dtype(at::kLong));
  if (n > 0) {
    ps_keys_kernel<<<num_blocks(n), kThreads, 0, stream>>>(points.data_ptr<float>(), t.data_ptr<double>(), n, g,
                                                            cutoff, sc, ckey.data_ptr<int64_t>(), tkey.data_ptr<double>(),
                                                            st);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  if (R > 0) {
    ps_expire_count_kernel<<<static_cast<unsigned int>(R), kThreads, 0, stream>>>(
        runs.data_ptr<int64_t>(), log_cell.data_ptr<int32_t>(), log_t.data_ptr<double>(), L, a.H * a.W, M, cutoff, sc,
        cell_slot.data_ptr<int32_t>(), slot_cell.data_ptr<int32_t>(), pops.data_ptr<int32_t>(),
        touched.data_ptr<int32_t>(), run_pops.data_ptr<int64_t>(), st);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  if (n > 0) {
    std::tie(sorted_t, order_t) = at::sort(tkey, /*stable=*/true, /*dim=*/0, /*descending=*/false);
    at::Tensor perm;
    std::tie(skeys, perm) = at::sort(ckey.index_select(0, order_t), /*stable=*/true, 0, false);
    order_c = order_t.index_select(0, perm);
    const int64_t* new_rank = nullptr;
    if (drop) {
      fully_expired = at::zeros({1}, opts.dtype(at::kLong));
      dropped = at::zeros({n}, opts.dtype(at::kBool));
      ps_fully_expired_kernel<<<num_blocks(M), kThreads, 0, stream>>>(
          touched.data_ptr<int32_t>(), M, count.data_ptr<int32_t>(), pops.data_ptr<int32_t>(), st,
          fully_expired.data_ptr<int64_t>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
      auto is_new = at::empty({n}, opts.dtype(at::kLong));
      ps_new_flags_kernel<<<num_blocks(n), kThreads, 0, stream>>>(
          skeys.data_ptr<int64_t>(), n, M, N, cell_slot.data_ptr<int32_t>(), count.data_ptr<int32_t>(),
          pops.data_ptr<int32_t>(), is_new.data_ptr<int64_t>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
      rank = at::cumsum(is_new, 0);
      new_rank = rank.data_ptr<int64_t>();
    }
    ps_segments_kernel<<<num_blocks(n), kThreads, 0, stream>>>(
        skeys.data_ptr<int64_t>(), order_c.data_ptr<int64_t>(), n, M, N, cell_slot.data_ptr<int32_t>(),
        slot_cell.data_ptr<int32_t>(), head.data_ptr<int32_t>(), count.data_ptr<int32_t>(), pops.data_ptr<int32_t>(),
        new_rank, num_free.data_ptr<int32_t>(), drop ? fully_expired.data_ptr<int64_t>() : nullptr,
        drop ? dropped.data_ptr<bool>() : nullptr, gains.data_ptr<int32_t>(), seg_start.data_ptr<int64_t>(),
        seg_len.data_ptr<int64_t>(), st);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    if (drop) {
      auto admitted = at::empty({n}, opts.dtype(at::kLong));
      ps_admitted_kernel<<<num_blocks(n), kThreads, 0, stream>>>(
          sorted_t.data_ptr<double>(), order_t.data_ptr<int64_t>(), dropped.data_ptr<bool>(), n,
          admitted.data_ptr<int64_t>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
      log_pos = at::cumsum(admitted, 0);
    }
  }
  ps_touched_plan_kernel<<<num_blocks(M), kThreads, 0, stream>>>(
      touched.data_ptr<int32_t>(), M, N, head.data_ptr<int32_t>(), count.data_ptr<int32_t>(),
      pops.data_ptr<int32_t>(), gains.data_ptr<int32_t>(), st);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  ps_free_check_kernel<<<num_blocks(M), kThreads, 0, stream>>>(
      num_free.data_ptr<int32_t>(), free_slots.data_ptr<int32_t>(), slot_cell.data_ptr<int32_t>(), M, st);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  ps_finalize_kernel<<<1, 1, 0, stream>>>(num_free.data_ptr<int32_t>(), M, N, sc, st);
  C10_CUDA_KERNEL_LAUNCH_CHECK();

  // apply
  bool* cm = change_map.data_ptr<bool>();
  ps_apply_expiry_kernel<<<num_blocks(M), kThreads, 0, stream>>>(
      touched.data_ptr<int32_t>(), M, N, pops.data_ptr<int32_t>(), gains.data_ptr<int32_t>(), head.data_ptr<int32_t>(),
      count.data_ptr<int32_t>(), slot_cell.data_ptr<int32_t>(), cell_slot.data_ptr<int32_t>(),
      free_slots.data_ptr<int32_t>(), num_free.data_ptr<int32_t>(), cm, run_pops.data_ptr<int64_t>(), R, st);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (n > 0) {
    ps_insert_kernel<<<num_blocks(n), kThreads, 0, stream>>>(
        skeys.data_ptr<int64_t>(), order_c.data_ptr<int64_t>(), seg_start.data_ptr<int64_t>(),
        seg_len.data_ptr<int64_t>(), n, N, points.data_ptr<float>(), t.data_ptr<double>(), pool_xyzi.data_ptr<float>(),
        pool_t.data_ptr<double>(), head.data_ptr<int32_t>(), count.data_ptr<int32_t>(), slot_cell.data_ptr<int32_t>(),
        cell_slot.data_ptr<int32_t>(), free_slots.data_ptr<int32_t>(), num_free.data_ptr<int32_t>(), cm, st);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    ps_log_kernel<<<num_blocks(n), kThreads, 0, stream>>>(
        sorted_t.data_ptr<double>(), order_t.data_ptr<int64_t>(), ckey.data_ptr<int64_t>(), t.data_ptr<double>(),
        drop ? log_pos.data_ptr<int64_t>() : nullptr, n, log_head, sc, L, log_cell.data_ptr<int32_t>(),
        log_t.data_ptr<double>(), st);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  return {change_map, stats, run_pops};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("pillar_decorate", &pillar_decorate_cuda);
  m.impl("pillar_stream_gather", &pillar_stream_gather_cuda);
  m.impl("pillar_stream_push", &pillar_stream_push_cuda);
}

}  // namespace lidarops
