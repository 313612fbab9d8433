// CUDA kernels of lidarops::greedy_assign and lidarops::fill_repeats (schemas and contracts: csrc/ops/assign.cpp).
// greedy_assign: the same assignment as the CPU's sequential scan, found in parallel rounds.
//
// Why rounds give the scan's answer: call a pair live while its row holds nothing and its col is free. A live
// pair that comes first among the live pairs of its row and among those of its col is taken by the scan too:
// every earlier pair sharing its row or col is dead (its row or col was taken by a pair earlier still, and
// stays taken), and pairs sharing neither do not touch it. A round takes every such pair at once (they share
// no row and no col); the first live pair is always one, so each round takes at least one and the rounds end.
// (Preis' locally dominant matching, with the list's positions as a strict order.) Rounds = the longest chain
// of conflicts: a handful for CAS-Net's candidates, up to one per row if every row ranks the same cols alike.
//
// One cooperative grid (every block resident, grid-wide barriers), two barriers a round: take the pairs first
// in their row and col; then keep the pairs still live as the next round's list (so later rounds touch only
// those) and mark their rows' and cols' firsts with 64-bit keys (round << 32 | ~position): atomicMax keeps
// the first pair of the newest round, so no reset pass is needed. `limit`: the scan stops after `limit`
// takes, i.e. it keeps the `limit` earliest pairs of the full matching; a grid-wide prefix count keeps those.
// Pairs outside [0, num_rows) x [0, num_cols) are skipped: the CPU raises on them, here that needs a host
// read, so the Python wrapper checks.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <math_constants.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <cooperative_groups.h>
#include <cub/block/block_reduce.cuh>
#include <cub/block/block_scan.cuh>

#include <algorithm>
#include <limits>
#include <map>
#include <mutex>

#include <torch/library.h>

#include "lidarops/assign.h"
#include "lidarops/common.h"

