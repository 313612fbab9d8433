// trace_shapes on CPU: rays that entered a labelled object's box followed onto the object's shape (sphere tracing of
// a signed distance function, then a bisection), parallel over rays.
//
// The shapes and the tracing follow lidarops/data/shapes.py (the NumPy reference) operation by operation, in
// float64, so hits and distances agree to rounding; a ray grazing a thin part within rounding of the hit tolerance
// may go either way.
#include <ATen/core/Tensor.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>

namespace lidarops {
namespace {

constexpr double kHit = 1e-4, kMinStep = 1e-2, kPi = 3.14159265358979323846;
constexpr int kSteps = 160, kBisect = 7;
constexpr int64_t kGrain = 256;
enum ShapeKind : int64_t { kCar = 0, kTruck, kBus, kPedestrian, kCyclist, kNumShapes };

struct V3 {
  double x, y, z;
};
inline V3 operator+(V3 a, V3 b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline V3 operator-(V3 a, V3 b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline V3 operator*(V3 a, double s) { return {a.x * s, a.y * s, a.z * s}; }
inline double dot(V3 a, V3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline double norm(V3 a) { return std::sqrt(a.x * a.x + a.y * a.y + a.z * a.z); }

// The primitives of shapes.py.
double round_box(V3 p, V3 c, V3 b, double r) {
  r = std::min(r, std::min({b.x, b.y, b.z}) * 0.999);
  const V3 q{std::abs(p.x - c.x) - (b.x - r), std::abs(p.y - c.y) - (b.y - r), std::abs(p.z - c.z) - (b.z - r)};
  const V3 out{std::max(q.x, 0.0), std::max(q.y, 0.0), std::max(q.z, 0.0)};
  return norm(out) + std::min(std::max({q.x, q.y, q.z}), 0.0) - r;
}

double capsule(V3 p, V3 a, V3 b, double r) {
  const V3 pa = p - a, ba = b - a;
  const double h = std::clamp(dot(pa, ba) / std::max(dot(ba, ba), 1e-12), 0.0, 1.0);
  return norm(pa - ba * h) - r;
}

double sphere(V3 p, V3 c, double r) { return norm(p - c) - r; }

double wheel(V3 p, V3 c, double radius, double half_width) {  // a cylinder about the y axis
  const double d_r = std::hypot(p.x - c.x, p.z - c.z) - radius, d_y = std::abs(p.y - c.y) - half_width;
  return std::min(std::max(d_r, d_y), 0.0) + std::hypot(std::max(d_r, 0.0), std::max(d_y, 0.0));
}

double ring(V3 p, V3 c, double radius, double tube) {  // a torus about the y axis
  const double q = std::hypot(p.x - c.x, p.z - c.z) - radius;
  return std::hypot(q, p.y - c.y) - tube;
}

double plane_xz(V3 p, double x0, double z0, double x1, double z1, bool forward) {
  const double dx = x1 - x0, dz = z1 - z0, n = std::hypot(dx, dz);
  const double nx = forward ? dz / n : -dz / n, nz = forward ? -dx / n : dx / n;
  return (p.x - x0) * nx + (p.z - z0) * nz;
}

// The shapes, in the frame of a box of half sizes h (x forward, z up, the origin at its centre).
double car(V3 p, V3 h, const double* u) {
  const double z0 = -h.z, H = 2 * h.z, L = 2 * h.x;
  const double belt = z0 + H * (0.56 + 0.08 * u[0]), clear = 0.11 * H, bz = (belt - z0 - clear) / 2;
  const double body = round_box(p, {0, 0, z0 + clear + bz}, {h.x - 0.03, h.y - 0.07, bz}, std::min(0.25, 0.8 * bz));
  const double rw = std::min(0.33, 0.21 * H), wx = h.x - std::min(0.9, 0.21 * L), wy = h.y - 0.17;
  double wheels = INFINITY;
  for (int sx : {-1, 1})
    for (int sy : {-1, 1}) wheels = std::min(wheels, wheel(p, {sx * wx, sy * wy, z0 + rw}, rw, 0.1));
  const double c0 = 0.18 + 0.06 * u[1], c1 = 0.74 + 0.08 * u[2];
  const double x_c0 = (c0 - 0.5) * L, x_c1 = (c1 - 0.5) * L, x_r0 = x_c0 + 0.13 * L, x_r1 = x_c1 - 0.2 * L;
  const double cz = (h.z - belt + 0.05) / 2;
  const double cabin =
      std::max({round_box(p, {(x_c0 + x_c1) / 2, 0, belt - 0.05 + cz}, {(x_c1 - x_c0) / 2, 0.82 * (h.y - 0.07), cz},
                          0.12),
                plane_xz(p, x_c1, belt, x_r1, h.z, true), plane_xz(p, x_c0, belt, x_r0, h.z, false)});
  double mirrors = INFINITY;
  for (int s : {-1, 1})
    mirrors = std::min(mirrors, round_box(p, {x_c1 - 0.1, s * (h.y - 0.07), belt + 0.06}, {0.06, 0.06, 0.05}, 0.02));
  return std::min({body, wheels, cabin, mirrors});
}

double truck(V3 p, V3 h, const double* u) {
  const double z0 = -h.z, H = 2 * h.z, L = 2 * h.x;
  const double cab = std::clamp(0.2 * L, 1.6, 2.4) * (0.9 + 0.2 * u[0]);
  const double cab_top = z0 + H * (0.78 + 0.1 * u[1]), clear = 0.12 * H, cab_z = (cab_top - z0 - clear) / 2;
  const double cabin = round_box(p, {h.x - cab / 2, 0, z0 + clear + cab_z}, {cab / 2, h.y - 0.04, cab_z}, 0.2);
  const double floor_z = z0 + 0.24 * H, cargo_len = L - cab - 0.15, cz = (h.z - floor_z) / 2;
  const double cargo =
      round_box(p, {-h.x + cargo_len / 2, 0, floor_z + cz}, {cargo_len / 2, h.y - 0.01, cz}, 0.06);
  const double chassis = round_box(p, {0, 0, z0 + 0.18 * H}, {h.x - 0.3, 0.5 * h.y, 0.05 * H}, 0.03);
  const double rw = std::min(0.52, 0.16 * H);
  double wheels = INFINITY;
  for (double x : {h.x - 0.6 * cab, -h.x + 0.22 * L})
    for (int s : {-1, 1}) wheels = std::min(wheels, wheel(p, {x, s * (h.y - 0.2), z0 + rw}, rw, 0.15));
  return std::min({cabin, cargo, chassis, wheels});
}

double bus(V3 p, V3 h, const double* u) {
  const double z0 = -h.z, H = 2 * h.z, clear = 0.1 * H, bz = (H - clear) / 2;
  const double body = round_box(p, {0, 0, z0 + clear + bz}, {h.x - 0.02, h.y - 0.03, bz}, 0.25 + 0.1 * u[0]);
  const double rw = std::min(0.5, 0.15 * H);
  double wheels = INFINITY;
  for (double x : {h.x - 0.2 * 2 * h.x, -h.x + 0.25 * 2 * h.x})
    for (int s : {-1, 1}) wheels = std::min(wheels, wheel(p, {x, s * (h.y - 0.2), z0 + rw}, rw, 0.15));
  return std::min(body, wheels);
}

double pedestrian(V3 p, V3 h, const double* u) {
  const double z0 = -h.z, H = 2 * h.z;
  const double stride = std::min(h.x - 0.07, 0.32) * std::sin(2 * kPi * u[0]);
  const double sw = std::min(0.1 * H, h.y - 0.1) * (1 - 0.25 * u[3]);
  const double hip_z = z0 + 0.52 * H, foot_z = z0 + 0.06;
  const double leg_r = 0.035 * H * (1 + u[1]), hem = 0.18 * H * u[2];
  double legs = INFINITY;
  for (int s : {-1, 1})
    legs = std::min(legs, capsule(p, {0, s * 0.09, hip_z}, {s * stride, s * 0.1, foot_z}, leg_r));
  const double torso =
      round_box(p, {0, 0, z0 + 0.70 * H - hem / 2}, {0.065 * H, sw, 0.16 * H + hem / 2}, 0.045 * H);
  const double head = sphere(p, {0.02, 0, z0 + 0.935 * H}, 0.065 * H);
  double arms = INFINITY;
  for (int s : {-1, 1})
    arms = std::min(arms, capsule(p, {0, s * (sw + 0.02), z0 + 0.80 * H},
                                  {-0.6 * s * stride, s * (sw + 0.04), z0 + 0.47 * H}, 0.028 * H));
  return std::min({legs, torso, head, arms});
}

double cyclist(V3 p, V3 h, const double* u) {
  const double z0 = -h.z, H = 2 * h.z;
  const double R = std::min(0.34, 0.42 * h.x), xr = -h.x + R + 0.02, xf = h.x - R - 0.02, D = xf - xr;
  const V3 hub_r{xr, 0, z0 + R}, hub_f{xf, 0, z0 + R};
  const double wheels = std::min(ring(p, hub_r, R, 0.03), ring(p, hub_f, R, 0.03));
  const V3 seat{xr + 0.32 * D, 0, z0 + 2.4 * R}, bar{xr + 0.86 * D, 0, z0 + 2.7 * R};
  const V3 bb{xr + 0.42 * D, 0, z0 + 0.85 * R}, head_tube{xr + 0.84 * D, 0, z0 + 2.1 * R};
  const V3 tubes[7][2] = {{hub_r, bb}, {hub_r, seat}, {bb, seat}, {seat, head_tube}, {bb, head_tube},
                          {head_tube, hub_f}, {head_tube, bar}};
  double frame = INFINITY;
  for (const auto& tb : tubes) frame = std::min(frame, capsule(p, tb[0], tb[1], 0.025));
  const V3 hip{xr + 0.3 * D, 0, z0 + 0.53 * H}, shoulder{xr + (0.37 + 0.2 * u[1]) * D, 0, z0 + 0.79 * H};
  const double torso = capsule(p, hip, shoulder, 0.07 * H);
  const double head = sphere(p, shoulder + V3{0.04, 0, 0.12 * H}, 0.062 * H);
  const double sw = std::min(0.17, h.y - 0.08);
  double arms = INFINITY;
  for (int s : {-1, 1})
    arms = std::min(arms, capsule(p, shoulder + V3{0, s * sw, 0}, bar + V3{0, s * (sw + 0.03), 0}, 0.024 * H));
  const double phase = 2 * kPi * u[0];  // the pedals' angle
  double legs = INFINITY;
  for (int s : {1, -1}) {
    const double ph = s == 1 ? phase : phase + kPi;
    const V3 pedal = bb + V3{0.17 * std::cos(ph), s * 0.1, 0.17 * std::sin(ph)};
    const V3 hip_s = hip + V3{0, s * 0.1, 0};
    const V3 knee = (hip_s + pedal) * 0.5 + V3{0.18, 0, 0.1};
    legs = std::min({legs, capsule(p, hip_s, knee, 0.034 * H), capsule(p, knee, pedal, 0.028 * H)});
  }
  return std::min({wheels, frame, torso, head, arms, legs});
}

// shapes.py's _distance: the shape cut to its box.
double distance(int64_t kind, V3 p, V3 h, const double* u) {
  double s = 0;
  switch (kind) {
    case kCar: s = car(p, h, u); break;
    case kTruck: s = truck(p, h, u); break;
    case kBus: s = bus(p, h, u); break;
    case kPedestrian: s = pedestrian(p, h, u); break;
    default: s = cyclist(p, h, u); break;
  }
  return std::max(s, round_box(p, {0, 0, 0}, h, 0.0));
}

double box_exit(V3 p, V3 d, V3 h) {
  auto far = [](double pi, double di, double hi) {
    return di > 0 ? (hi - pi) / di : (di < 0 ? (-hi - pi) / di : INFINITY);
  };
  return std::max(std::min({far(p.x, d.x, h.x), far(p.y, d.y, h.y), far(p.z, d.z, h.z)}), 0.0);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> trace_shapes_cpu(int64_t kind, const at::Tensor& entry_in,
                                                                const at::Tensor& d_in, const at::Tensor& half_in,
                                                                const at::Tensor& u_in) {
  TORCH_CHECK_VALUE(0 <= kind && kind < kNumShapes, "kind must be in [0, ", int64_t(kNumShapes), "), got ", kind);
  TORCH_CHECK_VALUE(entry_in.device().is_cpu() && entry_in.scalar_type() == at::kDouble && entry_in.dim() == 2 &&
                        entry_in.size(1) == 3,
                    "entry must be a CPU float64 (N, 3) tensor, got ", entry_in.sizes(), " ", entry_in.scalar_type(),
                    " on ", entry_in.device());
  const int64_t n = entry_in.size(0);
  for (const auto& [name, t, cols] : {std::tuple<const char*, const at::Tensor*, int64_t>{"d", &d_in, 3},
                                      {"half", &half_in, 3}, {"u", &u_in, 4}}) {
    TORCH_CHECK_VALUE(t->device().is_cpu() && t->scalar_type() == at::kDouble && t->dim() == 2 && t->size(0) == n &&
                          t->size(1) == cols,
                      name, " must be a CPU float64 (N, ", cols, ") tensor with N = ", n, ", got ", t->sizes(), " ",
                      t->scalar_type(), " on ", t->device());
  }
  const auto entry = entry_in.contiguous(), d = d_in.contiguous(), half = half_in.contiguous(), u = u_in.contiguous();
  auto t_out = at::zeros({n}, entry.options());
  auto hit_out = at::zeros({n}, entry.options().dtype(at::kBool));
  auto cos_out = at::zeros({n}, entry.options());
  const double *pe = entry.data_ptr<double>(), *pd = d.data_ptr<double>(), *ph = half.data_ptr<double>(),
               *pu = u.data_ptr<double>();
  double *ot = t_out.data_ptr<double>(), *oc = cos_out.data_ptr<double>();
  bool* oh = hit_out.data_ptr<bool>();
  at::parallel_for(0, n, kGrain, [&](int64_t lo, int64_t hi) {
    for (int64_t i = lo; i < hi; ++i) {
      const V3 e{pe[3 * i], pe[3 * i + 1], pe[3 * i + 2]}, dir{pd[3 * i], pd[3 * i + 1], pd[3 * i + 2]};
      const V3 h{ph[3 * i], ph[3 * i + 1], ph[3 * i + 2]};
      const double* ui = pu + 4 * i;
      const double exit_t = box_exit(e, dir, h);
      double t = 0, before = 0;
      bool hit = false;
      for (int k = 0; k < kSteps; ++k) {  // steps of at least 1 cm (shapes.py's _trace)
        const double dist = distance(kind, e + dir * t, h, ui);
        if (dist < kHit) {
          hit = true;
          break;
        }
        before = t;
        t += std::max(dist, kMinStep);
        if (!(t <= exit_t)) break;
      }
      ot[i] = t;
      if (!hit) continue;
      oh[i] = true;
      double a = before, b = t;
      for (int k = 0; k < kBisect; ++k) {
        const double mid = (a + b) / 2;
        if (distance(kind, e + dir * mid, h, ui) <= 0) b = mid;
        else a = mid;
      }
      ot[i] = b;
      const V3 p = e + dir * b;
      constexpr double eps = 5e-3;
      const V3 g{distance(kind, p + V3{eps, 0, 0}, h, ui) - distance(kind, p - V3{eps, 0, 0}, h, ui),
                 distance(kind, p + V3{0, eps, 0}, h, ui) - distance(kind, p - V3{0, eps, 0}, h, ui),
                 distance(kind, p + V3{0, 0, eps}, h, ui) - distance(kind, p - V3{0, 0, eps}, h, ui)};
      const double gn = norm(g);
      oc[i] = std::clamp(gn > 0 ? std::abs(g.x * dir.x + g.y * dir.y + g.z * dir.z) / std::max(gn, 1e-12) : 1.0,
                         0.0, 1.0);
    }
  });
  return {t_out, hit_out, cos_out};
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) { m.impl("trace_shapes", &trace_shapes_cpu); }

}  // namespace lidarops
