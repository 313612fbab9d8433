// Pillarization ops on CPU: pillar_decorate and pillar_stream_gather (independent pillars, in
// parallel) and pillar_stream_push (the pillar keys of the new points in parallel; the rest is a
// sequential pass whose cost is proportional to the points entering and leaving the window and the
// pillars they touch, small per 10 ms slice).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/zeros.h>

#include <algorithm>
#include <cstring>
#include <numeric>
#include <vector>

#include "lidarops/pillar_stream.h"

namespace lidarops {
namespace {

at::Tensor pillar_decorate_cpu(const at::Tensor& raw_in, const at::Tensor& num_points_in, const at::Tensor& coords_in,
                               at::ArrayRef<double> pillar_size, at::ArrayRef<double> origin) {
  check_pillar_decorate_args(raw_in, num_points_in, coords_in, pillar_size, origin);
  auto raw = raw_in.contiguous();
  auto num_points = num_points_in.contiguous();
  auto coords = coords_in.contiguous();
  const int64_t P = raw.size(0), N = raw.size(1);
  auto out = at::zeros({P, N, 9}, raw.options());
  if (out.numel() == 0) return out;
  const double vx = pillar_size[0], vy = pillar_size[1], x0 = origin[0], y0 = origin[1];
  AT_DISPATCH_FLOATING_TYPES(raw.scalar_type(), "lidarops_pillar_decorate_cpu", [&] {
    const scalar_t* r = raw.data_ptr<scalar_t>();
    const int32_t* np = num_points.data_ptr<int32_t>();
    const int32_t* c = coords.data_ptr<int32_t>();
    scalar_t* o = out.data_ptr<scalar_t>();
    at::parallel_for(0, P, 256, [&](int64_t s, int64_t e) {
      for (int64_t p = s; p < e; ++p) {
        const int64_t n = std::min<int64_t>(std::max<int32_t>(np[p], 0), N);
        const scalar_t* rp = r + p * N * 4;
        double mean[3];
        pillar_mean(rp, n, mean);
        const double cx = pillar_centre(x0, vx, c[3 * p + 2]), cy = pillar_centre(y0, vy, c[3 * p + 1]);
        for (int64_t k = 0; k < n; ++k) decorate_point(rp + 4 * k, mean, cx, cy, o + (p * N + k) * 9);
      }
    });
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor> pillar_stream_gather_cpu(const at::Tensor& pool_xyzi, const at::Tensor& head,
                                                            const at::Tensor& count, const at::Tensor& cell_slot,
                                                            const at::Tensor& cells_in) {
  check_pillar_gather_args(pool_xyzi, head, count, cell_slot, cells_in);
  auto cells = cells_in.contiguous();
  const int64_t P = cells.size(0), M = pool_xyzi.size(0), N = pool_xyzi.size(1), C = cell_slot.size(0);
  auto raw = at::zeros({P, N, 4}, pool_xyzi.options());
  auto num_points = at::zeros({P}, pool_xyzi.options().dtype(at::kInt));
  if (P == 0) return {raw, num_points};
  const float* pool = pool_xyzi.data_ptr<float>();
  const int32_t* hd = head.data_ptr<int32_t>();
  const int32_t* ct = count.data_ptr<int32_t>();
  const int32_t* cs = cell_slot.data_ptr<int32_t>();
  const int64_t* cl = cells.data_ptr<int64_t>();
  float* out = raw.data_ptr<float>();
  int32_t* np = num_points.data_ptr<int32_t>();
  at::parallel_for(0, P, 256, [&](int64_t s, int64_t e) {
    for (int64_t p = s; p < e; ++p) {
      const int64_t cell = cl[p];
      const int32_t slot = cell >= 0 && cell < C ? cs[cell] : -1;
      if (slot == -1) continue;
      // a slot, head or count out of range is never used as an index: the pillar reports -1 points
      if (slot < 0 || slot >= M || !ps_queue_ok(hd[slot], ct[slot], N)) {
        np[p] = -1;
        continue;
      }
      const int64_t n = ct[slot], h = hd[slot];
      np[p] = static_cast<int32_t>(n);
      for (int64_t k = 0; k < n; ++k)
        std::memcpy(out + (p * N + k) * 4, pool + (slot * N + (h + k) % N) * 4, 4 * sizeof(float));
    }
  });
  return {raw, num_points};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> pillar_stream_push_cpu(
    at::Tensor& pool_xyzi, at::Tensor& pool_t, at::Tensor& head, at::Tensor& count, at::Tensor& slot_cell,
    at::Tensor& cell_slot, at::Tensor& free_slots, at::Tensor& num_free, at::Tensor& log_cell, at::Tensor& log_t,
    const at::Tensor& points_in, const at::Tensor& t_in, const at::Tensor& runs_in, int64_t log_head, double cutoff,
    at::ArrayRef<double> point_range, at::ArrayRef<double> pillar_size, at::IntArrayRef grid_hw) {
  const PillarStreamArgs a =
      check_pillar_stream_push_args(pool_xyzi, pool_t, head, count, slot_cell, cell_slot, free_slots, num_free,
                                    log_cell, log_t, points_in, t_in, runs_in, log_head, cutoff, point_range,
                                    pillar_size, grid_hw);
  const VoxelGrid<float> g = pillar_voxel_grid(point_range, pillar_size, a);
  auto points = points_in.contiguous();
  auto t = t_in.contiguous();
  auto runs = runs_in.contiguous();
  const int64_t n = points.size(0), R = runs.size(0), M = a.M, N = a.N, L = a.L;
  auto change_map = at::zeros({a.H, a.W}, points.options().dtype(at::kBool));
  auto stats = at::zeros({kNumPillarStreamStats}, points.options().dtype(at::kLong));
  auto run_pops = at::zeros({R}, points.options().dtype(at::kLong));
  int64_t* st = stats.data_ptr<int64_t>();

  float* pool = pool_xyzi.data_ptr<float>();
  double* pt = pool_t.data_ptr<double>();
  int32_t* hd = head.data_ptr<int32_t>();
  int32_t* ct = count.data_ptr<int32_t>();
  int32_t* sc = slot_cell.data_ptr<int32_t>();
  int32_t* cs = cell_slot.data_ptr<int32_t>();
  int32_t* fs = free_slots.data_ptr<int32_t>();
  int32_t* nf = num_free.data_ptr<int32_t>();
  int32_t* lc = log_cell.data_ptr<int32_t>();
  double* lt = log_t.data_ptr<double>();
  const float* p = points.data_ptr<float>();
  const double* tp = t.data_ptr<double>();
  const int64_t* rn = runs.data_ptr<int64_t>();
  int64_t* rp = run_pops.data_ptr<int64_t>();

  // ---- plan (reads the state only) ----
  // Every state value used as an index is checked here, before anything is written; a bad one is
  // skipped and reported in `bad` (kPsBad* bits), and the push then changes nothing. The CUDA plan
  // makes the same checks (csrc/cuda/pillar_stream_kernel.cu).
  const int64_t C = a.H * a.W;
  int64_t bad = 0;
  // Expiry: each run is sorted by t, so its expired entries are a prefix; one entry per point, so a
  // pillar loses as many points (its queue's first ones, the queue being sorted) as it has entries.
  std::vector<int32_t> pops(M, 0), gains(M, 0);
  std::vector<int32_t> touched;  // slots that lose points
  for (int64_t r = 0; r < R; ++r) {
    const int64_t start = rn[2 * r], end = rn[2 * r + 1];
    if (!(0 <= start && start <= end && end - start <= L)) {
      bad |= kPsBadRuns;
      continue;
    }
    int64_t lo = start, hi = end;  // first position with t > cutoff
    while (lo < hi) {
      const int64_t mid = lo + (hi - lo) / 2;
      if (lt[mid % L] <= cutoff) lo = mid + 1;
      else hi = mid;
    }
    rp[r] = lo - start;
    for (int64_t q = start; q < lo; ++q) {
      const int64_t cell = lc[q % L];
      const int32_t slot = cell >= 0 && cell < C ? cs[cell] : -1;
      if (slot == -1) {
        bad |= kPsBadLog;
        continue;
      }
      if (slot < 0 || slot >= M || sc[slot] != cell) {
        bad |= kPsBadCellSlot;
        continue;
      }
      if (pops[slot]++ == 0) touched.push_back(slot);
    }
  }
  // New points: pillar keys in parallel, then the entering ones sorted by (t, arrival) for the log
  // run and by (pillar, t, arrival) for the queues.
  std::vector<int64_t> keys(n);
  at::parallel_for(0, n, 4096, [&](int64_t s, int64_t e) {
    for (int64_t i = s; i < e; ++i) keys[i] = voxel_key(g, p[4 * i], p[4 * i + 1], p[4 * i + 2]);
  });
  std::vector<int64_t> order;
  order.reserve(n);
  for (int64_t i = 0; i < n; ++i) {
    if (keys[i] == kNoVoxel) ++st[kPsPointsOutside];
    else if (!(tp[i] > cutoff)) ++st[kPsPointsLate];
    else order.push_back(i);
  }
  std::stable_sort(order.begin(), order.end(), [&](int64_t i, int64_t j) { return tp[i] < tp[j]; });
  std::vector<int64_t> by_cell(order);
  std::stable_sort(by_cell.begin(), by_cell.end(), [&](int64_t i, int64_t j) { return keys[i] < keys[j]; });
  const int64_t n_in = static_cast<int64_t>(order.size());
  std::vector<int64_t> seg_begin;
  for (int64_t j = 0; j < n_in; ++j)
    if (j == 0 || keys[by_cell[j]] != keys[by_cell[j - 1]]) seg_begin.push_back(j);
  seg_begin.push_back(n_in);
  const int64_t S = static_cast<int64_t>(seg_begin.size()) - 1;
  int64_t max_after = 0, new_pillars = 0, emptied = 0;
  for (int64_t s = 0; s < S; ++s) {
    const int64_t k = seg_begin[s + 1] - seg_begin[s];
    const int64_t key = keys[by_cell[seg_begin[s]]];
    const int32_t slot = cs[key];
    int64_t after = k;
    if (slot == -1) {
      ++new_pillars;
    } else if (slot < 0 || slot >= M || sc[slot] != key) {
      bad |= kPsBadCellSlot;
      continue;
    } else if (!ps_queue_ok(hd[slot], ct[slot], N)) {
      bad |= kPsBadQueue;
      continue;
    } else {
      gains[slot] = static_cast<int32_t>(k);
      after += ct[slot] - pops[slot];
    }
    max_after = std::max(max_after, after);
  }
  for (const int32_t slot : touched) {
    if (!ps_queue_ok(hd[slot], ct[slot], N) || pops[slot] < 0 || pops[slot] > ct[slot]) {
      bad |= kPsBadQueue;
      continue;
    }
    if (pops[slot] == ct[slot] && gains[slot] == 0) ++emptied;
  }
  // The free stack: the frees push `emptied` slots, then the new pillars pop; the pops that reach
  // below the freed slots take old entries, which must be free slots.
  const int64_t nf0 = nf[0];
  if (nf0 < 0 || nf0 > M || nf0 + emptied > M) {
    bad |= kPsBadNumFree;
  } else {
    for (int64_t i = std::max<int64_t>(nf0 - (new_pillars - emptied), 0); i < nf0; ++i) {
      const int32_t slot = fs[i];
      if (slot < 0 || slot >= M || sc[slot] != -1) {
        bad |= kPsBadFreeSlots;
        break;
      }
    }
  }
  const int64_t active = M - nf0, active_after = active - emptied + new_pillars;
  st[kPsPointsIn] = n_in;
  st[kPsMaxPointsNeeded] = max_after;
  st[kPsPillarsNeeded] = active_after;
  st[kPsNewPillars] = new_pillars;
  st[kPsEmptied] = emptied;
  st[kPsTouchedSlots] = static_cast<int64_t>(touched.size());
  st[kPsSegments] = S;
  st[kPsOverflow] = bad | (max_after > N ? kPsOverflowPoints : 0) | (active_after > M ? kPsOverflowPillars : 0);
  if (st[kPsOverflow]) {
    run_pops.zero_();
    return {change_map, stats, run_pops};
  }

  // ---- apply ----
  bool* cm = change_map.data_ptr<bool>();
  int64_t points_out = 0;
  for (const int32_t slot : touched) {
    const int32_t k = pops[slot];
    points_out += k;
    hd[slot] = static_cast<int32_t>((hd[slot] + k) % N);
    ct[slot] -= k;
    const int32_t cell = sc[slot];
    cm[cell] = true;
    if (ct[slot] == 0 && gains[slot] == 0) {
      cs[cell] = -1;
      sc[slot] = -1;
      hd[slot] = 0;
      fs[nf[0]++] = slot;
    }
  }
  st[kPsPointsOut] = points_out;
  for (int64_t s = 0; s < S; ++s) {
    const int64_t b = seg_begin[s], k = seg_begin[s + 1] - b;
    const int64_t cell = keys[by_cell[b]];
    int32_t slot = cs[cell];
    if (slot < 0) {
      slot = fs[--nf[0]];
      cs[cell] = slot;
      sc[slot] = static_cast<int32_t>(cell);
      hd[slot] = 0;
      ct[slot] = 0;
    }
    cm[cell] = true;
    // Merge the k new points (sorted by t) into the sorted queue from the back: the queue's points
    // that are later than a new point move; ties keep the queue's (earlier arrived) points first.
    const int64_t h = hd[slot];
    float* qx = pool + slot * N * 4;
    double* qt = pt + slot * N;
    int64_t i = ct[slot] - 1, j = k - 1, w = ct[slot] + k - 1;
    while (j >= 0) {
      const int64_t src = by_cell[b + j];
      const int64_t wq = (h + w) % N;
      if (i >= 0 && qt[(h + i) % N] > tp[src]) {
        const int64_t iq = (h + i) % N;
        std::memcpy(qx + wq * 4, qx + iq * 4, 4 * sizeof(float));
        qt[wq] = qt[iq];
        --i;
      } else {
        std::memcpy(qx + wq * 4, p + src * 4, 4 * sizeof(float));
        qt[wq] = tp[src];
        --j;
      }
      --w;
    }
    ct[slot] += static_cast<int32_t>(k);
  }
  for (int64_t j = 0; j < n_in; ++j) {
    const int64_t q = (log_head + j) % L, i = order[j];
    lc[q] = static_cast<int32_t>(keys[i]);
    lt[q] = tp[i];
  }
  return {change_map, stats, run_pops};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("pillar_decorate", &pillar_decorate_cpu);
  m.impl("pillar_stream_gather", &pillar_stream_gather_cpu);
  m.impl("pillar_stream_push", &pillar_stream_push_cpu);
}

}  // namespace lidarops
