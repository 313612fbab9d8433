// Schema of the ray caster of the synthetic LiDAR simulator (lidarops/data/_raycast.py, cast_rays). Kernel:
// csrc/cpu/raycast_kernel.cpp (CPU only: the simulator is a CPU data generator); fake kernel:
// lidarops/_meta_registrations.py.
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
}
