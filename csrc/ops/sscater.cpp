// Schemas of the SSCATeR delta-convolution ops. Kernels: csrc/cpu/sscater_kernel.cpp,
// csrc/cuda/sscater_kernel.cu; fake kernels: lidarops/sscater/_registrations.py; the streaming
// backbone that drives them: lidarops/sscater/delta.py. Geometry and state layout:
// csrc/include/lidarops/sscater.h.
// Direct calls (torch.ops.lidarops.*): every kernel checks shapes, dtypes and devices at entry (ValueError);
// values used as indices are never read out of bounds: the CPU kernels check them (ValueError), the CUDA
// kernels clamp or skip them as each op says below (docs/ops.md, "Calling the registered ops directly").
// Site lists: rows outside the grid (or negative: padding) are skipped wherever a kernel indexes with
// them, except sscater_finalize_ / sscater_finalize_compact_ on CPU, which raise for a listed site
// outside the grid (CUDA skips it). A count is clamped to [0, rows] on both devices. Stamp values:
// value (and status_value) must lie in [-2^31, 2^31 - 1), kh * kw <= 2^20, stride and padding
// <= 2^24 (ValueError): a wrapped stamp would list a site twice and overflow the candidate list.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(lidarops, m) {
  // acc (Ho, Wo, Cout) += the convolution of a zero image holding delta (n, Cin) at sites (n, 2) int32
  // (y, x) of the input grid: for every tap (ky, kx) of weight (Cout, kh, kw, Cin), the output site
  // reached (regular: o * stride - padding + k = i; transposed: o = i * stride - padding + k) gets
  // delta @ weight[:, ky, kx, :]^T. Sites outside the output grid are skipped. float32 / float64.
  // With out_active (Ho, Wo) bool, only active output sites are updated (the others' acc goes stale
  // and must be recomputed when they become active). Returns the reached output sites:
  // (n * kh * kw,) int64 linear keys oy * Wo + ox, entry i * K + ky * kw + kx, or -1 where the tap
  // falls outside the grid (or on an inactive site). A row with a negative coordinate is padding (no
  // site); with count (int64 (1,) on acc's device), only the first count[0] rows are read: the rest
  // get -1 and cost nothing (a padded list whose length is known only on the device). channel_sparse:
  // when at least this share of the delta's values (of the rows read) is exactly 0, the channel-sparse
  // kernel runs (each row's nonzero channels times the weight, straight into acc) instead of the per-tap
  // GEMM; 0 always, > 1 never; the two differ only in the order of the float sums. CUDA counts the zeros
  // on the device and launches both kernels, the one not chosen returning at once (no host sync). The
  // default is where the sparse kernel starts to win on AVX-512 (it rereads the weights per row; the GEMM
  // reuses them): docs/sscater.md.
  m.def(
      "sscater_scatter_(Tensor(a!) acc, Tensor sites, Tensor delta, Tensor weight, int stride, int padding,"
      " bool transposed, Tensor? out_active=None, Tensor? count=None, float channel_sparse=0.85) -> Tensor");
  // For each site (m, 2) int32 of the output grid: y = active ? relu(acc * scale + shift) : 0, written
  // into out (Ho, Wo, C), any strides. Returns (changed (m,) bool: y differs from out's previous
  // value in some channel, delta (m, C) = y - previous). Sites outside the grid: CPU ValueError, CUDA
  // skipped; sites must be unique (of duplicates, one writer wins).
  m.def(
      "sscater_finalize_(Tensor acc, Tensor(a!) out, Tensor active, Tensor sites, Tensor scale, Tensor shift)"
      " -> (Tensor, Tensor)");

  // ---- the fused layer step (lidarops/sscater/delta.py): site lists are int32 (n, 2) (y, x); a row
  // (-1, -1) is no site (lists are padded to an upper bound so that no host sync is needed). A
  // stamp map (Ho, Wo) int32 marks the sites a step touched: values only grow from step to step.
  //
  // Strided layer: cover (Ho, Wo) int32 counts the active inputs under each output's kernel; the
  // inputs `added` / `removed` (n, 2) add / remove one under every tap. Outputs whose cover crosses
  // zero flip `active` and are returned as (added, removed), both ((a + r) * kh * kw, 2), filled from
  // their first row (the rest is padding), with their counts (2,) int64; at most Ho * Wo rows each
  // (an output flips once). Dedup of the touched outputs: stamp = value.
  m.def(
      "sscater_cover_update_(Tensor(a!) cover, Tensor(b!) active, Tensor(c!) stamp, int value, Tensor added,"
      " Tensor removed, int kh, int kw, int stride, int padding) -> (Tensor, Tensor, Tensor)");
  // Transposed layer: the children (every tap's output) of the added / removed input sites become
  // active / inactive (the removed last); returned as (a * kh * kw, 2) and (r * kh * kw, 2), padded.
  m.def(
      "sscater_children_(Tensor(a!) active, Tensor added, Tensor removed, int kh, int kw, int stride,"
      " int padding) -> (Tensor, Tensor)");
  // acc at `sites` (m, 2) of the output grid (padded) = the full convolution (no bias) of input
  // (Hi, Wi, Cin) there: sum over taps of input[y * stride - padding + ky, x * stride - padding + kx]
  // @ weight[:, ky, kx, :]^T (zero outside the input grid). With count, only the first count[0] rows.
  m.def(
      "sscater_gather_(Tensor(a!) acc, Tensor input, Tensor weight, Tensor sites, int stride, int padding,"
      " Tensor? count=None) -> ()");
  // The sites to re-evaluate, each once: the reached keys `targets` (R,) int64 (-1: none; stamp =
  // value) and the status changes `added`, `removed` (padded; stamp = value + 1); acc is zeroed at
  // the removed sites. Returns (cand (min(R + a + r, Ho * Wo), 2) int32, padded: each site at most
  // once, and count (1,) int64: its used rows).
  m.def(
      "sscater_touch_(Tensor(a!) stamp, Tensor(b!) acc, int value, Tensor targets, Tensor added, Tensor removed)"
      " -> (Tensor, Tensor)");
  // sscater_finalize_ over the first count[0] rows of cand, compacted: returns (sites (m, 2) int32,
  // delta (m, C)) of the sites whose value changed, in their first rows (then (-1, -1) rows, whose
  // delta is unspecified),
  // and counts (3,) int64:
  // changed sites, sites changed or with a status change (stamp == status_value), sites evaluated
  // (count clamped to [0, rows of cand]).
  m.def(
      "sscater_finalize_compact_(Tensor acc, Tensor(a!) out, Tensor active, Tensor cand, Tensor count,"
      " Tensor stamp, int status_value, Tensor scale, Tensor shift) -> (Tensor, Tensor, Tensor)");
  // A layer set from a dense convolution of its whole input (a refresh): y (C, Ho, Wo), any strides (the
  // convolution's output, NCHW or channels-last), into acc (Ho, Wo, C) contiguous = active ? y : 0 and
  // out (Ho, Wo, C), any strides = active ? relu(y * scale + shift) : 0; with out_nchw (C, Ho, Wo)
  // contiguous, the same values as out there too (the next layer's NCHW input). active None: every site.
  // One pass over y for what takes torch a transposing copy and separate BatchNorm, ReLU and mask passes.
  m.def(
      "sscater_dense_finalize_(Tensor y, Tensor(a!) acc, Tensor(b!) out, Tensor scale, Tensor shift,"
      " Tensor? active=None, Tensor(c!)? out_nchw=None) -> ()");
}
