// Exact farthest point sampling on CPU.
//
// The cloud is split into leaves of at most kLeaf points by a k-d partition; each leaf keeps its
// bounding box and the largest distance-to-selected-set among its points. When a point is
// selected, a leaf whose box lies at least that far from the new point cannot change and is
// skipped (the box bound is computed with the same rounded arithmetic as the distances, so it is
// a true lower bound). The selection is identical to the plain O(N K) loop, ties to the lowest
// index, and costs O(N/kLeaf) per step plus the leaves that really change. Parallel over clouds.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>

#include <algorithm>
#include <numeric>
#include <vector>

#include "lidarops/neighbors.h"

namespace lidarops {
namespace {

constexpr int64_t kLeaf = 64;

template <typename T>
struct Leaf {
  int64_t begin, end;
  T lo[3], hi[3];
  T maxd;        // largest dist among unselected points (-1 if none left)
  int64_t best;  // original index of that point, lowest index among ties
};

// Lower bound of sqdist3(x, p) over x in the box, with the rounding sqdist3 applies.
template <typename T>
inline T box_sqdist(const Leaf<T>& L, const T* p) {
  T g[3];
  for (int a = 0; a < 3; ++a) g[a] = p[a] < L.lo[a] ? sub_rn(L.lo[a], p[a]) : (p[a] > L.hi[a] ? sub_rn(p[a], L.hi[a]) : T(0));
  return add_rn(add_rn(mul_rn(g[0], g[0]), mul_rn(g[1], g[1])), mul_rn(g[2], g[2]));
}

template <typename T>
void refresh_max(Leaf<T>& L, const T* dist, const int64_t* orig) {
  T m = T(-1);
  int64_t best = -1;
  for (int64_t i = L.begin; i < L.end; ++i) {
    if (dist[i] > m || (dist[i] == m && dist[i] >= 0 && orig[i] < best)) {
      m = dist[i];
      best = orig[i];
    }
  }
  L.maxd = m;
  L.best = best;
}

template <typename scalar_t>
void fps_cloud(const scalar_t* pts, int64_t n, int64_t k, int64_t start, int64_t* out, bool use_leaves) {
  using T = acc_t<scalar_t>;
  std::fill(out, out + k, -1);
  if (n == 0 || start < 0 || start >= n) return;  // fps_cpu rejects such starts; never index out of range
  const int64_t leaf_size = use_leaves ? kLeaf : n;
  std::vector<int64_t> perm(n);
  std::iota(perm.begin(), perm.end(), 0);
  std::vector<Leaf<T>> leaves;
  // k-d partition: split the widest axis at the median until leaves are small.
  std::vector<std::pair<int64_t, int64_t>> stack{{0, n}};
  while (!stack.empty()) {
    auto [b, e] = stack.back();
    stack.pop_back();
    Leaf<T> L{b, e, {}, {}, std::numeric_limits<T>::infinity(), -1};
    for (int a = 0; a < 3; ++a) {
      L.lo[a] = std::numeric_limits<T>::infinity();
      L.hi[a] = -std::numeric_limits<T>::infinity();
    }
    for (int64_t i = b; i < e; ++i)
      for (int a = 0; a < 3; ++a) {
        const T v = static_cast<T>(pts[3 * perm[i] + a]);
        L.lo[a] = std::min(L.lo[a], v);
        L.hi[a] = std::max(L.hi[a], v);
      }
    if (e - b <= leaf_size) {
      leaves.push_back(L);
      continue;
    }
    int axis = 0;
    for (int a = 1; a < 3; ++a)
      if (L.hi[a] - L.lo[a] > L.hi[axis] - L.lo[axis]) axis = a;
    const int64_t mid = b + (e - b) / 2;
    std::nth_element(perm.begin() + b, perm.begin() + mid, perm.begin() + e, [&](int64_t u, int64_t v) {
      const T pu = static_cast<T>(pts[3 * u + axis]), pv = static_cast<T>(pts[3 * v + axis]);
      return pu < pv || (pu == pv && u < v);
    });
    stack.push_back({mid, e});
    stack.push_back({b, mid});
  }
  std::vector<T> xyz(3 * n), dist(n, std::numeric_limits<T>::infinity());
  std::vector<int64_t> pos(n);
  for (int64_t i = 0; i < n; ++i) {
    for (int a = 0; a < 3; ++a) xyz[3 * i + a] = static_cast<T>(pts[3 * perm[i] + a]);
    pos[perm[i]] = i;
  }
  std::vector<int64_t> leaf_of(n);
  for (int64_t l = 0; l < static_cast<int64_t>(leaves.size()); ++l)
    for (int64_t i = leaves[l].begin; i < leaves[l].end; ++i) leaf_of[i] = l;

  int64_t sel = start;
  const int64_t steps = std::min(k, n);
  for (int64_t s = 0; s < steps; ++s) {
    out[s] = sel;
    const int64_t ps = pos[sel];
    dist[ps] = T(-1);  // selected: never again the farthest (real distances are >= 0)
    refresh_max(leaves[leaf_of[ps]], dist.data(), perm.data());
    if (s + 1 == steps) break;
    const T p[3] = {xyz[3 * ps], xyz[3 * ps + 1], xyz[3 * ps + 2]};
    T bestd = T(-1);
    int64_t besti = -1;
    for (auto& L : leaves) {
      if (L.maxd >= 0 && box_sqdist(L, p) < L.maxd) {
        bool changed = false;
        for (int64_t i = L.begin; i < L.end; ++i) {
          if (dist[i] < 0) continue;
          const T d = sqdist3<T>(xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2], p[0], p[1], p[2]);
          if (d < dist[i]) {
            dist[i] = d;
            changed = true;
          }
        }
        if (changed) refresh_max(L, dist.data(), perm.data());
      }
      if (L.maxd > bestd || (L.maxd == bestd && L.maxd >= 0 && L.best < besti)) {
        bestd = L.maxd;
        besti = L.best;
      }
    }
    if (besti < 0) break;  // only NaN distances left (value checks off): leave the rest -1
    sel = besti;
  }
}

at::Tensor fps_cpu(const at::Tensor& points_in, const at::Tensor& lengths_in, const at::Tensor& start_in,
                   int64_t k, int64_t method) {
  check_cloud(points_in, "points");
  check_lengths(lengths_in, points_in, "lengths");
  check_lengths(start_in, points_in, "start_idx");
  TORCH_CHECK_VALUE(k > 0, "k must be positive, got ", k);
  TORCH_CHECK_VALUE(method >= 0 && method <= 2, "method must be 0 (auto), 1 (plain loop) or 2 (leaves), got ", method);
  auto points = points_in.contiguous();
  auto lengths = lengths_in.contiguous();
  auto start = start_in.contiguous();
  const int64_t B = points.size(0), N = points.size(1);
  check_lengths_values_cpu(lengths, N, "lengths");
  const int64_t* len = lengths.data_ptr<int64_t>();
  const int64_t* st = start.data_ptr<int64_t>();
  for (int64_t b = 0; b < B; ++b)
    TORCH_CHECK_VALUE(len[b] == 0 || (st[b] >= 0 && st[b] < len[b]), "start_idx[", b, "] = ", st[b],
                      " is outside [0, lengths[", b, "] = ", len[b], ")");
  auto out = at::empty({B, k}, points.options().dtype(at::kLong));
  const bool leaves = method != 1;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, points.scalar_type(), "lidarops_fps_cpu", [&] {
    const scalar_t* p = points.data_ptr<scalar_t>();
    int64_t* o = out.data_ptr<int64_t>();
    at::parallel_for(0, B, std::max<int64_t>(1, 262144 / std::max<int64_t>(N * k, 1)), [&](int64_t b0, int64_t b1) {
      for (int64_t b = b0; b < b1; ++b) fps_cloud(p + b * N * 3, len[b], k, st[b], o + b * k, leaves);
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) { m.impl("fps", &fps_cpu); }

}  // namespace lidarops
