// raycast_scene on CPU: the nearest hit of every ray of a simulator block against the scene, parallel over rays.
//
// The arithmetic of every intersection test follows lidarops/data/_raycast.py (the NumPy reference) operation
// by operation, so distances agree to rounding (the ground's float32 sines may differ by an ulp from NumPy's
// SIMD ones). Culling differs: instead of candidate pairs, each primitive's conservative angular window
// (its bounding vertical cylinder, grown by its motion over the batch and by the spread of the ray origins,
// seen from the mean origin; for boxes that do not turn, narrowed to the corners of their footprint) is
// entered into a grid of azimuth bins x elevation bands, and each ray tests the primitives of its cell.
#include <ATen/core/Tensor.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <mutex>
#include <vector>

#include "lidarops/common.h"

namespace lidarops {
namespace {

// surface codes of lidarops/data/scene.py
constexpr uint8_t kSurfaceNone = 0;
constexpr uint8_t kSurfaceGround = 1;
constexpr uint8_t kSurfaceVegetation = 4;

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kPi = 3.14159265358979323846;
constexpr double kMargin = 1e-5;  // rad, on every window edge
constexpr int kAzimuthBins = 256;
constexpr int kElevationBands = 16;
constexpr int64_t kGrain = 16384;  // rays; smaller batches run on one thread: waking a second one costs more CPU time than it saves

// ------------------------------------------------------------------------------------------- arguments
void check_arg(const at::Tensor& t, const char* name, at::ScalarType dtype, std::initializer_list<int64_t> shape) {
  TORCH_CHECK_VALUE(t.scalar_type() == dtype, "raycast_scene: ", name, " must be ", dtype, ", got ", t.scalar_type());
  TORCH_CHECK_VALUE(t.dim() == static_cast<int64_t>(shape.size()), "raycast_scene: ", name, " must have ", shape.size(),
                    " dimension(s), got shape ", t.sizes());
  int64_t d = 0;
  for (int64_t want : shape) {
    TORCH_CHECK_VALUE(want < 0 || t.size(d) == want, "raycast_scene: ", name, " must have size ", want, " in dimension ", d,
                      ", got shape ", t.sizes());
    ++d;
  }
}

template <typename T>
const T* ptr(const at::Tensor& t) {
  return t.data_ptr<T>();
}

// ------------------------------------------------------------------------------------------- geometry
// Monotonic stand-in for atan2(y, x) mod 2 pi, in [0, 4): one division instead of an arctangent.
inline double pseudo_angle(double x, double y) {
  const double n = std::fabs(x) + std::fabs(y);
  if (!(n > 0.0)) return 0.0;
  const double r = x / n;
  return y >= 0.0 ? 1.0 - r : 3.0 + r;
}

constexpr int kBatch = 64;  // rays whose ground intersections are computed together

inline uint64_t bits_of(double v) {
  uint64_t b;
  std::memcpy(&b, &v, sizeof b);
  return b;
}

inline double double_of(uint64_t b) {
  double v;
  std::memcpy(&v, &b, sizeof v);
  return v;
}

// sin and cos of n float32 arguments, rounded to float32: Cody-Waite reduction by pi/2 and Taylor polynomials
// in double, the quadrant applied with bit operations so that the loop vectorises (about 4x faster than
// sincosf here). Correctly rounded on 2^21 random arguments in [-300, 300] (glibc's sincosf: 1.3 % off by
// an ulp); the reduction is exact while |x| < 1.6e6.
void sincos_f32(const float* __restrict x, float* __restrict sin_out, float* __restrict cos_out, int n) {
  constexpr double kTwoOverPi = 0.63661977236758134308;
  constexpr double kP1 = 1.5707963267341256;  // pi/2 = kP1 + kP2 + kP3, kP1 and kP2 with 33 significant bits
  constexpr double kP2 = 6.077100506303966e-11;
  constexpr double kP3 = 2.0222662487959506e-21;
  constexpr double kShift = 0x1.8p52;  // x * 2/pi + kShift holds the nearest integer in its low mantissa bits
  for (int j = 0; j < n; ++j) {
    const double xd = x[j];
    const double t = xd * kTwoOverPi + kShift;
    const uint64_t quadrant = bits_of(t);
    const double q = t - kShift;
    const double r = ((xd - q * kP1) - q * kP2) - q * kP3;
    const double r2 = r * r;
    const double sr = r + r * r2 * (-1.0 / 6 + r2 * (1.0 / 120 + r2 * (-1.0 / 5040 + r2 * (1.0 / 362880 +
                      r2 * (-1.0 / 39916800 + r2 * (1.0 / 6227020800.0))))));
    const double cr = 1.0 + r2 * (-0.5 + r2 * (1.0 / 24 + r2 * (-1.0 / 720 + r2 * (1.0 / 40320 +
                      r2 * (-1.0 / 3628800 + r2 * (1.0 / 479001600.0 + r2 * (-1.0 / 87178291200.0)))))));
    const uint64_t swap = 0 - (quadrant & 1);  // all ones in odd quadrants: sin <-> cos
    const uint64_t srb = bits_of(sr), crb = bits_of(cr);
    const uint64_t s0 = (srb & ~swap) | (crb & swap), c0 = (crb & ~swap) | (srb & swap);
    sin_out[j] = static_cast<float>(double_of(s0 ^ ((quadrant & 2) << 62)));
    cos_out[j] = static_cast<float>(double_of(c0 ^ (((quadrant + 1) & 2) << 62)));
  }
}

struct GroundField {
  double z0, a, b;
  int64_t waves;
  const double* amp;
  const double* k;  // [W, 2]
  const double* phase;

