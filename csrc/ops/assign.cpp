// Schemas of the greedy assignment over a ranked list of pairs and of the filling of repeated picks. Kernels: csrc/cpu/assign_kernel.cpp (a sequential
// scan), csrc/cuda/assign_kernel.cu (the same answer in parallel rounds); fake kernel:
// lidarops/ops/_registrations.py; callers: lidarops.ops.greedy_assign (CAS-Net's distinct picks,
// lidarops/models/casnet.py) and CAS-Net's whole-cloud sampler (fill_repeats).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(lidarops, m) {
  // rows (L,), cols (L,) int64: (row, col) pairs in the order they are offered (e.g. by decreasing score).
  // Each pair is taken unless its row already holds one or its col is already taken; the scan stops once
  // `limit` rows hold one. Returns (num_rows,) int64: each row's col, -1 where none.
  // Direct calls: equal lengths, 1-D int64 on one device, num_rows, num_cols, limit >= 0 (ValueError); rows in
  // [0, num_rows) and cols in [0, num_cols) (ValueError on the CPU; on CUDA, where checking needs a host read,
  // pairs outside are skipped: lidarops.greedy_assign checks them).
  m.def("greedy_assign(Tensor rows, Tensor cols, int num_rows, int num_cols, int limit) -> Tensor");
  // points (n, 3) float32/float64 contiguous, idx (m,) int64 picks of them. Returns idx with each repeat (a row
  // holding a point an earlier row holds) given the free point (held by no row, original picks and earlier fills
  // included) nearest to its pick instead, rows in order: squared distances in float64 with every step rounded
  // (CPU and CUDA agree to the bit), ties to the lower index; a repeat stays when no point is free (m > n).
  // Direct calls: shapes, dtypes, one device (ValueError); idx in [0, n) (ValueError on the CPU; on CUDA rows
  // outside are left as they are and hold nothing).
  m.def("fill_repeats(Tensor points, Tensor idx) -> Tensor");
}
