// Schema of the value-check op used by the Python wrappers (lidarops/ops/validation.py). Kernels:
// csrc/cpu/checks_kernel.cpp, csrc/cuda/checks_kernel.cu; fake kernel: lidarops/_meta_registrations.py.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(lidarops, m) {
  // One flag per tensor, 1 = bad: finite[i] holds a NaN or an infinity; ranged[j] holds a value
  // outside [lo[j], hi[j]]. Returns int32 (len(finite) + len(ranged),) on the tensors' device, so
  // that a wrapper checks all its arguments' values with one launch per tensor and one host sync.
  // Argument errors (lo / hi lengths, dtypes, mixed devices): ValueError.
  m.def("value_flags(Tensor[] finite, Tensor[] ranged, int[] lo, int[] hi) -> Tensor");
}