namespace lidarops {
namespace {

constexpr int kThreads = 512;

__device__ __forceinline__ bool in_range(int64_t r, int64_t c, int64_t num_rows, int64_t num_cols) {
  return r >= 0 && r < num_rows && c >= 0 && c < num_cols;
}

__device__ __forceinline__ int64_t least(int64_t a, int64_t b) { return a < b ? a : b; }

// The key of pair i in round t: a later round beats every earlier one, an earlier pair beats a later one.
__device__ __forceinline__ unsigned long long first_key(int t, int i) {
  return (static_cast<unsigned long long>(t) << 32) | (0xffffffffu - static_cast<unsigned>(i));
}

struct Workspace {
  unsigned long long* row_first;  // [num_rows]: the key of the row's first live pair in the newest round
  unsigned long long* col_first;  // [num_cols]
  int* row_pair;                  // [num_rows]: the pair the row took, -1
  int* col_taken;                 // [num_cols]: 0 / 1
  int* list[2];                   // [L] each: the live pairs of the next round (positions), alternating
  int* count;                     // [2]: their lengths, alternating
  int* block_takes;               // [gridDim.x]: taken pairs per block's slice (limit only)
};

__global__ void __launch_bounds__(kThreads)
    greedy_assign_kernel(const int64_t* __restrict__ rows, const int64_t* __restrict__ cols, int L, int64_t num_rows,
                         int64_t num_cols, int64_t limit, Workspace ws, int64_t* __restrict__ out) {
  namespace cg = cooperative_groups;
  cg::grid_group grid = cg::this_grid();
  const int64_t tid = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  const int64_t stride = static_cast<int64_t>(gridDim.x) * kThreads;
  for (int64_t r = tid; r < num_rows; r += stride) {
    ws.row_first[r] = 0;
    ws.row_pair[r] = -1;
    out[r] = -1;
  }
  for (int64_t c = tid; c < num_cols; c += stride) {
    ws.col_first[c] = 0;
    ws.col_taken[c] = 0;
  }
  if (tid == 0) ws.count[0] = ws.count[1] = 0;
  grid.sync();
  for (int64_t i = tid; i < L; i += stride) {  // round 1: every pair in range is live
    const int64_t r = rows[i], c = cols[i];
    if (!in_range(r, c, num_rows, num_cols)) continue;
    const unsigned long long key = first_key(1, static_cast<int>(i));
    atomicMax(&ws.row_first[r], key);
    atomicMax(&ws.col_first[c], key);
  }
  grid.sync();
  int n = L;
  const int* cur = nullptr;  // round 1's list: every position
  for (int t = 1;; ++t) {
    for (int64_t j = tid; j < n; j += stride) {  // take the pairs first in their row and their col
      const int i = cur ? cur[j] : static_cast<int>(j);
      const int64_t r = rows[i], c = cols[i];
      if (!in_range(r, c, num_rows, num_cols)) continue;
      const unsigned long long key = first_key(t, i);
      if (ws.row_first[r] == key && ws.col_first[c] == key) {
        ws.row_pair[r] = i;
        ws.col_taken[c] = 1;
      }
    }
    grid.sync();
    // every thread read count[(t + 1) & 1] (this round's n) before the barrier above: reset it for round t + 1
    if (tid == 0) ws.count[(t + 1) & 1] = 0;
    int* next = ws.list[t & 1];
    for (int64_t j = tid; j < n; j += stride) {  // the pairs still live: round t + 1's list and firsts
      const int i = cur ? cur[j] : static_cast<int>(j);
      const int64_t r = rows[i], c = cols[i];
      if (!in_range(r, c, num_rows, num_cols) || ws.row_pair[r] >= 0 || ws.col_taken[c]) continue;
      next[atomicAdd(&ws.count[t & 1], 1)] = i;
      const unsigned long long key = first_key(t + 1, i);
      atomicMax(&ws.row_first[r], key);
      atomicMax(&ws.col_first[c], key);
    }
    grid.sync();
    n = *static_cast<volatile int*>(&ws.count[t & 1]);
    if (n == 0) break;
    cur = next;
  }
  if (limit >= num_rows) {  // every take stands
    for (int64_t r = tid; r < num_rows; r += stride)
      if (ws.row_pair[r] >= 0) out[r] = cols[ws.row_pair[r]];
    return;
  }
  // The `limit` earliest takes: block b counts the takes in its slice of the list, thread by thread; a grid
  // barrier; each block adds the takes of the slices before its own.
  using Reduce = cub::BlockReduce<int, kThreads>;
  using Scan = cub::BlockScan<int, kThreads>;
  __shared__ union {
    typename Reduce::TempStorage reduce;
    typename Scan::TempStorage scan;
  } storage;
  __shared__ int before_block;
  const int64_t slice = (L + gridDim.x - 1) / gridDim.x, per = (slice + kThreads - 1) / kThreads;
  const int64_t end = least(L, (blockIdx.x + 1) * slice);
  const int64_t lo = least(end, blockIdx.x * slice + threadIdx.x * per), hi = least(end, lo + per);
  int mine = 0;
  for (int64_t i = lo; i < hi; ++i) {
    const int64_t r = rows[i];
    mine += in_range(r, cols[i], num_rows, num_cols) && ws.row_pair[r] == i;
  }
  const int block_total = Reduce(storage.reduce).Sum(mine);
  if (threadIdx.x == 0) ws.block_takes[blockIdx.x] = block_total;
  grid.sync();
  int earlier = 0;
  for (int b = threadIdx.x; b < static_cast<int>(blockIdx.x); b += kThreads) earlier += ws.block_takes[b];
  __syncthreads();  // storage.reduce is read by thread 0's Sum above; reused below
  earlier = Reduce(storage.reduce).Sum(earlier);
  if (threadIdx.x == 0) before_block = earlier;
  __syncthreads();
  int before = 0;
  Scan(storage.scan).ExclusiveSum(mine, before);
  before += before_block;
  for (int64_t i = lo; i < hi && before < limit; ++i) {
    const int64_t r = rows[i], c = cols[i];
    if (in_range(r, c, num_rows, num_cols) && ws.row_pair[r] == i) {
      out[r] = c;
      ++before;
    }
  }
}

// Blocks of greedy_assign_kernel that can all be resident on `device` at once (cached per device).
int resident_blocks(int device) {
  static std::mutex mutex;
  static std::map<int, int> cache;
  std::lock_guard<std::mutex> lock(mutex);
  if (auto it = cache.find(device); it != cache.end()) return it->second;
  int per_sm = 0, sms = 0;
  C10_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, greedy_assign_kernel, kThreads, 0));
  C10_CUDA_CHECK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device));
  const int blocks = std::max(1, per_sm * sms);
  cache[device] = blocks;
  return blocks;
}

