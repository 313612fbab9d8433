// sparse_conv_affine_chain (schema: csrc/ops/sparse_conv.cpp): consecutive fused submanifold layers on one
// kernel map, as one op call. Composite (CompositeImplicitAutograd): each layer is a sparse_conv_affine call
// through the dispatcher, so the devices, the kernels' checks and fake tensors are that op's; what it saves is
// the Python and the op-call overhead of each layer after the first.
#include <ATen/ATen.h>
#include <ATen/core/dispatch/Dispatcher.h>
#include <torch/library.h>

namespace lidarops {
namespace sparse {
namespace {

at::Tensor conv_affine_op(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& kernel_map,
                          const c10::optional<at::Tensor>& order, const c10::optional<at::Tensor>& scale,
                          const c10::optional<at::Tensor>& shift, bool relu, c10::string_view algo) {
  static auto op = c10::Dispatcher::singleton()
                       .findSchemaOrThrow("lidarops::sparse_conv_affine", "")
                       .typed<at::Tensor(const at::Tensor&, const at::Tensor&, const at::Tensor&,
                                         const c10::optional<at::Tensor>&, const c10::optional<at::Tensor>&,
                                         const c10::optional<at::Tensor>&, bool, c10::string_view, int64_t)>();
  return op.call(features, weight, kernel_map, order, scale, shift, relu, algo, 0);
}

at::Tensor sparse_conv_affine_chain(const at::Tensor& features, at::TensorList weights, const at::Tensor& kernel_map,
                                    const c10::optional<at::Tensor>& order, at::TensorList scales,
                                    at::TensorList shifts, const c10::List<bool>& relu, c10::string_view algo) {
  const size_t n = weights.size();
  TORCH_CHECK_VALUE(n >= 1, "weights must hold at least one layer's weight");
  TORCH_CHECK_VALUE(scales.size() == n && shifts.size() == n && relu.size() == n, "scales, shifts and relu must "
                    "have one entry per layer: weights has ", n, ", scales ", scales.size(), ", shifts ",
                    shifts.size(), ", relu ", relu.size());
  TORCH_CHECK_VALUE(kernel_map.dim() == 2 && kernel_map.size(0) == features.size(0), "kernel_map must be a "
                    "submanifold map, (N, K) with N = ", features.size(0), " rows (one per row of features), got "
                    "shape ", kernel_map.sizes());
  at::Tensor x = features;
  for (size_t i = 0; i < n; ++i) {
    // the kernel's own checks name "features" and "weight"; the layer and its input are named here
    TORCH_CHECK_VALUE(weights[i].dim() == 3 && weights[i].size(2) == x.size(1), "weights[", i, "] must be "
                      "(Cout, K, Cin = ", x.size(1), ") (Cin: the channels of ",
                      i == 0 ? "features" : "the previous layer's output", "), got shape ", weights[i].sizes());
    x = conv_affine_op(x, weights[i], kernel_map, order, scales[i], shifts[i], relu[i], algo);
  }
  return x;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CompositeImplicitAutograd, m) {
  m.impl("sparse_conv_affine_chain", &sparse_conv_affine_chain);
}

}  // namespace sparse
}  // namespace lidarops
