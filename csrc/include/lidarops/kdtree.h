// k-d tree for the CPU kNN (host code only; the CUDA kernels use the uniform grid of grid.h).
//
// Why a tree on CPU: the grid has one cell size per cloud, chosen from the mean density over the
// bounding box. A LiDAR sweep is dense near the sensor and sparse far away (over a ~140 m box), so
// most of its points sit in cells holding hundreds of points. A tree splits where the points are:
// every leaf holds 9-16 points whatever the local density.
//
// Structure: median splits on the widest axis of each node's bounding box, down to leaves of at
// most kKdLeaf points. Nodes are stored in preorder (left child = node + 1) with the tight bounding
// box of their points; the points are stored in tree order as separate x, y, z arrays, so a leaf is a
// short run of contiguous coordinates (the distance loop vectorizes). The tree's shape depends on
// the point count only, so each subtree's node range is known before it is built and the subtrees
// below the top levels are built in parallel.
//
// Candidates are kept as packed (dist2, index) keys (KdKey) in a sorted list of k, so the tie rule
// costs one integer comparison.
//
// Exactness: the search computes point distances exactly as the other paths (sqdist3, no FMA) and
// keeps the k smallest under the (dist2, index) order of closer(). A subtree is skipped only when the
// lower bound on its points' computed distances, its box distance computed in double minus the
// relative slack of bound_slack<T> and an absolute term below the smallest normal number, exceeds
// the current k-th distance strictly; points at a distance equal to the k-th are still visited (a
// lower index wins the tie). Non-finite points never enter a list (their distance is inf or NaN) and
// are left out of the tree. Results are therefore identical to brute force, ties included.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>

#include "lidarops/neighbors.h"

