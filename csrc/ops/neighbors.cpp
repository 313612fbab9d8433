// Schemas of the neighborhood ops. Kernels: csrc/cpu/*_kernel.cpp, csrc/cuda/*_kernel.cu;
// fake kernels: lidarops/_meta_registrations.py; autograd: lidarops/_autograd_registrations.py.
// Direct calls (torch.ops.lidarops.*): every kernel checks shapes, dtypes and devices at entry (ValueError);
// values used as indices are never read out of bounds: the CPU kernels check them (ValueError), the CUDA
// kernels clamp or skip them as each op says below (docs/ops.md, "Calling the registered ops directly").
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(lidarops, m) {
  // points (B, N, 3) float; lengths (B,) int64; start_idx (B,) int64 -> idx (B, k) int64, -1 padded.
  // method: 0 = choose automatically, other values force a path (see each kernel).
  // Values: lengths in [0, N], start_idx in [0, lengths) (CPU: ValueError; CUDA: clamped).
  m.def("fps(Tensor points, Tensor lengths, Tensor start_idx, int k, int method=0) -> Tensor");
  // query (B, M, 3), points (B, N, 3) -> dist2 (B, M, k), idx (B, M, k) int64; padding +inf / -1.
  // Values (knn and ball_query): query_lengths in [0, M], point_lengths in [0, N] (CPU: ValueError;
  // CUDA: clamped).
  m.def(
      "knn(Tensor query, Tensor points, Tensor query_lengths, Tensor point_lengths, int k,"
      " int method=0) -> (Tensor, Tensor)");
  // First k points in index order with dist2 < radius^2; padding +inf / -1.
  m.def(
      "ball_query(Tensor query, Tensor points, Tensor query_lengths, Tensor point_lengths, int k,"
      " float radius, int method=0) -> (Tensor, Tensor)");
  // x (B, N, C), idx (B, L) int64 -> (B, L, C); idx -1 gives zeros. Values: idx in [-1, N) (CPU:
  // ValueError; CUDA: any other value gives zeros too).
  m.def("gather(Tensor x, Tensor idx) -> Tensor");
  // Adjoint of gather: grad (B, L, C), idx (B, L) -> (B, n, C), scatter-add, idx -1 ignored. Values: idx
  // in [-1, n) (CPU: ValueError; CUDA: other values ignored too).
  m.def("gather_backward(Tensor grad, Tensor idx, int n) -> Tensor");
}