  // height and gradient at n points, as Ground.height_and_gradient: the plane in float64, each wave's phase
  // rounded to float32 and its terms computed in float32 (NumPy promotes the Python-float factors to float32)
  void eval(const double* x, const double* y, int n, double* z, double* gx, double* gy) const {
    for (int j = 0; j < n; ++j) {
      z[j] = (z0 + a * x[j]) + b * y[j];
      gx[j] = a;
      gy[j] = b;
    }
    float ph[kBatch], sn[kBatch], cs[kBatch];
    for (int64_t w = 0; w < waves; ++w) {
      const double kx = k[2 * w], ky = k[2 * w + 1];
      for (int j = 0; j < n; ++j) ph[j] = static_cast<float>((kx * x[j] + ky * y[j]) + phase[w]);
      sincos_f32(ph, sn, cs, n);
      const float az = static_cast<float>(amp[w]), ax = static_cast<float>(amp[w] * kx), ay = static_cast<float>(amp[w] * ky);
      for (int j = 0; j < n; ++j) {
        z[j] += static_cast<double>(az * sn[j]);
        gx[j] += static_cast<double>(ax * cs[j]);
        gy[j] += static_cast<double>(ay * cs[j]);
      }
    }
  }

  // intersect_ground for n <= kBatch rays (origins o, directions d: [n, 3]), the Newton steps of all rays not
  // yet converged taken together: distance (inf: no hit) and incidence cosine
  void intersect(const double* o, const double* d, int n, double max_distance, int64_t iterations, double tolerance,
                 double* s_out, double* cos_out) const {
    double s[kBatch], gx[kBatch], gy[kBatch], x[kBatch], y[kBatch], zg[kBatch], gxa[kBatch], gya[kBatch];
    bool converged[kBatch];
    int active[kBatch], n_active = 0;
    for (int i = 0; i < n; ++i) {
      const double* oi = o + 3 * i;
      const double* di = d + 3 * i;
      const double denom = (di[2] - a * di[0]) - b * di[1];
      const double s_plane = (((z0 + a * oi[0]) + b * oi[1]) - oi[2]) / denom;
      converged[i] = false;
      s[i] = s_plane;
      if (denom < -1e-9 && s_plane > 0 && s_plane < max_distance * 1.2) active[n_active++] = i;
    }
    for (int64_t step = 0; step <= iterations && n_active > 0; ++step) {
      for (int j = 0; j < n_active; ++j) {
        const int i = active[j];
        x[j] = o[3 * i] + s[i] * d[3 * i];
        y[j] = o[3 * i + 1] + s[i] * d[3 * i + 1];
      }
      eval(x, y, n_active, zg, gxa, gya);
      int still = 0;
      for (int j = 0; j < n_active; ++j) {
        const int i = active[j];
        const double* di = d + 3 * i;
        const double f = (o[3 * i + 2] + s[i] * di[2]) - zg[j];
        gx[i] = gxa[j];
        gy[i] = gya[j];
        if (std::fabs(f) < tolerance) {
          converged[i] = true;
        } else if (step < iterations && waves > 0) {
          const double fp = std::min((di[2] - gx[i] * di[0]) - gy[i] * di[1], -1e-6);
          s[i] = s[i] - f / fp;
          active[still++] = i;
        }
      }
      n_active = still;
    }
    for (int i = 0; i < n; ++i) {
      const double* di = d + 3 * i;
      const bool hit = converged[i] && s[i] > 0 && s[i] <= max_distance;
      s_out[i] = hit ? s[i] : kInf;
      cos_out[i] = hit ? std::fabs((-gx[i] * di[0] - gy[i] * di[1]) + di[2]) / std::sqrt((gx[i] * gx[i] + gy[i] * gy[i]) + 1.0)
                       : 0.0;
    }
  }
};

struct Boxes {
  int64_t n;
  const double *center, *half, *yaw, *velocity, *yaw_rate, *reflectivity;
  const uint8_t* kind;
  const int32_t* object;
  std::vector<double> cos_yaw, sin_yaw;

  // _intersect_boxes for one (ray, box) pair: slab test in the box frame at time t
  inline double intersect(int64_t j, const double* o, const double* d, double t, double& cos_inc) const {
    double cy = cos_yaw[j], sy = sin_yaw[j];
    if (yaw_rate[j] != 0.0) {
      const double w = yaw[j] + yaw_rate[j] * t;
      cy = std::cos(w);
      sy = std::sin(w);
    }
    const double* c = center + 3 * j;
    const double* v = velocity + 3 * j;
    const double* h = half + 3 * j;
    const double px = o[0] - (c[0] + v[0] * t);
    const double py = o[1] - (c[1] + v[1] * t);
    const double pz = o[2] - (c[2] + v[2] * t);
    const double ldx = cy * d[0] + sy * d[1];
    const double ldy = cy * d[1] - sy * d[0];
    double nx, fx, ny, fy, nz, fz;
    slab(cy * px + sy * py, ldx, h[0], nx, fx);
    slab(cy * py - sy * px, ldy, h[1], ny, fy);
    slab(pz, d[2], h[2], nz, fz);
    const double t_near = std::max(std::max(nx, ny), nz);
    const double t_far = std::min(std::min(fx, fy), fz);
    if (!(t_near <= t_far && t_near > 0)) return kInf;
    cos_inc = t_near == nx ? std::fabs(ldx) : (t_near == ny ? std::fabs(ldy) : std::fabs(d[2]));
    return t_near;
  }

