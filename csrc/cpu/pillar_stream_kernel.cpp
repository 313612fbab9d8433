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

// ------------------------------------------------------------------------------------------- pillar_stream_push
// The stream's state tensors (lidarops/pillar_stream.h), as pointers; sizes M slots, N points per
// pillar, L log entries, C grid cells.
struct StreamState {
  float* pool;
  double* pool_t;
  int32_t *head, *count, *slot_cell, *cell_slot, *free_slots, *num_free, *log_cell;
  double* log_t;
  int64_t M, N, L, C;
};

// What the plan decides and the apply phase writes.
struct PushPlan {
  int64_t bad = 0;                   // kPsBad* bits: a state value that cannot be used as an index
  std::vector<int32_t> pops, gains;  // per slot: points expiring, points entering
  std::vector<int32_t> touched;      // slots that lose points
  std::vector<int64_t> keys;         // per new point: its pillar (cell), or kNoVoxel
  std::vector<int64_t> order;        // entering points by (t, arrival): the log run
  std::vector<int64_t> by_cell;      // entering points by (pillar, t, arrival): the queues
  std::vector<int64_t> seg_begin;    // segments of by_cell, one per pillar, and the end
};

// Plan, expiry: each run is sorted by t, so its expired entries are a prefix; one entry per point, so a
// pillar loses as many points (its queue's first ones, the queue being sorted) as it has entries.
// Writes each run's expired count to ``run_pops``.
void plan_expiry(const StreamState& s, const int64_t* rn, int64_t R, double cutoff, int64_t* run_pops, PushPlan& plan) {
  for (int64_t r = 0; r < R; ++r) {
    const int64_t start = rn[2 * r], end = rn[2 * r + 1];
    if (!(0 <= start && start <= end && end - start <= s.L)) {
      plan.bad |= kPsBadRuns;
      continue;
    }
    int64_t lo = start, hi = end;  // first position with t > cutoff
    while (lo < hi) {
      const int64_t mid = lo + (hi - lo) / 2;
      if (s.log_t[mid % s.L] <= cutoff) lo = mid + 1;
      else hi = mid;
    }
    run_pops[r] = lo - start;
    for (int64_t q = start; q < lo; ++q) {
      const int64_t cell = s.log_cell[q % s.L];
      const int32_t slot = cell >= 0 && cell < s.C ? s.cell_slot[cell] : -1;
      if (slot == -1) {
        plan.bad |= kPsBadLog;
        continue;
      }
      if (slot < 0 || slot >= s.M || s.slot_cell[slot] != cell) {
        plan.bad |= kPsBadCellSlot;
        continue;
      }
      if (plan.pops[slot]++ == 0) plan.touched.push_back(slot);
    }
  }
}

// Plan, new points: pillar keys in parallel, then the entering ones sorted by (t, arrival) for the log
// run and by (pillar, t, arrival) for the queues, cut into one segment per pillar.
void plan_new_points(const VoxelGrid<float>& g, const float* p, const double* tp, int64_t n, double cutoff, int64_t* st,
                     PushPlan& plan) {
  std::vector<int64_t>& keys = plan.keys;
  keys.resize(n);
  at::parallel_for(0, n, 4096, [&](int64_t s, int64_t e) {
    for (int64_t i = s; i < e; ++i) keys[i] = voxel_key(g, p[4 * i], p[4 * i + 1], p[4 * i + 2]);
  });
  plan.order.reserve(n);
  for (int64_t i = 0; i < n; ++i) {
    if (keys[i] == kNoVoxel) ++st[kPsPointsOutside];
    else if (!(tp[i] > cutoff)) ++st[kPsPointsLate];
    else plan.order.push_back(i);
  }
  std::stable_sort(plan.order.begin(), plan.order.end(), [&](int64_t i, int64_t j) { return tp[i] < tp[j]; });
  plan.by_cell = plan.order;
  std::stable_sort(plan.by_cell.begin(), plan.by_cell.end(), [&](int64_t i, int64_t j) { return keys[i] < keys[j]; });
  const int64_t n_in = static_cast<int64_t>(plan.order.size());
  for (int64_t j = 0; j < n_in; ++j)
    if (j == 0 || keys[plan.by_cell[j]] != keys[plan.by_cell[j - 1]]) plan.seg_begin.push_back(j);
  plan.seg_begin.push_back(n_in);
}

