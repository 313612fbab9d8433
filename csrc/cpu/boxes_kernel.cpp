// Rotated-box ops on CPU: pairwise BEV overlap / IoU and 3D IoU, rotated NMS, points in boxes.
// The geometry (include/lidarops/boxes.h) is shared with the CUDA kernels, bit for bit.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/from_blob.h>
#include <ATen/ops/full.h>
#include <ATen/ops/isfinite.h>
#include <ATen/ops/zeros.h>

#include <algorithm>
#include <numeric>
#include <tuple>
#include <vector>

#include "lidarops/boxes.h"

namespace lidarops {
namespace {

using boxes::BoxGeom;


std::vector<BoxGeom> geoms_of(const at::Tensor& b_in) {
  auto b = b_in.contiguous();
  std::vector<BoxGeom> out(static_cast<size_t>(b.size(0)));
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, b.scalar_type(), "lidarops_box_geoms", [&] {
    const scalar_t* p = b.data_ptr<scalar_t>();
    at::parallel_for(0, b.size(0), 4096, [&](int64_t s, int64_t e) {
      for (int64_t i = s; i < e; ++i) out[i] = boxes::make_geom(p + 7 * i);
    });
  });
  return out;
}

at::ScalarType out_dtype(const at::Tensor& t) { return t.scalar_type() == at::kDouble ? at::kDouble : at::kFloat; }

at::Tensor pairwise_cpu(const at::Tensor& a, const at::Tensor& b, int mode) {
  boxes::check_pair_args(a, b);
  const int64_t N = a.size(0), M = b.size(0);
  auto out = at::empty({N, M}, a.options().dtype(out_dtype(a)));
  if (out.numel() == 0) return out;
  const auto ga = geoms_of(a), gb = geoms_of(b);
  AT_DISPATCH_FLOATING_TYPES(out.scalar_type(), "lidarops_box_pairwise", [&] {
    scalar_t* o = out.data_ptr<scalar_t>();
    at::parallel_for(0, N, std::max<int64_t>(1, 65536 / M), [&](int64_t s, int64_t e) {
      for (int64_t i = s; i < e; ++i)
        for (int64_t j = 0; j < M; ++j) o[i * M + j] = static_cast<scalar_t>(boxes::pair_value(ga[i], gb[j], mode));
    });
  });
  return out;
}

at::Tensor box_overlap_bev_cpu(const at::Tensor& a, const at::Tensor& b) { return pairwise_cpu(a, b, 0); }
at::Tensor box_iou_bev_cpu(const at::Tensor& a, const at::Tensor& b) { return pairwise_cpu(a, b, 1); }
at::Tensor box_iou_3d_cpu(const at::Tensor& a, const at::Tensor& b) { return pairwise_cpu(a, b, 2); }

// Descending score, then ascending index; -0.0 and 0.0 compare equal; NaN last (as the CUDA sort).
std::vector<int64_t> score_order(const at::Tensor& scores) {
  const double* sc = scores.data_ptr<double>();
  std::vector<int64_t> order(static_cast<size_t>(scores.numel()));
  std::iota(order.begin(), order.end(), int64_t{0});
  std::stable_sort(order.begin(), order.end(), [sc](int64_t i, int64_t j) {
    return sc[i] > sc[j] || (std::isnan(sc[j]) && !std::isnan(sc[i]));
  });
  return order;
}

// Greedy NMS over the first n boxes of `order`: the kept entries of `order`, at most max_keep.
std::vector<int64_t> greedy_nms(const at::Tensor& boxes_in, const std::vector<int64_t>& order, int64_t n,
                                const c10::optional<at::Tensor>& idxs, bool grouped, double iou_threshold,
                                int64_t max_keep) {
  std::vector<int64_t> keep;
  if (n == 0 || max_keep == 0) return keep;
  auto sorted_boxes = boxes_in.index_select(0, at::from_blob(const_cast<int64_t*>(order.data()), {n}, at::kLong));
  const auto g = geoms_of(sorted_boxes);
  std::vector<int64_t> group(static_cast<size_t>(n), 0);
  if (grouped) {
    auto id = idxs->contiguous();
    const int64_t* ip = id.data_ptr<int64_t>();
    for (int64_t p = 0; p < n; ++p) group[p] = ip[order[p]];
  }
  std::vector<char> removed(static_cast<size_t>(n), 0);
  for (int64_t p = 0; p < n; ++p) {
    if (removed[p]) continue;
    keep.push_back(order[p]);
    if (static_cast<int64_t>(keep.size()) >= max_keep) break;
    // the kept box is a: the same argument order as the CUDA bitmask, so the same bits
    at::parallel_for(p + 1, n, 2048, [&](int64_t s, int64_t e) {
      for (int64_t q = s; q < e; ++q)
        if (!removed[q] && group[q] == group[p] && !boxes::circles_apart(g[p], g[q]) &&
            (boxes::bev_iou_surely_above(g[p], g[q], iou_threshold) ||
             boxes::pair_value(g[p], g[q], 1) > iou_threshold))
          removed[q] = 1;
    });
  }
  return keep;
}

at::Tensor nms_bev_cpu(const at::Tensor& boxes_in, const at::Tensor& scores, const c10::optional<at::Tensor>& idxs,
                       double iou_threshold, int64_t pre_max, int64_t post_max) {
  const bool grouped = boxes::check_nms_args(boxes_in, scores, idxs, iou_threshold);
  const int64_t N = boxes_in.size(0);
  std::vector<int64_t> order = score_order(scores.to(at::kDouble).contiguous());
  if (pre_max >= 0 && pre_max < N) order.resize(static_cast<size_t>(pre_max));
  const int64_t n = static_cast<int64_t>(order.size());
  const int64_t max_keep = post_max >= 0 ? post_max : n;
  const auto keep = greedy_nms(boxes_in, order, n, idxs, grouped, iou_threshold, max_keep);
  auto out = at::empty({static_cast<int64_t>(keep.size())}, boxes_in.options().dtype(at::kLong));
  std::copy(keep.begin(), keep.end(), out.data_ptr<int64_t>());
  return out;
}

std::tuple<at::Tensor, at::Tensor> nms_bev_padded_cpu(const at::Tensor& boxes_in, const at::Tensor& scores,
                                                      const c10::optional<at::Tensor>& idxs, double iou_threshold,
                                                      c10::optional<double> score_threshold, int64_t pre_max,
                                                      int64_t post_max) {
  const bool grouped = boxes::check_nms_args(boxes_in, scores, idxs, iou_threshold);
  boxes::check_score_threshold(score_threshold);
  const int64_t N = boxes_in.size(0);
  const int64_t n = pre_max >= 0 ? std::min(pre_max, N) : N;
  const int64_t K = post_max >= 0 ? std::min(post_max, n) : n;
  auto keep = at::full({K}, -1, boxes_in.options().dtype(at::kLong));
  auto count = at::zeros({}, boxes_in.options().dtype(at::kLong));
  if (K == 0) return {keep, count};
  // the boxes scoring >= score_threshold (never NaN, which sorts last) are a prefix of the order
  auto key = scores.to(at::kDouble).contiguous();
  std::vector<int64_t> order = score_order(key);
  order.resize(static_cast<size_t>(n));
  const double* kp = key.data_ptr<double>();
  int64_t n_valid = score_threshold.has_value() ? 0 : n;
  if (score_threshold.has_value())
    while (n_valid < n && kp[order[n_valid]] >= *score_threshold) ++n_valid;
  const auto kept = greedy_nms(boxes_in, order, n_valid, idxs, grouped, iou_threshold, K);
  std::copy(kept.begin(), kept.end(), keep.data_ptr<int64_t>());
  count.fill_(static_cast<int64_t>(kept.size()));
  return {keep, count};
}

// Frame by frame: the CPU has no launches to share.
std::tuple<at::Tensor, at::Tensor> nms_bev_padded_batched_cpu(const at::Tensor& boxes, const at::Tensor& scores,
                                                              double iou_threshold,
                                                              c10::optional<double> score_threshold, int64_t pre_max,
                                                              int64_t post_max) {
  boxes::check_batched_nms_args(boxes, scores, iou_threshold);
  boxes::check_score_threshold(score_threshold);
  const int64_t B = boxes.size(0);
  const int64_t K = boxes::padded_nms_sizes(boxes.size(1), pre_max, post_max).K;
  auto keep = at::full({B, K}, -1, boxes.options().dtype(at::kLong));
  auto count = at::zeros({B}, boxes.options().dtype(at::kLong));
  for (int64_t b = 0; b < B && K > 0; ++b) {
    auto [k, c] = nms_bev_padded_cpu(boxes[b], scores[b], c10::nullopt, iou_threshold, score_threshold, pre_max,
                                     post_max);
    keep[b].copy_(k);
    count[b].copy_(c);
  }
  return {keep, count};
}

// Any finite box value outside the supported values (boxes::box_value_out_of_range), in its own precision.
bool box_values_out_of_range(const at::Tensor& boxes_in) {
  auto b = boxes_in.contiguous();
  bool bad = false;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, b.scalar_type(), "lidarops_box_range_cpu", [&] {
    using acc_t = std::conditional_t<std::is_same_v<scalar_t, double>, double, float>;
    const scalar_t* p = b.data_ptr<scalar_t>();
    for (int64_t i = 0, n = b.numel(); i < n && !bad; ++i)
      bad = boxes::box_value_out_of_range(static_cast<acc_t>(p[i]), static_cast<int>(i % 7));
  });
  return bad;
}

