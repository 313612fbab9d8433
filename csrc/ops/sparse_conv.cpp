// Schemas of the sparse convolution ops. Kernels: csrc/cpu/sparse_*_kernel.cpp,
// csrc/cuda/sparse_*_kernel.cu; fake kernels and autograd: lidarops/sparse/_registrations.py (sparse_conv's
// autograd: csrc/ops/autograd/sparse_conv_kernel.cpp).
// Conventions (indices layout, keys, kernel-offset order, transposed pairing): csrc/include/lidarops/sparse.h.
// Direct calls (torch.ops.lidarops.*): every kernel checks shapes, dtypes and devices at entry (ValueError);
// values used as indices are never read out of bounds: the CPU kernels check them (ValueError), the CUDA
// kernels clamp or skip them as each op says below (docs/ops.md, "Calling the registered ops directly").
// Kernel-map entries must lie in [-1, N_in) (-1: no input); the CPU kernels raise for others, the CUDA
// kernels treat them as -1 (sparse.h, map_row).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(lidarops, m) {
  // Output sites of a regular (transposed=False) or transposed convolution: every site of the output
  // grid that some input site feeds through some kernel offset. indices (N, 1 + D) int32 ->
  // (M, 1 + D) int32, sorted by linear key (batch, then row-major coordinates). Data-dependent M.
  // method: 0 auto, 1 dense grid, 2 hash table. validate: rows outside the batch / grid raise ValueError
  // (both devices; one host sync on CUDA); without it they are skipped. Sites need not be unique here.
  // checked: the caller vouches that the rows lie in the batch and grid and are unique (checked before, or
  // by the map built on them before the result is used); a transposed convolution whose kernel is its stride
  // (no padding or dilation, every input's block inside the output grid) then has N K outputs, which CUDA
  // does not read back. Rows that break the vouch give unspecified rows (CUDA: rows of -1).
  m.def(
      "sparse_conv_out_indices(Tensor indices, int batch_size, int[] spatial_shape, int[] out_spatial_shape,"
      " int[] kernel_size, int[] stride, int[] padding, int[] dilation, bool transposed=False, int method=0,"
      " bool validate=True, bool checked=False) -> Tensor");
  // Kernel map: (N_out, K) int32, entry [o, k] = input row feeding out_indices[o] through offset k, or -1.
  // validate: raise ValueError for input coordinates outside the grid or duplicated (costs one host
  // sync on CUDA); without it such rows are ignored (never read out of bounds; of duplicates the first
  // wins on CPU, any one on CUDA). out_indices rows outside the batch or grid get rows of -1.
  m.def(
      "sparse_kernel_map(Tensor indices, Tensor out_indices, int batch_size, int[] spatial_shape,"
      " int[] kernel_size, int[] stride, int[] padding, int[] dilation, bool transposed=False,"
      " bool validate=True, int method=0) -> Tensor");
  // sparse_kernel_map with validate=True whose check is read later: on CUDA the map's last kernel writes the
  // check's word into a pinned host slot and the returned ticket (-1: nothing to check, or checked at once) is
  // redeemed by sparse_site_check, which waits for the word and raises the same ValueError; a caller queues its
  // next work (the convolution on the map, which skips bad rows as without validation) before redeeming it, so
  // the host does not wait for the map. sparse_site_check_slots(like) is the ring of those words as a CPU int64
  // tensor (CUDA; empty for CPU indices, which are checked at once): slot ticket % len holds ticket << 2 once
  // the check has passed, so a caller may read it there and call sparse_site_check only when it does not.
  m.def(
      "sparse_kernel_map_deferred(Tensor indices, Tensor out_indices, int batch_size, int[] spatial_shape,"
      " int[] kernel_size, int[] stride, int[] padding, int[] dilation, bool transposed=False,"
      " int method=0) -> (Tensor, int)");
  m.def("sparse_site_check(Tensor indices, int ticket, int batch_size, int[] spatial_shape) -> ()");
  m.def("sparse_site_check_slots(Tensor like) -> Tensor");
  // Transposed kernel map: (n_in, K) int32 with [i, k] = o wherever kernel_map[o, k] = i, else -1
  // (unique: for a fixed offset the pairing is one-to-one; a caller's map that repeats an input in one
  // column gets one of the writers). Entries outside [-1, n_in): CPU ValueError, CUDA skipped.
  m.def("sparse_kernel_map_transpose(Tensor kernel_map, int n_in) -> Tensor");
  // Processing order of the output rows for the fused GPU kernel: a permutation (N_out,) int32 that
  // sorts the rows by the bit mask of their present kernel offsets (stable), so that the rows of one
  // tile share their offsets and absent offsets are skipped. Offsets beyond the 63rd do not count.
  // Only the sign of the entries is read: any values.
  m.def("sparse_kernel_map_order(Tensor kernel_map) -> Tensor");
  // out[o] = sum_k weight[:, k, :] @ features[kernel_map[o, k]]: features (N_in, Cin),
  // weight (Cout, K, Cin), kernel_map (N_out, K) int32 -> (N_out, Cout). Accumulates in float32
  // (float64 for float64). order (optional, from sparse_kernel_map_order) only changes the speed.
  // order must be a permutation of [0, N_out): only its shape is checked; the CPU kernel ignores it, the
  // CUDA kernels skip entries outside [0, N_out) and leave the rows it misses unspecified.
  // algo, splits: the CUDA kernel choice, "auto" / 0 or forced (sparse.h, ConvAlgo); every choice gives
  // the same sums in the dtype's precision. Checked on both devices (ValueError); the CPU ignores them.
  m.def(
      "sparse_conv(Tensor features, Tensor weight, Tensor kernel_map, Tensor? order=None, str algo=\"auto\","
      " int splits=0) -> Tensor");
  // Inference form with a fused per-channel epilogue on the float accumulator:
  // relu?(sparse_conv(...) * scale + shift), scale / shift float32 (Cout,) or None (BatchNorm in eval
  // mode folded to an affine map, then ReLU). No autograd formula: for use without gradients.
  m.def("sparse_conv_affine(Tensor features, Tensor weight, Tensor kernel_map, Tensor? order, Tensor? scale, "
        "Tensor? shift, bool relu=False, str algo=\"auto\", int splits=0) -> Tensor");
  // A run of such convolutions on one kernel map (a submanifold map: N_out = N_in), each layer's output the
  // next one's features: weights[i] (Cout_i, K, Cin_i) with Cin_i = Cout_{i-1}, scales / shifts float32
  // (Cout_i,), relu one flag per layer. What SparseSequential runs for consecutive fused SubM layers that share
  // an indice_key: one op call instead of one per layer (host time). Composite: the layers are
  // sparse_conv_affine calls, so every device and fake tensors follow that op; no autograd formula either.
  m.def("sparse_conv_affine_chain(Tensor features, Tensor[] weights, Tensor kernel_map, Tensor? order, "
        "Tensor[] scales, Tensor[] shifts, bool[] relu, str algo=\"auto\") -> Tensor");
  // Gradient of sparse_conv with respect to weight: (Cout, K, Cin), sum over o of
  // grad_out[o] (x) features[kernel_map[o, k]].
  m.def("sparse_conv_weight_grad(Tensor features, Tensor grad_out, Tensor kernel_map) -> Tensor");
  // Max over the kernel window: features (N_in, C), kernel_map (N_out, K) -> (out (N_out, C),
  // argmax (N_out, C) int64 input row, -1 where no input). Ties to the first offset; NaN propagates.
  m.def("sparse_max_pool(Tensor features, Tensor kernel_map) -> (Tensor, Tensor)");
  // Adjoint of sparse_max_pool: grad (N_out, C), argmax (N_out, C), kernel_map_t (N_in, K) -> (N_in, C).
  // kernel_map_t entries must lie in [-1, N_out) (CPU: ValueError; CUDA: skipped); argmax values are only
  // compared with input rows (any values).
  m.def("sparse_max_pool_backward(Tensor grad, Tensor argmax, Tensor kernel_map_t) -> Tensor");
  // Dense map of a sparse tensor: features (N, C), indices (N, 1 + D) int32 -> (B, C, *spatial_shape),
  // channels first, zeros at inactive sites (SparseConvTensor.dense()). Rows whose batch index or
  // coordinates lie outside the grid are skipped (dense() checks them first), on both devices. Sites
  // must be unique (of duplicates, one writer wins).
  m.def("sparse_to_dense(Tensor features, Tensor indices, int batch_size, int[] spatial_shape) -> Tensor");
  // Its adjoint: dense (B, C, *S), indices (N, 1 + D) -> (N, C), the feature vector at each site (0 for a
  // row outside the grid).
  m.def("sparse_from_dense(Tensor dense, Tensor indices) -> Tensor");
}