// Plan, drop mode: the overflow rule (lidarops/stream/pillar_stream.py) keeps the entering points that
// fit. Points in the window stay; a pillar's entering points are admitted in (t, arrival) order (their
// segment's order) while its queue has room; a pillar that keeps no point is new and needs a free slot:
// the slots free after the expiry go to the new pillars in key order (the segments' order). The plan's
// entering points become the admitted ones. State values are only bounds-guarded here: plan_capacity
// checks them and a bad one makes the push change nothing.
void plan_drops(const StreamState& s, PushPlan& plan, int64_t* st) {
  const int32_t *ct = s.count, *cs = s.cell_slot;
  int64_t fully_expired = 0;  // touched pillars that keep no point
  for (const int32_t slot : plan.touched)
    if (plan.pops[slot] >= ct[slot]) ++fully_expired;
  int64_t free = s.num_free[0] + fully_expired;  // M minus the pillars that keep points
  const int64_t S = static_cast<int64_t>(plan.seg_begin.size()) - 1, n = static_cast<int64_t>(plan.keys.size());
  std::vector<char> admitted(n, 0);
  std::vector<int64_t> by_cell, seg_begin;
  by_cell.reserve(plan.by_cell.size());
  for (int64_t seg = 0; seg < S; ++seg) {
    const int64_t b = plan.seg_begin[seg], k = plan.seg_begin[seg + 1] - b;
    const int32_t slot = cs[plan.keys[plan.by_cell[b]]];
    const int64_t has = slot >= 0 && slot < s.M ? std::clamp<int64_t>(ct[slot] - plan.pops[slot], 0, s.N) : 0;
    int64_t keep = std::min(k, s.N - has);
    if (has == 0 && free == 0) {
      keep = 0;
      st[kPsDroppedPillars] += k;
    } else {
      free -= has == 0;
      st[kPsDroppedPoints] += k - keep;
    }
    if (keep == 0) continue;
    seg_begin.push_back(static_cast<int64_t>(by_cell.size()));
    for (int64_t q = 0; q < keep; ++q) {
      admitted[plan.by_cell[b + q]] = 1;
      by_cell.push_back(plan.by_cell[b + q]);
    }
  }
  seg_begin.push_back(static_cast<int64_t>(by_cell.size()));
  plan.by_cell = std::move(by_cell);
  plan.seg_begin = std::move(seg_begin);
  plan.order.erase(std::remove_if(plan.order.begin(), plan.order.end(), [&](int64_t i) { return !admitted[i]; }),
                   plan.order.end());
}

// Plan, capacity: the points each pillar holds after the push, the pillars that empty and the new ones,
// the free stack's entries the new pillars will take; fills the stats and their overflow bits. Returns
// whether the push must change nothing (overflow or a bad state value).
bool plan_capacity(const StreamState& s, PushPlan& plan, int64_t* st) {
  const int32_t *hd = s.head, *ct = s.count, *sc = s.slot_cell, *cs = s.cell_slot, *fs = s.free_slots;
  const int64_t M = s.M, N = s.N;
  const int64_t S = static_cast<int64_t>(plan.seg_begin.size()) - 1;
  int64_t max_after = 0, new_pillars = 0, emptied = 0;
  for (int64_t seg = 0; seg < S; ++seg) {
    const int64_t k = plan.seg_begin[seg + 1] - plan.seg_begin[seg];
    const int64_t key = plan.keys[plan.by_cell[plan.seg_begin[seg]]];
    const int32_t slot = cs[key];
    int64_t after = k;
    if (slot == -1) {
      ++new_pillars;
    } else if (slot < 0 || slot >= M || sc[slot] != key) {
      plan.bad |= kPsBadCellSlot;
      continue;
    } else if (!ps_queue_ok(hd[slot], ct[slot], N)) {
      plan.bad |= kPsBadQueue;
      continue;
    } else {
      plan.gains[slot] = static_cast<int32_t>(k);
      after += ct[slot] - plan.pops[slot];
    }
    max_after = std::max(max_after, after);
  }
  for (const int32_t slot : plan.touched) {
    if (!ps_queue_ok(hd[slot], ct[slot], N) || plan.pops[slot] < 0 || plan.pops[slot] > ct[slot]) {
      plan.bad |= kPsBadQueue;
      continue;
    }
    if (plan.pops[slot] == ct[slot] && plan.gains[slot] == 0) ++emptied;
  }
  // The free stack: the frees push `emptied` slots, then the new pillars pop; the pops that reach
  // below the freed slots take old entries, which must be free slots.
  const int64_t nf0 = s.num_free[0];
  if (nf0 < 0 || nf0 > M || nf0 + emptied > M) {
    plan.bad |= kPsBadNumFree;
  } else {
    for (int64_t i = std::max<int64_t>(nf0 - (new_pillars - emptied), 0); i < nf0; ++i) {
      const int32_t slot = fs[i];
      if (slot < 0 || slot >= M || sc[slot] != -1) {
        plan.bad |= kPsBadFreeSlots;
        break;
      }
    }
  }
  const int64_t active = M - nf0, active_after = active - emptied + new_pillars;
  st[kPsPointsIn] = static_cast<int64_t>(plan.order.size());
  st[kPsMaxPointsNeeded] = max_after;
  st[kPsPillarsNeeded] = active_after;
  st[kPsNewPillars] = new_pillars;
  st[kPsEmptied] = emptied;
  st[kPsTouchedSlots] = static_cast<int64_t>(plan.touched.size());
  st[kPsSegments] = S;
  st[kPsOverflow] = plan.bad | (max_after > N ? kPsOverflowPoints : 0) | (active_after > M ? kPsOverflowPillars : 0);
  return st[kPsOverflow] != 0;
}

