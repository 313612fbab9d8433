// kitti_match on CPU: the greedy per-frame matching of KITTI's object benchmark, for many frames and
// thresholds at once (the Python evaluator calls it once per metric, class, difficulty and overlap).
//
// Within a frame the gts are visited in index order; each takes one still-unassigned detection with an
// overlap above min_overlap: in the first pass the highest-scoring one, in the counting pass the one with
// the largest overlap among counted detections (the first of equal ones), else the first ignored one.
// Frames are independent (parallel); sums over frames are taken in frame order, so results do not depend
// on the thread count. A detection set depends on a threshold only through how many of the frame's
// detections reach it, so each distinct set is matched once.
#include <ATen/core/Tensor.h>
#include <ATen/Parallel.h>
#include <ATen/ops/full.h>
#include <ATen/ops/zeros.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include <torch/library.h>

namespace lidarops {
namespace {

struct Counts {
  double tp = 0, fp = 0, fn = 0, similarity = 0;
};

struct FrameView {
  const double* overlaps;  // (D_f, G_f) row-major
  int64_t num_gt, num_dt;
  const int64_t* ignored_gt;
  const int64_t* ignored_dt;
  const double* scores;
  const double* dontcare;
  const double* gt_alpha;
  const double* dt_alpha;
};

// One frame at one threshold (compute_fp) or the first pass (matched[g] = score of the tp detection).
Counts match_frame(const FrameView& f, const std::vector<int64_t>& gts, const std::vector<int64_t>& dts,
                   double thresh, double min_overlap, bool compute_fp, bool compute_aos, double* matched) {
  constexpr double kNoDetection = -10000000.0;
  Counts c;
  std::vector<char> assigned(static_cast<size_t>(f.num_dt), 0);
  auto below = [&](int64_t j) { return compute_fp && f.scores[j] < thresh; };
  for (const int64_t i : gts) {
    int64_t det = -1;
    double valid = kNoDetection, max_overlap = 0.0;
    bool assigned_ignored = false;
    for (const int64_t j : dts) {
      if (assigned[j] || below(j)) continue;
      const double overlap = f.overlaps[j * f.num_gt + i];
      if (!(overlap > min_overlap)) continue;
      if (!compute_fp) {
        if (f.scores[j] > valid) {
          det = j;
          valid = f.scores[j];
        }
      } else if ((overlap > max_overlap || assigned_ignored) && f.ignored_dt[j] == 0) {
        max_overlap = overlap;
        det = j;
        valid = 1.0;
        assigned_ignored = false;
      } else if (valid == kNoDetection && f.ignored_dt[j] == 1) {
        det = j;
        valid = 1.0;
        assigned_ignored = true;
      }
    }
    if (valid == kNoDetection) {
      if (f.ignored_gt[i] == 0) c.fn += 1;
    } else if (f.ignored_gt[i] == 1 || f.ignored_dt[det] == 1) {
      assigned[det] = 1;
    } else {
      c.tp += 1;
      if (matched != nullptr) matched[i] = f.scores[det];
      if (compute_aos) c.similarity += (1.0 + std::cos(f.gt_alpha[i] - f.dt_alpha[det])) / 2.0;
      assigned[det] = 1;
    }
  }
  if (compute_fp) {
    for (const int64_t j : dts) {
      if (assigned[j] || f.ignored_dt[j] != 0 || below(j)) continue;
      // a false positive inside a DontCare region is not counted
      if (!(f.dontcare[j] > min_overlap)) c.fp += 1;
    }
  }
  return c;
}

void check_offsets(const at::Tensor& off, int64_t frames, int64_t total, const char* name) {
  TORCH_CHECK_VALUE(off.dim() == 1 && off.size(0) == frames + 1, name, " must be (F + 1,) = (", frames + 1, ",), got shape ",
                    off.sizes());
  const int64_t* p = off.data_ptr<int64_t>();
  TORCH_CHECK_VALUE(p[0] == 0 && p[frames] == total, name, " must start at 0 and end at ", total, ", got ", p[0], " and ",
                    p[frames]);
  for (int64_t f = 0; f < frames; ++f)
    TORCH_CHECK_VALUE(p[f] <= p[f + 1], name, " must be non-decreasing, got ", p[f], " > ", p[f + 1], " at frame ", f);
}

// Integer tables (offsets, ignore flags) must have an integer dtype: a float offset would be truncated
// silently. Real-valued arguments take any real dtype (computed in float64).
at::Tensor contiguous_as(const at::Tensor& t, at::ScalarType dtype, const char* name) {
  TORCH_CHECK_VALUE(t.device().is_cpu(), "kitti_match: ", name, " must be on the CPU, got ", t.device());
  TORCH_CHECK_VALUE(t.dim() == 1, "kitti_match: ", name, " must be one-dimensional, got shape ", t.sizes());
  if (dtype == at::kLong) {
    TORCH_CHECK_VALUE(at::isIntegralType(t.scalar_type(), /*includeBool=*/false), "kitti_match: ", name,
                      " must be an integer tensor, got ", t.scalar_type());
  } else {
    TORCH_CHECK_VALUE(!t.is_complex() && t.scalar_type() != at::kBool, "kitti_match: ", name,
                      " must be a real tensor, got ", t.scalar_type());
  }
  return t.to(dtype).contiguous();
}

std::tuple<at::Tensor, at::Tensor> kitti_match_cpu(const at::Tensor& overlaps_in, const at::Tensor& overlap_offsets_in,
                                                   const at::Tensor& gt_offsets_in, const at::Tensor& dt_offsets_in,
                                                   const at::Tensor& ignored_gt_in, const at::Tensor& ignored_dt_in,
                                                   const at::Tensor& dt_scores_in, const at::Tensor& dt_dontcare_in,
                                                   const at::Tensor& gt_alpha_in, const at::Tensor& dt_alpha_in,
                                                   const at::Tensor& thresholds_in, double min_overlap, bool compute_fp,
                                                   bool compute_aos) {
  auto overlaps = contiguous_as(overlaps_in, at::kDouble, "overlaps");
  auto overlap_offsets = contiguous_as(overlap_offsets_in, at::kLong, "overlap_offsets");
  auto gt_offsets = contiguous_as(gt_offsets_in, at::kLong, "gt_offsets");
  auto dt_offsets = contiguous_as(dt_offsets_in, at::kLong, "dt_offsets");
  auto ignored_gt = contiguous_as(ignored_gt_in, at::kLong, "ignored_gt");
  auto ignored_dt = contiguous_as(ignored_dt_in, at::kLong, "ignored_dt");
  auto scores = contiguous_as(dt_scores_in, at::kDouble, "dt_scores");
  auto dontcare = contiguous_as(dt_dontcare_in, at::kDouble, "dt_dontcare");
  auto gt_alpha = contiguous_as(gt_alpha_in, at::kDouble, "gt_alpha");
  auto dt_alpha = contiguous_as(dt_alpha_in, at::kDouble, "dt_alpha");
  auto thresholds = contiguous_as(thresholds_in, at::kDouble, "thresholds");
  const int64_t F = gt_offsets.size(0) - 1;
  TORCH_CHECK_VALUE(F >= 0, "kitti_match: gt_offsets must have at least one entry");
  const int64_t G = ignored_gt.size(0), D = ignored_dt.size(0);
  check_offsets(gt_offsets, F, G, "kitti_match: gt_offsets");
  check_offsets(dt_offsets, F, D, "kitti_match: dt_offsets");
  check_offsets(overlap_offsets, F, overlaps.size(0), "kitti_match: overlap_offsets");
  for (const auto& [t, n, name] : {std::tuple{&scores, D, "dt_scores"}, std::tuple{&dontcare, D, "dt_dontcare"},
                                   std::tuple{&dt_alpha, D, "dt_alpha"}, std::tuple{&gt_alpha, G, "gt_alpha"}})
    TORCH_CHECK_VALUE(t->size(0) == n, "kitti_match: ", name, " must have ", n, " entries, got ", t->size(0));
  const int64_t* go = gt_offsets.data_ptr<int64_t>();
  const int64_t* dof = dt_offsets.data_ptr<int64_t>();
  const int64_t* oo = overlap_offsets.data_ptr<int64_t>();
  for (int64_t f = 0; f < F; ++f)
    TORCH_CHECK_VALUE(oo[f + 1] - oo[f] == (dof[f + 1] - dof[f]) * (go[f + 1] - go[f]), "kitti_match: frame ", f,
                      " has ", dof[f + 1] - dof[f], " detections and ", go[f + 1] - go[f], " gts but ", oo[f + 1] - oo[f],
                      " overlaps");
  for (const auto& [t, name] : {std::pair{&ignored_gt, "ignored_gt"}, std::pair{&ignored_dt, "ignored_dt"}}) {
    const int64_t* p = t->data_ptr<int64_t>();
    for (int64_t i = 0; i < t->size(0); ++i)
      TORCH_CHECK_VALUE(p[i] >= -1 && p[i] <= 1, "kitti_match: ", name, " values must be -1, 0 or 1, got ", p[i],
                        " at ", i);
  }
  // NaN scores would break the matching's comparisons and the sort of each frame's scores
  for (const auto& [t, name] : {std::pair{&scores, "dt_scores"}, std::pair{&thresholds, "thresholds"}}) {
    const double* p = t->data_ptr<double>();
    for (int64_t i = 0; i < t->size(0); ++i)
      TORCH_CHECK_VALUE(!std::isnan(p[i]), "kitti_match: ", name, " must not hold NaN, got NaN at ", i);
  }
  const int64_t T = compute_fp ? thresholds.size(0) : 0;
  auto matched = at::full({compute_fp ? 0 : G}, std::numeric_limits<double>::quiet_NaN(), overlaps.options());
  std::vector<Counts> per_frame(static_cast<size_t>(F * T));
  const double* th = thresholds.data_ptr<double>();
  at::parallel_for(0, F, 16, [&](int64_t s, int64_t e) {
    std::vector<int64_t> gts, dts;
    std::vector<double> ranked;
    for (int64_t f = s; f < e; ++f) {
      FrameView v{overlaps.data_ptr<double>() + oo[f], go[f + 1] - go[f], dof[f + 1] - dof[f],
                  ignored_gt.data_ptr<int64_t>() + go[f], ignored_dt.data_ptr<int64_t>() + dof[f],
                  scores.data_ptr<double>() + dof[f], dontcare.data_ptr<double>() + dof[f],
                  gt_alpha.data_ptr<double>() + go[f], dt_alpha.data_ptr<double>() + dof[f]};
      gts.clear();
      dts.clear();
      for (int64_t i = 0; i < v.num_gt; ++i)
        if (v.ignored_gt[i] != -1) gts.push_back(i);
      for (int64_t j = 0; j < v.num_dt; ++j)
        if (v.ignored_dt[j] != -1) dts.push_back(j);
      if (!compute_fp) {
        match_frame(v, gts, dts, 0.0, min_overlap, false, false, matched.data_ptr<double>() + go[f]);
        continue;
      }
      ranked.clear();
      for (const int64_t j : dts) ranked.push_back(v.scores[j]);
      std::sort(ranked.begin(), ranked.end());
      std::vector<Counts> by_size(dts.size() + 1);
      std::vector<char> done(dts.size() + 1, 0);
      for (int64_t t = 0; t < T; ++t) {
        // detections reaching th[t]: how many of the frame's scores are >= it
        const size_t k = ranked.end() - std::lower_bound(ranked.begin(), ranked.end(), th[t]);
        if (!done[k]) {
          by_size[k] = match_frame(v, gts, dts, th[t], min_overlap, true, compute_aos, nullptr);
          done[k] = 1;
        }
        per_frame[f * T + t] = by_size[k];
      }
    }
  });
  auto counts = at::zeros({T, 4}, overlaps.options());
  double* cp = counts.data_ptr<double>();
  for (int64_t f = 0; f < F; ++f)
    for (int64_t t = 0; t < T; ++t) {
      const Counts& c = per_frame[f * T + t];
      cp[4 * t] += c.tp;
      cp[4 * t + 1] += c.fp;
      cp[4 * t + 2] += c.fn;
      cp[4 * t + 3] += c.similarity;
    }
  return {matched, counts};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) { m.impl("kitti_match", &kitti_match_cpu); }

}  // namespace lidarops