  static inline void slab(double lo, double ld, double half, double& near, double& far) {
    const double inv = 1.0 / (ld == 0.0 ? 1e-300 : ld);
    const double a = (-half - lo) * inv;
    const double b = (half - lo) * inv;
    near = std::min(a, b);
    far = std::max(a, b);
  }
};

struct Cylinders {
  int64_t n;
  const double *center_xy, *z_min, *z_max, *radius, *reflectivity;
  const uint8_t* kind;

  // _intersect_cylinders for one pair: side, then the top and bottom caps
  inline double intersect(int64_t j, const double* o, const double* d, double& cos_inc) const {
    const double lx = o[0] - center_xy[2 * j], ly = o[1] - center_xy[2 * j + 1];
    const double r = radius[j], z0 = z_min[j], z1 = z_max[j];
    const double a = d[0] * d[0] + d[1] * d[1];
    const double bh = lx * d[0] + ly * d[1];
    const double cc = (lx * lx + ly * ly) - r * r;
    const double disc = bh * bh - a * cc;
    const double s_side = (-bh - std::sqrt(std::max(disc, 0.0))) / std::max(a, 1e-18);
    const double z_side = o[2] + s_side * d[2];
    double s = kInf, cos = 0.0;
    if (disc >= 0 && a > 1e-18 && s_side > 0 && z_side >= z0 && z_side <= z1) {
      s = s_side;
      cos = std::fabs((lx + s_side * d[0]) * d[0] + (ly + s_side * d[1]) * d[1]) / r;
    }
    const double dz = std::fabs(d[2]) < 1e-12 ? 1e-12 : d[2];
    const double caps[2] = {z1, z0};
    const double signs[2] = {1.0, -1.0};
    for (int i = 0; i < 2; ++i) {
      const double s_cap = (caps[i] - o[2]) / dz;
      const double px = lx + s_cap * d[0], py = ly + s_cap * d[1];
      if (signs[i] * (o[2] - caps[i]) > 0 && s_cap > 0 && px * px + py * py <= r * r && s_cap < s) {
        s = s_cap;
        cos = std::fabs(d[2]);
      }
    }
    cos_inc = cos;
    return s;
  }
};

// Counter-based randomness of the foliage: two uniforms in [0, 1) per (ray, ellipsoid), as in
// lidarops/data/_raycast.py (_foliage_uniforms): mix64 of key + ray * G1 + (ellipsoid + 1) * G2, and of that + G3.
struct Ellipsoids {
  int64_t n;
  const double *center, *radii, *mean_free_path, *reflectivity;
  uint64_t key;

  // _intersect_ellipsoids for one pair: a return after an exponential free path inside the ellipsoid
  inline double intersect(int64_t j, int64_t ray, const double* o, const double* d, double& cos_inc) const {
    const double* c = center + 3 * j;
    const double* r = radii + 3 * j;
    double u[3], v[3];
    for (int i = 0; i < 3; ++i) {
      u[i] = (o[i] - c[i]) / r[i];
      v[i] = d[i] / r[i];
    }
    const double a = (v[0] * v[0] + v[1] * v[1]) + v[2] * v[2];
    const double b = (u[0] * v[0] + u[1] * v[1]) + u[2] * v[2];
    const double cc = ((u[0] * u[0] + u[1] * u[1]) + u[2] * u[2]) - 1.0;
    const double disc = b * b - a * cc;
    if (!(disc > 0)) return kInf;
    const double root = std::sqrt(disc);
    const double s_out = (-b + root) / a;
    if (!(s_out > 0)) return kInf;
    const double s_in = std::max((-b - root) / a, 0.0);
    const uint64_t h = key + static_cast<uint64_t>(ray) * 0x9E3779B97F4A7C15ull +
                       static_cast<uint64_t>(j + 1) * 0xD1B54A32D192ED03ull;
    const double u_depth = static_cast<double>(mix64(h) >> 11) * 0x1.0p-53;
    const double s = s_in + (-std::log1p(-u_depth)) * mean_free_path[j];
    if (!(s < s_out)) return kInf;
    const double u_cos = static_cast<double>(mix64(h + 0x632BE59BD9B4E019ull) >> 11) * 0x1.0p-53;
    cos_inc = 0.3 + 0.7 * u_cos;
    return s;
  }
};

// ------------------------------------------------------------------------------------------- culling grid
struct Grid {
  double dz0 = 0, band_scale = 0, bin_scale = kAzimuthBins / 4.0;
  std::vector<int32_t> offsets;  // [cells + 1]
  std::vector<int32_t> ids;      // per cell: the labelled objects' boxes, then the other primitives by dmin
  std::vector<double> dmin;      // per primitive: lower bound of the distance from any ray origin