// Apply, expiry: the touched queues drop their first points; a pillar left empty with nothing entering
// frees its slot. Returns the points removed.
int64_t apply_expiry(StreamState& s, const PushPlan& plan, bool* cm) {
  int64_t points_out = 0;
  for (const int32_t slot : plan.touched) {
    const int32_t k = plan.pops[slot];
    points_out += k;
    s.head[slot] = static_cast<int32_t>((s.head[slot] + k) % s.N);
    s.count[slot] -= k;
    const int32_t cell = s.slot_cell[slot];
    cm[cell] = true;
    if (s.count[slot] == 0 && plan.gains[slot] == 0) {
      s.cell_slot[cell] = -1;
      s.slot_cell[slot] = -1;
      s.head[slot] = 0;
      s.free_slots[s.num_free[0]++] = slot;
    }
  }
  return points_out;
}

// Merges the k new points src[0..k) (sorted by t) into the sorted queue of ``slot`` from the back: the
// queue's points that are later than a new point move; ties keep the queue's (earlier arrived) points first.
void merge_into_queue(StreamState& s, int32_t slot, const int64_t* src, int64_t k, const float* p, const double* tp) {
  const int64_t N = s.N, h = s.head[slot];
  float* qx = s.pool + slot * N * 4;
  double* qt = s.pool_t + slot * N;
  int64_t i = s.count[slot] - 1, j = k - 1, w = s.count[slot] + k - 1;
  while (j >= 0) {
    const int64_t from = src[j];
    const int64_t wq = (h + w) % N;
    if (i >= 0 && qt[(h + i) % N] > tp[from]) {
      const int64_t iq = (h + i) % N;
      std::memcpy(qx + wq * 4, qx + iq * 4, 4 * sizeof(float));
      qt[wq] = qt[iq];
      --i;
    } else {
      std::memcpy(qx + wq * 4, p + from * 4, 4 * sizeof(float));
      qt[wq] = tp[from];
      --j;
    }
    --w;
  }
  s.count[slot] += static_cast<int32_t>(k);
}

// Apply, new points: each pillar's segment enters its queue (a new pillar takes a slot off the free stack).
void apply_new_points(StreamState& s, const PushPlan& plan, const float* p, const double* tp, bool* cm) {
  const int64_t S = static_cast<int64_t>(plan.seg_begin.size()) - 1;
  for (int64_t seg = 0; seg < S; ++seg) {
    const int64_t b = plan.seg_begin[seg], k = plan.seg_begin[seg + 1] - b;
    const int64_t cell = plan.keys[plan.by_cell[b]];
    int32_t slot = s.cell_slot[cell];
    if (slot < 0) {
      slot = s.free_slots[--s.num_free[0]];
      s.cell_slot[cell] = slot;
      s.slot_cell[slot] = static_cast<int32_t>(cell);
      s.head[slot] = 0;
      s.count[slot] = 0;
    }
    cm[cell] = true;
    merge_into_queue(s, slot, plan.by_cell.data() + b, k, p, tp);
  }
}

