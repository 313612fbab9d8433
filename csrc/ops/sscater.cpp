// Schemas of the SSCATeR delta-convolution ops. Kernels: csrc/cpu/sscater_kernel.cpp,
// csrc/cuda/sscater_kernel.cu; fake kernels: lidarops/sscater/_registrations.py; the streaming
// backbone that drives them: lidarops/sscater/delta.py. Geometry and state layout:
// csrc/include/lidarops/sscater.h.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(lidarops, m) {
  // acc (Ho, Wo, Cout) += the convolution of a zero image holding delta (n, Cin) at sites (n, 2) int32
  // (y, x) of the input grid: for every tap (ky, kx) of weight (Cout, kh, kw, Cin), the output site
  // reached (regular: o * stride - padding + k = i; transposed: o = i * stride - padding + k) gets
  // delta @ weight[:, ky, kx, :]^T. Sites outside the output grid are skipped. float32 / float64.
  // With out_active (Ho, Wo) bool, only active output sites are updated (the others' acc goes stale
  // and must be recomputed when they become active). Returns the reached output sites:
  // (n * kh * kw,) int64 linear keys oy * Wo + ox, entry i * K + ky * kw + kx, or -1 where the tap
  // falls outside the grid (or on an inactive site).
  m.def(
      "sscater_scatter_(Tensor(a!) acc, Tensor sites, Tensor delta, Tensor weight, int stride, int padding,"
      " bool transposed, Tensor? out_active=None) -> Tensor");
  // For each site (m, 2) int32 of the output grid: y = active ? relu(acc * scale + shift) : 0, written
  // into out (Ho, Wo, C), any strides. Returns (changed (m,) bool: y differs from out's previous
  // value in some channel, delta (m, C) = y - previous).
  m.def(
      "sscater_finalize_(Tensor acc, Tensor(a!) out, Tensor active, Tensor sites, Tensor scale, Tensor shift)"
      " -> (Tensor, Tensor)");
}