  inline int band(double dz) const {
    const int b = static_cast<int>((dz - dz0) * band_scale);
    return std::min(std::max(b, 0), kElevationBands - 1);
  }
  inline int bin(double p) const { return std::min(static_cast<int>(p * bin_scale), kAzimuthBins - 1); }
  inline int cell(const double* d) const { return band(d[2]) * kAzimuthBins + bin(pseudo_angle(d[0], d[1])); }
};

// The window of one primitive's bounding vertical cylinder (centre, radius, z range, all grown), seen from
// the mean origin; ``rect`` (half extents and yaw of a grown footprint rectangle, or null) narrows it.
struct Window {
  bool live = false;
  bool full = false;
  double az_lo = 0, az_hi = 0, el_lo = 0, el_hi = 0, dmin = 0;
};

Window window(const double* origin, double cx, double cy, double radius, double z_lo, double z_hi, double max_distance,
              const double* rect) {
  Window w;
  const double rx = cx - origin[0], ry = cy - origin[1];
  const double dist_h = std::hypot(rx, ry);
  const double phi = std::atan2(ry, rx);
  const double ratio = radius / std::max(dist_h, 1e-12);
  w.full = ratio >= 1.0;
  const double half_width = w.full ? kPi : std::asin(ratio);
  double d_min = std::max(dist_h - radius, 0.0), d_max = dist_h + radius;
  w.az_lo = phi - half_width - kMargin;
  w.az_hi = phi + half_width + kMargin;
  if (rect != nullptr && !w.full) {
    const double ex = rect[0], ey = rect[1], c = std::cos(rect[2]), s = std::sin(rect[2]);
    const double qx = -(c * rx + s * ry), qy = -(c * ry - s * rx);  // the origin in the rectangle's frame
    if (std::fabs(qx) > ex + 1e-3 || std::fabs(qy) > ey + 1e-3) {  // outside: the corners bound the window
      double lo = kInf, hi = -kInf;
      const double sx[4] = {1, -1, -1, 1}, sy[4] = {1, 1, -1, -1};
      for (int i = 0; i < 4; ++i) {
        const double lx = sx[i] * ex, ly = sy[i] * ey;
        double dphi = std::atan2(ry + s * lx + c * ly, rx + c * lx - s * ly) - phi;
        if (dphi > kPi) dphi -= 2 * kPi;
        if (dphi <= -kPi) dphi += 2 * kPi;
        lo = std::min(lo, dphi);
        hi = std::max(hi, dphi);
      }
      w.az_lo = std::max(w.az_lo, phi + lo - kMargin);
      w.az_hi = std::min(w.az_hi, phi + hi + kMargin);
      d_min = std::max(d_min, std::hypot(std::max(std::fabs(qx) - ex, 0.0), std::max(std::fabs(qy) - ey, 0.0)));
      d_max = std::min(d_max, std::hypot(std::fabs(qx) + ex, std::fabs(qy) + ey));
    }
  }
  const double dz_hi = z_hi - origin[2], dz_lo = z_lo - origin[2];
  w.el_hi = std::atan2(dz_hi, dz_hi >= 0 ? d_min : d_max) + kMargin;
  w.el_lo = std::atan2(dz_lo, dz_lo >= 0 ? d_max : d_min) - kMargin;
  w.dmin = std::hypot(d_min, std::max(std::max(dz_lo, -dz_hi), 0.0));
  w.live = w.dmin <= max_distance;
  return w;
}

// Enters every live window into the grid (counting pass, then filling pass), the primitives in the order
// ``order``, so that every cell lists them in that order.
void fill_grid(Grid& grid, const std::vector<Window>& windows, const std::vector<int32_t>& order) {
  const int cells = kAzimuthBins * kElevationBands;
  struct Span {
    int b0, b1, a[4];  // bands [b0, b1]; azimuth bins [a0, a1] and [a2, a3] (second empty unless wrapped)
  };
  std::vector<Span> spans(windows.size());
  std::vector<int32_t> count(cells + 1, 0);
  for (size_t i = 0; i < windows.size(); ++i) {
    const Window& w = windows[i];
    Span& sp = spans[i];
    sp.b0 = 1;
    sp.b1 = 0;
    if (!w.live) continue;
    const double s_lo = std::sin(std::max(w.el_lo, -kPi / 2)), s_hi = std::sin(std::min(w.el_hi, kPi / 2));
    sp.b0 = grid.band(s_lo);
    sp.b1 = grid.band(s_hi);
    if (w.full || w.az_hi - w.az_lo >= 2 * kPi) {
      sp.a[0] = 0, sp.a[1] = kAzimuthBins - 1, sp.a[2] = 1, sp.a[3] = 0;
    } else {
      const double p_lo = pseudo_angle(std::cos(w.az_lo), std::sin(w.az_lo));
      const double p_hi = pseudo_angle(std::cos(w.az_hi), std::sin(w.az_hi));
      if (p_lo <= p_hi) {
        sp.a[0] = grid.bin(p_lo), sp.a[1] = grid.bin(p_hi), sp.a[2] = 1, sp.a[3] = 0;
      } else {  // the window contains azimuth 0
        sp.a[0] = grid.bin(p_lo), sp.a[1] = kAzimuthBins - 1, sp.a[2] = 0, sp.a[3] = grid.bin(p_hi);
      }
    }
    for (int b = sp.b0; b <= sp.b1; ++b)
      for (int r = 0; r < 2; ++r)
        for (int a = sp.a[2 * r]; a <= sp.a[2 * r + 1]; ++a) ++count[b * kAzimuthBins + a + 1];
  }
  for (int c = 0; c < cells; ++c) count[c + 1] += count[c];
  grid.offsets = count;
  grid.ids.resize(count[cells]);
  std::vector<int32_t> fill(count.begin(), count.end() - 1);
  for (const int32_t i : order) {
    const Span& sp = spans[i];
    for (int b = sp.b0; b <= sp.b1; ++b)
      for (int r = 0; r < 2; ++r)
        for (int a = sp.a[2 * r]; a <= sp.a[2 * r + 1]; ++a) grid.ids[fill[b * kAzimuthBins + a]++] = static_cast<int32_t>(i);
  }
}

// ------------------------------------------------------------------------------------------- the op's phases
// The scene's tensors by primitive family (references to the op's arguments).
struct GroundArgs {
  const at::Tensor &plane, &wave_amp, &wave_k, &wave_phase;
};
struct BoxArgs {
  const at::Tensor &center, &half, &yaw, &velocity, &yaw_rate, &reflectivity, &kind, &object;
};
struct CylinderArgs {
  const at::Tensor &center_xy, &z_min, &z_max, &radius, &reflectivity, &kind;
};
struct EllipsoidArgs {
  const at::Tensor &center, &radii, &mean_free_path, &reflectivity;
};

// Phase 1: the dtype and shape of every argument, then the counts; returns the number of rays.
int64_t check_args(const at::Tensor& origins, const at::Tensor& dirs, const at::Tensor& times, const at::Tensor& samples,
                   const GroundArgs& g, const BoxArgs& b, const CylinderArgs& cy, const EllipsoidArgs& el,
                   int64_t num_objects, int64_t ground_iterations) {
  const auto f64 = at::kDouble;
  const int64_t n = origins.dim() == 2 ? origins.size(0) : -1;
  check_arg(origins, "origins", f64, {-1, 3});
  check_arg(dirs, "dirs", f64, {n, 3});
  check_arg(times, "times", f64, {n});
  check_arg(samples, "origin_samples", f64, {-1, 3});
  TORCH_CHECK_VALUE(n == 0 || samples.size(0) > 0, "raycast_scene: origin_samples must not be empty when there are rays");
  check_arg(g.plane, "ground_plane", f64, {3});
  const int64_t nw = g.wave_amp.dim() == 1 ? g.wave_amp.size(0) : -1;
  check_arg(g.wave_amp, "wave_amp", f64, {-1});
  check_arg(g.wave_k, "wave_k", f64, {nw, 2});
  check_arg(g.wave_phase, "wave_phase", f64, {nw});
  const int64_t nb = b.center.dim() == 2 ? b.center.size(0) : -1;
  check_arg(b.center, "box_center", f64, {-1, 3});
  check_arg(b.half, "box_half", f64, {nb, 3});
  check_arg(b.yaw, "box_yaw", f64, {nb});
  check_arg(b.velocity, "box_velocity", f64, {nb, 3});
  check_arg(b.yaw_rate, "box_yaw_rate", f64, {nb});
  check_arg(b.reflectivity, "box_reflectivity", f64, {nb});
  check_arg(b.kind, "box_kind", at::kByte, {nb});
  check_arg(b.object, "box_object", at::kInt, {nb});
  const int64_t nc = cy.center_xy.dim() == 2 ? cy.center_xy.size(0) : -1;
  check_arg(cy.center_xy, "cyl_center_xy", f64, {-1, 2});
  check_arg(cy.z_min, "cyl_z_min", f64, {nc});
  check_arg(cy.z_max, "cyl_z_max", f64, {nc});
  check_arg(cy.radius, "cyl_radius", f64, {nc});
  check_arg(cy.reflectivity, "cyl_reflectivity", f64, {nc});
  check_arg(cy.kind, "cyl_kind", at::kByte, {nc});
  const int64_t ne = el.center.dim() == 2 ? el.center.size(0) : -1;
  check_arg(el.center, "ell_center", f64, {-1, 3});
  check_arg(el.radii, "ell_radii", f64, {ne, 3});
  check_arg(el.mean_free_path, "ell_mean_free_path", f64, {ne});
  check_arg(el.reflectivity, "ell_reflectivity", f64, {ne});
  TORCH_CHECK_VALUE(num_objects >= 0, "raycast_scene: num_objects must be >= 0, got ", num_objects);
  TORCH_CHECK_VALUE(ground_iterations >= 0, "raycast_scene: ground_iterations must be >= 0, got ", ground_iterations);
  TORCH_CHECK_VALUE(nb + nc + ne < (int64_t{1} << 31), "raycast_scene: too many primitives");
  return n;
}

// Phase 2: views of the scene. The contiguous tensors they point into are kept alive in ``keep``.
template <typename T>
const T* kept(std::vector<at::Tensor>& keep, const at::Tensor& t) {
  keep.push_back(t.contiguous());
  return ptr<T>(keep.back());
}

GroundField ground_view(const GroundArgs& g, std::vector<at::Tensor>& keep) {
  const double* pl = kept<double>(keep, g.plane);
  return GroundField{pl[0], pl[1], pl[2], g.wave_amp.size(0), kept<double>(keep, g.wave_amp),
                     kept<double>(keep, g.wave_k), kept<double>(keep, g.wave_phase)};
}

// The boxes, with the cosine and sine of their yaws; checks that every object index is < num_objects.
Boxes box_view(const BoxArgs& b, int64_t num_objects, std::vector<at::Tensor>& keep) {
  const int64_t nb = b.center.size(0);
  Boxes boxes{nb, kept<double>(keep, b.center), kept<double>(keep, b.half), kept<double>(keep, b.yaw),
              kept<double>(keep, b.velocity), kept<double>(keep, b.yaw_rate), kept<double>(keep, b.reflectivity),
              kept<uint8_t>(keep, b.kind), kept<int32_t>(keep, b.object), {}, {}};
  boxes.cos_yaw.resize(nb);
  boxes.sin_yaw.resize(nb);
  for (int64_t j = 0; j < nb; ++j) {
    boxes.cos_yaw[j] = std::cos(boxes.yaw[j]);
    boxes.sin_yaw[j] = std::sin(boxes.yaw[j]);
    const int32_t obj = boxes.object[j];
    TORCH_CHECK_VALUE(obj < num_objects, "raycast_scene: box_object[", j, "] = ", obj, " but num_objects = ", num_objects);
  }
  return boxes;
}

Cylinders cylinder_view(const CylinderArgs& c, std::vector<at::Tensor>& keep) {
  return Cylinders{c.center_xy.size(0), kept<double>(keep, c.center_xy), kept<double>(keep, c.z_min),
                   kept<double>(keep, c.z_max), kept<double>(keep, c.radius), kept<double>(keep, c.reflectivity),
                   kept<uint8_t>(keep, c.kind)};
}

Ellipsoids ellipsoid_view(const EllipsoidArgs& e, int64_t foliage_key, std::vector<at::Tensor>& keep) {
  return Ellipsoids{e.center.size(0), kept<double>(keep, e.center), kept<double>(keep, e.radii),
                    kept<double>(keep, e.mean_free_path), kept<double>(keep, e.reflectivity),
                    static_cast<uint64_t>(foliage_key)};
}

// Phase 3: the batch as seen from its mean origin: spread of the origins, time span, elevation range of the rays.
struct BatchFrame {
  double origin[3] = {0, 0, 0};
  double spread_xy = 0, spread_z = 0, t_mid = 0, half_span = 0, dz_lo = kInf, dz_hi = -kInf;
};

BatchFrame batch_frame(const double* smp, int64_t ns, const double* tm, const double* dir, int64_t n) {
  BatchFrame f;
  for (int64_t i = 0; i < ns; ++i)
    for (int c = 0; c < 3; ++c) f.origin[c] += smp[3 * i + c];
  for (int c = 0; c < 3; ++c) f.origin[c] /= static_cast<double>(ns);
  for (int64_t i = 0; i < ns; ++i) {
    f.spread_xy = std::max(f.spread_xy, std::hypot(smp[3 * i] - f.origin[0], smp[3 * i + 1] - f.origin[1]));
    f.spread_z = std::max(f.spread_z, std::fabs(smp[3 * i + 2] - f.origin[2]));
  }
  f.spread_xy += 1e-6;
  f.spread_z += 1e-6;
  double t_lo = kInf, t_hi = -kInf;
  for (int64_t i = 0; i < n; ++i) {
    t_lo = std::min(t_lo, tm[i]);
    t_hi = std::max(t_hi, tm[i]);
    f.dz_lo = std::min(f.dz_lo, dir[3 * i + 2]);
    f.dz_hi = std::max(f.dz_hi, dir[3 * i + 2]);
  }
  f.t_mid = 0.5 * (t_lo + t_hi);
  f.half_span = 0.5 * (t_hi - t_lo);
  return f;
}

// Phase 4: every primitive's window (boxes, then cylinders, then ellipsoids: the primitive ids).
std::vector<Window> primitive_windows(const BatchFrame& f, const Boxes& boxes, const Cylinders& cyl,
                                      const Ellipsoids& ell, double max_distance) {
  const int64_t nb = boxes.n, nc = cyl.n, ne = ell.n;
  std::vector<Window> windows(nb + nc + ne);
  for (int64_t j = 0; j < nb; ++j) {
    const double* c = boxes.center + 3 * j;
    const double* v = boxes.velocity + 3 * j;
    const double* h = boxes.half + 3 * j;
    const double grow_xy = std::hypot(v[0], v[1]) * f.half_span + f.spread_xy;
    const double grow_z = std::fabs(v[2]) * f.half_span + f.spread_z;
    const double cz = c[2] + v[2] * f.t_mid;
    const double rect[3] = {h[0] + grow_xy, h[1] + grow_xy, boxes.yaw[j]};
    windows[j] = window(f.origin, c[0] + v[0] * f.t_mid, c[1] + v[1] * f.t_mid, std::hypot(h[0], h[1]) + grow_xy,
                        cz - h[2] - grow_z, cz + h[2] + grow_z, max_distance, boxes.yaw_rate[j] == 0.0 ? rect : nullptr);
  }
  for (int64_t j = 0; j < nc; ++j)
    windows[nb + j] = window(f.origin, cyl.center_xy[2 * j], cyl.center_xy[2 * j + 1], cyl.radius[j] + f.spread_xy,
                             cyl.z_min[j] - f.spread_z, cyl.z_max[j] + f.spread_z, max_distance, nullptr);
  for (int64_t j = 0; j < ne; ++j) {
    const double* c = ell.center + 3 * j;
    const double* r = ell.radii + 3 * j;
    windows[nb + nc + j] = window(f.origin, c[0], c[1], std::max(r[0], r[1]) + f.spread_xy, c[2] - r[2] - f.spread_z,
                                  c[2] + r[2] + f.spread_z, max_distance, nullptr);
  }
  return windows;
}

// Phase 5: the culling grid. Labelled objects first (every crossing is counted), then the rest nearest first:
// a ray stops at the first primitive that is farther than its nearest hit so far.
Grid build_grid(const BatchFrame& f, const std::vector<Window>& windows, const Boxes& boxes) {
  Grid grid;
  grid.dz0 = f.dz_lo;
  grid.band_scale = kElevationBands / std::max(f.dz_hi - f.dz_lo, 1e-9);
  const int64_t nb = boxes.n;
  std::vector<int32_t> order(windows.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = static_cast<int32_t>(i);
  auto is_object = [&](int32_t id) { return id < nb && boxes.object[id] >= 0; };
  std::stable_sort(order.begin(), order.end(), [&](int32_t x, int32_t y) {
    if (is_object(x) != is_object(y)) return is_object(x);
    return !is_object(x) && windows[x].dmin < windows[y].dmin;
  });
  fill_grid(grid, windows, order);
  grid.dmin.resize(windows.size());
  for (size_t i = 0; i < windows.size(); ++i) grid.dmin[i] = windows[i].dmin;
  return grid;
}

// Phase 6, one ray: the nearest of its ground hit and the primitives of its grid cell; counts the ray in
// ``rays`` for every labelled object it crosses within max_distance.
struct Hit {
  double s;     // distance; infinite for none
  int64_t id;   // -1 none or ground, else a primitive id; equal distances go to the larger id
  double cos;   // cosine of the incidence angle
};

Hit nearest_hit(const Grid& grid, const Boxes& boxes, const Cylinders& cyl, const Ellipsoids& ell, int64_t i,
                const double* ro, const double* rd, double t, double ground_s, double ground_cos, double max_distance,
                int64_t* rays) {
  const int64_t first_cyl = boxes.n, first_ell = boxes.n + cyl.n;
  Hit best{ground_s, -1, ground_cos};
  double limit = std::min(best.s, max_distance);  // a primitive farther than this from every origin cannot win
  const int cell = grid.cell(rd);
  for (int32_t e = grid.offsets[cell]; e < grid.offsets[cell + 1]; ++e) {
    const int64_t id = grid.ids[e];
    double c = 0.0, s;
    if (id < first_cyl) {
      const int32_t obj = boxes.object[id];
      if (obj < 0 && grid.dmin[id] > limit) break;
      s = boxes.intersect(id, ro, rd, t, c);
      if (obj >= 0 && s <= max_distance) ++rays[obj];
    } else if (grid.dmin[id] > limit) {
      break;
    } else if (id < first_ell) {
      s = cyl.intersect(id - first_cyl, ro, rd, c);
    } else {
      s = ell.intersect(id - first_ell, i, ro, rd, c);
    }
    if (s <= limit && (s < best.s || (s == best.s && id > best.id))) {
      best = {s, id, c};
      limit = s;
    }
  }
  return best;
}

// Phase 7, one ray: the surface kind, reflectivity and object of its hit; counts a visible labelled object.
void classify_hit(const Hit& hit, const Boxes& boxes, const Cylinders& cyl, const Ellipsoids& ell, uint8_t& kind,
                  double& refl, int32_t& obj, int64_t* visible) {
  const int64_t first_cyl = boxes.n, first_ell = boxes.n + cyl.n;
  refl = 0.0;
  kind = std::isfinite(hit.s) ? kSurfaceGround : kSurfaceNone;
  obj = -1;
  if (hit.id >= first_ell) {
    kind = kSurfaceVegetation;
    refl = ell.reflectivity[hit.id - first_ell];
  } else if (hit.id >= first_cyl) {
    kind = cyl.kind[hit.id - first_cyl];
    refl = cyl.reflectivity[hit.id - first_cyl];
  } else if (hit.id >= 0) {
    kind = boxes.kind[hit.id];
    refl = boxes.reflectivity[hit.id];
    obj = boxes.object[hit.id];
    if (obj >= 0) ++visible[obj];
  }
}

// ------------------------------------------------------------------------------------------- the op
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> raycast_scene_cpu(
    const at::Tensor& origins_in, const at::Tensor& dirs_in, const at::Tensor& times_in, const at::Tensor& samples_in,
    const at::Tensor& plane_in, const at::Tensor& wave_amp_in, const at::Tensor& wave_k_in, const at::Tensor& wave_phase_in,
    const at::Tensor& box_center_in, const at::Tensor& box_half_in, const at::Tensor& box_yaw_in,
    const at::Tensor& box_velocity_in, const at::Tensor& box_yaw_rate_in, const at::Tensor& box_refl_in,
    const at::Tensor& box_kind_in, const at::Tensor& box_object_in, const at::Tensor& cyl_center_in,
    const at::Tensor& cyl_z_min_in, const at::Tensor& cyl_z_max_in, const at::Tensor& cyl_radius_in,
    const at::Tensor& cyl_refl_in, const at::Tensor& cyl_kind_in, const at::Tensor& ell_center_in,
    const at::Tensor& ell_radii_in, const at::Tensor& ell_mfp_in, const at::Tensor& ell_refl_in, double max_distance,
    int64_t foliage_key, int64_t num_objects, int64_t ground_iterations, double ground_tolerance) {
  const GroundArgs ground_args{plane_in, wave_amp_in, wave_k_in, wave_phase_in};
  const BoxArgs box_args{box_center_in, box_half_in, box_yaw_in, box_velocity_in,
                         box_yaw_rate_in, box_refl_in, box_kind_in, box_object_in};
  const CylinderArgs cyl_args{cyl_center_in, cyl_z_min_in, cyl_z_max_in, cyl_radius_in, cyl_refl_in, cyl_kind_in};
  const EllipsoidArgs ell_args{ell_center_in, ell_radii_in, ell_mfp_in, ell_refl_in};
  const int64_t n = check_args(origins_in, dirs_in, times_in, samples_in, ground_args, box_args, cyl_args, ell_args,
                               num_objects, ground_iterations);

  const auto f64 = at::kDouble;
  auto distance = at::empty({n}, at::dtype(f64));
  auto surface = at::empty({n}, at::dtype(at::kByte));
  auto object_index = at::empty({n}, at::dtype(at::kInt));
  auto cos_incidence = at::empty({n}, at::dtype(f64));
  auto reflectivity = at::empty({n}, at::dtype(f64));
  auto object_rays = at::zeros({num_objects}, at::dtype(at::kLong));
  auto object_visible = at::zeros({num_objects}, at::dtype(at::kLong));
  if (n == 0) return {distance, surface, object_index, cos_incidence, reflectivity, object_rays, object_visible};

  std::vector<at::Tensor> keep;
  const double* o = kept<double>(keep, origins_in);
  const double* dir = kept<double>(keep, dirs_in);
  const double* tm = kept<double>(keep, times_in);
  const GroundField ground = ground_view(ground_args, keep);
  const Boxes boxes = box_view(box_args, num_objects, keep);
  const Cylinders cyl = cylinder_view(cyl_args, keep);
  const Ellipsoids ell = ellipsoid_view(ell_args, foliage_key, keep);

  const BatchFrame frame = batch_frame(kept<double>(keep, samples_in), samples_in.size(0), tm, dir, n);
  const Grid grid = build_grid(frame, primitive_windows(frame, boxes, cyl, ell, max_distance), boxes);

  double* out_s = distance.data_ptr<double>();
  uint8_t* out_surface = surface.data_ptr<uint8_t>();
  int32_t* out_object = object_index.data_ptr<int32_t>();
  double* out_cos = cos_incidence.data_ptr<double>();
  double* out_refl = reflectivity.data_ptr<double>();
  int64_t* rays_total = object_rays.data_ptr<int64_t>();
  int64_t* visible_total = object_visible.data_ptr<int64_t>();
  std::mutex merge;

  at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
    std::vector<int64_t> rays_local(num_objects, 0), visible_local(num_objects, 0);
    double ground_s[kBatch], ground_cos[kBatch];
    for (int64_t i = begin; i < end; ++i) {
      if ((i - begin) % kBatch == 0)
        ground.intersect(o + 3 * i, dir + 3 * i, static_cast<int>(std::min<int64_t>(kBatch, end - i)), max_distance,
                         ground_iterations, ground_tolerance, ground_s, ground_cos);
      const Hit hit = nearest_hit(grid, boxes, cyl, ell, i, o + 3 * i, dir + 3 * i, tm[i], ground_s[(i - begin) % kBatch],
                                  ground_cos[(i - begin) % kBatch], max_distance, rays_local.data());
      classify_hit(hit, boxes, cyl, ell, out_surface[i], out_refl[i], out_object[i], visible_local.data());
      out_s[i] = hit.s;
      out_cos[i] = std::isfinite(hit.s) ? hit.cos : 0.0;
    }
    if (num_objects > 0) {
      std::lock_guard<std::mutex> lock(merge);
      for (int64_t k = 0; k < num_objects; ++k) {
        rays_total[k] += rays_local[k];
        visible_total[k] += visible_local[k];
      }
    }
  });
  return {distance, surface, object_index, cos_incidence, reflectivity, object_rays, object_visible};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) { m.impl("raycast_scene", &raycast_scene_cpu); }

}  // namespace lidarops