namespace lidarops {

constexpr int32_t kKdLeaf = 16;

template <typename T>
struct KdNode {
  T lo[3], hi[3];      // bounding box of the node's points
  int32_t begin, end;  // the node's points, [begin, end) in tree order
  int32_t right;       // right child (the left one is this node + 1), or -1 for a leaf
  T split;             // internal nodes: the left child's points have coordinate <= split on `axis`,
  int32_t axis;        // the right child's >= split
};

template <typename T>
struct KdTree {
  std::vector<KdNode<T>> nodes;  // preorder; empty when the cloud has no finite point
  std::vector<T> x, y, z;        // coordinates in tree order
  std::vector<int32_t> index;    // point index in the cloud, in tree order
};

// Number of nodes of the tree over n points (n >= 1).
inline int32_t kd_node_count(int64_t n) {
  if (n <= kKdLeaf) return 1;
  const int64_t a = n / 2, b = n - a;
  const int32_t ca = kd_node_count(a);
  return 1 + ca + (a == b ? ca : kd_node_count(b));
}

namespace detail {

template <typename T>
struct KdPoint {
  T c[3];
  int32_t i;
};

template <typename T>
struct KdTask {
  int64_t cloud;
  int32_t node, begin, end;
};

// Builds node `id` over pts[begin, end); below `depth` levels, hands the subtrees to `tasks`.
template <typename T>
void kd_build(KdNode<T>* nodes, KdPoint<T>* pts, int64_t cloud, int32_t id, int32_t begin, int32_t end, int depth,
              std::vector<KdTask<T>>* tasks) {
  KdNode<T>& nd = nodes[id];
  for (int a = 0; a < 3; ++a) {
    nd.lo[a] = pts[begin].c[a];
    nd.hi[a] = pts[begin].c[a];
  }
  for (int32_t i = begin + 1; i < end; ++i)
    for (int a = 0; a < 3; ++a) {
      nd.lo[a] = std::min(nd.lo[a], pts[i].c[a]);
      nd.hi[a] = std::max(nd.hi[a], pts[i].c[a]);
    }
  nd.begin = begin;
  nd.end = end;
  if (end - begin <= kKdLeaf) {
    nd.right = -1;
    return;
  }
  int axis = 0;
  for (int a = 1; a < 3; ++a)
    if (nd.hi[a] - nd.lo[a] > nd.hi[axis] - nd.lo[axis]) axis = a;
  const int32_t mid = begin + (end - begin) / 2;
  std::nth_element(pts + begin, pts + mid, pts + end,
                   [axis](const KdPoint<T>& u, const KdPoint<T>& v) { return u.c[axis] < v.c[axis]; });
  nd.right = id + 1 + kd_node_count(mid - begin);
  nd.split = pts[mid].c[axis];
  nd.axis = axis;
  if (depth == 0 && tasks != nullptr) {
    tasks->push_back({cloud, id + 1, begin, mid});
    tasks->push_back({cloud, nd.right, mid, end});
    return;
  }
  kd_build(nodes, pts, cloud, id + 1, begin, mid, depth - 1, tasks);
  kd_build(nodes, pts, cloud, nd.right, mid, end, depth - 1, tasks);
}

}  // namespace detail

// One tree per cloud over its first lengths[b] points (T: the computation dtype). Parallel over
// clouds, and over the subtrees below the top levels when there are fewer clouds than threads.
template <typename T, typename S>
std::vector<KdTree<T>> build_kd_trees(const S* points, int64_t B, int64_t N, const int64_t* lengths) {
  TORCH_CHECK_VALUE(N < std::numeric_limits<int32_t>::max(), "the k-d tree takes clouds of fewer than 2^31 points, got ",
                    N);
  using detail::KdPoint;
  using detail::KdTask;
  std::vector<KdTree<T>> trees(B);
  std::vector<std::vector<KdPoint<T>>> pts(B);
  std::vector<std::vector<KdTask<T>>> tasks(B);
  const int threads = at::get_num_threads();
  // Levels built before the rest is split into tasks: about 2 tasks per thread in all.
  int depth = 0;
  while ((B << depth) < 2 * threads && depth < 8) ++depth;
  at::parallel_for(0, B, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      const S* p = points + b * N * 3;
      auto& v = pts[b];
      v.reserve(lengths[b]);
      for (int64_t i = 0; i < lengths[b]; ++i) {
        const T x = static_cast<T>(p[3 * i]), y = static_cast<T>(p[3 * i + 1]), z = static_cast<T>(p[3 * i + 2]);
        if (std::isfinite(x) && std::isfinite(y) && std::isfinite(z))
          v.push_back({{x, y, z}, static_cast<int32_t>(i)});
      }
      const int32_t n = static_cast<int32_t>(v.size());
      if (n == 0) continue;
      trees[b].nodes.resize(kd_node_count(n));
      detail::kd_build(trees[b].nodes.data(), v.data(), b, 0, 0, n, depth - 1, depth > 0 ? &tasks[b] : nullptr);
    }
  });
  std::vector<KdTask<T>> all;
  for (auto& t : tasks) all.insert(all.end(), t.begin(), t.end());
  at::parallel_for(0, static_cast<int64_t>(all.size()), 1, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      const KdTask<T>& w = all[t];
      detail::kd_build(trees[w.cloud].nodes.data(), pts[w.cloud].data(), w.cloud, w.node, w.begin, w.end, -1,
                       static_cast<std::vector<KdTask<T>>*>(nullptr));
    }
  });
  at::parallel_for(0, B, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      const auto& v = pts[b];
      KdTree<T>& tr = trees[b];
      const size_t n = v.size();
      tr.x.resize(n);
      tr.y.resize(n);
      tr.z.resize(n);
      tr.index.resize(n);
      for (size_t i = 0; i < n; ++i) {
        tr.x[i] = v[i].c[0];
        tr.y[i] = v[i].c[1];
        tr.z[i] = v[i].c[2];
        tr.index[i] = v[i].i;
      }
    }
  });
  return trees;
}

// (dist2, index) of a candidate packed into one integer whose order is the (dist2, index) order of
// closer(): dist2 >= +0 here (a sum of squares), so its IEEE bits order like the value.
template <typename T>
struct KdKey;
template <>
struct KdKey<float> {
  uint64_t v;
  static KdKey make(float d, int32_t i) {
    uint32_t b;
    std::memcpy(&b, &d, 4);
    return {(static_cast<uint64_t>(b) << 32) | static_cast<uint32_t>(i)};
  }
  static KdKey none() { return {~uint64_t(0)}; }
  bool operator<(const KdKey& o) const { return v < o.v; }
  bool is_none() const { return v == ~uint64_t(0); }
  float dist() const {
    const uint32_t b = static_cast<uint32_t>(v >> 32);
    float d;
    std::memcpy(&d, &b, 4);
    return d;
  }
  int32_t index() const { return static_cast<int32_t>(static_cast<uint32_t>(v)); }
};
template <>
struct KdKey<double> {
  uint64_t d;
  uint32_t i;
  static KdKey make(double dd, int32_t ii) {
    KdKey k;
    std::memcpy(&k.d, &dd, 8);
    k.i = static_cast<uint32_t>(ii);
    return k;
  }
  static KdKey none() { return {~uint64_t(0), ~uint32_t(0)}; }
  bool operator<(const KdKey& o) const { return d < o.d || (d == o.d && i < o.i); }
  bool is_none() const { return d == ~uint64_t(0) && i == ~uint32_t(0); }
  double dist() const {
    double v;
    std::memcpy(&v, &d, 8);
    return v;
  }
  int32_t index() const { return static_cast<int32_t>(i); }
};