at::Tensor greedy_assign_cuda(const at::Tensor& rows_in, const at::Tensor& cols_in, int64_t num_rows,
                              int64_t num_cols, int64_t limit) {
  check_greedy_assign_args(rows_in, cols_in, num_rows, num_cols, limit);
  const int64_t L = rows_in.size(0);
  TORCH_CHECK_VALUE(L < std::numeric_limits<int>::max(), "greedy_assign: at most 2^31 - 2 pairs on CUDA, got ", L);
  TORCH_CHECK_VALUE(num_rows + num_cols < std::numeric_limits<int>::max() / 2,
                    "greedy_assign: num_rows + num_cols must be below 2^30 on CUDA, got ", num_rows, " + ", num_cols);
  c10::cuda::CUDAGuard guard(rows_in.device());
  auto out = at::empty({num_rows}, rows_in.options());
  if (num_rows == 0 || L == 0 || limit == 0) return out.fill_(-1);
  auto rows = rows_in.contiguous();
  auto cols = cols_in.contiguous();
  const int64_t most = std::max({L, num_rows, num_cols});
  const int blocks = static_cast<int>(
      std::min<int64_t>(resident_blocks(rows.device().index()), (most + kThreads - 1) / kThreads));
  // one int64 buffer: the firsts (64-bit), then int32 arrays two to a slot
  const int64_t ints = num_rows + num_cols + 2 * L + 2 + blocks;
  auto ws_t = at::empty({num_rows + num_cols + (ints + 1) / 2}, rows.options());
  Workspace ws;
  ws.row_first = reinterpret_cast<unsigned long long*>(ws_t.data_ptr<int64_t>());
  ws.col_first = ws.row_first + num_rows;
  int* p = reinterpret_cast<int*>(ws.col_first + num_cols);
  ws.row_pair = p;
  ws.col_taken = ws.row_pair + num_rows;
  ws.list[0] = ws.col_taken + num_cols;
  ws.list[1] = ws.list[0] + L;
  ws.count = ws.list[1] + L;
  ws.block_takes = ws.count + 2;
  const int64_t* rp = rows.data_ptr<int64_t>();
  const int64_t* cp = cols.data_ptr<int64_t>();
  int Li = static_cast<int>(L);
  int64_t* op = out.data_ptr<int64_t>();
  void* args[] = {&rp, &cp, &Li, &num_rows, &num_cols, &limit, &ws, &op};
  C10_CUDA_CHECK(cudaLaunchCooperativeKernel(reinterpret_cast<void*>(greedy_assign_kernel), dim3(blocks),
                                             dim3(kThreads), args, 0, at::cuda::getCurrentCUDAStream()));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

// fill_repeats: one block, the CPU's order. The rows are scanned in blocks of kFillThreads; a block's repeats
// (compacted in row order by a block scan) are served one after another, each by a block-wide argmin over the free
// points, so a point a row takes is taken for every later row. A cloud has a few repeats (rows whose candidates
// other rows took), so one block of a scan over the points each is enough; no host read.
constexpr int kFillThreads = 1024;
constexpr int kFree = std::numeric_limits<int>::max();

// (d, j) lexicographic minimum: the nearer, ties to the lower index
__device__ __forceinline__ void nearer(double& d, int& j, double od, int oj) {
  if (od < d || (od == d && oj < j)) d = od, j = oj;
}

template <typename T>
__global__ void __launch_bounds__(kFillThreads)
    fill_repeats_kernel(const T* __restrict__ pts, int n, const int64_t* __restrict__ idx, int m, int* holder,
                        int64_t* __restrict__ out) {
  using Scan = cub::BlockScan<int, kFillThreads>;
  __shared__ typename Scan::TempStorage scan;
  __shared__ int rep[kFillThreads];
  __shared__ double warp_d[kFillThreads / 32];
  __shared__ int warp_j[kFillThreads / 32];
  const int t = threadIdx.x, lane = t & 31, warp = t >> 5;
  for (int j = t; j < n; j += kFillThreads) holder[j] = kFree;
  __syncthreads();
  for (int r = t; r < m; r += kFillThreads) {  // each point's first row
    const int64_t i = idx[r];
    out[r] = i;
    if (i >= 0 && i < n) atomicMin(&holder[i], r);
  }
  __syncthreads();
  for (int base = 0; base < m; base += kFillThreads) {
    const int r = base + t;
    int repeat = 0;
    if (r < m) {
      const int64_t i = idx[r];
      repeat = i >= 0 && i < n && holder[i] != r;
    }
    int pos = 0, total = 0;
    Scan(scan).ExclusiveSum(repeat, pos, total);
    if (repeat) rep[pos] = r;
    __syncthreads();
    for (int k = 0; k < total; ++k) {
      const int row = rep[k];
      const int64_t i = idx[row];
      const double x = pts[3 * i], y = pts[3 * i + 1], z = pts[3 * i + 2];
      double d = CUDART_INF;
      int j = kFree;
      for (int c = t; c < n; c += kFillThreads) {  // c rises: a thread's ties keep the lower index
        if (holder[c] != kFree) continue;
        const double dc = sqdist3<double>(x, y, z, pts[3 * c], pts[3 * c + 1], pts[3 * c + 2]);
        if (dc < d) d = dc, j = c;
      }
      for (int off = 16; off > 0; off >>= 1) nearer(d, j, __shfl_down_sync(0xffffffffu, d, off),
                                                    __shfl_down_sync(0xffffffffu, j, off));
      if (lane == 0) warp_d[warp] = d, warp_j[warp] = j;
      __syncthreads();
      if (warp == 0) {
        d = warp_d[lane];
        j = warp_j[lane];
        for (int off = 16; off > 0; off >>= 1) nearer(d, j, __shfl_down_sync(0xffffffffu, d, off),
                                                      __shfl_down_sync(0xffffffffu, j, off));
        if (lane == 0 && j != kFree) {  // no free point (m > n): the repeat stays
          out[row] = j;
          holder[j] = row;
        }
      }
      __syncthreads();  // the point taken is seen by the next row's scan
    }
  }
}

at::Tensor fill_repeats_cuda(const at::Tensor& points, const at::Tensor& idx_in) {
  check_fill_repeats_args(points, idx_in);
  c10::cuda::CUDAGuard guard(points.device());
  auto idx = idx_in.contiguous();
  const int64_t n = points.size(0), m = idx.size(0);
  auto out = at::empty_like(idx);
  if (m == 0) return out;
  auto holder = at::empty({std::max<int64_t>(n, 1)}, idx.options().dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "fill_repeats_cuda", [&] {
    fill_repeats_kernel<scalar_t><<<1, kFillThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
        points.data_ptr<scalar_t>(), static_cast<int>(n), idx.data_ptr<int64_t>(), static_cast<int>(m),
        holder.data_ptr<int>(), out.data_ptr<int64_t>());
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("greedy_assign", &greedy_assign_cuda);
  m.impl("fill_repeats", &fill_repeats_cuda);
}

}  // namespace lidarops
