// Schemas of the rotated-box ops. Kernels: csrc/cpu/boxes_kernel.cpp, csrc/cuda/boxes_kernel.cu (geometry
// in include/lidarops/boxes.h); fake kernels: lidarops/ops/_registrations.py; wrappers and float64
// references: lidarops/ops/boxes.py.
//
// Direct calls: shapes, dtypes and devices are checked at entry (ValueError); no op indexes with values
// read from a tensor (nms_bev's idxs are only compared: any int64 values).
//
// Boxes are (N, 7) x, y, z, dx, dy, dz, heading (LiDAR frame, z the box centre, heading counter-clockwise
// from +x). Every op computes in float64 and returns float64 for float64 boxes, float32 otherwise.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(lidarops, m) {
  // a (N, 7), b (M, 7) -> (N, M): intersection area of the bird's-eye-view rectangles.
  m.def("box_overlap_bev(Tensor a, Tensor b) -> Tensor");
  // a (N, 7), b (M, 7) -> (N, M): BEV intersection over union; 0 where the union is empty.
  m.def("box_iou_bev(Tensor a, Tensor b) -> Tensor");
  // a (N, 7), b (M, 7) -> (N, M): BEV intersection x z overlap / union of the volumes.
  m.def("box_iou_3d(Tensor a, Tensor b) -> Tensor");
  // Greedy rotated NMS on the BEV IoU. boxes (N, 7), scores (N,), idxs (N,) int64 or None (groups: boxes of
  // different groups never suppress each other). Boxes are visited in descending score order, equal scores
  // by ascending index; the first pre_max of that order take part (-1: all); a box is suppressed when its
  // IoU with a kept box of its group is strictly greater than iou_threshold; at most post_max are kept
  // (-1: all). Returns the kept indices (K,) int64 in visiting order (K data-dependent). NaN scores
  // are visited last.
  m.def(
      "nms_bev(Tensor boxes, Tensor scores, Tensor? idxs, float iou_threshold, int pre_max=-1,"
      " int post_max=-1) -> Tensor");
  // nms_bev with outputs of a size fixed by the shapes (no device-to-host read: CUDA-graph capturable).
  // With a score_threshold, the candidates are those of the first pre_max boxes of the visiting order
  // whose score is >= score_threshold (NaN scores never are); None: all of them, as nms_bev. Returns
  // (keep (K,) int64, count () int64) with K = min(post_max, pre_max, N) (-1 arguments: no limit):
  // keep[:count] the kept indices in visiting order, keep[count:] = -1.
  m.def(
      "nms_bev_padded(Tensor boxes, Tensor scores, Tensor? idxs, float iou_threshold, float? score_threshold=None,"
      " int pre_max=-1, int post_max=-1) -> (Tensor, Tensor)");
  // nms_bev_padded of B frames at once: boxes (B, N, 7), scores (B, N) -> (keep (B, K) int64, count (B,) int64),
  // row b frame b's nms_bev_padded (indices into its N boxes, -1 after count[b]); K as nms_bev_padded's.
  // On CUDA the frames share each launch (one sort of all frames' keys, one mask kernel, one reduction block
  // per frame).
  m.def(
      "nms_bev_padded_batched(Tensor boxes, Tensor scores, float iou_threshold, float? score_threshold=None,"
      " int pre_max=-1, int post_max=-1) -> (Tensor, Tensor)");
  // nms_bev_padded and the value checks of its inputs in one call: returns (keep (K,) int64, status (4,)
  // int64) with status[0] the number kept and status[1], [2], [3] nonzero when a box value is NaN or
  // infinite, a score is, a box has a negative size (the kernels are safe on any values; the caller reads
  // the status once and raises).
  m.def(
      "nms_bev_checked(Tensor boxes, Tensor scores, Tensor? idxs, float iou_threshold, float? score_threshold=None,"
      " int pre_max=-1, int post_max=-1) -> (Tensor, Tensor)");
  // points (P, C >= 3), boxes (M, 7) -> (P,) int64: the lowest index of the closed boxes holding each
  // point, -1 when none does.
  m.def("points_in_boxes(Tensor points, Tensor boxes) -> Tensor");
}