std::tuple<at::Tensor, at::Tensor> nms_bev_checked_cpu(const at::Tensor& boxes_in, const at::Tensor& scores,
                                                       const c10::optional<at::Tensor>& idxs, double iou_threshold,
                                                       c10::optional<double> score_threshold, int64_t pre_max,
                                                       int64_t post_max) {
  auto [keep, count] = nms_bev_padded_cpu(boxes_in, scores, idxs, iou_threshold, score_threshold, pre_max, post_max);
  auto status = at::zeros({4}, keep.options());
  auto* st = status.data_ptr<int64_t>();
  st[0] = count.item<int64_t>();
  st[1] = !at::isfinite(boxes_in).all().item<bool>();
  st[2] = !at::isfinite(scores).all().item<bool>();
  st[3] = box_values_out_of_range(boxes_in);
  return {keep, status};
}

at::Tensor points_in_boxes_cpu(const at::Tensor& points_in, const at::Tensor& boxes_in) {
  boxes::check_points_args(points_in, boxes_in);
  const int64_t P = points_in.size(0), M = boxes_in.size(0);
  auto out = at::full({P}, -1, points_in.options().dtype(at::kLong));
  if (P == 0 || M == 0) return out;
  const auto g = geoms_of(boxes_in);
  auto points = points_in.contiguous();
  const int64_t C = points.size(1);
  int64_t* o = out.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, points.scalar_type(), "lidarops_points_in_boxes", [&] {
    const scalar_t* pp = points.data_ptr<scalar_t>();
    at::parallel_for(0, P, std::max<int64_t>(1, 65536 / M), [&](int64_t s, int64_t e) {
      for (int64_t i = s; i < e; ++i) {
        const double x = static_cast<double>(pp[i * C]), y = static_cast<double>(pp[i * C + 1]),
                     z = static_cast<double>(pp[i * C + 2]);
        for (int64_t j = 0; j < M; ++j) {
          if (boxes::point_in_box(x, y, z, g[j])) {
            o[i] = j;
            break;
          }
        }
      }
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) {
  m.impl("box_overlap_bev", &box_overlap_bev_cpu);
  m.impl("box_iou_bev", &box_iou_bev_cpu);
  m.impl("box_iou_3d", &box_iou_3d_cpu);
  m.impl("nms_bev", &nms_bev_cpu);
  m.impl("nms_bev_padded", &nms_bev_padded_cpu);
  m.impl("nms_bev_checked", &nms_bev_checked_cpu);
  m.impl("nms_bev_padded_batched", &nms_bev_padded_batched_cpu);
  m.impl("points_in_boxes", &points_in_boxes_cpu);
}

}  // namespace lidarops