// Apply, log: the entering points' (pillar, t) in arrival-time order, from ``log_head``.
void append_log(StreamState& s, const PushPlan& plan, const double* tp, int64_t log_head) {
  const int64_t n_in = static_cast<int64_t>(plan.order.size());
  for (int64_t j = 0; j < n_in; ++j) {
    const int64_t q = (log_head + j) % s.L, i = plan.order[j];
    s.log_cell[q] = static_cast<int32_t>(plan.keys[i]);
    s.log_t[q] = tp[i];
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> pillar_stream_push_cpu(
    at::Tensor& pool_xyzi, at::Tensor& pool_t, at::Tensor& head, at::Tensor& count, at::Tensor& slot_cell,
    at::Tensor& cell_slot, at::Tensor& free_slots, at::Tensor& num_free, at::Tensor& log_cell, at::Tensor& log_t,
    const at::Tensor& points_in, const at::Tensor& t_in, const at::Tensor& runs_in, int64_t log_head, double cutoff,
    at::ArrayRef<double> point_range, at::ArrayRef<double> pillar_size, at::IntArrayRef grid_hw, bool drop,
    const c10::optional<at::Tensor>& scalars) {
  bool bad_scalars = false;  // state values, as the CUDA kernels read them: reported, not raised
  if (scalars.has_value()) {
    check_pillar_stream_scalars(*scalars, pool_xyzi);
    const auto sc = scalars->contiguous();
    log_head = sc.data_ptr<int64_t>()[0];
    std::memcpy(&cutoff, sc.data_ptr<int64_t>() + 1, sizeof(double));
    bad_scalars = !(log_head >= 0 && log_head < kPsMaxLogHead) || std::isnan(cutoff);
    if (bad_scalars) log_head = 0, cutoff = 0.0;
  }
  const PillarStreamArgs a =
      check_pillar_stream_push_args(pool_xyzi, pool_t, head, count, slot_cell, cell_slot, free_slots, num_free,
                                    log_cell, log_t, points_in, t_in, runs_in, log_head, cutoff, point_range,
                                    pillar_size, grid_hw);
  const VoxelGrid<float> g = pillar_voxel_grid(point_range, pillar_size, a);
  auto points = points_in.contiguous();
  auto t = t_in.contiguous();
  auto runs = runs_in.contiguous();
  const int64_t n = points.size(0), R = runs.size(0);
  auto change_map = at::zeros({a.H, a.W}, points.options().dtype(at::kBool));
  auto stats = at::zeros({kNumPillarStreamStats}, points.options().dtype(at::kLong));
  auto run_pops = at::zeros({R}, points.options().dtype(at::kLong));
  int64_t* st = stats.data_ptr<int64_t>();
  if (bad_scalars) {
    st[kPsOverflow] = kPsBadLog;
    return {change_map, stats, run_pops};
  }
  StreamState s{pool_xyzi.data_ptr<float>(),
                pool_t.data_ptr<double>(),
                head.data_ptr<int32_t>(),
                count.data_ptr<int32_t>(),
                slot_cell.data_ptr<int32_t>(),
                cell_slot.data_ptr<int32_t>(),
                free_slots.data_ptr<int32_t>(),
                num_free.data_ptr<int32_t>(),
                log_cell.data_ptr<int32_t>(),
                log_t.data_ptr<double>(),
                a.M, a.N, a.L, a.H * a.W};
  const float* p = points.data_ptr<float>();
  const double* tp = t.data_ptr<double>();

  // Plan (reads the state only). Every state value used as an index is checked before anything is
  // written; a bad one is skipped and reported (kPsBad* bits), and the push then changes nothing. The
  // CUDA plan makes the same checks (csrc/cuda/pillar_stream_kernel.cu).
  PushPlan plan;
  plan.pops.assign(s.M, 0);
  plan.gains.assign(s.M, 0);
  plan_expiry(s, runs.data_ptr<int64_t>(), R, cutoff, run_pops.data_ptr<int64_t>(), plan);
  plan_new_points(g, p, tp, n, cutoff, st, plan);
  if (drop) plan_drops(s, plan, st);
  if (plan_capacity(s, plan, st)) {
    run_pops.zero_();
    return {change_map, stats, run_pops};
  }

  // Apply
  bool* cm = change_map.data_ptr<bool>();
  st[kPsPointsOut] = apply_expiry(s, plan, cm);
  apply_new_points(s, plan, p, tp, cm);
  append_log(s, plan, tp, log_head);
  return {change_map, stats, run_pops};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("pillar_decorate", &pillar_decorate_cpu);
  m.impl("pillar_stream_gather", &pillar_stream_gather_cpu);
  m.impl("pillar_stream_push", &pillar_stream_push_cpu);
}

}  // namespace lidarops
