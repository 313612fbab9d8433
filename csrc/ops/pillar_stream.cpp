// Schemas of the pillarization ops (lidarops.stream). Kernels: csrc/cpu/pillar_stream_kernel.cpp,
// csrc/cuda/pillar_stream_kernel.cu; fake kernels: lidarops/stream/_registrations.py; wrappers:
// lidarops/stream/pillars.py (pillarize, which also uses voxelize_assign / voxelize_scatter) and
// lidarops/stream/stream.py (PillarStream). The layout of a stream's state is described in
// csrc/include/lidarops/pillar_stream.h.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(lidarops, m) {
  // raw (P, N, 4) float32/float64: x, y, z, intensity of the points of each pillar in its first
  // num_points[p] slots; coords (P, 3) int32 (batch, y, x); pillar_size (vx, vy); origin (x0, y0).
  // Returns (P, N, 9) in raw's dtype: x, y, z, intensity, x - mean_x, y - mean_y, z - mean_z,
  // x - centre_x, y - centre_y with the mean over the num_points[p] points (summed in slot order in
  // float64) and centre = origin + (index + 0.5) * size; every feature is computed in float64 and
  // rounded once. Slots >= num_points[p] are zero.
  m.def("pillar_decorate(Tensor raw, Tensor num_points, Tensor coords, float[2] pillar_size, float[2] origin)"
        " -> Tensor");
  // The queues of the pillars with linear keys cells (P,) int64 (y * W + x), in queue order:
  // raw (P, N, 4) float32, zeros beyond num_points (P,) int32. A pillar with no slot (or a key outside
  // [0, H W)) gives 0 points; one whose slot, head or count is out of range gives -1 points and is
  // never indexed with (the state is corrupt: PillarStream.pillars raises).
  m.def("pillar_stream_gather(Tensor pool_xyzi, Tensor head, Tensor count, Tensor cell_slot, Tensor cells)"
        " -> (Tensor raw, Tensor num_points)");
  // One push of a stream: expire the points with t <= cutoff (the first entries of each run of the
  // log: runs (R, 2) int64 absolute [start, end) positions, each run sorted by t), then enqueue the
  // points (n, 4) float32 with timestamps t (n,) float64 that lie in the grid and have t > cutoff,
  // keeping every queue sorted by t (ties in arrival order), and write them to the log as a new run
  // (sorted by t, ties in arrival order) at the absolute positions [log_head, log_head + points_in).
  // If the result would exceed a capacity (a queue longer than N, or more than M active pillars),
  // nothing is changed and stats[kPsOverflow] says which (see PillarStreamStat); with drop = true the
  // push instead admits what fits by the overflow rule (lidarops/stream/pillar_stream.py: points in the
  // window stay, a pillar's entering points in (t, arrival) order while its queue has room, pillars that
  // keep no point take the free slots in key order) and counts the others in kPsDropped*. State values are
  // checked where they are read; a broken invariant sets a kPsBad* bit of stats[kPsOverflow] and
  // nothing is changed either (csrc/include/lidarops/pillar_stream.h; docs/stream.md).
  // Returns change_map (H, W) bool (pillars that gained or lost a point), stats (kNumPillarStreamStats,)
  // int64, run_pops (R,) int64 (entries expired from the front of each run). With scalars, an int64 (2,)
  // tensor on the state's device holding log_head and the bits of cutoff (float64), the op reads those two
  // there and ignores the arguments: a CUDA graph's push, whose window is decided on the device.
  m.def(
      "pillar_stream_push(Tensor(a!) pool_xyzi, Tensor(b!) pool_t, Tensor(c!) head, Tensor(d!) count,"
      " Tensor(e!) slot_cell, Tensor(f!) cell_slot, Tensor(g!) free_slots, Tensor(h!) num_free,"
      " Tensor(i!) log_cell, Tensor(j!) log_t, Tensor points, Tensor t, Tensor runs, int log_head, float cutoff,"
      " float[6] point_range, float[2] pillar_size, int[2] grid_hw, bool drop=False, Tensor? scalars=None) ->"
      " (Tensor change_map,"
      " Tensor stats, Tensor run_pops)");
}