// Exact kNN of one query: depth-first, nearer child first, skipping subtrees that cannot hold a
// point closer than the current k-th (see the header comment for the bound). The near child is
// chosen by the splitting plane; a pending far child carries the plane's distance as a cheap bound
// and is tested against its box when popped. keys: k entries preceded by a sentinel keys[-1] =
// KdKey<T>{} (the smallest key), filled with KdKey<T>::none() by the caller; on return the k
// nearest, ascending, then none().
template <typename T>
void knn_tree_search(const KdTree<T>& tree, T qx, T qy, T qz, int64_t k, KdKey<T>* keys) {
  if (tree.nodes.empty()) return;
  const KdNode<T>* nodes = tree.nodes.data();
  const double slack = 1.0 - bound_slack<T>();
  const double tiny = std::is_same_v<T, double> ? 1e-300 : 1e-36;
  const double q[3] = {static_cast<double>(qx), static_cast<double>(qy), static_cast<double>(qz)};
  // Lower bound on the computed dist2 of a node's points (NaN for a NaN query: never skipped).
  auto bound = [&](const KdNode<T>& nd) {
    double s = 0.0;
    for (int a = 0; a < 3; ++a) {
      const double u = static_cast<double>(nd.lo[a]) - q[a], v = q[a] - static_cast<double>(nd.hi[a]);
      const double g = 0.5 * ((std::fabs(u) + u) + (std::fabs(v) + v));  // max(u, v, 0): u, v not both > 0
      s += g * g;
    }
    return s * slack - tiny;
  };
  const T* X = tree.x.data();
  const T* Y = tree.y.data();
  const T* Z = tree.z.data();
  const int32_t* index = tree.index.data();
  struct Pending {
    int32_t node;
    double bound;
  };
  Pending stack[64];  // depth < 32 for n < 2^31, at most one pending sibling per level
  int sp = 0;
  int32_t node = 0;
  // Candidates need dist2 <= limit: the k-th distance once the list is full, before that the
  // largest finite value (an infinite or NaN distance never enters a list, as in closer()).
  T limit = std::numeric_limits<T>::max();
  T d[kKdLeaf];
  for (;;) {
    const KdNode<T>& nd = nodes[node];
    bool descend = false;
    if (nd.right < 0) {
      const int32_t b = nd.begin, n = nd.end - nd.begin;
      for (int32_t j = 0; j < n; ++j) d[j] = sqdist3<T>(X[b + j], Y[b + j], Z[b + j], qx, qy, qz);
      for (int32_t j = 0; j < n; ++j)
        if (d[j] <= limit) {
          const KdKey<T> key = KdKey<T>::make(d[j], index[b + j]);
          if (!(key < keys[k - 1])) continue;
          int64_t p = k - 1;
          while (key < keys[p - 1]) {  // keys[-1] is the smallest key: a sentinel
            keys[p] = keys[p - 1];
            --p;
          }
          keys[p] = key;
          if (!keys[k - 1].is_none()) limit = keys[k - 1].dist();
        }
    } else {
      const double gap = q[nd.axis] - static_cast<double>(nd.split);
      int32_t near = node + 1, far = nd.right;
      if (gap >= 0.0) std::swap(near, far);
      const double bf = gap * gap * slack - tiny;  // far side of the splitting plane
      const double lim = static_cast<double>(limit);
      if (!(bf > lim)) stack[sp++] = {far, bf};
      node = near;
      descend = limit == std::numeric_limits<T>::max() || !(bound(nodes[near]) > lim);
    }
    if (descend) continue;
    for (;;) {
      if (sp == 0) return;
      const Pending& e = stack[--sp];
      if (!(e.bound > static_cast<double>(limit)) && !(bound(nodes[e.node]) > static_cast<double>(limit))) {
        node = e.node;
        break;
      }
    }
  }
}

}  // namespace lidarops
