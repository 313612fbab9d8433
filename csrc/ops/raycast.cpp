// Schemas of the ray caster of the synthetic LiDAR simulator (lidarops/data/_raycast.py, cast_rays) and of its
// shape tracer (lidarops/data/shapes.py, trace). Kernels: csrc/cpu/raycast_kernel.cpp, csrc/cpu/shapes_kernel.cpp
// (CPU only: the simulator is a CPU data generator); fake kernels: lidarops/data/_registrations.py.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(lidarops, m) {
  // Nearest hit of N rays (origins, unit dirs, times: float64) against the ground height field (plane
  // z0 + slope . xy plus waves amp * sin(k . xy + phase), float32 sines, Newton refinement), upright
  // oriented boxes moving with velocity and yaw rate (taken at each ray's time), vertical capped
  // cylinders and foliage ellipsoids (exponential penetration depth from a counter-based hash of
  // (foliage_key, ray, ellipsoid)). Hits farther than max_distance are ignored.
  // Returns distance (f64[N], inf: no hit), surface (u8[N]: 0 none, 1 ground, box/cylinder kind, 4
  // vegetation), object_index (i32[N], -1), cos_incidence (f64[N]), reflectivity (f64[N], 0 for ground:
  // the caller's material map fills it), object_rays and object_visible (i64[num_objects]).
  // Direct calls: dtypes and shapes are checked at entry, and box_object entries must be < num_objects
  // (negative: not an object) (ValueError).
  m.def(
      "raycast_scene(Tensor origins, Tensor dirs, Tensor times, Tensor origin_samples, Tensor ground_plane, "
      "Tensor wave_amp, Tensor wave_k, Tensor wave_phase, Tensor box_center, Tensor box_half, Tensor box_yaw, "
      "Tensor box_velocity, Tensor box_yaw_rate, Tensor box_reflectivity, Tensor box_kind, Tensor box_object, "
      "Tensor cyl_center_xy, Tensor cyl_z_min, Tensor cyl_z_max, Tensor cyl_radius, Tensor cyl_reflectivity, "
      "Tensor cyl_kind, Tensor ell_center, Tensor ell_radii, Tensor ell_mean_free_path, Tensor ell_reflectivity, "
      "float max_distance, int foliage_key, int num_objects, int ground_iterations, float ground_tolerance) "
      "-> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)");
  // Rays that entered a labelled object's box followed onto its shape (lidarops/data/shapes.py: kind 0 Car,
  // 1 Truck, 2 Bus, 3 Pedestrian, 4 Cyclist; kernel csrc/cpu/shapes_kernel.cpp): entry points, unit directions,
  // half sizes (N, 3) and the per-object numbers u (N, 4), float64 in the box's frame. Returns t (f64[N]: the
  // distance from the entry to the shape where hit), hit (bool[N]) and cos (f64[N], |cos| of the incidence).
  m.def("trace_shapes(int kind, Tensor entry, Tensor d, Tensor half, Tensor u) -> (Tensor, Tensor, Tensor)");
}
