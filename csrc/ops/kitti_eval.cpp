// Schema of the KITTI evaluation's matching step (CPU only). Kernel: csrc/cpu/kitti_eval_kernel.cpp; fake
// kernel: lidarops/eval/_registrations.py; caller: lidarops/eval/kitti.py.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(lidarops, m) {
  // The per-frame greedy matching of KITTI's object benchmark (compute_statistics of the official
  // evaluation), for F frames at once. Frame f holds gts [gt_offsets[f], gt_offsets[f+1]) and detections
  // [dt_offsets[f], dt_offsets[f+1]); overlaps holds, from overlap_offsets[f], its (D_f, G_f) row-major
  // detection x gt overlap matrix. ignored_gt / ignored_dt (int64): 0 counted, 1 ignored (matching one is
  // neither a hit nor a false positive), -1 not of the class. dt_dontcare: each detection's largest overlap
  // with a DontCare region, as the area of the intersection over the detection's own 2D box area (KITTI's
  // criterion 0; 0 where none). gt_alpha / dt_alpha: observation angles (for AOS).
  // compute_fp = false: the first pass (the highest-scoring detection above min_overlap wins); returns
  //   matched (G,) float64 = the score of the detection matched to each counted gt, NaN where none, and an
  //   empty (0, 4) tensor.
  // compute_fp = true: for each threshold t (detections scoring below t are left out; the detection with
  //   the largest overlap wins), returns counts (T, 4) float64 = tp, fp, fn, AOS similarity summed over the
  //   frames, and an empty (0,) tensor.
  // Direct calls: the tables are checked at entry (ValueError): offsets and ignore flags must be integer
  // tensors, each offset table starts at 0, ends at its total and never decreases, frame f's overlap
  // count is D_f * G_f, ignore flags are -1, 0 or 1, scores and thresholds hold no NaN.
  m.def(
      "kitti_match(Tensor overlaps, Tensor overlap_offsets, Tensor gt_offsets, Tensor dt_offsets,"
      " Tensor ignored_gt, Tensor ignored_dt, Tensor dt_scores, Tensor dt_dontcare, Tensor gt_alpha,"
      " Tensor dt_alpha, Tensor thresholds, float min_overlap, bool compute_fp, bool compute_aos)"
      " -> (Tensor, Tensor)");
}
