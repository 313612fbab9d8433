// Geometry of rotated 3D boxes (x, y, z, dx, dy, dz, heading), shared by the CPU and CUDA kernels
// of the box ops (csrc/cpu/boxes_kernel.cpp, csrc/cuda/boxes_kernel.cu).
//
// Everything is computed in float64 with every operation rounded on its own (no fused multiply-add,
// see common.h) and with a sine/cosine evaluated by the same polynomial on both devices, so the CPU
// and CUDA kernels give the same bits: NMS keep lists agree exactly across devices.
//
// The overlap of boxes a and b is computed in a's frame: b's rectangle is clipped against a's
// axis-aligned one (Sutherland-Hodgman against four half-planes, no line-line intersections), which
// stays exact where it matters: two identical boxes give IoU exactly 1 at any heading, and near-axis-
// aligned or far-from-origin boxes lose no digits to the absolute position.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "lidarops/common.h"

namespace lidarops {
namespace boxes {

// sin and cos of x, identical on CPU and CUDA: Cody-Waite reduction by pi/2 (33-bit high part, so
// k * kPio2Hi is exact for |k| < 2^20), Taylor polynomials to degree 17 / 18 on |r| <= pi/4
// (truncation below 1e-19), then the quadrant.
LIDAROPS_HD void sincos_det(double x, double* s_out, double* c_out) {
  constexpr double kTwoOverPi = 0.6366197723675814;
  constexpr double kPio2Hi = 1.57079632673412561417e+00;  // first 33 bits of pi/2
  constexpr double kPio2Lo = 6.07710050650619224932e-11;  // pi/2 - kPio2Hi
  const double k = floor(add_rn(mul_rn(x, kTwoOverPi), 0.5));
  const double r = sub_rn(sub_rn(x, mul_rn(k, kPio2Hi)), mul_rn(k, kPio2Lo));
  const double z = mul_rn(r, r);
  // sin r = r + r^3 P(r^2), cos r = 1 + r^2 Q(r^2); coefficients (-1)^n / (2n+1)! and (-1)^n / (2n)!
  double p = 2.8114572543455206e-15;
  p = add_rn(mul_rn(p, z), -7.647163731819816e-13);
  p = add_rn(mul_rn(p, z), 1.6059043836821613e-10);
  p = add_rn(mul_rn(p, z), -2.505210838544172e-08);
  p = add_rn(mul_rn(p, z), 2.7557319223985893e-06);
  p = add_rn(mul_rn(p, z), -0.0001984126984126984);
  p = add_rn(mul_rn(p, z), 0.008333333333333333);
  p = add_rn(mul_rn(p, z), -0.16666666666666666);
  const double s = add_rn(r, mul_rn(mul_rn(r, z), p));
  double q = -1.5619206968586225e-16;
  q = add_rn(mul_rn(q, z), 4.779477332387385e-14);
  q = add_rn(mul_rn(q, z), -1.1470745597729725e-11);
  q = add_rn(mul_rn(q, z), 2.08767569878681e-09);
  q = add_rn(mul_rn(q, z), -2.755731922398589e-07);
  q = add_rn(mul_rn(q, z), 2.48015873015873e-05);
  q = add_rn(mul_rn(q, z), -0.001388888888888889);
  q = add_rn(mul_rn(q, z), 0.041666666666666664);
  q = add_rn(mul_rn(q, z), -0.5);
  const double c = add_rn(1.0, mul_rn(z, q));
  switch (static_cast<int64_t>(k) & 3) {  // two's complement: -1 & 3 == 3
    case 0: *s_out = s; *c_out = c; break;
    case 1: *s_out = c; *c_out = -s; break;
    case 2: *s_out = -s; *c_out = -c; break;
    default: *s_out = -c; *c_out = s; break;
  }
}

// One box, ready for pair tests: centre, half sizes, heading with its sine and cosine, the radius of
// its circumscribed circle (BEV), z range and BEV area.
// The values a box may hold (lidarops.ops.boxes: MAX_ABS_BOX_CENTRE, MIN_BOX_SIZE, MAX_BOX_SIZE,
// MAX_ABS_HEADING): inside them the reduction of sincos_det is exact and every area a normal double.
constexpr double kMaxAbsBoxCentre = 1e6, kMinBoxSize = 1e-6, kMaxBoxSize = 1e6, kMaxAbsHeading = 1e6;

// Whether value v of box column col (0..6) is outside those values (NaN is not: it is flagged apart).
template <typename T>
LIDAROPS_HD bool box_value_out_of_range(T v, int col) {
  if (col < 3) return v < T(-kMaxAbsBoxCentre) || v > T(kMaxAbsBoxCentre);
  if (col < 6) return v != T(0) && (v < T(kMinBoxSize) || v > T(kMaxBoxSize));
  return v < T(-kMaxAbsHeading) || v > T(kMaxAbsHeading);
}

struct BoxGeom {
  double x, y, z, hx, hy, hz, heading, c, s, radius, zlo, zhi, area;
};

template <typename T>
LIDAROPS_HD BoxGeom make_geom(const T* b) {
  BoxGeom g;
  g.x = static_cast<double>(b[0]);
  g.y = static_cast<double>(b[1]);
  g.z = static_cast<double>(b[2]);
  g.hx = mul_rn(static_cast<double>(b[3]), 0.5);
  g.hy = mul_rn(static_cast<double>(b[4]), 0.5);
  g.hz = mul_rn(static_cast<double>(b[5]), 0.5);
  g.heading = static_cast<double>(b[6]);
  sincos_det(g.heading, &g.s, &g.c);
  g.radius = sqrt(add_rn(mul_rn(g.hx, g.hx), mul_rn(g.hy, g.hy)));
  g.zlo = sub_rn(g.z, g.hz);
  g.zhi = add_rn(g.z, g.hz);
  g.area = mul_rn(4.0, mul_rn(g.hx, g.hy));  // the clipped polygon of two identical boxes gives these bits
  return g;
}

// Keeps the part of the polygon (x, y)[0..n) with sign * v <= bound, where v is x (axis 0) or y
// (axis 1); points on the line are inside, and points it creates lie exactly on it. Returns the new
// vertex count (at most n + 1).
LIDAROPS_HD int clip_half_plane(const double* xs, const double* ys, int n, int axis, double sign, double bound,
                                double* ox, double* oy) {
  int m = 0;
  for (int i = 0; i < n; ++i) {
    const int j = i + 1 == n ? 0 : i + 1;
    const double vi = sub_rn(mul_rn(sign, axis == 0 ? xs[i] : ys[i]), bound);
    const double vj = sub_rn(mul_rn(sign, axis == 0 ? xs[j] : ys[j]), bound);
    if (vi <= 0.0) {
      ox[m] = xs[i];
      oy[m] = ys[i];
      ++m;
    }
    if ((vi < 0.0 && vj > 0.0) || (vi > 0.0 && vj < 0.0)) {
      const double t = vi / sub_rn(vi, vj);
      const double line = mul_rn(sign, bound);
      if (axis == 0) {
        ox[m] = line;
        oy[m] = add_rn(ys[i], mul_rn(t, sub_rn(ys[j], ys[i])));
      } else {
        ox[m] = add_rn(xs[i], mul_rn(t, sub_rn(xs[j], xs[i])));
        oy[m] = line;
      }
      ++m;
    }
  }
  return m;
}

// Whether the circumscribed circles of a and b are apart: then the boxes cannot overlap (the slack covers
// the rounding of this test).
LIDAROPS_HD bool circles_apart(const BoxGeom& a, const BoxGeom& b) {
  const double dx = sub_rn(b.x, a.x), dy = sub_rn(b.y, a.y);
  const double reach = mul_rn(add_rn(a.radius, b.radius), 1.0 + 1e-9);
  return add_rn(mul_rn(dx, dx), mul_rn(dy, dy)) > mul_rn(reach, reach);
}

// A sufficient test for BEV IoU(a, b) > threshold, exact in its decision: the boxes hold their inscribed
// disks, whose lens holds a disk of radius rho = (ra + rb - d) / 2 (at most the smaller radius), so the
// intersection is at least pi rho^2 and IoU >= pi rho^2 / (A + B - pi rho^2). NMS at a small threshold
// (PointPillars: 0.01) decides most overlapping pairs with it instead of clipping; the margins keep it
// below the IoU that pair_value computes, so every decision is the one clipping would give.
LIDAROPS_HD bool bev_iou_surely_above(const BoxGeom& a, const BoxGeom& b, double threshold) {
  const double ra = a.hx < a.hy ? a.hx : a.hy, rb = b.hx < b.hy ? b.hx : b.hy;
  const double dx = sub_rn(b.x, a.x), dy = sub_rn(b.y, a.y);
  double rho = mul_rn(sub_rn(add_rn(ra, rb), sqrt(add_rn(mul_rn(dx, dx), mul_rn(dy, dy)))), 0.5);
  const double rmin = ra < rb ? ra : rb;
  if (rho > rmin) rho = rmin;
  if (!(rho > 0.0)) return false;
  rho = mul_rn(rho, 1.0 - 1e-9);
  const double disk = mul_rn(3.141592653589793, mul_rn(rho, rho));  // the double below pi: an underestimate
  const double u = sub_rn(add_rn(a.area, b.area), disk);
  return u > 0.0 && disk / u > add_rn(threshold, 1e-9);
}

// Area of the intersection of the BEV rectangles of a and b (0 when they are apart or degenerate).
LIDAROPS_HD double bev_intersection(const BoxGeom& a, const BoxGeom& b) {
  if (circles_apart(a, b)) return 0.0;
  const double dx = sub_rn(b.x, a.x), dy = sub_rn(b.y, a.y);
  if (!(a.hx > 0.0 && a.hy > 0.0 && b.hx > 0.0 && b.hy > 0.0)) return 0.0;
  // b's centre and axes in a's frame
  const double px = add_rn(mul_rn(a.c, dx), mul_rn(a.s, dy));
  const double py = sub_rn(mul_rn(a.c, dy), mul_rn(a.s, dx));
  double sp, cp;
  sincos_det(sub_rn(b.heading, a.heading), &sp, &cp);
  const double ux = mul_rn(cp, b.hx), uy = mul_rn(sp, b.hx);
  const double vx = -mul_rn(sp, b.hy), vy = mul_rn(cp, b.hy);
  // b's corners counter-clockwise: front-left, rear-left, rear-right, front-right
  double x0[8], y0[8], x1[8], y1[8];
  x0[0] = add_rn(add_rn(px, ux), vx); y0[0] = add_rn(add_rn(py, uy), vy);
  x0[1] = add_rn(sub_rn(px, ux), vx); y0[1] = add_rn(sub_rn(py, uy), vy);
  x0[2] = sub_rn(sub_rn(px, ux), vx); y0[2] = sub_rn(sub_rn(py, uy), vy);
  x0[3] = sub_rn(add_rn(px, ux), vx); y0[3] = sub_rn(add_rn(py, uy), vy);
  int n = clip_half_plane(x0, y0, 4, 0, 1.0, a.hx, x1, y1);
  n = clip_half_plane(x1, y1, n, 0, -1.0, a.hx, x0, y0);
  n = clip_half_plane(x0, y0, n, 1, 1.0, a.hy, x1, y1);
  n = clip_half_plane(x1, y1, n, 1, -1.0, a.hy, x0, y0);
  if (n < 3) return 0.0;
  double twice = 0.0;  // shoelace
  for (int i = 0; i < n; ++i) {
    const int j = i + 1 == n ? 0 : i + 1;
    twice = add_rn(twice, sub_rn(mul_rn(x0[i], y0[j]), mul_rn(x0[j], y0[i])));
  }
  double area = mul_rn(twice, 0.5);
  if (!(area > 0.0)) return 0.0;
  const double cap = a.area < b.area ? a.area : b.area;
  return area < cap ? area : cap;
}

// 0: BEV intersection area, 1: BEV IoU, 2: 3D IoU (BEV intersection x z overlap / union of volumes).
// Degenerate boxes (a zero size) have no overlap: 0, never NaN.
LIDAROPS_HD double pair_value(const BoxGeom& a, const BoxGeom& b, int mode) {
  if (mode == 2) {
    const double top = a.zhi < b.zhi ? a.zhi : b.zhi;
    const double bottom = a.zlo > b.zlo ? a.zlo : b.zlo;
    const double dz = sub_rn(top, bottom);
    if (!(dz > 0.0)) return 0.0;
    const double inter = bev_intersection(a, b);
    if (!(inter > 0.0)) return 0.0;
    const double i3 = mul_rn(inter, dz);
    // volumes with the same z expression as the overlap: identical boxes give exactly 1
    const double va = mul_rn(a.area, sub_rn(a.zhi, a.zlo)), vb = mul_rn(b.area, sub_rn(b.zhi, b.zlo));
    const double u = sub_rn(add_rn(va, vb), i3);
    return u > 0.0 ? i3 / u : 0.0;
  }
  const double inter = bev_intersection(a, b);
  if (mode == 0) return inter;
  if (!(inter > 0.0)) return 0.0;
  const double u = sub_rn(add_rn(a.area, b.area), inter);
  return u > 0.0 ? inter / u : 0.0;
}

// Whether (px, py, pz) lies in the closed box g.
LIDAROPS_HD bool point_in_box(double px, double py, double pz, const BoxGeom& g) {
  const double dx = sub_rn(px, g.x), dy = sub_rn(py, g.y);
  // bounding square first (most boxes are far from most points), with slack for its own rounding
  const double reach = mul_rn(g.radius, 1.0 + 1e-9);
  if (!((dx < 0.0 ? -dx : dx) <= reach && (dy < 0.0 ? -dy : dy) <= reach)) return false;
  const double dz = sub_rn(pz, g.z);
  if (!((dz < 0.0 ? -dz : dz) <= g.hz)) return false;
  const double lx = add_rn(mul_rn(g.c, dx), mul_rn(g.s, dy));
  if (!((lx < 0.0 ? -lx : lx) <= g.hx)) return false;
  const double ly = sub_rn(mul_rn(g.c, dy), mul_rn(g.s, dx));
  return (ly < 0.0 ? -ly : ly) <= g.hy;
}

// Argument checks shared by the CPU and CUDA kernels (host code).
inline void check_boxes(const at::Tensor& b, const char* name) {
  TORCH_CHECK_VALUE(b.dim() == 2 && b.size(1) == 7, name, " must be (N, 7) boxes (x, y, z, dx, dy, dz, heading), got shape ",
                    b.sizes());
  TORCH_CHECK_VALUE(at::isFloatingType(b.scalar_type()), name, " must be floating, got ", b.scalar_type());
}

inline void check_pair_args(const at::Tensor& a, const at::Tensor& b) {
  check_boxes(a, "a");
  check_boxes(b, "b");
  TORCH_CHECK_VALUE(a.scalar_type() == b.scalar_type(), "a and b must have the same dtype, got ", a.scalar_type(), " and ",
                    b.scalar_type());
  TORCH_CHECK_VALUE(a.device() == b.device(), "b is on ", b.device(), " but a is on ", a.device());
}

// Returns whether idxs (groups) is given.
inline bool check_nms_args(const at::Tensor& boxes, const at::Tensor& scores, const c10::optional<at::Tensor>& idxs,
                           double iou_threshold) {
  check_boxes(boxes, "boxes");
  // an IoU lies in [0, 1]; below 0 boxes that do not touch would count as overlapping (NaN: no order)
  TORCH_CHECK_VALUE(iou_threshold >= 0 && iou_threshold < INFINITY, "iou_threshold must be a finite number >= 0, got ",
                    iou_threshold);
  const int64_t N = boxes.size(0);
  TORCH_CHECK_VALUE(scores.dim() == 1 && scores.size(0) == N, "scores must be (N,) with N = ", N, ", got shape ",
                    scores.sizes());
  TORCH_CHECK_VALUE(at::isFloatingType(scores.scalar_type()), "scores must be floating, got ", scores.scalar_type());
  TORCH_CHECK_VALUE(scores.device() == boxes.device(), "scores is on ", scores.device(), " but boxes is on ", boxes.device());
  const bool grouped = idxs.has_value() && idxs->defined();
  if (grouped) {
    TORCH_CHECK_VALUE(idxs->dim() == 1 && idxs->size(0) == N, "idxs must be (N,) with N = ", N, ", got shape ",
                      idxs->sizes());
    TORCH_CHECK_VALUE(idxs->scalar_type() == at::kLong, "idxs must be int64, got ", idxs->scalar_type());
    TORCH_CHECK_VALUE(idxs->device() == boxes.device(), "idxs is on ", idxs->device(), " but boxes is on ", boxes.device());
  }
  return grouped;
}

// nms_bev_padded_batched: boxes (B, N, 7) and scores (B, N), frames of N boxes each.
inline void check_batched_nms_args(const at::Tensor& boxes, const at::Tensor& scores, double iou_threshold) {
  TORCH_CHECK_VALUE(boxes.dim() == 3 && boxes.size(2) == 7,
                    "boxes must be (B, N, 7) boxes (x, y, z, dx, dy, dz, heading) per frame, got shape ", boxes.sizes());
  TORCH_CHECK_VALUE(at::isFloatingType(boxes.scalar_type()), "boxes must be floating, got ", boxes.scalar_type());
  TORCH_CHECK_VALUE(iou_threshold >= 0 && iou_threshold < INFINITY, "iou_threshold must be a finite number >= 0, got ",
                    iou_threshold);
  TORCH_CHECK_VALUE(scores.dim() == 2 && scores.size(0) == boxes.size(0) && scores.size(1) == boxes.size(1),
                    "scores must be (B, N) with (B, N) = (", boxes.size(0), ", ", boxes.size(1), "), got shape ",
                    scores.sizes());
  TORCH_CHECK_VALUE(at::isFloatingType(scores.scalar_type()), "scores must be floating, got ", scores.scalar_type());
  TORCH_CHECK_VALUE(scores.device() == boxes.device(), "scores is on ", scores.device(), " but boxes is on ", boxes.device());
}

// Candidates are boxes with score >= score_threshold: NaN would make none a candidate silently.
inline void check_score_threshold(const c10::optional<double>& score_threshold) {
  TORCH_CHECK_VALUE(!score_threshold.has_value() || !std::isnan(*score_threshold),
                    "score_threshold must be a number or None, got nan");
}

// A padded NMS of N boxes: n = min(pre_max, N) candidates at most, K = min(post_max, n) kept (-1: no limit).
struct PaddedNmsSizes {
  int64_t n, K;
};
inline PaddedNmsSizes padded_nms_sizes(int64_t N, int64_t pre_max, int64_t post_max) {
  const int64_t n = pre_max >= 0 ? std::min(pre_max, N) : N;
  return {n, post_max >= 0 ? std::min(post_max, n) : n};
}

inline void check_points_args(const at::Tensor& points, const at::Tensor& boxes) {
  TORCH_CHECK_VALUE(points.dim() == 2 && points.size(1) >= 3, "points must be (P, C >= 3), got shape ", points.sizes());
  TORCH_CHECK_VALUE(at::isFloatingType(points.scalar_type()), "points must be floating, got ", points.scalar_type());
  check_boxes(boxes, "boxes");
  TORCH_CHECK_VALUE(points.device() == boxes.device(), "boxes is on ", boxes.device(), " but points is on ", points.device());
}

}  // namespace boxes
}  // namespace lidarops
